# tidee: make setup | make demo | make test
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.tidee-setup

.PHONY: setup demo test test-all clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh $(VENV)
	touch $(STAMP)

demo: setup
	$(VENV)/bin/tidee demo

test: setup
	$(PY) -m pytest -q

test-all: setup
	$(PY) -m pytest -q -m ""

clean:
	rm -rf demo_out runs bench/*.tmp
