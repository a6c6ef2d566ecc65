from physmorph.stages import tradeoff_stage

tradeoff_stage(snakemake.params.points, snakemake.params.names, snakemake.input.runs, snakemake.params.out_dir,
               log=snakemake.log[0])
