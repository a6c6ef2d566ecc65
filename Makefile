# Two entry points for a fresh machine (Python 3.11 + pip): `make tables` and `make test`.
# Each creates .venv from environment.lock when it is missing or the lock changed.
PYTHON ?= python3
VENV := .venv
CORES ?= 2
# DEVICE=cuda (`make venv DEVICE=cuda`, on a machine with an NVIDIA GPU): .venv from
# environment.cuda.lock instead, torch's CUDA build from PyPI and the CUDA libraries it pins, so
# that `make gpu-check` runs there. The venv keeps its device (.venv/.device) for later targets;
# `make venv DEVICE=cpu` goes back.
ifndef DEVICE
DEVICE := $(or $(shell cat $(VENV)/.device 2>/dev/null),cpu)
endif
ifeq ($(filter cpu cuda,$(DEVICE)),)
$(error DEVICE must be cpu or cuda, got '$(DEVICE)')
endif
LOCK := $(if $(filter cuda,$(DEVICE)),environment.cuda.lock,environment.lock)
STAMP := $(VENV)/.installed$(if $(filter cuda,$(DEVICE)),-cuda)
# torch's CPU build (2.13.0+cpu) is not on PyPI: pip takes it from a local wheel directory
# (WHEEL_DIR, default /opt/wheels) when there is one, else from PyTorch's CPU wheel index.
WHEEL_DIR ?= /opt/wheels
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
WHEELS := $(if $(filter cuda,$(DEVICE)),,$(if $(wildcard $(WHEEL_DIR)),--find-links $(WHEEL_DIR),--extra-index-url $(TORCH_CPU_INDEX)))

.PHONY: venv conda-env tables figures tradeoff export morph report test gpu-check gpu-bundle slurm-check dag recover clean-venv

$(STAMP): $(LOCK) pyproject.toml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	rm -f $(VENV)/.installed $(VENV)/.installed-cuda
	$(VENV)/bin/python -m pip install --quiet --no-deps $(WHEELS) -r $(LOCK)
	$(VENV)/bin/python -m pip install --quiet --no-deps --no-build-isolation -e .
	echo $(DEVICE) > $(VENV)/.device
	touch $(STAMP)

# Extra Snakemake arguments for the targets below, e.g.
# make tables ARGS="--configfile config/test.yaml --config mesh_dir=path/to/meshes"
ARGS ?=

venv: $(STAMP)

# workflow/envs/physmorph.yaml, the conda environment of every rule (snakemake --use-conda), from
# environment.lock: rerun after the lock changed (tests/workflow/test_workflow_lint.py checks they agree).
conda-env:
	$(PYTHON) workflow/envs/make_env.py

tables: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) tables $(ARGS)

figures: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) figures $(ARGS)

tradeoff: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) tradeoff $(ARGS)

export: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) export $(ARGS)

# A user's own morph, start to finish (physmorph morph --help): make morph SOURCE=iso TARGET=path/to/mesh.obj,
# its options in ARGS (e.g. ARGS="--profile fast"); TARGET is the morph's target here, not recover's default.
morph: $(STAMP)
	@test -n "$(SOURCE)" -a "$(origin TARGET)" != file || { echo "make morph needs SOURCE=... TARGET=... (a mesh file, a point cloud or a shape name)"; exit 2; }
	$(VENV)/bin/physmorph morph "$(SOURCE)" "$(TARGET)" --cores $(CORES) $(ARGS)

report: $(STAMP)
	$(VENV)/bin/snakemake --cores $(CORES) tables figures tradeoff --report report.html $(ARGS)

test: $(STAMP)
	$(VENV)/bin/python -m pytest -q

# The solver, the renderer and the plasticity's device work on CUDA against the CPU
# (tests/test_gpu.py); skips, saying why, without a usable CUDA device (and a CUDA build of torch:
# make venv DEVICE=cuda).
gpu-check: $(STAMP)
	$(VENV)/bin/python -m pytest -m gpu -n 0 -rs tests/test_gpu.py

# What a lent GPU machine without network needs for the GPU check (benchmarks/gpu_bundle.py):
# .gpu_bundle/ with the packages its image lacks, for its Python (PYTHON_DEVICE), and the raw
# meshes from MESH_DIR; there, `bash benchmarks/gpu_check.sh` with .gpu_bundle carried.
PYTHON_DEVICE ?= 3.12
MESH_DIR ?= ../shared/meshes
gpu-bundle: $(STAMP)
	$(VENV)/bin/python benchmarks/gpu_bundle.py --python $(PYTHON_DEVICE) --mesh-dir $(MESH_DIR)

# The SLURM profile on a one-node SLURM cluster brought up on this machine (root, Debian; docs/cluster.md).
slurm-check: $(STAMP)
	bash tests/cluster/slurm-up.sh
	$(VENV)/bin/python -m pytest -m slurm -n 0 -rs tests/workflow/test_slurm.py

dag: $(STAMP)
	$(VENV)/bin/snakemake -n --cores $(CORES) tables $(ARGS)

# After a kill (SIGKILL, power loss, OOM): unlock the directory Snakemake left locked and rerun
# what was incomplete; a killed morph resumes from its last committed frame. Only while no other
# Snakemake runs here. E.g. make recover TARGET=figures ARGS="--configfile config/test.yaml"
TARGET ?= tables
recover: $(STAMP)
	$(VENV)/bin/snakemake --unlock $(TARGET) $(ARGS)
	$(VENV)/bin/snakemake --cores $(CORES) --rerun-incomplete $(TARGET) $(ARGS)

clean-venv:
	rm -rf $(VENV)
