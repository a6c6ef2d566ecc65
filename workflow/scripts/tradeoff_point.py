from physmorph.stages import tradeoff_point_stage

tradeoff_point_stage(snakemake.config, snakemake.wildcards.point, snakemake.input.particles,
                     snakemake.input.target, snakemake.output[0])
