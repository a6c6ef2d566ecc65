"""Stages 1-2: fetch raw benchmark meshes and turn them into clean, watertight, normalised solids.

fetch_mesh
    Download (or copy from a local mirror) one raw mesh file and verify its SHA-256. The file is
    written to ``<dest>.partial`` and renamed only after the checksum matches, so a failure never
    leaves a file that looks finished.

prepare_mesh
    Load an OBJ/GLB (or build a procedural shape: the isosphere, extruded letters), repair it into
    a watertight solid, centre its bounding box on the origin and scale its longest extent to
    ``ShapeSpec.size`` (the paper's assets are ~14-20 units across in the [-16, 16]^3 domain).

Repair order (the first step that yields a watertight mesh wins; every step is logged in the
output's ``repair`` attribute):

1. merge vertices ignoring UV/normal differences (Spot and Duck are split along UV seams),
   drop degenerate and duplicate faces, fix winding/normals, fill small holes (trimesh);
2. MeshFix (pymeshfix) for holes trimesh cannot close (the Bunny's base);
3. a generalized-winding-number remesh: marching cubes of the winding-number field of the
   triangle soup (oriented outward first), which is well defined for open or self-intersecting
   input; its output is closed, consistently wound and of positive volume whenever the field has
   an inside.

A repaired mesh must keep its volume within ``volume_tolerance`` of the raw mesh's
(divergence-theorem) volume, so a repair that silently drops components or caps a shape wrongly
is an error, not a quiet change of shape; after the remesh, less what that volume counts twice
where the raw surface overlaps itself. A refusal (MeshError) names the file or shape and the
check that failed; the fit helper and the prepare_mesh job end on it in one line, exit status 2.

Modules: ``fetch`` (stage 1), ``shapes`` (specs, procedural shapes), ``repair`` (loading and
repair), ``point_cloud`` (a point cloud's closed surface, which loading builds for a file of points),
``prepare`` (stage 2: normalise, write, read), ``mesh_record`` (a raw mesh measured once repaired,
kept in a cache), ``fit`` (the size helper: ``python -m physmorph.meshes.fit MESH``),
``user_shapes`` (what a dry run says of a user's meshes), ``particles`` (stage 3: particle sampling).

May import physmorph.records, physmorph.settings and physmorph.base.
"""
