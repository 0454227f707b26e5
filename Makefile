# tidee: make setup | make demo | make test
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.tidee-setup

.PHONY: setup demo test test-all lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

demo: setup
	$(VENV)/bin/tidee demo

# ruff (format + the rules in pyproject.toml) and mypy: what CI runs before the tests.
lint: setup
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

test: setup
	$(PY) -m pytest -q

test-all: setup
	$(PY) -m pytest -q -m ""

clean:
	rm -rf demo_out runs bench/*.tmp
