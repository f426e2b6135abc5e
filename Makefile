# ardflow: two commands do everything on a fresh clone: `make demo`, `make test`.
SHELL := /bin/bash
PYENV_ROOT ?= $(shell pyenv root 2>/dev/null || echo $$HOME/.pyenv)
PY312 := $(shell \
  for c in "$(PYENV_ROOT)/versions/3.12.1/bin/python3" "$$(PYENV_VERSION=3.12.1 pyenv which python3.12 2>/dev/null)" "$$(command -v python3.12)"; do \
    if [ -n "$$c" ] && [ -x "$$c" ] && "$$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' 2>/dev/null; then echo "$$c"; break; fi; \
  done)
VENV := .venv
DEMO_ARGS ?=
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# setuptools announces every editable install of a package-dir layout with a ten-line
# "Editable installation" notice (information only: ardflow.* maps to the top-level folders)
EDITABLE_ENV := PYTHONWARNINGS="ignore:Editable installation"

.PHONY: venv demo test test-slow bench clean

$(STAMP): pyproject.toml
	@if [ -z "$(PY312)" ]; then \
	  echo "error: Python >= 3.12 not found. Install it with 'pyenv install 3.12.1' (looked in $(PYENV_ROOT)/versions/3.12.1, pyenv, PATH)." >&2; exit 1; fi
	@test -x $(PY) || $(PY312) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(EDITABLE_ENV) $(PY) -m pip install -q -e '.[test,bench]'
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/ardflow demo --out runs/demo $(DEMO_ARGS)

# two processes: most tests wait on services, clusters and browsers, so two share the cores well (one file per
# process at a time keeps each module's service and cluster fixtures to one start). test_stop.py runs alone
# after them: it signals a whole service's process group and reads every line it prints, and beside the other
# process's load that raced (a resource tracker's traceback on Ctrl-C, a client past its timeout)
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile --ignore=tests/service/test_stop.py
	$(PY) -m pytest -q tests/service/test_stop.py

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

bench: $(STAMP)
	$(PY) -m tests.bench.run --out .bench/results.json

clean:
	rm -rf $(VENV) .bench runs
