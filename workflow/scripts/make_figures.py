from physmorph.stages import figures_stage

figures_stage(snakemake.params.names, snakemake.input.runs, snakemake.params.shapes, snakemake.input.targets,
              snakemake.config["target"], "results/figures")
