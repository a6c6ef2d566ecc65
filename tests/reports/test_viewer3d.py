"""The vendored 3D viewer bundle (physmorph/reports/export/assets/viewer3d.js, built by
physmorph/reports/export/viewer3d/build.sh) in a real browser: Debian's chromium driven by Playwright,
the page opened as file:// with its data inlined as base64 (GLB surfaces made with trimesh, a splat PLY
from physmorph.reports.export.splats.write_splats). After `ready` the body (left half) and the target
(right half) are drawn; another frame changes the pixels and the label; the splats draw in the left
half; the canvas follows its element's width; a bad GLB, or no WebGL2, leaves a one-line message and
rejects `ready`; nothing logs a console error, throws or asks for a URL off the page. WebGL runs on
SwiftShader (software). Skips, saying why, only where no chromium or no playwright is installed
(.ci/run installs Debian's chromium)."""

from __future__ import annotations

import base64
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from physmorph.reports.export.splats import write_splats

CHROMIUM = "/usr/bin/chromium"
BUNDLE = Path(__file__).resolve().parents[2] / "physmorph" / "reports" / "export" / "assets" / "viewer3d.js"
# headless chromium has no GPU here: WebGL2 on SwiftShader through ANGLE
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
BACKGROUND = np.array([0xF4, 0xF4, 0xF4])


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _glb(mesh) -> str:
    return _b64(mesh.export(file_type="glb"))


def _data(tmp_path: Path, bad_glb: bool = False) -> dict:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=8.0)
    ellipsoid = sphere.copy()
    ellipsoid.apply_scale([1.25, 0.7, 1.0])
    frames = [{"frame": 0, "glb": _glb(sphere)},
              {"frame": 5, "glb": _glb(trimesh.creation.box(extents=[12.0, 12.0, 12.0]))},
              {"frame": 10, "glb": _b64(b"glTF but not a GLB") if bad_glb else _glb(ellipsoid)}]
    x = ellipsoid.vertices  # the last frame's Gaussians on its surface
    ply = write_splats(tmp_path / "last.ply", x, np.broadcast_to(np.eye(3), (len(x), 3, 3)), 0.6)
    return {"frames": frames, "target": _glb(trimesh.creation.box(extents=[14.0, 10.0, 10.0])),
            "splats": _b64(ply.read_bytes()), "label": "test morph"}


def _page(tmp_path: Path, name: str, data: dict) -> Path:
    shutil.copy(BUNDLE, tmp_path / "viewer3d.js")
    page = tmp_path / f"{name}.html"
    page.write_text(f"""<!doctype html>
<html><head><meta charset="utf-8"><title>viewer3d test</title></head>
<body style="margin:0">
<div id="view" style="width:640px"></div>
<script src="viewer3d.js"></script>
<script>
  window.view = PhysmorphViewer3D.mount(document.getElementById('view'), {json.dumps(data)});
  window.readyState = window.view.ready.then(() => 'ready', (e) => 'rejected: ' + e.message);
</script>
</body></html>""")
    return page


def _pixels(page) -> np.ndarray:  # [H, W, 3] uint8, the canvas as it is drawn now
    from PIL import Image

    url = page.evaluate("() => document.querySelector('#view canvas').toDataURL('image/png')")
    png = base64.b64decode(url.split(",", 1)[1])
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def _drawn(img: np.ndarray) -> np.ndarray:  # [H, W] bool: differs from the background
    return np.abs(img.astype(int) - BACKGROUND).max(axis=2) > 12


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.skip(f"no chromium at {CHROMIUM} (Debian: apt-get install chromium; .ci/run installs it)")
    pw = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (environment.lock pins it)")
    if not BUNDLE.exists():
        pytest.fail(f"{BUNDLE} is missing: run physmorph/reports/export/viewer3d/build.sh")
    with pw.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def _open(browser, page_path: Path):
    errors: list[str] = []
    page = browser.new_page(viewport={"width": 800, "height": 600})
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("request", lambda r: errors.append(f"request {r.url}")
            if not r.url.startswith(("file:", "data:", "blob:")) else None)
    page.goto(page_path.as_uri())
    return page, errors


def test_viewer3d_draws_frames_target_and_splats(browser, tmp_path):
    page, errors = _open(browser, _page(tmp_path, "good", _data(tmp_path)))
    try:
        assert page.evaluate("() => window.readyState") == "ready", errors
        view = page.locator("#view")
        assert view.locator("canvas").count() == 1
        box = view.locator("canvas").bounding_box()
        assert abs(box["width"] - 640) < 2 and abs(box["height"] - 360) < 2
        slider, label = view.locator("input.frame3d"), view.locator(".frame3d-label")
        assert slider.get_attribute("max") == "2" and slider.input_value() == "2"
        assert label.inner_text() == "frame 10" and "test morph" in view.inner_text()

        last = _pixels(page)
        half = last.shape[1] // 2
        drawn = _drawn(last)
        left, right = drawn[:, :half].mean(), drawn[:, half:].mean()
        assert left > 0.02 and right > 0.02, (left, right)
        body = last[:, :half][drawn[:, :half]].astype(int).mean(axis=0)
        target = last[:, half:][drawn[:, half:]].astype(int).mean(axis=0)
        assert body[0] > body[2] and target[2] > target[0]  # warm body, cool target

        page.evaluate("() => window.view.setFrame(0)")
        first = _pixels(page)
        assert label.inner_text() == "frame 0" and slider.input_value() == "0"
        assert _drawn(first)[:, :half].mean() > 0.02
        assert (np.abs(first.astype(int) - last).max(axis=2) > 12)[:, :half].mean() > 0.005  # sphere vs ellipsoid
        assert np.array_equal(first[:, half:], last[:, half:])  # the target stays

        slider.fill("1")  # the slider itself (its input event): the box
        page.wait_for_function("() => document.querySelector('.frame3d-label').textContent === 'frame 5'")

        page.wait_for_function("() => !document.querySelector('input.splats3d').disabled", timeout=15000)
        page.evaluate("() => window.view.showSplats(true)")
        assert view.locator("input.splats3d").is_checked() and label.inner_text() == "frame 10"
        splats = _pixels(page)
        drawn_splats = _drawn(splats)
        assert drawn_splats[:, :half].mean() > 0.02, drawn_splats[:, :half].mean()
        assert (np.abs(splats.astype(int) - last).max(axis=2) > 12)[:, :half].mean() > 0.005  # not the surface
        page.evaluate("() => window.view.showSplats(false)")
        back = _pixels(page)
        assert (np.abs(back.astype(int) - last).max(axis=2) > 12).mean() < 0.005  # the last surface again

        page.evaluate("() => { document.getElementById('view').style.width = '480px'; }")
        page.wait_for_function("() => document.querySelector('#view canvas').clientWidth === 480")
        assert abs(view.locator("canvas").bounding_box()["height"] - 270) < 2
    finally:
        page.close()
    assert not errors, errors


def test_viewer3d_bad_glb_shows_a_message(browser, tmp_path):
    page, errors = _open(browser, _page(tmp_path, "bad", _data(tmp_path, bad_glb=True)))
    try:
        state = page.evaluate("() => window.readyState")
        text = page.locator("#view").inner_text()
    finally:
        page.close()
    assert state.startswith("rejected: ") and "frame 10" in state, state
    assert text.strip() == state.removeprefix("rejected: ") and "\n" not in text.strip()
    assert not errors, errors


def test_viewer3d_without_webgl2_shows_a_message(browser, tmp_path):
    other = browser.browser_type.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-webgl2"])
    try:
        page, errors = _open(other, _page(tmp_path, "nogl", _data(tmp_path)))
        state = page.evaluate("() => window.readyState")
        text = page.locator("#view").inner_text().strip()
    finally:
        other.close()
    assert state == "rejected: 3D view unavailable: this browser has no WebGL2"
    assert text == state.removeprefix("rejected: ")
    assert not errors, errors
