from physmorph.reports.export.stage import splats_stage

splats_stage(snakemake.input.run, snakemake.params.frame, snakemake.input.target_mesh, snakemake.output[0],
             log=snakemake.log[0])
