# Two entry points for people: `make run` and `make test`.  Everything else is plumbing.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# One stamp per install set: running (the package and its dependencies) and testing (that plus the `dev` extra).
RUN_STAMP := $(VENV)/.installed-run
TEST_STAMP := $(VENV)/.installed-test

.PHONY: run test lint install install-test bench-tokens web chromium assimp blender blender-addon gpu-check

# torch: PyPI's default Linux wheel is the CUDA build (about 2.7 GB with its nvidia-* packages).  On Linux
# without an NVIDIA GPU we install the CPU build (about 200 MB) from PyTorch's CPU index instead; its own
# dependencies then come from your usual index with the package.  Override: make install TORCH='torch==2.13.0'.
TORCH_VERSION := 2.13.0
TORCH_CPU_INDEX := https://download.pytorch.org/whl/cpu
HAS_GPU := $(shell nvidia-smi -L >/dev/null 2>&1 && echo yes)
ifeq ($(shell uname -s)-$(HAS_GPU),Linux-)
TORCH ?= torch==$(TORCH_VERSION)+cpu --extra-index-url $(TORCH_CPU_INDEX)
else
TORCH ?= torch==$(TORCH_VERSION)
endif

# What running needs: torch, then this package and its dependencies (the service, the worker, the CLI).
$(RUN_STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q --no-deps $(TORCH)
	$(BIN)/pip install -q -e .
	touch $(RUN_STAMP)

# What testing adds: pyproject's `dev` extra (pytest, ruff, hypothesis, schemathesis, playwright, pyyaml).
$(TEST_STAMP): $(RUN_STAMP)
	$(BIN)/pip install -q -e '.[dev]'
	touch $(TEST_STAMP)

install: $(RUN_STAMP)

install-test: $(TEST_STAMP)

# The page's three.js (npm, pinned by service/web/package-lock.json) and, for the browser tests, Debian's chromium.
WEB_STAMP := service/web/node_modules/.package-lock.json
$(WEB_STAMP): service/web/package-lock.json
	sh scripts/install-web.sh

web: $(WEB_STAMP)

chromium:
	sh scripts/install-chromium.sh

# Debian's assimp-testmodels: real model files for tests/test_assimp_corpus.py.
assimp:
	sh scripts/install-assimp-testmodels.sh

# Debian's blender: the add-on's test in Blender itself (tests/test_blender_client.py).
blender:
	sh scripts/install-blender.sh

# The Blender add-on (clients/blender/) as the zip Blender's Preferences > Add-ons > Install takes.
BLENDER_ZIP ?= build/fastmesh_blender.zip
blender-addon:
	$(PY) scripts/blender_addon.py $(BLENDER_ZIP)

run: $(RUN_STAMP) web
	$(BIN)/python -m service.run

test: $(TEST_STAMP) web chromium assimp blender
	$(BIN)/ruff check fastmesh fastmesh_jobs service worker tests benchmarks clients
	$(BIN)/python -m pytest -q tests

lint: $(TEST_STAMP)
	$(BIN)/ruff check fastmesh fastmesh_jobs service worker tests benchmarks clients

bench-tokens: $(RUN_STAMP)
	$(BIN)/python benchmarks/tokens.py ../shared/corpus

# The device check: on a machine with one CUDA GPU and PyTorch (nothing else of ours), given this repository and,
# without a network there, ./wheels (benchmarks/gpu_check.py says how to fill it): installs what is missing,
# runs `pytest -m gpu` and the throughput benchmark, ends with one JSON line.  Without CUDA: the same on the CPU,
# fewer runs.  Python: this checkout's .venv where there is one, else $(PY).
GPU_PY := $(if $(wildcard $(BIN)/python),$(BIN)/python,$(PY))
gpu-check:
	$(GPU_PY) benchmarks/gpu_check.py
