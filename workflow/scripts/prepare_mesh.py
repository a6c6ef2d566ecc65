from physmorph.stages import prepare_mesh_stage

prepare_mesh_stage(snakemake.wildcards.shape, snakemake.params.spec, next(iter(snakemake.input), None),
                   snakemake.output[0], domain=snakemake.params.domain, log=snakemake.log[0],
                   raw_sha256=snakemake.params.raw_sha256)
