from physmorph.reports.export.stage import viewer_bundle_stage

viewer_bundle_stage(snakemake.output[0], log=snakemake.log[0])
