# Shared helpers. The merged config is turned into typed, frozen settings once (physmorph.config:
# the one validator; every experiment resolved and a memory estimate checked before any job
# runs). Rules get what they depend on as `params` (canonical JSON without the fields at their
# defaults: physmorph.config.params_json), so changing a setting reruns
# exactly the jobs that use it. Every output lives under results/{profile}/.
import sys
from pathlib import Path

from physmorph.config import Settings, morph_params, params_json, particle_estimate, without_defaults
from physmorph.config import SECONDS_PER_PARTICLE_FRAME, morph_memory, sampling_memory, target_memory
from physmorph.metrics import TABLE_NAMES as TABLES, FIGURE_NAMES as FIGURES
from physmorph.layout import load_layout
from physmorph.particles import stored_particle_count
from physmorph.tradeoff import tradeoff_points

S = Settings.from_mapping(config)
R = f"results/{S.profile}"  # this profile's result tree
RES = S.sampling.tag
POINTS = tradeoff_points(S) if S.tradeoff is not None else {}
# the main table's runs (physics-only and full per target, config/paper_results.yaml): `paper_main`
MAIN_EXPERIMENTS = [n for c in load_layout("config/paper_results.yaml").tables.main.values()
                    for n in (c.physics_only, c.full)]
# ... their targets, and the figures drawn from those six runs alone (results/{profile}/main_figures/)
MAIN_TARGETS = sorted({S.experiment(n).target for n in MAIN_EXPERIMENTS})
MAIN_FIGURES = ("sequences_main", "optimization_traces")
FULL_RUNS = [n for n in S.experiments if S.experiment(n).method == "full"]  # what the export stage exports
EXPORT_RUNS = [n for n in S.tables.experiments if n in FULL_RUNS]  # `snakemake export`: the tables' full runs


wildcard_constraints:
    shape=r"[A-Za-z][A-Za-z0-9]*",
    res=r"\d+x\d+x\d+",
    file=r"[^/]+",
    experiment=r"[A-Za-z0-9_]+",


def raw_mesh_path(shape):
    spec = S.shape(shape)
    if spec.kind != "file":
        return []
    return spec.path if spec.path is not None else f"resources/meshes/{spec.file}"


# A dry run names the experiments whose target holds another volume than their source (the morph's
# log says it too, with the volumes of the prepared shapes).
def _raw_mesh_here(shape):
    """The raw mesh of a file shape where it is on disk before any job (the download or the mirror)."""
    spec = S.shape(shape)
    if spec.kind != "file" or spec.path is not None:
        return raw_mesh_path(shape) or None
    local = Path(raw_mesh_path(shape))
    return local if local.is_file() or not S.mesh_dir else Path(S.mesh_dir) / spec.file


_VOLUMES = {}  # shape -> its volume before any job (or None), for morph_particles' warnings
_VOLUME_WARNED = set()


def morph_particles(wc):
    """The experiment's source particles (the morph rule's input); on the first call for an
    experiment whose target holds another volume than its source, the warning its morph log will
    give, while the DAG is built (so a dry run says it before any job)."""
    from physmorph.meshes.fit import volume_warnings

    exp = S.experiment(wc.experiment)
    if wc.experiment not in _VOLUME_WARNED:
        _VOLUME_WARNED.add(wc.experiment)
        for line in volume_warnings(S, [wc.experiment], lambda shape: f"{R}/meshes/{shape}.h5", _raw_mesh_here,
                                    _VOLUMES):
            logger.warning(f"warning: {line}")
    return particles_path(exp.source)


def particles_path(shape, res=RES):
    return f"{R}/particles/{shape}_{res}.h5"


def target_path(shape, res=RES, image=None):
    return f"{R}/targets/{shape}_{res}{'' if image is None else '_' + image}.h5"


def table_inputs():
    shapes = set(S.tables.shapes)
    for name in S.tables.experiments:
        exp = S.experiment(name)
        shapes.update([exp.source, exp.target])
    runs = [f"{R}/runs/{name}.h5" for name in S.tables.experiments]
    tables = [f"{R}/tables/{t}.md" for t in TABLES] if runs else []
    return [p for s in sorted(shapes) for p in (particles_path(s), target_path(s))] + runs + tables


def figure_outputs():
    return [f"{R}/figures/{f}.png" for f in FIGURES] if S.tables.experiments else []


def mb(estimate):
    return int(estimate.mb) + 1


def morph_runtime_min(n_particles, frames):
    """Minutes for a morph: physmorph.config.SECONDS_PER_PARTICLE_FRAME on a CPU, x2 margin."""
    return int(10 + 2 * frames * n_particles * SECONDS_PER_PARTICLE_FRAME / 60)


def experiment_source(name):
    return S.shape(S.experiment(name).source)


def point_target(point):
    p = POINTS[point]
    exp = S.experiment(S.tradeoff.experiment)
    image = None if (p.width, p.height) == (S.target.width, S.target.height) else p.image_tag
    return target_path(exp.target, p.res_tag, image)


def point_settings(point):
    return S.point_config(POINTS[point])


# ---- SLURM (workflow/profiles/slurm; docs/cluster.md). Under the SLURM executor a rule's threads
# are capped at the CPUs of the largest node of its partition, and before anything is submitted
# every job is checked against its partition (CPUs, memory, GPUs, time limit), and the way the
# executor reads job states against the cluster's settings: a job no node can hold stops the run with an error naming the setting, instead of
# pending for ever. Other executors are untouched.
from physmorph.cluster import ClusterError, JobRequest, cap_threads, check_account, check_job, check_status
from physmorph.cluster import job_threads_here, read_cluster
from snakemake.exceptions import WorkflowError
from snakemake.logging import logger

_SLURM = {}


def _executor():
    plugin = workflow.executor_plugin
    return None if plugin is None else plugin.name


def _cli_resource(rname, name):
    """A resource given on the command line or in the profile (--set-resources, else --default-resources)."""
    rs = workflow.resource_settings
    for mapping in (rs.overwrite_resources.get(rname), rs.default_resources):
        value = mapping.get(name) if mapping is not None else None
        value = getattr(value, "raw", value)  # a snakemake Resource: its value as given
        if isinstance(value, str) and value.strip("'\""):
            return value.strip("'\"")
    return None


def slurm_cluster():
    if "cluster" not in _SLURM:
        try:
            _SLURM["cluster"] = read_cluster()
        except ClusterError as exc:
            raise WorkflowError(f"the SLURM executor cannot read this cluster: {exc}")
    return _SLURM["cluster"]


def cluster_threads(rname, threads):
    """The rule's threads (a callable for `threads:`): `threads` as given; with the SLURM executor at
    most the CPUs of the largest node of the rule's partition; inside a SLURM job at most its CPUs."""
    def rule_threads(wildcards):
        executor = _executor()
        if executor == "slurm":
            try:
                return cap_threads(threads, slurm_cluster().partition(_cli_resource(rname, "slurm_partition")))
            except ClusterError:
                return threads  # an unknown partition is reported by check_slurm_jobs, naming it
        if executor == "slurm-jobstep":
            return job_threads_here(threads)
        return threads
    return rule_threads


def _source(rname, name, default):
    if rname in workflow.resource_settings.overwrite_resources and \
            workflow.resource_settings.overwrite_resources[rname].get(name) is not None:
        return f"--set-resources {rname}:{name}"
    return default


def _known(value):
    """A resource's number, or None where it is not known before the job's inputs exist."""
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def check_slurm_jobs():
    """Every job to run fits a node of its partition, and the executor can see jobs end."""
    if _executor() != "slurm":
        return
    cluster = slurm_cluster()
    problems, account = [], None
    for job in workflow.dag.needrun_jobs():
        if job.is_local or job.is_norun:  # run by snakemake itself, not submitted
            continue
        rname, res = job.rule.name, job.resources
        label = f"{rname} ({', '.join(f'{v}' for v in job.wildcards_dict.values())})" if job.wildcards_dict else rname
        threads_from = (f"--set-threads {rname}={job.threads}" if rname in workflow.resource_settings.overwrite_threads
                        else f"--set-resources {rname}:cpus_per_task" if res.get("cpus_per_task") else f"the {rname} rule's threads")
        estimate = "its memory estimate (from sampling.*, target.*: a smaller profile)"
        problems += check_job(JobRequest(
            label=label, rule=rname, threads=int(res.get("cpus_per_task") or job.threads),
            mem_mb=_known(res.get("mem_mb")), gpus=_known(res.get("gpu")) or 0,
            runtime_min=_known(res.get("runtime")), partition=res.get("slurm_partition"),
            threads_from=threads_from,
            mem_from=_source(rname, "mem_mb", estimate if rname in ("morph", "tradeoff_point") else f"the {rname} rule's mem_mb"),
            gpus_from=_source(rname, "gpu", "config key 'morph_gpus'"),
            runtime_from=_source(rname, "runtime", f"the {rname} rule's runtime estimate")), cluster)
        account = account or res.get("slurm_account")
    status = check_status(cluster, getattr(workflow.executor_settings, "status_command", None))
    if status:
        problems.append(status)
    if problems:
        raise WorkflowError("these jobs could never start on this SLURM cluster (nothing was submitted):\n  - "
                            + "\n  - ".join(problems))
    note = check_account(cluster, account)
    if note:
        logger.warning(note)


onstart:
    check_slurm_jobs()


def export_outputs():
    out = [f"{R}/viewer/index.html"]
    for name in EXPORT_RUNS:
        out += [f"{R}/videos/{name}.mp4", f"{R}/videos/{name}.webm", f"{R}/meshes/{name}", f"{R}/splats/{name}"]
    return out
