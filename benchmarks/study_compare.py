"""Compare study runs (benchmarks/study_convergence.py writes them to <workdir>/<tag>/<exp>.h5):
the paper's matched-convergence comparison between a baseline run and others.

    python benchmarks/study_compare.py BASE.h5 OTHER.h5 [OTHER.h5 ...]

For each run: alpha MSE at frame 0 / best / final, the share of the reachable gap closed, and the
alpha MSE at the frame where BASE reached 90 % of its total improvement (the paper's matched
convergence, Table 2) with the improvement over BASE there (positive: lower error than BASE), the
in-run rebound and, for runs with release frames, the release rebound.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from physmorph.reports.metrics import improvement_percent, matched_convergence_frame, rebound_percent, release_rebound_percent
from physmorph.morph.quality import gap_closed
from physmorph.records.runfile import read_metrics


def main(paths: list[str]) -> None:
    runs = [(p, read_metrics(p)) for p in paths]
    base = runs[0][1]["alpha_mse"]
    k = matched_convergence_frame(base)
    print(f"matched frame (baseline {paths[0]} at 90 % of its improvement): {k}")
    for p, m in runs:
        a = m["alpha_mse"]
        c = float(m["attrs"]["ceiling_alpha_mse"])
        kk = min(k, len(a) - 1)
        print(f"{p}: a0 {a[0]:.4f} best {np.nanmin(a):.4f} final {a[-1]:.4f} "
              f"closed best/final {100 * gap_closed(a[0], np.nanmin(a), c):.1f}/{100 * gap_closed(a[0], a[-1], c):.1f} % "
              f"at matched frame {a[kk]:.4f} ({improvement_percent(base[kk], a[kk]):+.1f} % vs baseline) "
              f"in-run rebound {rebound_percent(a):.1f} %", end="")
        if "release_alpha_mse" in m["attrs"]:
            release = json.loads(m["attrs"]["release_alpha_mse"])
            print(f", released {len(release) - 1} frames: rebound {release_rebound_percent(a, release):.1f} %", end="")
        print()


if __name__ == "__main__":
    main(sys.argv[1:])
