from physmorph.stages import tradeoff_stage

tradeoff_stage(snakemake.config, snakemake.params.names, snakemake.input.runs, "results/tradeoff")
