# Two entry points for a fresh machine (Python 3.11 + pip): `make tables` and `make test`.
# Each creates .venv from environment.lock when it is missing or the lock changed.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed
CORES ?= 2
# torch's CPU build (2.13.0+cpu) is not on PyPI: pip finds it through PIP_FIND_LINKS / a local
# wheel directory (these machines keep it in /opt/wheels) or the PyTorch CPU wheel index.
WHEELS := $(if $(wildcard /opt/wheels),--find-links /opt/wheels,)

.PHONY: venv tables figures tradeoff test dag recover clean-venv

$(STAMP): environment.lock pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --no-deps $(WHEELS) -r environment.lock
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

# After a kill (SIGKILL, power loss, OOM): unlock the directory Snakemake left locked and rerun
# what was incomplete; a killed morph resumes from its last committed frame. Only while no other
# Snakemake runs here. E.g. make recover TARGET=figures ARGS="--configfile config/test.yaml"
TARGET ?= tables
ARGS ?=
recover: $(STAMP)
	$(VENV)/bin/snakemake --unlock $(TARGET) $(ARGS)
	$(VENV)/bin/snakemake --cores $(CORES) --rerun-incomplete $(TARGET) $(ARGS)

clean-venv:
	rm -rf $(VENV)
