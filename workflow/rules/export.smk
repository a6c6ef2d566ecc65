# Stage 8: what a user takes away from a run (physmorph.reports.export, docs/outputs.md "Exports"): for
# every full-method run of the profile a video of every frame (MP4 and WebM), the body's closed
# surface at each saved frame (PLY, the last also GLB) with what it shows measured, its Gaussians
# as 3D Gaussian splatting PLY files, and one viewer page over them all. `snakemake --cores 2 export`.
# The video keys of `export` are the video rules' params and the surface keys the mesh rules', so
# editing one reruns only those jobs (and the viewer).
rule export:  # videos, surface meshes, splat files and a viewer of the full-method runs
    input:
        export_outputs(),


rule export_video:
    input:
        run=f"{R}/runs/{{experiment}}.h5",
        particles=lambda wc: particles_path(S.experiment(wc.experiment).source),
        target_mesh=lambda wc: f"{R}/meshes/{S.experiment(wc.experiment).target}.h5",
    output:
        mp4=f"{R}/videos/{{experiment}}.mp4",
        webm=f"{R}/videos/{{experiment}}.webm",
        stills=directory(f"{R}/videos/{{experiment}}_stills"),
    params:
        # the video keys, and the mesh keys that make the surface it draws (none when it draws the particles)
        video=params_json({**S.export.video(), **S.export.video_surface()}),
        target=params_json(S.target),
    log:
        f"{R}/logs/export/{{experiment}}_video.log",
    benchmark:
        f"{R}/benchmarks/export/{{experiment}}_video.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    conda:
        CONDA_ENV
    script:
        "../scripts/export_video.py"


rule export_meshes:
    input:
        run=f"{R}/runs/{{experiment}}.h5",
        particles=lambda wc: particles_path(S.experiment(wc.experiment).source),
        source_mesh=lambda wc: f"{R}/meshes/{S.experiment(wc.experiment).source}.h5",
        target_mesh=lambda wc: f"{R}/meshes/{S.experiment(wc.experiment).target}.h5",
    output:
        directory(f"{R}/meshes/{{experiment}}"),
    wildcard_constraints:
        experiment="|".join(FULL_RUNS) or "^$",
    params:
        mesh=params_json(S.export.mesh()),
        # what measures.csv holds: a new measure reruns the mesh jobs (and the tables after them)
        measures=",".join(MEASURE_COLUMNS),
    log:
        f"{R}/logs/export/{{experiment}}_meshes.log",
    benchmark:
        f"{R}/benchmarks/export/{{experiment}}_meshes.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    conda:
        CONDA_ENV
    script:
        "../scripts/export_meshes.py"


rule export_splats:
    input:
        run=f"{R}/runs/{{experiment}}.h5",
        target_mesh=lambda wc: f"{R}/meshes/{S.experiment(wc.experiment).target}.h5",
    output:
        directory(f"{R}/splats/{{experiment}}"),
    params:
        frame=params_json({"frame": S.export.frame}),
    log:
        f"{R}/logs/export/{{experiment}}_splats.log",
    benchmark:
        f"{R}/benchmarks/export/{{experiment}}_splats.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../scripts/export_splats.py"


rule export_viewer:  # the page over every exported run
    input:
        **viewer_inputs(EXPORT_RUNS),
    output:
        f"{R}/viewer/index.html",
    params:
        names=EXPORT_RUNS,
        profile=S.profile,
    log:
        f"{R}/logs/export/viewer.log",
    benchmark:
        f"{R}/benchmarks/export/viewer.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../scripts/export_viewer.py"


use rule export_viewer as export_viewer_run with:  # one run's own page (what `physmorph morph` opens)
    input:
        unpack(lambda wc: viewer_inputs([wc.experiment])),
    output:
        f"{R}/viewer/{{experiment}}.html",
    wildcard_constraints:
        experiment="|".join(FULL_RUNS) or "^$",
    params:
        names=lambda wc: [wc.experiment],
        profile=S.profile,
        title=lambda wc: f"physmorph: {wc.experiment}, the {S.profile} profile",
    log:
        f"{R}/logs/export/{{experiment}}_viewer.log",
    benchmark:
        f"{R}/benchmarks/export/{{experiment}}_viewer.tsv"


rule export_viewer_data:  # a run's 3D view: every saved frame's surface, the target's, the last frame's splats
    input:
        run=f"{R}/runs/{{experiment}}.h5",
        meshes=f"{R}/meshes/{{experiment}}",
        target_mesh=lambda wc: f"{R}/meshes/{S.experiment(wc.experiment).target}.h5",
    output:
        f"{R}/viewer/data/{{experiment}}.js",
    wildcard_constraints:
        experiment="|".join(FULL_RUNS) or "^$",
    log:
        f"{R}/logs/export/{{experiment}}_viewer_data.log",
    benchmark:
        f"{R}/benchmarks/export/{{experiment}}_viewer_data.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../scripts/export_viewer_data.py"


rule export_viewer_bundle:  # the 3D view's script beside the pages (three.js and Spark, vendored)
    output:
        f"{R}/viewer/viewer3d.js",
    params:
        # a new bundle reruns the copy (and the pages after it)
        sha256=sha256_of(VIEWER_BUNDLE) if VIEWER_BUNDLE.exists() else "missing",
    log:
        f"{R}/logs/export/viewer_bundle.log",
    benchmark:
        f"{R}/benchmarks/export/viewer_bundle.tsv"
    threads: 1
    resources:
        mem_mb=500,
        runtime=5,
    conda:
        CONDA_ENV
    script:
        "../scripts/export_viewer_bundle.py"
