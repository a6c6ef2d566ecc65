from physmorph.reports.export.stage import meshes_stage

meshes_stage(snakemake.input.run, snakemake.input.particles, snakemake.input.source_mesh, snakemake.input.target_mesh,
             snakemake.params.mesh, snakemake.output[0], log=snakemake.log[0])
