# Stage 5: one morph experiment (paper Algorithm 1) -> results/{profile}/runs/{experiment}.h5.
# params.settings is the run's resolved settings (what its method reads): changing any of them
# reruns this experiment, and nothing else. A killed run resumes from its last committed frame in {output}.partial/.
rule morph:
    input:
        # (an input function: evaluated while the DAG is built, so it also warns about a target of
        # another volume than its source before any job, in a dry run too)
        particles=morph_particles,
        target=lambda wc: target_path(S.experiment(wc.experiment).target),
    output:
        f"{R}/runs/{{experiment}}.h5",
    params:
        settings=lambda wc: morph_params(S.experiment_config(wc.experiment)),
        experiment=lambda wc: params_json(S.experiment(wc.experiment)),
        name=lambda wc: wc.experiment,
        # the target's configured size: a target of another volume than its source is warned
        # about with the size that would hold it (physmorph.meshes.fit.volume_mismatch)
        target_size=lambda wc: S.shape(S.experiment(wc.experiment).target).size,
    log:
        f"{R}/logs/morph/{{experiment}}.log",
    benchmark:
        f"{R}/benchmarks/morph/{{experiment}}.tsv"
    threads: cluster_threads("morph", S.threads)
    resources:
        # from the sampled particle count once the particles exist (the estimate before)
        mem_mb=lambda wc, input, threads: mb(morph_memory(experiment_source(wc.experiment), S.sampling, S.target, S.mpm,
                                                          S.domain, "", stored_particle_count(input.particles), threads)),
        runtime=lambda wc, input: morph_runtime_min(
            stored_particle_count(input.particles)
            or particle_estimate(experiment_source(wc.experiment), S.sampling, S.domain),
            S.experiment_config(wc.experiment).frames),
        gpu=S.morph_gpus,
    conda:
        CONDA_ENV
    script:
        "../scripts/morph.py"
