"""Turn exported surfaces around: each mesh (an exported final.glb or frame PLY) drawn from above,
below and two oblique sides, one row per mesh, into one PNG (matplotlib, flat-shaded).

    python benchmarks/surface_views.py OUT.png MESH [MESH ...]

The views are of the mesh's own axes (an exported GLB is in the input mesh's frame): a letter's
glyph faces the first two, its extrusion shows in the other two.
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib
import numpy as np
import trimesh

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

VIEWS = ((90, -90), (-90, -90), (40, -60), (-40, -120))  # (elevation, azimuth), degrees
LIGHT = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])


def draw_row(fig, row: int, rows: int, mesh: trimesh.Trimesh, label: str) -> None:
    """One mesh from every view of VIEWS, centred, at one scale."""
    v = mesh.vertices - mesh.vertices.mean(axis=0)
    r = float(np.abs(v).max())
    shade = 0.35 + 0.65 * np.clip(mesh.face_normals @ LIGHT, 0.0, 1.0)
    for i, (elevation, azimuth) in enumerate(VIEWS):
        ax = fig.add_subplot(rows, len(VIEWS), row * len(VIEWS) + i + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(v[mesh.faces], facecolors=plt.cm.copper(shade), edgecolor="none"))
        ax.set_xlim(-r, r), ax.set_ylim(-r, r), ax.set_zlim(-r, r)
        ax.view_init(elevation, azimuth)
        ax.set_axis_off()
        ax.set_title(f"{label}: elevation {elevation}, azimuth {azimuth}", fontsize=8)


def main(argv: list[str]) -> None:
    out, *paths = argv
    fig = plt.figure(figsize=(4 * len(VIEWS), 4 * len(paths)))
    for row, path in enumerate(paths):
        draw_row(fig, row, len(paths), trimesh.load(path, force="mesh"), Path(path).parent.name or Path(path).stem)
    fig.savefig(out, dpi=60, bbox_inches="tight")
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1:])
