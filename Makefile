# Two entry points for people: `make run` and `make test`.  Everything else is plumbing.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint install bench-tokens

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/python -m service.run

test: $(STAMP)
	$(BIN)/ruff check fastmesh service worker tests benchmarks
	$(BIN)/python -m pytest -q tests

lint: $(STAMP)
	$(BIN)/ruff check fastmesh service worker tests benchmarks

bench-tokens: $(STAMP)
	$(BIN)/python benchmarks/tokens.py ../shared/corpus
