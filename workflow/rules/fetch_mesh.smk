# Stage 1: raw benchmark meshes, downloaded from their pinned URL (or copied from a local
# mirror when `mesh_dir` is set) and checked against their SHA-256. Shared by every profile.
# (A shape given by `path` is read where it is, with no fetch.)
rule fetch_mesh:
    output:
        "resources/meshes/{file}",
    # Only the source (URL and SHA-256: what the file is) is a param. Where a mirror lies
    # (`mesh_dir`) changes no byte of the output, so the script reads it from the config: a
    # profile run with a mirror must not make every other profile's runs rerun.
    params:
        source=lambda wc: params_json(S.raw_meshes[wc.file]),
    log:
        f"{R}/logs/fetch_mesh/{{file}}.log",
    benchmark:
        f"{R}/benchmarks/fetch_mesh/{{file}}.tsv"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../scripts/fetch_mesh.py"
