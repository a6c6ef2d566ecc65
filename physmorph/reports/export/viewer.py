"""results/{profile}/viewer/index.html: one page, no network, that lists a profile's full runs,
each with its video, a slider over its saved frames (the body beside the target, the images inlined
as data URIs) and its numbers (the share of the gap closed, the volume IoU)."""

from __future__ import annotations

import base64
import html
import json
import os
from dataclasses import dataclass
from pathlib import Path


@dataclass
class ViewerRun:
    """What the page shows of one run."""

    name: str
    mp4: Path
    webm: Path | None
    stills: list[tuple[int, Path]]  # (frame, JPEG of the body beside the target)
    numbers: dict[str, str]  # label -> value, e.g. {"gap closed, last": "99.2 %"}


_SCRIPT = """
document.querySelectorAll('.run').forEach(function (run) {
  var stills = JSON.parse(run.querySelector('script.stills').textContent);
  var slider = run.querySelector('input[type=range]');
  var img = run.querySelector('img.still');
  var label = run.querySelector('.frame');
  function show() {
    var s = stills[Number(slider.value)];
    img.src = s.src;
    label.textContent = 'frame ' + s.frame;
  }
  slider.addEventListener('input', show);
  show();
});
"""

_STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1100px; }
.run { border-top: 1px solid #ccc; padding: 0.8em 0; }
.media { display: flex; flex-wrap: wrap; gap: 1em; align-items: flex-start; }
video, img.still { max-width: 100%; border: 1px solid #ddd; }
table { border-collapse: collapse; } td { padding: 0.1em 0.8em 0.1em 0; }
"""


def _data_uri(path: Path) -> str:
    mime = "image/png" if path.suffix.lower() == ".png" else "image/jpeg"
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _run_html(run: ViewerRun, page_dir: Path) -> str:
    stills = [{"frame": k, "src": _data_uri(p)} for k, p in run.stills]
    rel = lambda p: html.escape(Path(os.path.relpath(p, page_dir)).as_posix())  # noqa: E731
    sources = f'<source src="{rel(run.mp4)}" type="video/mp4">'
    if run.webm is not None:
        sources += f'<source src="{rel(run.webm)}" type="video/webm">'
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in run.numbers.items())
    stills_json = json.dumps(stills).replace("</", "<\\/")
    return (f'<section class="run" id="{html.escape(run.name)}"><h2>{html.escape(run.name)}</h2>'
            f"<table>{rows}</table><div class=\"media\">"
            f'<video controls preload="metadata" muted>{sources}</video>'
            f'<div><img class="still" alt="{html.escape(run.name)}: saved frame"><br>'
            f'<input type="range" min="0" max="{max(len(stills) - 1, 0)}" value="{max(len(stills) - 1, 0)}" '
            f'aria-label="saved frame"> <span class="frame"></span></div></div>'
            f'<script type="application/json" class="stills">{stills_json}</script></section>')


def write_viewer(runs: list[ViewerRun], out_html: Path, title: str) -> Path:
    """Write the page (videos linked relative to it, stills inlined)."""
    out_html = Path(out_html)
    out_html.parent.mkdir(parents=True, exist_ok=True)
    body = "".join(_run_html(r, out_html.parent) for r in runs) or "<p>No full-method run in this profile.</p>"
    page = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{_STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
            "<p>Each run: its video (every frame, the body beside the target from an orbiting camera), a "
            "slider over its saved frames, and its numbers.</p>"
            f"{body}<script>{_SCRIPT}</script></body></html>\n")
    tmp = out_html.with_suffix(".partial")
    tmp.write_text(page)
    tmp.replace(out_html)
    return out_html
