"""The API's routers, one module-level ``router`` per resource: :mod:`.jobs` (``/v1/jobs``), :mod:`.batches`
(``/v1/batches``) and :mod:`.ops` (health, readiness, metrics); the submission form the first two share is
:mod:`.form`.  The previews' router is :mod:`service.preview`'s."""
