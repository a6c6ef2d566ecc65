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
