# Two entry points for a fresh machine (Python 3.11 + pip): `make tables` and `make test`.
# Each creates .venv from environment.lock when it is missing or the lock changed.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
CORES ?= 2

.PHONY: venv tables figures tradeoff test dag clean-venv

$(STAMP): environment.lock pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --no-deps -r environment.lock
	$(VENV)/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
	touch $(STAMP)

venv: $(STAMP)

tables: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) tables

figures: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) figures

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

dag: $(STAMP)
	$(VENV)/bin/snakemake -n --cores $(CORES) tables

clean-venv:
	rm -rf $(VENV)
