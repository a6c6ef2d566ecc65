from physmorph.reports.stages import results_doc_stage

results_doc_stage(snakemake.params.tables_dir, snakemake.params.figures_dir, snakemake.output[0],
                  snakemake.params.profile, log=snakemake.log[0])
