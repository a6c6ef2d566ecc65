from physmorph.studies.extremes import cell_stage

cell_stage(snakemake.params.cell, snakemake.params.mapping, snakemake.input.get("source_mesh"),
           snakemake.input.get("target_mesh"), snakemake.output[0], snakemake.params.work_dir, threads=snakemake.threads,
           log=snakemake.log[0])
