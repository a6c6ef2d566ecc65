"""results/{profile}/viewer/index.html: one page, no network, that lists a profile's full runs,
each with its video, a slider over its saved frames (the body beside the target, the images inlined
as data URIs), its numbers (the share of the gap closed, the volume IoU) and a 3D view of its body
beside the target (viewer3d.js over data/{experiment}.js: physmorph.reports.export.viewer_data)."""

from __future__ import annotations

import base64
import html
import json
import os
from dataclasses import dataclass
from pathlib import Path


# the 3D view's script the pages load, vendored with the package (physmorph/reports/export/viewer3d/ builds it)
BUNDLE = Path(__file__).with_name("assets") / "viewer3d.js"


@dataclass
class ViewerRun:
    """What the page shows of one run."""

    name: str
    mp4: Path
    webm: Path | None
    stills: list[tuple[int, Path]]  # (frame, JPEG of the body beside the target)
    numbers: dict[str, str]  # label -> value, e.g. {"gap closed, last": "99.2 %"}
    data_js: Path | None = None  # its 3D view's data (physmorph.reports.export.viewer_data), None: no 3D view


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
  var view = run.querySelector('.view3d');
  var button = run.querySelector('button.open3d');
  if (!view || !button) return;
  // the 3D view: its data is a script beside the page (a page opened as a file may load scripts)
  function open3d() {
    button.disabled = true;
    button.textContent = 'loading the 3D view...';
    var script = document.createElement('script');
    script.src = view.dataset.src;
    script.onload = function () {
      var data = (window.PHYSMORPH_RUNS || {})[view.dataset.run];
      button.remove();
      view.mounted = window.PhysmorphViewer3D.mount(view, data);
    };
    script.onerror = function () { button.textContent = 'no 3D data beside the page: ' + view.dataset.src; };
    document.head.appendChild(script);
  }
  button.addEventListener('click', open3d);
  if (document.querySelectorAll('.run').length === 1) open3d();
});
"""

_STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1100px; }
.run { border-top: 1px solid #ccc; padding: 0.8em 0; }
.view3d { width: 640px; max-width: 100%; }
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
    view3d = "" if run.data_js is None else (
        f'<div><button class="open3d">turn it around in 3D</button>'
        f'<div class="view3d" data-run="{html.escape(run.name)}" data-src="{rel(run.data_js)}"></div></div>')
    return (f'<section class="run" id="{html.escape(run.name)}"><h2>{html.escape(run.name)}</h2>'
            f"<table>{rows}</table><div class=\"media\">"
            f'<video controls preload="metadata" muted>{sources}</video>'
            f'<div><img class="still" alt="{html.escape(run.name)}: saved frame"><br>'
            f'<input type="range" min="0" max="{max(len(stills) - 1, 0)}" value="{max(len(stills) - 1, 0)}" '
            f'aria-label="saved frame"> <span class="frame"></span></div>{view3d}</div>'
            f'<script type="application/json" class="stills">{stills_json}</script></section>')


def write_viewer(runs: list[ViewerRun], out_html: Path, title: str, bundle: Path | None = None) -> Path:
    """Write the page (videos linked relative to it, stills inlined; ``bundle``: the 3D view's
    script, viewer3d.js, linked where the runs have 3D data)."""
    out_html = Path(out_html)
    out_html.parent.mkdir(parents=True, exist_ok=True)
    body = "".join(_run_html(r, out_html.parent) for r in runs) or "<p>No full-method run in this profile.</p>"
    script3d = "" if bundle is None else \
        f'<script src="{html.escape(Path(os.path.relpath(bundle, out_html.parent)).as_posix())}"></script>'
    page = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{_STYLE}</style>{script3d}</head><body><h1>{html.escape(title)}</h1>"
            "<p>Each run: its video (every frame, the body beside the target from an orbiting camera), a "
            "slider over its saved frames, its numbers, and its body in 3D beside the target (every saved "
            "frame's surface, the last also as Gaussian splats), to turn around with the mouse.</p>"
            f"{body}<script>{_SCRIPT}</script></body></html>\n")
    tmp = out_html.with_suffix(".partial")
    tmp.write_text(page)
    tmp.replace(out_html)
    return out_html
