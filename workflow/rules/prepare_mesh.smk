# Stage 2: load, repair, verify watertight, normalise into the simulation domain.
rule prepare_mesh:
    input:
        raw=lambda wc: raw_mesh_path(wc.shape),
    output:
        "results/meshes/{shape}.h5",
    params:
        spec=lambda wc: shape_entry(PM, wc.shape),
        # the raw mesh is verified against its checksum again: it may have changed since it was fetched
        raw_sha256=lambda wc: PM["raw_meshes"].get(shape_entry(PM, wc.shape).get("file") or "", {}).get("sha256"),
    benchmark:
        "results/benchmarks/prepare_mesh/{shape}.tsv"
    script:
        "../scripts/prepare_mesh.py"
