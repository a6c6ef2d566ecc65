"""`physmorph morph SOURCE TARGET` (physmorph.cli): the shapes sized as the fit helper sizes them,
a valid config file written, the workflow run through the export, and the four paths printed; run
again it does nothing more; a dry run writes nothing; a shape it cannot use is refused in one line
before any job."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh
import yaml

from physmorph.cli.own_shapes import plan_own_morph
from physmorph.meshes.errors import MeshError
from physmorph.meshes.fit import isosphere_volume, target_cameras
from physmorph.settings.workflow import load_settings

REPO = Path(__file__).resolve().parents[2]
COMMAND = Path(sys.executable).with_name("physmorph")  # the console script `make venv` installs


def _settings(*files):
    return load_settings(REPO / "config/config.yaml", *[REPO / f for f in files])


def _plan(source, target, settings=None, **kw):
    settings = settings or _settings()
    return plan_own_morph(str(source), str(target), settings, target_cameras(settings), lambda shape: None, **kw)


def _capsule(path: Path, height: float = 2.0) -> Path:
    trimesh.creation.capsule(height=height, radius=1.0).export(path)
    return path


def test_a_mesh_target_is_sized_to_hold_the_sources_volume_and_the_config_is_valid(tmp_path):
    settings = _settings()
    plan = _plan("iso", _capsule(tmp_path / "capsule.obj"), settings)
    assert plan.experiment == "iso_capsule" and plan.source.name == "iso"
    assert plan.target.volume == pytest.approx(isosphere_volume(settings.shape("iso").size), rel=0.03)
    cfg = yaml.safe_load(plan.config_text())
    assert cfg["shapes"]["capsule"]["path"] == str((tmp_path / "capsule.obj").resolve())
    merged = load_settings(REPO / "config/config.yaml", overrides=cfg)
    assert merged.experiment("iso_capsule").method == "full"


def test_a_long_target_shrinks_the_isosphere_and_a_mesh_source_holds_a_letters_volume(tmp_path):
    plan = _plan("iso", _capsule(tmp_path / "long.obj", height=30.0))
    assert plan.target.entry["size"] == pytest.approx(26.0)  # the largest that fits grid 32
    shrunk = yaml.safe_load(plan.config_text())["shapes"]["isolong"]
    assert shrunk["kind"] == "isosphere" and isosphere_volume(shrunk["size"]) == pytest.approx(plan.target.volume, rel=0.03)
    assert plan.experiment == "iso_long" and yaml.safe_load(plan.config_text())["experiments"]["iso_long"]["source"] == "isolong"
    letter = _plan(_capsule(tmp_path / "pill.obj"), "A")
    from physmorph.meshes.shapes import letter_mesh

    a = _settings().shape("A")
    assert letter.source.volume == pytest.approx(letter_mesh("A", a.size, a.depth).volume, rel=0.03)


def test_names_are_valid_and_clash_with_nothing_shipped(tmp_path):
    plan = _plan("iso", _capsule(tmp_path / "bunny.obj"))
    assert plan.target.name == "bunnymine" and plan.experiment == "iso_bunnymine"
    with pytest.raises(MeshError, match="--name 'my-morph': an experiment name is letters, digits and _"):
        _plan("iso", tmp_path / "bunny.obj", name="my-morph")
    with pytest.raises(MeshError, match="--name 'iso_bunny_full': the config already has an experiment of that name"):
        _plan("iso", tmp_path / "bunny.obj", name="iso_bunny_full")
    with pytest.raises(MeshError, match=r"target 'teapot': no such file, and not a shape of the config \(shapes: A, C"):
        _plan("iso", "teapot")
    with pytest.raises(MeshError, match=r"size 40 does not fit .* \(the largest size that fits: 2\d\.\d\)"):
        _plan("iso", tmp_path / "bunny.obj", size=40.0)


def _workdir(tmp_path: Path) -> Path:
    wd = tmp_path / "wd"
    wd.mkdir()
    for name in ("Snakefile", "config", "workflow"):
        (wd / name).symlink_to(REPO / name)
    return wd


def _morph(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PHYSMORPH_THREADS": "2", "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([str(COMMAND), "morph", *args], cwd=cwd, capture_output=True, text=True, env=env, timeout=900)


def test_a_refused_shape_ends_in_one_line_before_any_job(tmp_path):
    wd = _workdir(tmp_path)
    s = trimesh.creation.icosphere(3)
    trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0]).export(tmp_path / "open.obj")
    run = _morph("iso", str(tmp_path / "open.obj"), "--workdir", str(wd), "-n", cwd=tmp_path)
    assert run.returncode == 2 and run.stdout == ""
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{tmp_path / 'open.obj'}: the mesh is open"), run.stderr
    assert not (wd / "morphs").exists() and not (wd / "results").exists()


def test_own_mesh_to_a_point_cloud_start_to_finish(tmp_path, mesh_dir):
    """Slow (~50 s): the test profile's 3 frames from nothing, a mesh source given by path into a
    point cloud's shape (the full method: alpha MSE falls by 5 % at least, to 0.93 of frame 0 when
    measured, 2026-12-02), through the video, the meshes, the splats and the run's viewer page;
    then again (nothing to do). (A dry run writes nothing: test_readme.py's test of the README's
    command.)"""
    import imageio_ffmpeg

    wd = _workdir(tmp_path)
    _capsule(tmp_path / "pill.obj")
    p = np.random.default_rng(0).normal(size=(3000, 3))
    trimesh.PointCloud(p / np.linalg.norm(p, axis=1, keepdims=True)).export(tmp_path / "ball.ply")
    args = ("pill.obj", "ball.ply", "--profile", "test", "--frames", "3", "--workdir", str(wd), "--mesh-dir", str(mesh_dir))
    run = _morph(*args, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "job morph (experiment=pill_ball)" in run.stdout and "morph: frame 3/3: gap closed" in run.stdout
    paths = dict(line.split(": ", 1) for line in run.stdout.splitlines()[-4:])
    r = wd / "results/test"
    assert paths == {"video": str(r / "videos/pill_ball.mp4"), "meshes": str(r / "meshes/pill_ball"),
                     "splats": str(r / "splats/pill_ball"), "viewer page": str(r / "viewer/pill_ball.html")}
    assert imageio_ffmpeg.count_frames_and_secs(paths["video"])[0] == 4  # frames 0..3
    assert trimesh.load(Path(paths["meshes"]) / "final.glb", force="mesh").is_watertight
    assert (Path(paths["meshes"]) / "measures.csv").is_file() and sorted(Path(paths["splats"]).glob("frame_*.ply"))
    page = Path(paths["viewer page"]).read_text()
    assert 'id="pill_ball"' in page and "../videos/pill_ball.mp4" in page and 'data-src="data/pill_ball.js"' in page
    import json

    script = (r / "viewer/data/pill_ball.js").read_text()
    data = json.loads(script.split("window.PHYSMORPH_RUNS[\"pill_ball\"] = ", 1)[1].rstrip().rstrip(";"))
    saved = sorted(int(p.stem.removeprefix("frame_")) for p in Path(paths["meshes"]).glob("frame_*.ply"))
    assert [f["frame"] for f in data["frames"]] == saved and data["splats"] and data["target"]
    assert (r / "viewer/viewer3d.js").stat().st_size > 1e6
    config = yaml.safe_load((wd / "morphs/pill_ball.yaml").read_text())
    assert config["experiments"]["pill_ball"] == {"source": "pill", "target": "ball", "method": "full", "frames": 3}
    with h5py.File(r / "meshes/pill.h5") as f:  # the source prepared from the user's file
        assert f.attrs["raw_sha256"] == hashlib.sha256((tmp_path / "pill.obj").read_bytes()).hexdigest()
    with h5py.File(r / "runs/pill_ball.h5") as f:  # the full method ran: the render gradient injected
        assert f.attrs["status"] == "complete" and f.attrs["method"] == "full"
        alpha = f["metrics/alpha_mse"][()]
        assert len(alpha) == 4 and np.isfinite(alpha).all() and (f["metrics/grad_F_norm"][1:] > 0).all()
    assert alpha[-1] < 0.95 * alpha[0], alpha
    again = _morph(*args, cwd=tmp_path)
    assert again.returncode == 0 and "nothing to be done" in again.stdout and again.stdout.endswith(run.stdout[-200:])
