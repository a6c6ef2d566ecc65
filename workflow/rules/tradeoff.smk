# The speed/accuracy study: the base experiment with one knob changed at a time (physmorph.studies.tradeoff).
rule rasterize_target_image:
    # A target at another image size than the profile's (for the image-size knob).
    input:
        f"{R}/meshes/{{shape}}.h5",
    output:
        h5=f"{R}/targets/{{shape}}_{{res}}_{{img}}.h5",
        png=f"{R}/previews/targets/{{shape}}_{{res}}_{{img}}.png",
    wildcard_constraints:
        img=r"\d+x\d+",
    params:
        sampling=lambda wc: params_json(S.sampling.with_tag(wc.res)),
        target=lambda wc: params_json(S.target.__class__(**{**S.target.__dict__, "width": int(wc.img.split("x")[0]),
                                                                "height": int(wc.img.split("x")[1])})),
        seed=S.seed,
        render=params_json(S.render.__class__(**{**S.render.__dict__, "device": "cpu"})),
    log:
        f"{R}/logs/rasterize_target/{{shape}}_{{res}}_{{img}}.log",
    benchmark:
        f"{R}/benchmarks/rasterize_target/{{shape}}_{{res}}_{{img}}.tsv"
    threads: cluster_threads("rasterize_target_image", S.threads)
    resources:
        mem_mb=lambda wc: mb(target_memory(S.sampling.with_tag(wc.res), S.target, "")),
        runtime=30,
    conda:
        CONDA_ENV
    script:
        "../scripts/rasterize_target.py"


rule tradeoff_point:
    input:
        particles=lambda wc: particles_path(S.experiment(S.tradeoff.experiment).source, POINTS[wc.point].res_tag),
        target=lambda wc: point_target(wc.point),
    output:
        f"{R}/tradeoff/runs/{{point}}.h5",
    wildcard_constraints:
        point=r"[A-Za-z0-9_.x-]+",
    params:
        settings=lambda wc: morph_params(point_settings(wc.point)[2]),
        experiment=lambda wc: params_json({"tradeoff_point": wc.point, **without_defaults(S.experiment(S.tradeoff.experiment))}),
        name=lambda wc: f"tradeoff {wc.point}",
        target_size=lambda wc: S.shape(S.experiment(S.tradeoff.experiment).target).size,
    log:
        f"{R}/logs/tradeoff/{{point}}.log",
    benchmark:
        f"{R}/benchmarks/tradeoff/{{point}}.tsv"
    threads: lambda wc: cluster_threads("tradeoff_point", POINTS[wc.point].threads)(wc)
    resources:
        mem_mb=lambda wc, threads: mb(morph_memory(experiment_source(S.tradeoff.experiment), point_settings(wc.point)[0],
                                                   point_settings(wc.point)[1], point_settings(wc.point)[2].mpm, S.domain, "",
                                                   threads=threads)),
        runtime=lambda wc: morph_runtime_min(particle_estimate(experiment_source(S.tradeoff.experiment),
                                                               point_settings(wc.point)[0], S.domain), POINTS[wc.point].frames),
        gpu=S.morph_gpus,
    conda:
        CONDA_ENV
    script:
        "../scripts/morph.py"


rule make_tradeoff:
    input:
        runs=expand(f"{R}/tradeoff/runs/{{point}}.h5", point=list(POINTS)),
    output:
        csv=report(f"{R}/tradeoff/tradeoff.csv", caption="../report/tradeoff.rst", category="Speed / accuracy"),
        md=f"{R}/tradeoff/tradeoff.md",
        png=report(f"{R}/tradeoff/pareto.png", caption="../report/pareto.rst", category="Speed / accuracy"),
    params:
        names=list(POINTS),
        points=params_json(POINTS),
        out_dir=folder_of_first_output,
        domain_width=S.domain[1] - S.domain[0],
    log:
        f"{R}/logs/make_tradeoff.log",
    benchmark:
        f"{R}/benchmarks/make_tradeoff.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../scripts/make_tradeoff.py"
