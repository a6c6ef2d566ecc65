"""physmorph.reports.export: run frames, closed particle surfaces, the domain -> input transform, 3DGS splat files."""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from physmorph.reports.export.splats import SH_C0, covariances_from_F, quaternion_to_rotation, read_splat_covariances, rotation_to_quaternion, write_splats
from physmorph.reports.export.body import components_and_genus
from physmorph.reports.export.surface import domain_to_input, particle_surface, taubin_smooth, write_glb, write_ply
from physmorph.reports.export.runs import frame_state, saved_frames
from physmorph.records.h5io import stored_checksum, stored_identity
from physmorph.meshes.prepare import load_mesh, prepare_mesh
from physmorph.meshes.shapes import ShapeSpec
from physmorph.meshes.particles import sample_particles
from physmorph.settings.render import RenderConfig
from physmorph.records.runfile import RunFileError, RunWriter
from physmorph.records.runkey import RunKey

SIGMA0 = 0.35


def rotation(axis: str, degrees: float) -> np.ndarray:  # [3, 3]
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def homogeneous(A: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:  # [4, 4] for x -> A x + t
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = A, t
    return T


def frame_map(k: int) -> np.ndarray:  # [3, 3] the affine map x -> A x of the test run's frame k
    """Rotation about y and a stretch along x: det grows from 1 (frame 0) to 1.5 (frame 4)."""
    return rotation("y", 10.0 * k) @ np.diag([1.0 + 0.125 * k, 1.0, 1.0])


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A sampled isosphere (grid 32, PPC 2/1: ~7K particles) and a 4-frame run whose frame k moves
    the particles by x -> A_k x (F = A_k), saved at frames 0, 2, 4 by the project's RunWriter."""
    d = tmp_path_factory.mktemp("export")
    prepare_mesh(ShapeSpec("iso", "isosphere", size=13.7), None, d / "iso.h5")
    sample_particles(d / "iso.h5", d / "p_iso.h5", grid_res=32, ppc_surface=2, ppc_interior=1, density=75.0)
    with h5py.File(d / "p_iso.h5", "r") as f:
        x0 = f["x"][()]
    n = len(x0)
    key = RunKey(json.dumps({"frames": 4}), (("particles", stored_identity(d / "p_iso.h5")), ("target", "bb" * 32)))
    with RunWriter(d / "run.h5", key) as w:
        w.set_meta({"experiment": "iso_test", "sigma0": SIGMA0, "n_particles": n})
        for k in range(5):
            A = frame_map(k)
            state = {"x": x0 @ A.T, "F": np.tile(A, (n, 1, 1)), "Fp": np.tile(np.eye(3), (n, 1, 1))}
            w.commit(k, {"alpha_mse": 1.0 / (k + 1)}, np.zeros(2), state if k % 2 == 0 else None, [],
                     {"x": state["x"]}, last=k == 4)
        w.finish("complete", {}, {"frames": 4})
    return d


def test_run_frames_and_state(tiny_run):
    run, parts = tiny_run / "run.h5", tiny_run / "p_iso.h5"
    assert saved_frames(run) == [0, 2, 4]
    s = frame_state(run, 4, parts)
    with h5py.File(parts, "r") as f:
        x0, volume, dx = f["x"][()], f["volume"][()], float(f.attrs["dx"])
    A = frame_map(4)
    np.testing.assert_allclose(s["x"], x0 @ A.T, atol=1e-5)  # float32 storage
    np.testing.assert_allclose(s["F"], np.broadcast_to(A, s["F"].shape), atol=1e-6)
    np.testing.assert_allclose(s["det_F"], np.linalg.det(A), rtol=1e-6)
    np.testing.assert_array_equal(s["volume"], volume)
    assert s["dx"] == dx and s["sigma0"] == SIGMA0 and s["frame"] == 4
    assert "volume" not in frame_state(run, 2)  # without the particle file: no rest volumes
    with pytest.raises(RunFileError, match=r"frame 3 was not saved \(saved frames: \[0, 2, 4\]\)"):
        frame_state(run, 3)


def test_frame_state_refuses_another_particle_file(tiny_run, tmp_path):
    other = tmp_path / "p_other.h5"
    sample_particles(tiny_run / "iso.h5", other, grid_res=32, ppc_surface=2, ppc_interior=1, density=75.0, seed=1)
    with pytest.raises(RunFileError, match="not the particle file"):
        frame_state(tiny_run / "run.h5", 4, other)


def test_frame_state_accepts_the_particle_file_made_again(tiny_run, tmp_path):
    """The same particles sampled again (another wall time and peak memory, so another content
    checksum) hold the same data: the run exports against them; a run made before the data digest
    existed, which names its particle file by content checksum, exports against that file."""
    again = tmp_path / "p_again.h5"
    sample_particles(tiny_run / "iso.h5", again, grid_res=32, ppc_surface=2, ppc_interior=1, density=75.0)
    first = tiny_run / "p_iso.h5"
    assert stored_checksum(again) != stored_checksum(first)
    assert stored_identity(again) == stored_identity(first) != stored_checksum(first)
    np.testing.assert_array_equal(frame_state(tiny_run / "run.h5", 4, again)["volume"],
                                  frame_state(tiny_run / "run.h5", 4, first)["volume"])
    old_key = RunKey(json.dumps({"frames": 0}), (("particles", stored_checksum(first)), ("target", "bb" * 32)))
    with h5py.File(first, "r") as f:
        x0 = f["x"][()]
    eye = np.tile(np.eye(3), (len(x0), 1, 1))
    with RunWriter(tmp_path / "old.h5", old_key) as w:
        w.set_meta({"experiment": "iso_test", "sigma0": SIGMA0, "n_particles": len(x0)})
        w.commit(0, {"alpha_mse": 1.0}, np.zeros(2), {"x": x0, "F": eye, "Fp": eye}, [], {"x": x0}, last=True)
        w.finish("complete", {}, {"frames": 0})
    assert frame_state(tmp_path / "old.h5", 0, first)["volume"].shape == (len(x0),)
    with pytest.raises(RunFileError, match="not the particle file"):
        frame_state(tmp_path / "old.h5", 0, again)  # that run's key names the first file's bytes only


def test_final_surface_is_closed_with_the_particles_volume(tiny_run, tmp_path):
    s = frame_state(tiny_run / "run.h5", 4, tiny_run / "p_iso.h5")
    mesh = particle_surface(s["x"], s["volume"], s["det_F"], s["dx"])
    particles_volume = float((s["volume"] * np.linalg.det(s["F"])).sum())  # sum V_p det F_p
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0 and abs(mesh.volume / particles_volume - 1.0) <= 0.05
    # and it is the body's surface: the sampled isosphere moved by the frame's map
    body = load_mesh(tiny_run / "iso.h5")
    body.apply_transform(homogeneous(frame_map(4)))
    _, dist, _ = trimesh.proximity.closest_point(body, mesh.vertices)
    assert dist.mean() < 0.15 * s["dx"] and dist.max() < 0.6 * s["dx"]
    # the writers: a binary PLY and a GLB that read back as the same closed mesh
    for path in (write_ply(mesh, tmp_path / "body.ply"), write_glb(mesh, tmp_path / "body.glb")):
        back = trimesh.load(path, force="mesh")
        assert back.is_watertight and back.volume == pytest.approx(mesh.volume, rel=1e-4)
    assert b"binary_little_endian" in (tmp_path / "body.ply").read_bytes()[:200]


def test_surface_at_rest_matches_the_sampled_mesh(tiny_run):
    s = frame_state(tiny_run / "run.h5", 0, tiny_run / "p_iso.h5")
    mesh = particle_surface(s["x"], s["volume"], s["det_F"], s["dx"])
    body = load_mesh(tiny_run / "iso.h5")
    _, dist, _ = trimesh.proximity.closest_point(mesh, body.sample(3000, seed=0))  # every part of the body is there
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1
    assert dist.mean() < 0.15 * s["dx"] and dist.max() < 0.6 * s["dx"]


def test_surface_in_the_input_frame(tiny_run):
    s = frame_state(tiny_run / "run.h5", 0, tiny_run / "p_iso.h5")
    to_input = domain_to_input(tiny_run / "iso.h5")
    scale = 1.0 / to_input[0, 0]
    mesh = particle_surface(s["x"], s["volume"], s["det_F"], s["dx"], transform=to_input)
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.volume == pytest.approx((s["volume"] * s["det_F"]).sum() / scale ** 3, rel=1e-6)


def test_domain_to_input_maps_the_prepared_mesh_onto_the_raw_one(tmp_path):
    # an asymmetric solid (a cone: centroid != bounding-box centre) far from the origin, in other units
    raw = trimesh.creation.cone(radius=1.0, height=3.0, sections=24)
    raw.apply_transform(homogeneous(40.0 * rotation("x", 30.0), [120.0, -45.0, 33.0]))
    raw.export(tmp_path / "cone.obj")
    prepare_mesh(ShapeSpec("cone", "file", file="cone.obj", size=16.0), tmp_path / "cone.obj", tmp_path / "cone.h5")
    prepared = load_mesh(tmp_path / "cone.h5")
    raw_back = trimesh.load(tmp_path / "cone.obj", force="mesh")
    assert np.abs(prepared.center_mass).max() < 1e-6 and prepared.extents.max() == pytest.approx(16.0)
    back = prepared.copy()
    back.apply_transform(domain_to_input(tmp_path / "cone.h5"))

    tol = 1e-9 * raw_back.extents.max()
    assert cKDTree(raw_back.vertices).query(back.vertices)[0].max() < tol
    assert cKDTree(back.vertices).query(raw_back.vertices)[0].max() < tol
    with h5py.File(tmp_path / "cone.h5", "r") as f:  # the attributes as a mapping: the same matrix
        np.testing.assert_array_equal(domain_to_input(f.attrs), domain_to_input(tmp_path / "cone.h5"))


def test_pore_closing_fills_a_tunnel_two_cells_across_and_keeps_a_wider_hole():
    """A slab of particles (spacing 0.25, MPM cell 0.5) pierced by a hole whose particle-free gap is
    two MPM cells across exports as a torus without the pore closing (width 3 surface cells) and as
    a slab with it; holes three and five cells across stay holes either way; the closing keeps the
    enclosed volume at the particles' own."""
    h = 0.25
    ax, az = np.arange(0.125, 4.0, h), np.arange(0.125, 2.0, h)
    x = np.stack(np.meshgrid(ax, ax, az, indexing="ij"), -1).reshape(-1, 3)
    for radius, genus_open, genus_closed in ((0.5, 1, 0), (0.75, 1, 1), (1.2, 1, 1)):
        body = x[np.hypot(x[:, 0] - 2.0, x[:, 1] - 2.0) > radius]
        volume = np.full(len(body), h ** 3)
        for width, genus in ((0, genus_open), (3, genus_closed)):
            mesh = particle_surface(body, volume, np.ones(len(body)), 0.5, pore_closing=width)
            assert components_and_genus(mesh) == (1, genus), (radius, width)
            np.testing.assert_allclose(mesh.volume, volume.sum(), rtol=1e-9)


def test_taubin_smoothing_damps_noise_without_shrinking():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
    rng = np.random.default_rng(0)
    noisy = sphere.vertices + rng.normal(0.0, 0.05, sphere.vertices.shape)
    smooth = taubin_smooth(noisy, sphere.faces, iterations=10)
    shrunk = taubin_smooth(noisy, sphere.faces, iterations=10, mu=0.0)  # plain Laplacian steps
    radius = {name: np.linalg.norm(v, axis=1) for name, v in (("noisy", noisy), ("smooth", smooth), ("shrunk", shrunk))}
    assert radius["smooth"].std() < 0.5 * radius["noisy"].std()
    assert abs(radius["smooth"].mean() / 5.0 - 1.0) < 0.002
    assert radius["shrunk"].mean() < 0.99 * 5.0  # the shrinkage the mu step prevents


def test_quaternion_is_unit_and_w_first():
    q = rotation_to_quaternion(rotation("z", 90.0)[None])[0]
    np.testing.assert_allclose(q, [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], atol=1e-12)
    # every branch of the conversion (trace > 0, 180 degree turns about each axis) round-trips
    rng = np.random.default_rng(1)
    Rs = [rotation(a, d) for a in "xyz" for d in (0.0, 90.0, 179.0, 180.0, -120.0)]
    Rs += [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(50)]
    Rs = np.array([R * np.sign(np.linalg.det(R)) for R in Rs])
    q = rotation_to_quaternion(Rs)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(quaternion_to_rotation(q), Rs, atol=1e-12)


def _test_F() -> np.ndarray:  # [M, 3, 3]
    rng = np.random.default_rng(2)
    Q1, Q2 = rotation("z", 37.0) @ rotation("x", 71.0), rotation("y", -23.0) @ rotation("z", 12.0)
    Fs = [np.eye(3), rotation("z", 90.0), Q1 @ np.diag([3.0, 1.0, 0.05]) @ Q2]  # isotropic, rotation, 60:1
    Fs += [np.eye(3) + 0.2 * rng.normal(size=(3, 3)) for _ in range(40)]  # well conditioned
    for det in (0.5, 2.0):  # volume halved and doubled, anisotropic and rotated
        G = Q2 @ np.diag([1.6, 0.7, 1.1]) @ Q1
        Fs.append(G * (det / np.linalg.det(G)) ** (1.0 / 3.0))
    return np.array(Fs)


def _covariance_from_file(path) -> np.ndarray:  # [N, 3, 3], rebuilt here from the raw properties
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    w, x, y, z = (np.asarray(v[f"rot_{i}"], np.float64) for i in range(4))  # w first
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                  np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                  np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], axis=1)
    s = np.exp(np.stack([np.asarray(v[f"scale_{i}"], np.float64) for i in range(3)], axis=1))
    return R @ (s[:, :, None] ** 2 * np.swapaxes(R, 1, 2))


def test_splat_file_round_trips_the_covariances(tmp_path):
    from plyfile import PlyData

    F = _test_F()
    x = np.random.default_rng(3).normal(size=(len(F), 3))
    path = write_splats(tmp_path / "splats.ply", x, F, SIGMA0)
    ply = PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"  # the vertex's properties: test_splat_layout.py
    expected = SIGMA0 ** 2 * F @ np.swapaxes(F, 1, 2)  # F Sigma0 F^T, Sigma0 = sigma0^2 I
    norm = np.linalg.norm(expected, axis=(1, 2))
    for rebuilt in (_covariance_from_file(path), read_splat_covariances(path)):
        assert (np.linalg.norm(rebuilt - expected, axis=(1, 2)) / norm).max() <= 1e-5
    q = np.stack([ply["vertex"].data[f"rot_{i}"] for i in range(4)], axis=1).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.stack([ply["vertex"].data[k] for k in "xyz"], 1), x, atol=1e-6)
    # per-particle sigma0 and a transform to another frame: Sigma -> A Sigma A^T, x -> A x + t
    sig = np.linspace(0.1, 0.5, len(F))
    T = homogeneous(2.5 * rotation("x", 40.0), [1.0, -2.0, 3.0])
    write_splats(tmp_path / "moved.ply", x, F, sig, transform=T)
    expected = T[:3, :3] @ covariances_from_F(F, sig) @ T[:3, :3].T
    rebuilt = _covariance_from_file(tmp_path / "moved.ply")
    assert (np.linalg.norm(rebuilt - expected, axis=(1, 2)) / np.linalg.norm(expected, axis=(1, 2))).max() <= 1e-5


def test_splat_opacity_and_colour(tmp_path):
    from plyfile import PlyData

    F = np.tile(np.eye(3), (3, 1, 1))
    x = np.zeros((3, 3))

    def stored(name: str, **kwargs) -> np.ndarray:  # the vertex records as written
        return PlyData.read(str(write_splats(tmp_path / name, x, F, SIGMA0, **kwargs)))["vertex"].data

    def sigmoid(logit) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.asarray(logit, np.float64)))

    def colour(v) -> np.ndarray:  # [3, 3] rgb of SH degree 0
        return 0.5 + SH_C0 * np.stack([np.asarray(v[f"f_dc_{i}"], np.float64) for i in range(3)], axis=1)

    v = stored("default.ply")
    np.testing.assert_allclose(sigmoid(v["opacity"]), RenderConfig().opacity, atol=1e-6)  # the renderer's
    np.testing.assert_allclose(colour(v), np.broadcast_to([0.80, 0.62, 0.45], (3, 3)), atol=1e-6)
    rgb = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.2, 0.2, 0.9]])
    v = stored("opaque.ply", opacity=1.0, rgb=rgb)
    assert np.all(np.isfinite(v["opacity"])) and np.all(sigmoid(v["opacity"]) > 0.999)
    np.testing.assert_allclose(colour(v), rgb, atol=1e-6)
    np.testing.assert_allclose(sigmoid(stored("faint.ply", opacity=0.3)["opacity"]), 0.3, atol=1e-6)


def test_stray_share_counts_the_mass_beyond_two_cells_outside_the_target(tmp_path):
    """A sphere target (radius 5, dx 1): particles inside and within 2 cells outside are not stray,
    those 3 cells out are; the share is theirs by weight."""
    import h5py
    import trimesh

    from physmorph.reports.export.measures import stray_share, surface_distance, target_mesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
    mesh_h5 = tmp_path / "sphere.h5"
    with h5py.File(mesh_h5, "w") as f:
        f["vertices"], f["faces"] = sphere.vertices, sphere.faces
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(300, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    inside, near, far = 3.0 * dirs[:100], 6.5 * dirs[100:200], 8.5 * dirs[200:]  # 0, 1.5 and 3.5 cells out
    x = np.concatenate([inside, near, far])
    weight = np.concatenate([np.ones(100), np.ones(100), 2.0 * np.ones(100)])
    assert stray_share(x, weight, mesh_h5, dx=1.0) == pytest.approx(200 / 400)
    assert stray_share(inside, np.ones(100), mesh_h5, dx=1.0) == 0.0
    # the surface distance: 0 against itself, the radii's difference against a larger sphere
    assert surface_distance(target_mesh(mesh_h5), sphere, dx=1.0) < 0.1
    bigger = trimesh.creation.icosphere(subdivisions=4, radius=6.0)
    assert surface_distance(bigger, sphere, dx=0.5) == pytest.approx(2.0, rel=0.05)


def test_orbit_camera_starts_at_the_first_ring_view_and_turns_about_y():
    from physmorph.base.cameras import ring_cameras
    from physmorph.reports.export.video import orbit_camera
    from physmorph.reports.export.video_body import subsample

    ring = ring_cameras(4, 21.0, 40.0, 64, 48, 36.0)
    for view, az in enumerate((0.0, 90.0, 180.0)):
        cam = orbit_camera(az, 21.0, 40.0, 36.0, 64, 48)
        np.testing.assert_allclose(cam.world_to_cam[0], ring.world_to_cam[view], atol=1e-12)
        np.testing.assert_allclose(cam.intrinsics[0], ring.intrinsics[view])
    # a subsample keeps the body's fill: M Gaussians of sigma s (N / M)^(1/3) for N of sigma s
    x, F = np.zeros((1000, 3)), np.broadcast_to(np.eye(3), (1000, 3, 3))
    xs, Fs, s = subsample(x, F, 0.5, 250)
    assert len(xs) == 250 and s == pytest.approx(0.5 * 4 ** (1 / 3))
    assert subsample(x, F, 0.5, 5000)[2] == 0.5


TAICHI_LINE = re.compile(r"^\[(Taichi\]|[DIWE] \d\d/\d\d/\d\d )")


def test_a_run_without_every_frames_motion_ends_the_video_job_in_one_line(tmp_path):
    """A run file made before every frame's motion was kept: the video job's log ends in one line
    naming the file and what to do, the job exits 2, no traceback."""
    import subprocess
    import sys

    from physmorph.records.runfile import RunWriter
    from physmorph.records.runkey import RunKey

    run = tmp_path / "old.h5"
    key = RunKey(json.dumps({"frames": 2}), (("particles", "aa" * 32), ("target", "bb" * 32)))
    with RunWriter(run, key) as w:
        w.resume(log=lambda m: None)
        w.set_meta({"experiment": "old", "views": 1, "sigma0": 0.3})
        for k in range(3):
            state = {"x": np.zeros((4, 3)), "F": np.tile(np.eye(3), (4, 1, 1)), "Fp": np.tile(np.eye(3), (4, 1, 1))}
            w.commit(k, {"alpha_mse": 1.0}, np.ones(1), state if k != 1 else None, [], {"x": state["x"]},
                     last=k == 2)  # frame 1: neither a state nor its motion, as runs made before
        w.finish("complete", {}, {"frames": 2})
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=3.0)
    mesh_h5 = tmp_path / "target_mesh.h5"
    with h5py.File(mesh_h5, "w") as f:
        f["vertices"], f["faces"] = sphere.vertices, sphere.faces

    def video_job(target: Path, log: Path):
        code = ("from physmorph.reports.export.stage import video_stage; "
                f"video_stage({str(run)!r}, {str(target)!r}, '{{}}', '{{\"body\": \"particles\"}}', "
                f"{str(tmp_path / 'v.mp4')!r}, None, "
                f"{str(tmp_path / 'stills')!r}, log={str(log)!r})")
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)

    for target, says, culprit in ((mesh_h5, "frame 1 has no positions", run),
                                  (tmp_path / "missing.h5", "missing (the target's prepared mesh)", tmp_path / "missing.h5")):
        log = tmp_path / f"{target.stem}.log"
        out = video_job(target, log)
        assert out.returncode == 2, out.stderr[-2000:]
        assert "Traceback" not in out.stderr and "Traceback" not in log.read_text()
        # Taichi's own lines (its banner; a warning when another process holds its kernel cache's
        # lock as this one starts or exits) are not the job's
        last = [line for line in out.stderr.strip().splitlines() if not TAICHI_LINE.match(line)][-1]
        assert log.read_text().strip().splitlines()[-1] == last and says in last and str(culprit) in last


def test_video_draws_a_held_frames_body_once(tiny_run, tmp_path, monkeypatch):
    """A frame whose positions and F equal the frame before's (held, or undone by the settle gate)
    reuses that frame's body surface: one surface per distinct frame, the same Gaussians as drawn anew."""
    import physmorph.reports.export.surface as surface
    from physmorph.records.runfile import frame_motion
    from physmorph.reports.export.runs import rest_particles
    from physmorph.reports.export.video import video_frames
    from physmorph.reports.export.video_body import BodyDrawing
    from physmorph.settings.export import ExportConfig

    parts = tiny_run / "p_iso.h5"
    with h5py.File(parts, "r") as f:
        x0 = f["x"][()]
    n = len(x0)
    maps = [frame_map(0), frame_map(1), frame_map(1), frame_map(1), frame_map(2)]  # frames 2 and 3 held
    key = RunKey(json.dumps({"frames": 4}), (("particles", stored_identity(parts)), ("target", "bb" * 32)))
    run = tmp_path / "held.h5"
    with RunWriter(run, key) as w:
        w.set_meta({"experiment": "iso_held", "sigma0": SIGMA0, "n_particles": n})
        for k, A in enumerate(maps):
            state = {"x": x0 @ A.T, "F": np.tile(A, (n, 1, 1)), "Fp": np.tile(np.eye(3), (n, 1, 1))}
            w.commit(k, {"alpha_mse": 1.0 / (k + 1)}, np.zeros(2), state if k in (0, 4) else None, [],
                     {"x": state["x"]}, last=k == 4, motion=state)
        w.finish("complete", {}, {"frames": 4})
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=6.0)
    mesh_h5 = tmp_path / "target_mesh.h5"
    with h5py.File(mesh_h5, "w") as f:
        f["vertices"], f["faces"] = sphere.vertices, sphere.faces
    calls = []
    real = surface.particle_surface
    monkeypatch.setattr(surface, "particle_surface", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    drawn = []
    monkeypatch.setattr("physmorph.render.api.shade",
                        lambda x, F, s, *a, **kw: drawn.append((x, F, s)) or np.zeros((36, 64, 3)))
    settings = ExportConfig(width=64, height=36)
    cfg = {"elevation_deg": 10.0, "fov_y_deg": 40.0, "distance": 60.0}
    frames = list(video_frames(run, mesh_h5, cfg, settings, lambda m: None, parts))
    assert [k for k, _ in frames] == [0, 1, 2, 3, 4]
    assert len(calls) == 3  # frames 0, 1 and 4; 2 and 3 as frame 1
    bodies = drawn[0::2]  # each frame draws the body, then the target
    with h5py.File(run, "r") as f:
        fresh = BodyDrawing(settings, SIGMA0, rest_particles(run, parts)).gaussians(*frame_motion(f, 3))
    for got, want in zip(bodies[3], fresh):
        np.testing.assert_array_equal(got, want)
    assert not np.array_equal(bodies[4][0], bodies[3][0])
