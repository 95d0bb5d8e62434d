"""The API's routers, one per resource: :mod:`.jobs` (``/v1/jobs``), :mod:`.batches` (``/v1/batches``) and
:mod:`.ops` (health, readiness, metrics)."""
