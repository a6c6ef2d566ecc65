# A refused mesh ends the log in one line and the job with status 2 (physmorph.stages.prepare_mesh_job).
from physmorph.stages import prepare_mesh_job

prepare_mesh_job(snakemake.wildcards.shape, snakemake.params.spec, next(iter(snakemake.input), None),
                 snakemake.output[0], domain=snakemake.params.domain, log=snakemake.log[0],
                 raw_sha256=snakemake.params.raw_sha256)
