"""The viewer page (physmorph.reports.export.viewer) in a real browser: Debian's chromium driven by
Playwright. It loads without a console error, a run's slider changes its image, and its video
element reports a duration. Skips, saying why, only where no browser is installed
(.ci/run installs Debian's chromium)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from physmorph.reports.export.viewer import ViewerRun, write_viewer

CHROMIUM = next((p for p in (shutil.which("chromium"), shutil.which("chromium-browser"), "/usr/bin/chromium")
                 if p and Path(p).exists()), None)


def _page(tmp_path: Path) -> Path:
    import imageio_ffmpeg
    from PIL import Image

    videos = tmp_path / "videos"
    videos.mkdir()
    frames = [np.full((32, 64, 3), 40 * k, np.uint8) for k in range(5)]
    mp4 = videos / "a_full.mp4"
    w = imageio_ffmpeg.write_frames(str(mp4), (64, 32), fps=5, codec="libx264", pix_fmt_out="yuv420p",
                                    ffmpeg_log_level="error")
    w.send(None)
    for fr in frames:
        w.send(fr)
    w.close()
    stills = []
    for k in (0, 2, 4):
        p = videos / f"frame_{k:04d}.png"
        Image.fromarray(frames[k]).save(p)
        stills.append((k, p))
    run = ViewerRun("a_full", mp4, None, stills, {"gap closed, last": "99.0 %", "volume IoU, last": "0.930"})
    return write_viewer([run], tmp_path / "viewer" / "index.html", "test page")


def test_viewer_page_is_self_contained(tmp_path):
    text = _page(tmp_path).read_text()
    assert "http://" not in text and "https://" not in text  # no network
    assert text.count("data:image/png;base64,") == 3 and 'src="../videos/a_full.mp4"' in text
    assert "99.0 %" in text and "0.930" in text


def test_viewer_page_in_a_browser(tmp_path):
    if CHROMIUM is None:
        pytest.skip("no chromium here (Debian: apt-get install chromium; .ci/run installs it)")
    pw = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (environment.lock pins it)")
    page_path = _page(tmp_path)
    errors: list[str] = []
    with pw.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--autoplay-policy=no-user-gesture-required"])
        try:
            page = browser.new_page()
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(page_path.as_uri())
            run = page.locator("section.run")
            assert run.count() == 1
            img, slider = run.locator("img.still"), run.locator("input[type=range]")
            last = img.get_attribute("src")
            assert last.startswith("data:image/png;base64,") and "frame 4" in run.locator(".frame").inner_text()
            slider.fill("0")  # moves the slider to the first saved frame (fires its input event)
            first = img.get_attribute("src")
            assert first != last and "frame 0" in run.locator(".frame").inner_text()
            duration = page.evaluate("""() => new Promise((done, fail) => {
                const v = document.querySelector('video');
                if (v.readyState >= 1) return done(v.duration);
                v.addEventListener('loadedmetadata', () => done(v.duration));
                v.addEventListener('error', () => fail('video error ' + (v.error && v.error.code)));
                setTimeout(() => fail('no metadata in 20 s'), 20000);
            })""")
        finally:
            browser.close()
    assert duration == pytest.approx(1.0, abs=0.25)  # 5 frames at 5 fps
    assert not errors, errors


def test_the_page_turns_the_body_around_in_3d(tmp_path):
    """A run with 3D data: its page (one run, so the view opens by itself) loads the data script and
    the vendored bundle beside it, and the 3D canvas draws the body on the left and the target on
    the right, with no console error."""
    if CHROMIUM is None:
        pytest.skip("no chromium here (Debian: apt-get install chromium; .ci/run installs it)")
    pw = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (environment.lock pins it)")
    import base64
    import io
    import shutil

    import trimesh
    from PIL import Image

    from physmorph.reports.export.viewer import BUNDLE
    from physmorph.reports.export.viewer_data import body_frames, write_data_script

    meshes = tmp_path / "meshes" / "a_full"
    meshes.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=3, radius=7.0).export(meshes / "frame_0000.ply")
    trimesh.creation.box(extents=[11.0, 11.0, 11.0]).export(meshes / "frame_0004.ply")
    target = base64.b64encode(trimesh.creation.capsule(height=8.0, radius=5.0).export(file_type="glb")).decode()
    data = write_data_script("a_full", {"frames": body_frames(meshes), "target": target, "splats": None,
                                        "label": "a_full"}, tmp_path / "viewer" / "data" / "a_full.js")
    shutil.copy(BUNDLE, tmp_path / "viewer" / "viewer3d.js")
    _page(tmp_path)  # the video and the still of the run below
    run = ViewerRun("a_full", tmp_path / "videos" / "a_full.mp4", None, [(0, tmp_path / "videos" / "frame_0000.png")],
                    {"gap closed, last": "99.0 %"}, data)
    page_path = write_viewer([run], tmp_path / "viewer" / "a_full.html", "one run", tmp_path / "viewer" / "viewer3d.js")
    errors: list[str] = []
    with pw.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"])
        try:
            page = browser.new_page()
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(page_path.as_uri())
            page.wait_for_function("() => document.querySelector('.view3d').mounted !== undefined", timeout=20000)
            state = page.evaluate("() => document.querySelector('.view3d').mounted.ready.then(() => 'ready', e => String(e))")
            url = page.evaluate("() => document.querySelector('.view3d canvas').toDataURL('image/png')")
            labels = page.evaluate("() => document.querySelector('.frame3d-label').textContent")
        finally:
            browser.close()
    assert state == "ready" and errors == [], (state, errors)
    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")).astype(int)
    drawn = np.abs(img - np.array([0xF4, 0xF4, 0xF4])).max(axis=2) > 12
    half = drawn.shape[1] // 2
    assert drawn[:, :half].mean() > 0.02 and drawn[:, half:].mean() > 0.02, (drawn[:, :half].mean(), drawn[:, half:].mean())
    assert labels == "frame 4"
