from physmorph.stages import tables_stage

tables_stage(snakemake.params.names, snakemake.input.runs, "results/tables")
