"""How well the transport plan's destinations themselves fill a target: the volume IoU
(physmorph.morph.quality.volume_metrics) of the source's particles placed at their destinations.

    python benchmarks/plan_destinations.py letters iso B,R,K,G [--blurs 1,0.5]

For each target of the profile (results/{profile}/particles and targets prepared), the plan the
plasticity and the push use (physmorph.plasticity.transport.destinations_in_grid_mass) at each blur
in cells, read off by both projections (plasticity.transport_projection): barycentric, the mean of
a source node's plan row interpolated to its particles, and sampled, a target node drawn from it.
A push that carries the particles onto their destinations ends near these numbers.
"""

from __future__ import annotations

import argparse

from physmorph.meshes.particles import load_particles
from physmorph.morph.quality import volume_metrics
from physmorph.morph.targets import load_target
from physmorph.plasticity.transport import destinations_in_grid_mass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("profile")
    ap.add_argument("source")
    ap.add_argument("targets", help="comma-separated")
    ap.add_argument("--blurs", default="1,0.5", help="the plan's blur in cells, comma-separated")
    ap.add_argument("--tag", default=None, help="the sampling tag (default: 32x2x1, or 64x2x1 for mid)")
    args = ap.parse_args()
    tag = args.tag or ("64x2x1" if args.profile.startswith("mid") else "32x2x1")
    parts = load_particles(f"results/{args.profile}/particles/{args.source}_{tag}.h5")
    for name in args.targets.split(","):
        target = load_target(f"results/{args.profile}/targets/{name}_{tag}.h5")
        cells = []
        for blur in (float(b) for b in args.blurs.split(",")):
            iou = [volume_metrics(destinations_in_grid_mass(parts.x, parts.mass, target.grid_mass, target.grid, blur,
                                                            projection=projection),
                                  parts.mass, target.grid_mass, target.grid)["volume_iou"]
                   for projection in ("barycentric", "sampled")]
            cells.append(f"blur {blur:g}: barycentric {iou[0]:.3f}, sampled {iou[1]:.3f}")
        print(f"{args.source} -> {name}: " + "; ".join(cells), flush=True)


if __name__ == "__main__":
    main()
