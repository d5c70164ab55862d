# One entry point a command. `make demo` and `make test` set up everything they need.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup demo test protos lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)  ## create .venv with the backend, simulator, training and test dependencies

demo: $(STAMP)  ## start a backend, track a simulated sequence over gRPC, print the table, write plots
	$(PY) -m flextrack demo --out out/demo

test: lint  ## lint (ruff + import contracts), then the whole test suite (about 10 minutes on 2 cores)
	$(PY) -m pytest -q

protos: $(STAMP)  ## regenerate flextrack/v1 from protos/ (never edit the generated files)
	$(PY) -m flextrack.protogen

lint: $(STAMP)  ## ruff, and the import contracts of pyproject.toml's [tool.importlinter] (lint-imports)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports --no-cache

clean:
	rm -rf $(VENV) out .pytest_cache
