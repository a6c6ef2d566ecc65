"""The release rebound with the last frame's velocity kept and released from rest (as the morph's
release probe does), with and without the absorbed shape (docs/study/log.md finding 112).

    python benchmarks/release_velocity_probe.py --eta 0.05                 # the test profile, iso -> bunny full
    python benchmarks/release_velocity_probe.py --eta 0.1 --profile config/test.yaml

Needs the profile's prepared particles and target under results/{profile}/ (e.g. `snakemake
--cores 2 results/test/particles/iso_32x1x1.h5 results/test/targets/bunny_32x1x1.h5 --configfile
config/test.yaml`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path


from physmorph.morph import loop as morph
from physmorph.settings.workflow import load_settings
from physmorph.reports.metrics import release_rebound_percent
from physmorph.morph.loop import morph_config, run_morph
from physmorph.records.runfile import read_metrics
from physmorph.records.runfile import partial_dir

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eta", type=float, required=True)
    ap.add_argument("--profile", default="config/test.yaml")
    ap.add_argument("--experiment", default="iso_bunny_full")
    ap.add_argument("--release-frames", type=int, default=12)
    ap.add_argument("--workdir", default="/tmp/physmorph_release_probe")
    args = ap.parse_args()
    cfg = load_settings(REPO / "config/config.yaml", REPO / args.profile, overrides={"plasticity": {"eta": args.eta}})
    exp, tag = cfg.experiment(args.experiment), cfg.sampling.tag
    parts = REPO / "results" / cfg.profile / "particles" / f"{exp.source}_{tag}.h5"
    target = REPO / "results" / cfg.profile / "targets" / f"{exp.target}_{tag}.h5"
    real = morph.release_curve
    for at_rest in (False, True):
        def release(solver, st, frames, alpha_mse, log, name, _at_rest=at_rest):
            return real(solver, st, frames, alpha_mse, log, name, keep_velocity=not _at_rest)

        morph.release_curve = release
        for absorb in (True, False):
            mc = morph_config(cfg, args.experiment)
            mc = dataclasses.replace(mc, progress=False, release_frames=args.release_frames,
                                     plasticity=dataclasses.replace(mc.plasticity, absorb_control=absorb))
            out = Path(args.workdir) / f"v{'0' if at_rest else 'kept'}_absorb{int(absorb)}.h5"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.unlink(missing_ok=True)
            shutil.rmtree(partial_dir(out), ignore_errors=True)
            run_morph(parts, target, out, mc, name=args.experiment, log=lambda m: None)
            m = read_metrics(out)
            r = release_rebound_percent(m["alpha_mse"], json.loads(m["attrs"]["release_alpha_mse"]))
            print(f"eta {args.eta}, released {'from rest' if at_rest else 'with its velocity'}, "
                  f"absorbed shape {'yes' if absorb else 'no'}: closed {m['gap_closed'][-1]:.3f}, rebound {r:.1f} %",
                  flush=True)
    morph.release_curve = real


if __name__ == "__main__":
    main()
