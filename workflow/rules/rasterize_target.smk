# Stage 4: per-camera target alpha/depth/SDT, target grid mass and surface points, and the
# ceiling (the target's own particles rendered at rest, with the render section's settings).
rule rasterize_target:
    input:
        f"{R}/meshes/{{shape}}.h5",
    output:
        h5=f"{R}/targets/{{shape}}_{{res}}.h5",
        png=f"{R}/previews/targets/{{shape}}_{{res}}.png",
    params:
        sampling=lambda wc: params_json(S.sampling.with_tag(wc.res)),
        target=params_json(S.target),
        seed=S.seed,
        render=params_json(S.render.__class__(**{**S.render.__dict__, "device": "cpu"})),
    log:
        f"{R}/logs/rasterize_target/{{shape}}_{{res}}.log",
    benchmark:
        f"{R}/benchmarks/rasterize_target/{{shape}}_{{res}}.tsv"
    threads: cluster_threads("rasterize_target", S.threads)
    resources:
        mem_mb=lambda wc: mb(target_memory(S.sampling.with_tag(wc.res), S.target, "")),
        runtime=30,
    conda:
        CONDA_ENV
    script:
        "../scripts/rasterize_target.py"
