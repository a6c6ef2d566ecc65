# The stability map of the extremes (physmorph.extremes, docs/stability.md): the base experiment
# with one setting at a time at its limit, each cell run in its own process under a wall-clock
# limit and classified (converged, not converged, warned, refused, stopped; never a crash or a hang).
# A cell's config is checked as the workflow checks any config: a refused cell needs no inputs and
# its job only records the refusal; an accepted one samples, rasterizes and morphs in its own files
# (runs/{cell}/), so a stage's refusal or failure is recorded as the cell's outcome. `snakemake --cores 2 stability_map --configfile config/test.yaml`.
from physmorph.config import canonical_json
from physmorph.extremes import MAP_EXPERIMENT, cell_mapping, cell_timeout_s, check_cell, map_cells

STABILITY_CELLS = map_cells(config) if MAP_EXPERIMENT in S.experiments else {}
STABILITY_DIR = f"{R}/stability_map"
_STABILITY_CHECKS = {}


def stability_check(cell):
    """The cell's config check (physmorph.extremes.CellCheck), made once per cell."""
    if cell not in _STABILITY_CHECKS:
        _STABILITY_CHECKS[cell] = check_cell(cell_mapping(config, STABILITY_CELLS[cell]))
    return _STABILITY_CHECKS[cell]


def stability_inputs(wildcards):
    """The prepared meshes of a cell's source and target (its job samples and rasterizes them at its
    own resolution); none for a cell the config refuses."""
    s = stability_check(wildcards.cell).settings
    if s is None:
        return {}
    exp = s.experiment(MAP_EXPERIMENT)
    return {"source_mesh": f"{R}/meshes/{exp.source}.h5", "target_mesh": f"{R}/meshes/{exp.target}.h5"}


def stability_particles(cell):
    """The estimated particle count of an accepted cell (0 for a refused one)."""
    s = stability_check(cell).settings
    return 0 if s is None else particle_estimate(s.shape(s.experiment(MAP_EXPERIMENT).source), s.sampling, s.domain)


def stability_threads(wildcards):
    """One thread for a small cell (two run side by side), the profile's threads above 20K particles."""
    return cluster_threads("stability_cell", S.threads if stability_particles(wildcards.cell) > 20000 else 1)(wildcards)


def stability_mem_mb(wildcards):
    s = stability_check(wildcards.cell).settings
    if s is None:
        return 1000
    return mb(max(s.memory_estimates(), key=lambda e: e.mb))


def stability_runtime_min(wildcards):
    s = stability_check(wildcards.cell).settings
    if s is None:
        return 5
    cfg = s.experiment_config(MAP_EXPERIMENT)
    return int(cell_timeout_s(stability_particles(wildcards.cell), cfg.frames + cfg.release_frames + 2) / 60) + 5


rule stability_cell:
    input:
        unpack(stability_inputs),
    output:
        f"{STABILITY_DIR}/cells/{{cell}}.json",
    wildcard_constraints:
        cell=r"[A-Za-z0-9_.+-]+",
    params:
        cell=lambda wc: canonical_json(STABILITY_CELLS[wc.cell]),
        mapping=lambda wc: canonical_json(cell_mapping(config, STABILITY_CELLS[wc.cell])),
        work_dir=lambda wc: f"{STABILITY_DIR}/runs/{wc.cell}",  # its particles, target and run
    log:
        f"{R}/logs/stability_map/{{cell}}.log",
    benchmark:
        f"{R}/benchmarks/stability_map/{{cell}}.tsv"
    threads: stability_threads
    resources:
        mem_mb=stability_mem_mb,
        runtime=stability_runtime_min,
    script:
        "../scripts/stability_cell.py"


rule make_stability_map:
    input:
        cells=expand(f"{STABILITY_DIR}/cells/{{cell}}.json", cell=list(STABILITY_CELLS)),
    output:
        csv=report(f"{STABILITY_DIR}/stability_map.csv", caption="../report/stability_map.rst", category="Stability"),
        md=f"{STABILITY_DIR}/stability_map.md",
        png=report(f"{STABILITY_DIR}/stability_map.png", caption="../report/stability_map.rst", category="Stability"),
    params:
        out_dir=STABILITY_DIR,
        title=f"stability map, profile {S.profile}: {MAP_EXPERIMENT}, one setting at a time from the default (bold)",
    log:
        f"{R}/logs/make_stability_map.log",
    benchmark:
        f"{R}/benchmarks/make_stability_map.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    script:
        "../scripts/make_stability_map.py"
