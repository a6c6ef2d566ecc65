# The stability map of the extremes (physmorph.studies.extremes, docs/stability.md): the base experiment
# with one setting at a time at its limit, each cell run in its own process under a wall-clock
# limit and classified (converged, not converged, warned, refused, stopped; never a crash or a hang).
# A cell's config is checked as the workflow checks any config: a refused cell needs no inputs and
# its job only records the refusal; an accepted one samples, rasterizes and morphs in its own files
# (runs/{cell}/), so a stage's refusal or failure is recorded as the cell's outcome. `snakemake --cores 2 stability_map --configfile config/test.yaml`.
from common import StabilityCells
from physmorph.settings.params import canonical_json
from physmorph.studies.stability_map import MAP_EXPERIMENT
from physmorph.studies.extremes import cell_mapping, map_cells

STABILITY_CELLS = map_cells(config) if MAP_EXPERIMENT in S.experiments else {}
STABILITY_DIR = f"{R}/stability_map"
STABILITY = StabilityCells(config, S, R, STABILITY_CELLS, SLURM)  # each cell's config check, inputs and resources


rule stability_cell:
    input:
        unpack(STABILITY.inputs),
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
    threads: STABILITY.threads
    resources:
        mem_mb=STABILITY.mem_mb,
        runtime=STABILITY.runtime_min,
    conda:
        CONDA_ENV
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
        out_dir=folder_of_first_output,
        title=f"stability map, profile {S.profile}: {MAP_EXPERIMENT}, one setting at a time from the default (bold)",
    log:
        f"{R}/logs/make_stability_map.log",
    benchmark:
        f"{R}/benchmarks/make_stability_map.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../scripts/make_stability_map.py"
