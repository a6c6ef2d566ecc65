from physmorph.reports.stages import tables_stage

exported = {n: d for n, d in zip([n for n in snakemake.params.names if n in snakemake.params.full], snakemake.input.exported)}
tables_stage(snakemake.params.names, snakemake.input.runs, snakemake.input.layout, snakemake.params.out_dir,
             log=snakemake.log[0], exported=exported, noise=snakemake.params.noise)
