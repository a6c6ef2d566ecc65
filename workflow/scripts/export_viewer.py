from physmorph.reports.export.stage import viewer_stage

viewer_stage(snakemake.params.names, snakemake.input.runs, snakemake.input.mp4s, snakemake.input.webms or None,
             snakemake.input.stills, [f"{d}/measures.csv" for d in snakemake.input.measures], snakemake.output[0],
             snakemake.params.profile, title=snakemake.params.get("title"), data=snakemake.input.data,
             bundle=snakemake.input.bundle, log=snakemake.log[0])
