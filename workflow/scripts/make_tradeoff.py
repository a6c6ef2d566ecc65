from physmorph.reports.stages import tradeoff_stage

tradeoff_stage(snakemake.params.points, snakemake.params.names, snakemake.input.runs, snakemake.params.out_dir,
               domain_width=snakemake.params.domain_width, log=snakemake.log[0])
