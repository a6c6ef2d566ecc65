"""The workflow's helper functions, kept out of the snakefiles so that none mixes rules and functions.

workflow/rules/common.smk builds these once from the merged config and binds the names the rules
use (particles_path, cluster_threads, stability_inputs, ...). Only the workflow imports this module
(Snakemake puts workflow/rules/ on sys.path when it includes common.smk); the physmorph library
never imports Snakemake.
"""

import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.logging import logger

from physmorph.base.cluster import (
    ClusterError,
    JobRequest,
    cap_threads,
    check_account,
    check_job,
    check_status,
    job_threads_here,
    read_cluster,
)
from physmorph.reports.metrics import FIGURE_NAMES, TABLE_NAMES
from physmorph.settings.memory_model import (
    SECONDS_PER_PARTICLE_FRAME,
    particle_estimate,
)
from physmorph.studies.extremes import cell_mapping, cell_timeout_s, check_cell
from physmorph.studies.stability_map import MAP_EXPERIMENT


def mb(estimate):
    """A memory estimate (physmorph.settings.workflow's MemoryEstimate) as a rule's whole mem_mb."""
    return int(estimate.mb) + 1


def morph_runtime_min(n_particles, frames):
    """Minutes for a morph: physmorph.settings.workflow.SECONDS_PER_PARTICLE_FRAME on a CPU, x2 margin."""
    return int(10 + 2 * frames * n_particles * SECONDS_PER_PARTICLE_FRAME / 60)


class ResultTree:
    """The files of one profile, results/{profile}/ (``root``), and the shapes and experiments
    behind them (``settings``: physmorph.settings.workflow.Settings; ``points``: the tradeoff study's points)."""

    def __init__(self, settings, points, base_experiments=()):
        self.settings = settings
        self.points = points
        self.root = f"results/{settings.profile}"
        self.res = settings.sampling.tag
        # what the export stage can export, and of those what `snakemake export` asks for: export.experiments,
        # else the tables' full runs and the full runs that config files beside config/config.yaml add
        # (``base_experiments``: the experiments config/config.yaml has), a user's own
        self.full_runs = [n for n in settings.experiments if settings.experiment(n).method == "full"]
        own = [n for n in self.full_runs if n in settings.tables.experiments or n not in base_experiments]
        self.export_runs = list(settings.export.experiments) or own

    def raw_mesh_path(self, shape):
        spec = self.settings.shape(shape)
        if spec.kind != "file":
            return []
        return spec.path if spec.path is not None else f"resources/meshes/{spec.file}"

    def particles_path(self, shape, res=None):
        """``res``: a resolution tag (default the profile's, settings.sampling.tag)."""
        return f"{self.root}/particles/{shape}_{self.res if res is None else res}.h5"

    def target_path(self, shape, res=None, image=None):
        """``image``: an image-size tag, for a target at another image size than the profile's."""
        image_tag = "" if image is None else f"_{image}"
        return f"{self.root}/targets/{shape}_{self.res if res is None else res}{image_tag}.h5"

    def table_inputs(self):
        s = self.settings
        sources, targets = set(s.tables.shapes), set(s.tables.shapes)  # the listed shapes: both, for the previews
        for name in s.tables.experiments:
            exp = s.experiment(name)
            sources.add(exp.source)
            targets.add(exp.target)
        runs = [f"{self.root}/runs/{name}.h5" for name in s.tables.experiments]
        tables = [f"{self.root}/tables/{t}.md" for t in TABLE_NAMES] if runs else []
        data = [self.particles_path(shape) for shape in sorted(sources)] + [self.target_path(shape) for shape in sorted(targets)]
        return data + runs + tables

    def figure_outputs(self):
        return [f"{self.root}/figures/{f}.png" for f in FIGURE_NAMES] if self.settings.tables.experiments else []

    def export_outputs(self):
        out = [f"{self.root}/viewer/index.html"]
        for name in self.export_runs:
            out += self.run_exports(name)
        return out

    def run_exports(self, name):
        """What the export stage makes of one full run: its video, meshes, splats and its own viewer page."""
        r = self.root
        return [f"{r}/videos/{name}.mp4", f"{r}/videos/{name}.webm", f"{r}/meshes/{name}", f"{r}/splats/{name}",
                f"{r}/viewer/{name}.html"]

    def viewer_inputs(self, names):
        """A viewer page's inputs over the runs ``names``: run files, videos, stills, measures, their 3D
        view data, and the 3D view's script."""
        r = self.root
        return {"runs": [f"{r}/runs/{n}.h5" for n in names], "mp4s": [f"{r}/videos/{n}.mp4" for n in names],
                "webms": [f"{r}/videos/{n}.webm" for n in names], "stills": [f"{r}/videos/{n}_stills" for n in names],
                "measures": [f"{r}/meshes/{n}" for n in names], "data": [f"{r}/viewer/data/{n}.js" for n in names],
                "bundle": f"{r}/viewer/viewer3d.js"}

    def experiment_source(self, name):
        return self.settings.shape(self.settings.experiment(name).source)

    def point_target(self, point):
        s, p = self.settings, self.points[point]
        exp = s.experiment(s.tradeoff.experiment)
        image = None if (p.width, p.height) == (s.target.width, s.target.height) else p.image_tag
        return self.target_path(exp.target, p.res_tag, image)

    def point_settings(self, point):
        return self.settings.point_config(self.points[point])


class VolumeWarnings:
    """A dry run names the experiments whose target holds another volume than their source (the
    morph's log says it too, with the volumes of the prepared shapes)."""

    def __init__(self, tree: ResultTree):
        self.tree = tree
        self.volumes = {}  # shape -> its volume before any job (or None)
        self.warned = set()  # experiments already warned about

    def raw_mesh_here(self, shape):
        """The raw mesh of a file shape where it is on disk before any job (the download or the mirror)."""
        from physmorph.meshes.fit import raw_mesh_on_disk

        return raw_mesh_on_disk(self.tree.settings, shape)

    def morph_particles(self, wc):
        """The experiment's source particles (the morph rule's input); on the first call for an
        experiment whose target holds another volume than its source, the warning its morph log will
        give, while the DAG is built (so a dry run says it before any job)."""
        from physmorph.meshes.fit import (
            volume_warnings,  # imports trimesh: only once a morph is planned
        )

        s = self.tree.settings
        if wc.experiment not in self.warned:
            self.warned.add(wc.experiment)
            for line in volume_warnings(s, [wc.experiment], lambda shape: f"{self.tree.root}/meshes/{shape}.h5",
                                        self.raw_mesh_here, self.volumes):
                logger.warning(f"warning: {line}")
        return self.tree.particles_path(s.experiment(wc.experiment).source)


def check_user_shapes(settings):
    """A user's own meshes (file shapes given by path), before any job: what their prepare_mesh or
    sample_particles job would refuse stops the workflow here in that one line (status 2); what it
    would accept but not do well is warned."""
    if not any(spec.kind == "file" and spec.path is not None for spec in settings.shapes.values()):
        return  # (no trimesh import for the shipped shapes alone)
    from physmorph.meshes.fit import target_cameras
    from physmorph.meshes.user_shapes import user_shape_report

    warnings, refusal = user_shape_report(settings, target_cameras(settings))
    for line in warnings:
        logger.warning(f"warning: {line}")
    if refusal is not None:
        print(refusal, file=sys.stderr)
        raise SystemExit(2)


def folder_of_first_output(wildcards, output):
    """The folder of a rule's first output (a params function, so the prefix follows the outputs
    wherever a storage provider puts them, instead of naming results/{profile}/... again)."""
    return str(Path(output[0]).parent)


def folder_of_input(name):
    """A params function: the folder of the rule's input ``name`` (its first file), None where that
    input holds no file (derived from the input files, as folder_of_first_output)."""
    def input_folder(wildcards, input):
        files = input.get(name) or []
        files = [files] if isinstance(files, str) else list(files)
        return str(Path(files[0]).parent) if files else None
    return input_folder


# ---- SLURM (workflow/profiles/slurm; docs/cluster.md). Under the SLURM executor a rule's threads
# are capped at the CPUs of the largest node of its partition, and before anything is submitted
# every job is checked against its partition (CPUs, memory, GPUs, time limit), and the way the
# executor reads job states against the cluster's settings: a job no node can hold stops the run
# with an error naming the setting, instead of pending for ever. Other executors are untouched.
class SlurmGuard:
    """``workflow``: the Snakemake workflow (its executor, resource settings and DAG)."""

    def __init__(self, workflow):
        self.workflow = workflow
        self._cluster = None

    def executor(self):
        plugin = self.workflow.executor_plugin
        return None if plugin is None else plugin.name

    def cli_resource(self, rname, name):
        """A resource given on the command line or in the profile (--set-resources, else --default-resources)."""
        rs = self.workflow.resource_settings
        for mapping in (rs.overwrite_resources.get(rname), rs.default_resources):
            value = mapping.get(name) if mapping is not None else None
            value = getattr(value, "raw", value)  # a snakemake Resource: its value as given
            if isinstance(value, str) and value.strip("'\""):
                return value.strip("'\"")
        return None

    def cluster(self):
        if self._cluster is None:
            try:
                self._cluster = read_cluster()
            except ClusterError as exc:
                raise WorkflowError(f"the SLURM executor cannot read this cluster: {exc}")
        return self._cluster

    def cluster_threads(self, rname, threads):
        """The rule's threads (a callable for `threads:`): `threads` as given; with the SLURM executor at
        most the CPUs of the largest node of the rule's partition; inside a SLURM job at most its CPUs."""
        def rule_threads(wildcards):
            executor = self.executor()
            if executor == "slurm":
                try:
                    return cap_threads(threads, self.cluster().partition(self.cli_resource(rname, "slurm_partition")))
                except ClusterError:
                    return threads  # an unknown partition is reported by check_jobs, naming it
            if executor == "slurm-jobstep":
                return job_threads_here(threads)
            return threads
        return rule_threads

    def _source(self, rname, name, default):
        overwrite = self.workflow.resource_settings.overwrite_resources
        if rname in overwrite and overwrite[rname].get(name) is not None:
            return f"--set-resources {rname}:{name}"
        return default

    def _request(self, job):
        """The job's request (physmorph.base.cluster.JobRequest), each resource with the setting it comes from."""
        rname, res = job.rule.name, job.resources
        overwrite_threads = self.workflow.resource_settings.overwrite_threads
        label = f"{rname} ({', '.join(f'{v}' for v in job.wildcards_dict.values())})" if job.wildcards_dict else rname
        threads_from = (f"--set-threads {rname}={job.threads}" if rname in overwrite_threads
                        else f"--set-resources {rname}:cpus_per_task" if res.get("cpus_per_task")
                        else f"the {rname} rule's threads")
        mem_from = ("its memory estimate (from sampling.*, target.*: a smaller profile)"
                    if rname in ("morph", "tradeoff_point") else f"the {rname} rule's mem_mb")
        return JobRequest(
            label=label, rule=rname, threads=int(res.get("cpus_per_task") or job.threads),
            mem_mb=_known(res.get("mem_mb")), gpus=_known(res.get("gpu")) or 0,
            runtime_min=_known(res.get("runtime")), partition=res.get("slurm_partition"),
            threads_from=threads_from,
            mem_from=self._source(rname, "mem_mb", mem_from),
            gpus_from=self._source(rname, "gpu", "config key 'morph_gpus'"),
            runtime_from=self._source(rname, "runtime", f"the {rname} rule's runtime estimate"))

    def check_jobs(self):
        """Every job to run fits a node of its partition, and the executor can see jobs end."""
        if self.executor() != "slurm":
            return
        cluster = self.cluster()
        problems, account = [], None
        for job in self.workflow.dag.needrun_jobs():
            if job.is_local or job.is_norun:  # run by snakemake itself, not submitted
                continue
            problems += check_job(self._request(job), cluster)
            account = account or job.resources.get("slurm_account")
        status = check_status(cluster, getattr(self.workflow.executor_settings, "status_command", None))
        if status:
            problems.append(status)
        if problems:
            raise WorkflowError("these jobs could never start on this SLURM cluster (nothing was submitted):\n  - "
                                + "\n  - ".join(problems))
        note = check_account(cluster, account)
        if note:
            logger.warning(note)


def _known(value):
    """A resource's number, or None where it is not known before the job's inputs exist."""
    return value if isinstance(value, int) and not isinstance(value, bool) else None


class StabilityCells:
    """The cells of the stability map (workflow/rules/stability_map.smk): ``cells`` name -> Cell
    (physmorph.studies.extremes.map_cells) around the merged ``config``; ``root`` the profile's result tree."""

    def __init__(self, config, settings, root, cells, slurm: SlurmGuard):
        self.config = config
        self.settings = settings
        self.root = root
        self.cells = cells
        self.slurm = slurm
        self._checks = {}

    def check(self, cell):
        """The cell's config check (physmorph.studies.extremes.CellCheck), made once per cell."""
        if cell not in self._checks:
            self._checks[cell] = check_cell(cell_mapping(self.config, self.cells[cell]))
        return self._checks[cell]

    def inputs(self, wildcards):
        """The prepared meshes of a cell's source and target (its job samples and rasterizes them at its
        own resolution); none for a cell the config refuses."""
        s = self.check(wildcards.cell).settings
        if s is None:
            return {}
        exp = s.experiment(MAP_EXPERIMENT)
        return {"source_mesh": f"{self.root}/meshes/{exp.source}.h5",
                "target_mesh": f"{self.root}/meshes/{exp.target}.h5"}

    def particles(self, cell):
        """The estimated particle count of an accepted cell (0 for a refused one)."""
        s = self.check(cell).settings
        return 0 if s is None else particle_estimate(s.shape(s.experiment(MAP_EXPERIMENT).source), s.sampling, s.domain)

    def threads(self, wildcards):
        """One thread for a small cell (two run side by side), the profile's threads above 20K particles."""
        threads = self.settings.threads if self.particles(wildcards.cell) > 20000 else 1
        return self.slurm.cluster_threads("stability_cell", threads)(wildcards)

    def mem_mb(self, wildcards):
        s = self.check(wildcards.cell).settings
        if s is None:
            return 1000
        return mb(max(s.memory_estimates(), key=lambda e: e.mb))

    def runtime_min(self, wildcards):
        s = self.check(wildcards.cell).settings
        if s is None:
            return 5
        cfg = s.experiment_config(MAP_EXPERIMENT)
        return int(cell_timeout_s(self.particles(wildcards.cell), cfg.frames + cfg.release_frames + 2) / 60) + 5
