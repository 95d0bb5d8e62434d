"""TEMPORARY stand-in for fastmesh.pipeline until the real module lands (tests only)."""
import importlib.util
import sys

if importlib.util.find_spec("fastmesh.pipeline") is None:
    import fake_pipeline

    sys.modules["fastmesh.pipeline"] = fake_pipeline
