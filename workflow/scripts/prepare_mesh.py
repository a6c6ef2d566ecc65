from physmorph.stages import prepare_mesh_stage

raw = snakemake.input.raw
prepare_mesh_stage(snakemake.wildcards.shape, snakemake.params.spec, raw[0] if len(raw) else None, snakemake.output[0])
