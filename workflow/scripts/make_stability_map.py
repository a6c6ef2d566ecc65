from physmorph.studies.extremes import map_stage

map_stage(snakemake.input.cells, snakemake.params.out_dir, snakemake.params.title, log=snakemake.log[0])
