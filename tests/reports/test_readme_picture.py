"""README.md's opening picture (physmorph.reports.readme_picture): the run shown is an honest one
(its gap closed, its target's genus) and, of those, the one whose body is closest to the target's;
its caption carries its numbers; the README line is replaced, not added twice."""

import pandas as pd

from physmorph.reports.readme_picture import MARKER, caption, pick_run, update_readme_picture


def _table(tmp_path, rows):
    path = tmp_path / "convergence.csv"
    pd.DataFrame(rows, columns=["experiment", "method", "closed_final_%", "volume_iou_final", "genus",
                                "target_genus"]).to_csv(path, index=False)
    videos = tmp_path / "videos"
    videos.mkdir(exist_ok=True)
    for r in rows:
        (videos / f"{r[0]}.mp4").write_bytes(b"")
    return path, videos


def test_the_honest_run_with_the_best_body_is_shown(tmp_path):
    rows = [("a_full", "full", 99.0, 0.80, 0, 0), ("b_full", "full", 90.0, 0.95, 0, 0),  # short of its gap
            ("c_full", "full", 98.0, 0.93, 1, 0),  # a spurious tunnel
            ("d_full", "full", 97.0, 0.91, 0, 0), ("d_physics_only", "physics_only", 99.0, 0.99, 0, 0)]
    path, videos = _table(tmp_path, rows)
    row = pick_run(path, videos)
    assert row["experiment"] == "d_full"
    assert caption(row, "iso", "duck", "default") == (
        "iso -> duck, the default profile: 97 % of the gap closed at the last frame, volume IoU 0.91; the body's "
        "smoothed surface (left) beside the target (right), every frame")
    (videos / "d_full.mp4").unlink()
    assert pick_run(path, videos)["experiment"] == "a_full"
    for r in rows:
        (videos / f"{r[0]}.mp4").unlink(missing_ok=True)
    assert pick_run(path, videos) is None


def test_the_readme_line_is_replaced(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("# title\n\nintro\n\n![old caption](docs/images/old.gif)\n\n## next\n")
    update_readme_picture(readme, "first")
    update_readme_picture(readme, "second")
    text = readme.read_text()
    assert text.count("![") == 1 and f"{MARKER}\n![second](docs/images/morph.gif)\n" in text and "old" not in text
