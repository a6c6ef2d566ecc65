from physmorph.stages import morph_stage

morph_stage(snakemake.config, snakemake.wildcards.experiment, snakemake.input.particles,
            snakemake.input.target, snakemake.output[0])
