from physmorph.reports.export.stage import video_stage

video_stage(snakemake.input.run, snakemake.input.target_mesh, snakemake.params.target, snakemake.params.video,
            snakemake.output.mp4, snakemake.output.webm or None, snakemake.output.stills, log=snakemake.log[0],
            particles_h5=snakemake.input.particles)
