# Stage 4: per-camera target alpha/depth/SDT, target grid mass and surface points.
rule rasterize_target:
    input:
        "results/meshes/{shape}.h5",
    output:
        h5="results/targets/{shape}_{res}.h5",
        png="results/previews/targets/{shape}_{res}.png",
    params:
        sampling=lambda wc: SamplingConfig.from_tag(wc.res, PM),
        seed=PM.get("seed", 0),
        render=PM.get("render", {}),  # the renderer of the ceiling (the target's own particles at rest)
    benchmark:
        "results/benchmarks/rasterize_target/{shape}_{res}.tsv"
    script:
        "../scripts/rasterize_target.py"
