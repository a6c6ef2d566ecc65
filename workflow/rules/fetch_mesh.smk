# Stage 1: raw benchmark meshes, downloaded from their pinned URL (or copied from a local
# mirror when `mesh_dir` is set) and checked against their SHA-256. Shared by every profile.
# (A shape given by `path` is read where it is, with no fetch.)
rule fetch_mesh:
    output:
        "resources/meshes/{file}",
    params:
        source=lambda wc: params_json(S.raw_meshes[wc.file]),
        mesh_dir=S.mesh_dir,
    log:
        f"{R}/logs/fetch_mesh/{{file}}.log",
    benchmark:
        f"{R}/benchmarks/fetch_mesh/{{file}}.tsv"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    script:
        "../scripts/fetch_mesh.py"
