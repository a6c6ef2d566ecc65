from physmorph.reports.stages import figures_stage

figures_stage(snakemake.params.names, snakemake.input.runs, snakemake.params.shapes, snakemake.input.targets,
              snakemake.params.target, snakemake.input.layout, snakemake.params.out_dir, log=snakemake.log[0],
              figures=snakemake.params.get("figures"))
