from physmorph.stages import morph_stage

morph_stage(snakemake.params.settings, snakemake.params.name, snakemake.input.particles, snakemake.input.target,
            snakemake.output[0], threads=snakemake.threads, log=snakemake.log[0], experiment=snakemake.params.experiment,
            target_size=snakemake.params.target_size)
