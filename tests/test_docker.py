"""docker/: the compose file runs CPU and GPU workers on one Redis, and every image builds from files that exist.

No Docker engine is needed: the compose file is read as YAML and the Dockerfiles as text.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker" / "compose.yaml"
PYPROJECT = (ROOT / "pyproject.toml").read_text()


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _dockerfile(service: dict) -> Path:
    build = service["build"]
    return (COMPOSE.parent / build["context"] / build["dockerfile"]).resolve()


def test_cpu_worker_by_default_and_gpu_workers_in_the_gpu_profile_on_the_same_redis(compose):
    services = compose["services"]
    cpu, gpu = services["worker"], services["worker-gpu"]
    assert "profiles" not in cpu and _dockerfile(cpu).name == "Dockerfile.worker-cpu"
    assert gpu["profiles"] == ["gpu"] and _dockerfile(gpu).name == "Dockerfile.worker-cuda"
    devices = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert devices == [{"driver": "nvidia", "count": "all", "capabilities": ["gpu"]}]  # compose's `gpus: all`
    redis_urls = {name: s["environment"]["FASTMESH_REDIS_URL"] for name, s in services.items() if "environment" in s}
    assert set(redis_urls) == {"api", "worker", "worker-gpu"} and len(set(redis_urls.values())) == 1
    assert redis_urls["api"].startswith("redis://redis:")
    for name in ("worker", "worker-gpu"):  # restarted after a GPU error's exit; SIGTERM's warm shutdown has time
        assert services[name]["restart"] == "unless-stopped" and services[name]["stop_grace_period"] == "30s"
        assert services[name]["depends_on"] == {"redis": {"condition": "service_healthy"}}


def test_every_image_builds_from_files_that_exist_and_runs_the_entry_point(compose):
    assert re.search(r'^fastmesh-worker = "worker\.main:main"$', PYPROJECT, flags=re.M)
    for name, service in compose["services"].items():
        if "build" not in service:
            continue
        text = _dockerfile(service).read_text()
        for src in re.findall(r"^COPY\s+(\S+)\s+\S+$", text, flags=re.M):
            assert (ROOT / src).exists(), f"{name}: COPY {src}"
        if name.startswith("worker"):
            assert 'CMD ["fastmesh-worker"]' in text and "STOPSIGNAL SIGTERM" in text


def test_the_gpu_image_is_pytorchs_cuda_runtime_of_the_pinned_torch():
    text = (ROOT / "docker" / "Dockerfile.worker-cuda").read_text()
    base = re.search(r"^ARG BASE_IMAGE=(\S+)$", text, flags=re.M).group(1)
    pin = re.search(r'^  "torch==([^"]+)",$', PYPROJECT, flags=re.M).group(1)
    repo, tag = base.split(":")
    assert repo == "pytorch/pytorch" and tag.startswith(pin + "-cuda")
    assert tag.endswith("-runtime") and re.search(r"^FROM \$\{BASE_IMAGE\}$", text, flags=re.M)
    assert "FASTMESH_DEVICE=cuda" in text
