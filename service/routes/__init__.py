"""The API's routers, one per resource: :mod:`.jobs` (``/v1/jobs``) and :mod:`.ops` (health, readiness, metrics)."""
