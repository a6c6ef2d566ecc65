# Stage 2: load, repair, verify watertight, normalise into the simulation domain.
rule prepare_mesh:
    input:
        raw=lambda wc: raw_mesh_path(wc.shape),
    output:
        f"{R}/meshes/{{shape}}.h5",
    params:
        spec=lambda wc: params_json(S.shape(wc.shape)),
        domain=list(S.domain),
        # the raw mesh is verified against its checksum again: it may have changed since it was fetched
        raw_sha256=lambda wc: S.raw_meshes[S.shape(wc.shape).file].sha256 if S.shape(wc.shape).file else None,
    log:
        # a refused mesh (missing, unreadable, flat, irreparable, ...) ends it in one line saying why; the job exits 2
        f"{R}/logs/prepare_mesh/{{shape}}.log",
    benchmark:
        f"{R}/benchmarks/prepare_mesh/{{shape}}.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../scripts/prepare_mesh.py"
