# physmorph workflow entry point. Stages live in workflow/rules/*.smk, one per stage; each rule
# runs a thin script in workflow/scripts/ that calls one physmorph function, in the conda environment
# workflow/envs/physmorph.yaml under --use-conda. The rules' helper functions are in workflow/rules/common.py.
# Outputs go to results/{profile}/ (the config's `profile`), so profiles never share a file.
configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"


rule all:
    input:
        table_inputs(),
        figure_outputs(),


rule tables:
    input:
        table_inputs(),


rule figures:
    input:
        figure_outputs(),


rule paper_main:  # the main table's six runs, their tables and figures, results/{profile}/main_{tables,figures}/
    input:
        f"{R}/main_tables/main.md",
        f"{R}/main_tables/convergence.md",
        f"{R}/main_tables/directions.md",
        f"{R}/main_tables/timing.md",
        expand(f"{R}/main_figures/{{figure}}.png", figure=MAIN_FIGURES),


rule results_page:
    input:
        f"{R}/results.md",


rule tradeoff:
    input:
        f"{R}/tradeoff/tradeoff.md",
        f"{R}/tradeoff/pareto.png",


rule stability_map:  # the extremes, one setting at a time (docs/stability.md), results/{profile}/stability_map/
    input:
        f"{R}/stability_map/stability_map.md",
        f"{R}/stability_map/stability_map.png",


include: "workflow/rules/fetch_mesh.smk"
include: "workflow/rules/prepare_mesh.smk"
include: "workflow/rules/sample_particles.smk"
include: "workflow/rules/rasterize_target.smk"
include: "workflow/rules/morph.smk"
include: "workflow/rules/tables.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/tradeoff.smk"
include: "workflow/rules/results_doc.smk"
include: "workflow/rules/stability_map.smk"
include: "workflow/rules/export.smk"
