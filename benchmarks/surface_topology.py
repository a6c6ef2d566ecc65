"""How a run's final surface's topology depends on how the surface is drawn, and how wide its tunnels are.

    python benchmarks/surface_topology.py RUN.h5 PARTICLES.h5 [--frame F] [--pitches 0.1 0.25 0.4 0.5]

RUN.h5 a run file, PARTICLES.h5 its source particles (results/{profile}/particles/...). For a saved
frame (the last by default) it prints the (components, genus) of the surface that
physmorph.reports.export.surface draws at the export's settings and at other refine / pore-closing
pairs (SETTINGS), then that export-setting surface voxelised at each pitch (trimesh's surface voxels,
filled: conservative, so a thin part stays solid) with its solid's pieces, tunnels and cavities. A
tunnel that is counted at a pitch of a tenth of a cell and gone at half a cell is narrower than the
surface's own grid draws stably; a hole a viewer sees (a torus's, a letter's) stays at a cell.
"""

from __future__ import annotations

import argparse

import trimesh

from physmorph.reports.export.body import components_and_genus, voxel_topology
from physmorph.reports.export.runs import frame_state, saved_frames
from physmorph.reports.export.surface import particle_surface
from physmorph.settings.export import ExportConfig

# (refine, pore_closing) pairs the surface is drawn with besides the export's own
SETTINGS = ((2.0, 4), (2.0, 5), (3.0, 3), (3.0, 4), (1.5, 3))


def export_surface(state: dict) -> trimesh.Trimesh:
    """The surface of ``state`` (frame_state) as the export draws it."""
    return particle_surface(state["x"], state["volume"], state["det_F"], state["dx"], **ExportConfig().surface())


def settings_topology(state: dict, settings=SETTINGS,
                      exported: trimesh.Trimesh | None = None) -> list[tuple[float, int, int, int]]:
    """(refine, pore_closing, components, genus) of the surface of ``state`` (frame_state) drawn at
    the export's settings first (``exported`` where it is drawn already), then at each of ``settings``."""
    export = ExportConfig()
    first = export_surface(state) if exported is None else exported
    rows = [(export.refine, export.pore_closing, *components_and_genus(first))]
    for refine, closing in settings:
        mesh = particle_surface(state["x"], state["volume"], state["det_F"], state["dx"], refine=refine,
                                smooth_iterations=export.smooth_iterations, pore_closing=closing)
        rows.append((refine, closing, *components_and_genus(mesh)))
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("particles")
    ap.add_argument("--frame", type=int, default=None, help="a saved frame (default: the last)")
    ap.add_argument("--pitches", type=float, nargs="+", default=[0.1, 0.25, 0.4, 0.5],
                    help="voxel pitches, in domain units")
    args = ap.parse_args(argv)
    frame = saved_frames(args.run)[-1] if args.frame is None else args.frame
    state = frame_state(args.run, frame, args.particles)
    print(f"{args.run}, frame {frame}, dx {state['dx']:g}")
    mesh = export_surface(state)
    for refine, closing, components, genus in settings_topology(state, exported=mesh):
        print(f"  surface at refine {refine:g}, pore closing {closing}: {components} piece(s), genus {genus}")
    for pitch in args.pitches:
        pieces, tunnels, cavities = voxel_topology(mesh, pitch)
        print(f"  the export's surface in voxels of {pitch:g} ({pitch / state['dx']:.2f} dx): {pieces} piece(s), "
              f"{tunnels} tunnel(s), {cavities} cavit{'y' if cavities == 1 else 'ies'}")


if __name__ == "__main__":
    main()
