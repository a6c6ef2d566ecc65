from physmorph.reports.export.stage import viewer_data_stage

viewer_data_stage(snakemake.wildcards.experiment, snakemake.input.run, snakemake.input.meshes,
                  snakemake.input.target_mesh, snakemake.output[0], log=snakemake.log[0])
