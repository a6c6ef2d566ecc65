# Stage 3: shell-biased volumetric particle sampling at resolution {res} = grid x ppc_s x ppc_i.
rule sample_particles:
    input:
        "results/meshes/{shape}.h5",
    output:
        h5="results/particles/{shape}_{res}.h5",
        png="results/previews/particles/{shape}_{res}.png",
    params:
        sampling=lambda wc: SamplingConfig.from_tag(wc.res, PM),
        seed=PM.get("seed", 0),
    benchmark:
        "results/benchmarks/sample_particles/{shape}_{res}.tsv"
    script:
        "../scripts/sample_particles.py"
