# Shared settings and helpers. The merged config is turned into typed, frozen settings once (physmorph.settings.workflow:
# the one validator; every experiment resolved and a memory estimate checked before any job
# runs). Rules get what they depend on as `params` (canonical JSON without the fields at their
# defaults: physmorph.settings.workflow.params_json), so changing a setting reruns
# exactly the jobs that use it. Every output lives under results/{profile}/.
# The helper functions are in common.py beside this file (Snakemake puts this folder on sys.path).
from common import ResultTree, SlurmGuard, VolumeWarnings, folder_of_first_output, folder_of_input, mb
from common import check_user_shapes, morph_runtime_min
from physmorph.settings.workflow import Settings
from physmorph.settings.params import morph_params, params_json, without_defaults
from physmorph.settings.memory_model import particle_estimate
from physmorph.settings.memory_model import morph_memory, sampling_memory, target_memory
from physmorph.reports.metrics import TABLE_NAMES as TABLES, FIGURE_NAMES as FIGURES
from physmorph.reports.layout import load_layout
from physmorph.reports.export.columns import MEASURE_COLUMNS
from physmorph.reports.export.viewer import BUNDLE as VIEWER_BUNDLE
from physmorph.meshes.fetch import sha256_of
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate
from physmorph.meshes.particles import stored_particle_count
from physmorph.settings.study_points import tradeoff_points
from pathlib import Path
import yaml

# The merged config is checked against the schema generated from the settings' declarations
# (python -m physmorph.settings --schema); where it refuses, the settings say why in their own words,
# naming the key and the allowed values.
try:
    validate(config, "../schemas/config.schema.yaml", set_default=False)
except WorkflowError:
    Settings.from_mapping(config)
    raise
S = Settings.from_mapping(config)
# a user's own meshes: what their jobs would refuse stops here, in one line, before any job
check_user_shapes(S)
# every rule's conda environment under --use-conda (workflow/envs/make_env.py writes both from the locks)
CONDA_ENV = "../envs/physmorph_cuda.yaml" if S.device == "cuda" else "../envs/physmorph.yaml"
POINTS = tradeoff_points(S) if S.tradeoff is not None else {}
# the experiments of config/config.yaml (the shipped ones): a full run that another config file adds is exported too
BASE_EXPERIMENTS = set((yaml.safe_load(Path("config/config.yaml").read_text()) or {}).get("experiments") or {})
RESULTS = ResultTree(S, POINTS, BASE_EXPERIMENTS)
R = RESULTS.root  # this profile's result tree, results/{profile}
# the main table's runs (physics-only and full per target, config/paper_results.yaml): `paper_main`
MAIN_EXPERIMENTS = [n for c in load_layout("config/paper_results.yaml").tables.main.values()
                    for n in (c.physics_only, c.full)]
# ... their targets, and the figures drawn from those six runs alone (results/{profile}/main_figures/)
MAIN_TARGETS = sorted({S.experiment(n).target for n in MAIN_EXPERIMENTS})
MAIN_FIGURES = ("sequences_main", "optimization_traces")
FULL_RUNS = RESULTS.full_runs  # what the export stage exports
EXPORT_RUNS = RESULTS.export_runs  # `snakemake export`: export.experiments, or the tables' and the user's full runs

# bound to the plain names the rules call
raw_mesh_path = RESULTS.raw_mesh_path
particles_path = RESULTS.particles_path
target_path = RESULTS.target_path
table_inputs = RESULTS.table_inputs
figure_outputs = RESULTS.figure_outputs
export_outputs = RESULTS.export_outputs
viewer_inputs = RESULTS.viewer_inputs
experiment_source = RESULTS.experiment_source
point_target = RESULTS.point_target
point_settings = RESULTS.point_settings
# an input function: a dry run names a morph whose target holds another volume than its source
morph_particles = VolumeWarnings(RESULTS).morph_particles
SLURM = SlurmGuard(workflow)
cluster_threads = SLURM.cluster_threads


wildcard_constraints:
    shape=r"[A-Za-z][A-Za-z0-9]*",
    res=r"\d+x\d+x\d+",
    file=r"[^/]+",
    experiment=r"[A-Za-z0-9_]+",


# under the SLURM executor, a job no node of its partition can hold stops the run before anything is submitted
onstart:
    SLURM.check_jobs()
