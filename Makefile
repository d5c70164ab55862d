# One entry point a command. `make demo` and `make test` set up everything they need.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup demo test protos lint bench clean test-deps

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)  ## create .venv with the backend, simulator, training and test dependencies

demo: $(STAMP)  ## start a backend, track a simulated sequence over gRPC, print the table, write plots
	$(PY) -m flextrack demo --out out/demo

test: lint test-deps  ## lint (ruff + import contracts), then the whole test suite (about 7 minutes on 2 cores)
	$(PY) -m pytest -q --durations=15

# What tests need beyond Python: nginx for the two front-proxy tests. Installed when missing as root or in
# CI (CI=true, with sudo); elsewhere those tests skip with a message. Under CI=true a skip fails the run
# (tests/conftest.py) unless the data under ../shared is absent.
test-deps:
	@if [ -z "$$(command -v nginx || ls /usr/sbin/nginx 2>/dev/null)" ]; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; elif [ "$${CI:-}" = true ] && command -v sudo >/dev/null; then SUDO=sudo; \
	  else echo "nginx is not installed: the front-proxy tests will skip (apt-get install nginx-light)"; exit 0; fi; \
	  $$SUDO apt-get install -y -q nginx-light >/dev/null 2>&1 \
	    || { $$SUDO apt-get update -q >/dev/null && $$SUDO apt-get install -y -q nginx-light >/dev/null; }; \
	fi

protos: $(STAMP)  ## regenerate flextrack/v1 from protos/ (never edit the generated files)
	$(PY) -m flextrack.protogen

lint: $(STAMP)  ## ruff, and the import contracts of pyproject.toml's [tool.importlinter] (lint-imports)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports --no-cache

clean:
	rm -rf $(VENV) out .pytest_cache
