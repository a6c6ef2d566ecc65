from physmorph.stages import sample_particles_stage

sample_particles_stage(snakemake.input[0], snakemake.output.h5, snakemake.output.png, snakemake.params.sampling,
                       snakemake.params.seed, log=snakemake.log[0])
