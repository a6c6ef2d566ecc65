# Stage 1: raw benchmark meshes, downloaded from their pinned URL (or copied from a local
# mirror when `mesh_dir` is set) and checked against their SHA-256.
rule fetch_mesh:
    output:
        "resources/meshes/{file}",
    params:
        source=lambda wc: PM["raw_meshes"][wc.file],
        mesh_dir=PM.get("mesh_dir"),
    script:
        "../scripts/fetch_mesh.py"
