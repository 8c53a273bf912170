# Quick start: `make demo` and `make test` on a fresh machine with only python3.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip

.PHONY: demo test docs lint typecheck bench clean

$(VENV)/.base:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	touch $@

$(VENV)/.installed: $(VENV)/.base pyproject.toml
	$(PIP) install --quiet -e .
	touch $@

$(VENV)/.installed-test: $(VENV)/.base pyproject.toml
	$(PIP) install --quiet -e '.[test]'
	touch $@

demo: $(VENV)/.installed
	$(VENV)/bin/lightplane demo --out demo-out --force

test: $(VENV)/.installed-test
	$(PY) -m pytest -q -n 2 --dist loadfile

docs: $(VENV)/.installed-test
	$(VENV)/bin/mkdocs build --strict --site-dir build/site

lint: $(VENV)/.installed-test
	$(VENV)/bin/ruff check src tests benchmarks docs

typecheck: $(VENV)/.installed-test
	$(PY) -m mypy

bench: $(VENV)/.installed-test
	$(PY) benchmarks/run_all.py

clean:
	rm -rf $(VENV) demo-out build src/*.egg-info
