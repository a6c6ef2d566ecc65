from physmorph.stages import rasterize_target_stage

rasterize_target_stage(snakemake.input[0], snakemake.output.h5, snakemake.output.png, snakemake.params.sampling,
                       snakemake.params.target, snakemake.params.seed, render=snakemake.params.render,
                       log=snakemake.log[0], threads=snakemake.threads)
