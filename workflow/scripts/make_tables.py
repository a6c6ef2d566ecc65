from physmorph.stages import tables_stage

tables_stage(snakemake.params.names, snakemake.input.runs, snakemake.input.layout, snakemake.params.out_dir,
             log=snakemake.log[0])
