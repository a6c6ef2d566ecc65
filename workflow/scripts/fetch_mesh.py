from physmorph.stages import fetch_mesh_stage

fetch_mesh_stage(snakemake.output[0], snakemake.params.source, snakemake.config.get("mesh_dir"), log=snakemake.log[0])
