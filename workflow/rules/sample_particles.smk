# Stage 3: shell-biased volumetric particle sampling at resolution {res} = grid x ppc_s x ppc_i.
rule sample_particles:
    input:
        f"{R}/meshes/{{shape}}.h5",
    output:
        h5=f"{R}/particles/{{shape}}_{{res}}.h5",
        png=f"{R}/previews/particles/{{shape}}_{{res}}.png",
    params:
        sampling=lambda wc: params_json(S.sampling.with_tag(wc.res)),
        seed=lambda wc: S.particle_seed(wc.shape),
    log:
        f"{R}/logs/sample_particles/{{shape}}_{{res}}.log",
    benchmark:
        f"{R}/benchmarks/sample_particles/{{shape}}_{{res}}.tsv"
    threads: 1
    resources:
        mem_mb=lambda wc: mb(sampling_memory(S.shape(wc.shape), S.sampling.with_tag(wc.res), S.domain, "")),
        runtime=30,
    conda:
        CONDA_ENV
    script:
        "../scripts/sample_particles.py"
