# Stage 2: load, repair, verify watertight, normalise into the simulation domain.
rule prepare_mesh:
    input:
        raw=lambda wc: raw_mesh_path(wc.shape),
    output:
        "results/meshes/{shape}.h5",
    params:
        spec=lambda wc: shape_entry(PM, wc.shape),
    benchmark:
        "results/benchmarks/prepare_mesh/{shape}.tsv"
    script:
        "../scripts/prepare_mesh.py"
