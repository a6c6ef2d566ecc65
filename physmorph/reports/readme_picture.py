"""README.md's opening picture: the video of the default profile's best-looking honest run as a
GIF, and its caption with that run's numbers, both made by ``python -m physmorph.reports.userdocs
results default``.

Honest: of the profile's full runs that have a video, those that end at 95 % of their gap or more,
with the target's genus where both are measured; best-looking: of those, the highest volume IoU
at the last frame (the body a person sees), else the largest share of the gap.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

PICTURE = Path("docs/images/morph.gif")
MARKER = "<!-- the opening picture and its caption: made by `python -m physmorph.reports.userdocs results default` -->"
ARRIVED_PERCENT = 95.0  # the share of the gap a run must close at its last frame to be shown


def pick_run(convergence_csv: Path, videos_dir: Path) -> pd.Series | None:
    """The convergence table's row of the run to show (None: no full run with a video)."""
    table = pd.read_csv(convergence_csv)
    runs = table[(table["method"] == "full") & table["experiment"].map(lambda n: (videos_dir / f"{n}.mp4").exists())]
    if runs.empty:
        return None
    arrived = runs[runs["closed_final_%"] >= ARRIVED_PERCENT]
    if "genus" in arrived and "target_genus" in arrived:
        known = arrived["genus"].notna() & arrived["target_genus"].notna()
        arrived = arrived[~known | (arrived["genus"] == arrived["target_genus"])]
    if arrived.empty:
        return runs.sort_values("closed_final_%", ascending=False).iloc[0]
    return arrived.sort_values(["volume_iou_final", "closed_final_%"], ascending=False).iloc[0]


def caption(row: pd.Series, source: str, target: str, profile: str) -> str:
    text = (f"{source} -> {target}, the {profile} profile: {row['closed_final_%']:.0f} % of the gap closed at the "
            "last frame")
    if math.isfinite(float(row.get("volume_iou_final", math.nan))):
        text += f", volume IoU {row['volume_iou_final']:.2f}"
    return text + "; the body's smoothed surface (left) beside the target (right), every frame"


def update_readme_picture(readme: Path, text: str, picture: Path = PICTURE) -> None:
    """Put ``![text](picture)`` on the line after the README's MARKER (added after the title when missing)."""
    lines = Path(readme).read_text().split("\n")
    image = f"![{text}]({picture.as_posix()})"
    if MARKER in lines:
        i = lines.index(MARKER)
        if i + 1 < len(lines) and lines[i + 1].startswith("!["):
            lines[i + 1] = image
        else:
            lines.insert(i + 1, image)
    else:
        old = next((k for k, line in enumerate(lines) if line.startswith("![")), None)
        if old is not None:
            lines[old:old + 1] = [MARKER, image]
        else:
            lines[1:1] = ["", MARKER, image]
    Path(readme).write_text("\n".join(lines))
