"""TEMPORARY stand-in for fastmesh.pipeline while the real one is incomplete (tests only, via PYTHONPATH)."""
import sys

import fake_pipeline

sys.modules["fastmesh.pipeline"] = fake_pipeline
