"""Stage rasterize_target: coverage alpha, depth, signed distance transform, grid mass."""

import numpy as np
import pytest
import trimesh

from physmorph.base.cameras import ring_cameras
from physmorph.base.grid import Grid, splat_mass
from physmorph.morph.targets import rasterize_mesh, signed_distance_transform


def test_sdt_sign_convention_and_magnitude():
    mask = np.zeros((21, 21), bool)
    mask[5:16, 5:16] = True
    sdt = signed_distance_transform(mask)
    assert sdt[10, 10] < 0 and sdt[0, 0] > 0
    # A pixel just inside/outside the boundary sits half a pixel from it.
    assert sdt[5, 10] == pytest.approx(-0.5)
    assert sdt[4, 10] == pytest.approx(0.5)
    assert sdt[10, 0] == pytest.approx(4.5)  # 5 pixel centres left of the edge column
    assert sdt[10, 10] == pytest.approx(-5.5)
    assert np.all(sdt[mask] < 0) and np.all(sdt[~mask] > 0)


def test_sdt_empty_and_full_masks_are_finite():
    empty = signed_distance_transform(np.zeros((4, 6), bool))
    full = signed_distance_transform(np.ones((4, 6), bool))
    assert np.all(np.isfinite(empty)) and np.all(empty > 0)
    assert np.all(np.isfinite(full)) and np.all(full < 0)


def test_ring_cameras_geometry():
    cams = ring_cameras(count=8, elevation_deg=21.0, distance=40.0, width=64, height=48)
    centers = cams.centers
    assert np.allclose(np.linalg.norm(centers, axis=1), 40.0)
    assert np.allclose(np.degrees(np.arcsin(centers[:, 1] / 40.0)), 21.0)
    uv, z = cams.project(np.zeros((1, 3)))
    assert np.allclose(uv[:, 0], [32.0, 24.0]) and np.allclose(z, 40.0)
    # Rotations are orthonormal.
    R = cams.rotation
    assert np.allclose(R @ np.transpose(R, (0, 2, 1)), np.eye(3), atol=1e-12)


def test_a_ring_at_two_heights_alternates_its_views_and_keeps_their_azimuths():
    """target.elevation_spread_deg: even views that much above the ring's elevation, odd ones below,
    each still looking at the origin from the same distance and azimuth; 0 is the one ring."""
    one = ring_cameras(count=8, elevation_deg=21.0, distance=40.0, width=64, height=48)
    two = ring_cameras(count=8, elevation_deg=21.0, distance=40.0, width=64, height=48, elevation_spread_deg=30.0)
    el = np.degrees(np.arcsin(two.centers[:, 1] / 40.0))
    np.testing.assert_allclose(el, [51.0, -9.0] * 4)
    np.testing.assert_allclose(np.arctan2(two.centers[:, 0], two.centers[:, 2]),
                               np.arctan2(one.centers[:, 0], one.centers[:, 2]), atol=1e-12)
    uv, z = two.project(np.zeros((1, 3)))
    assert np.allclose(uv[:, 0], [32.0, 24.0]) and np.allclose(z, 40.0)
    same = ring_cameras(count=8, elevation_deg=21.0, distance=40.0, width=64, height=48, elevation_spread_deg=0.0)
    np.testing.assert_array_equal(same.world_to_cam, one.world_to_cam)
    with pytest.raises(ValueError, match="camera elevation 91.0 degrees is not between -90 and 90"):
        ring_cameras(count=2, elevation_deg=60.0, elevation_spread_deg=31.0)


def test_sphere_silhouette_area_and_depth():
    r, D = 6.0, 40.0
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=r)
    cams = ring_cameras(count=2, elevation_deg=21.0, fov_y_deg=40.0, width=96, height=96, distance=D)
    alpha, depth = rasterize_mesh(sphere, cams, supersample=4)
    f = cams.intrinsics[0, 1]
    radius_px = f * np.tan(np.arcsin(r / D))  # perspective silhouette of a sphere, centred
    expected = np.pi * radius_px**2
    for v in range(2):
        assert alpha[v].sum() == pytest.approx(expected, rel=0.01)
        # The centre pixel sees the near pole at depth D - r.
        assert depth[v, 47:49, 47:49].mean() == pytest.approx(D - r, abs=0.05)
        assert np.all(depth[v][alpha[v] == 0] == 0)
    assert alpha.min() >= 0 and alpha.max() <= 1


def test_occlusion_depth_is_nearest_surface():
    near = trimesh.creation.box(extents=[4, 4, 4])
    near.apply_translation([0, 0, 0])
    far = trimesh.creation.box(extents=[12, 12, 2])
    cams = ring_cameras(count=1, elevation_deg=0.0, fov_y_deg=40.0, width=32, height=32, distance=30.0)
    far.apply_translation([0, 0, -6])  # camera 0 sits on +z: the big plate is behind the cube
    scene = trimesh.util.concatenate([near, far])
    _, depth = rasterize_mesh(scene, cams, supersample=1)
    assert depth[0, 16, 16] == pytest.approx(28.0, abs=1e-6)  # cube's front face at z = +2
    assert depth[0, 16, 2] == 0 or depth[0, 16, 2] > 28.0


def test_splat_mass_conserves_mass():
    grid = Grid(16)
    lo, hi = grid.interior_bounds()
    rng = np.random.default_rng(0)
    x = rng.uniform(lo, hi, size=(500, 3))
    m = rng.uniform(0.5, 2.0, size=500)
    gm = splat_mass(x, m, grid)
    assert gm.sum() == pytest.approx(m.sum(), rel=1e-12)
    assert gm.min() >= 0


def test_rasterize_target_bad_input_leaves_nothing(tmp_path):
    from physmorph.settings.sections import SamplingConfig, TargetConfig
    from physmorph.records.h5io import StageInputError
    from physmorph.morph.targets import rasterize_target

    bad = tmp_path / "mesh.h5"
    bad.write_bytes(b"not an hdf5 file")
    out, png = tmp_path / "t.h5", tmp_path / "t.png"
    with pytest.raises(StageInputError, match="mesh.h5"):
        rasterize_target(bad, out, SamplingConfig(16, 1, 1, 75.0, 0.7), TargetConfig(width=16, height=12), preview_png=png)
    assert not out.exists() and not png.exists() and not list(tmp_path.glob("*.partial"))


def test_target_file_round_trip_and_missing_field(tmp_path):
    import h5py

    from physmorph.settings.sections import SamplingConfig, TargetConfig
    from physmorph.records.h5io import StageInputError
    from physmorph.meshes.shapes import ShapeSpec
    from physmorph.meshes.prepare import prepare_mesh
    from physmorph.morph.targets import load_target, rasterize_target

    prepare_mesh(ShapeSpec("iso", "isosphere", size=10.0), None, tmp_path / "iso.h5")
    tc = TargetConfig(cameras=4, width=24, height=16, supersample=1, surface_points=500)
    summary = rasterize_target(tmp_path / "iso.h5", tmp_path / "t.h5", SamplingConfig(16, 1, 1, 75.0, 0.7), tc)
    t = load_target(tmp_path / "t.h5")
    assert t.alpha.shape == (4, 16, 24) and t.cameras.count == 4 and t.surface_points.shape == (500, 3)
    # The grid mass is the target's own particle sampling splatted with the MPM's B-spline.
    from physmorph.base.grid import Grid, splat_mass
    from physmorph.meshes.prepare import load_mesh
    from physmorph.meshes.particles import sample_volume

    x, vol, _ = sample_volume(load_mesh(tmp_path / "iso.h5"), Grid(16), 1, 1, 0)
    np.testing.assert_allclose(t.grid_mass, splat_mass(x, 75.0 * vol, Grid(16)), rtol=1e-12)
    assert t.grid_mass.sum() == pytest.approx(75.0 * t.volume, rel=0.1)  # coarse grid 16: ~7 % over
    assert np.all((t.sdt < 0) == (t.alpha >= 0.5))
    assert summary["views"] == 4
    from physmorph.records.h5io import stamp_checksum

    with h5py.File(tmp_path / "t.h5", "a") as f:
        del f["sdt"]
    # Edited after it was written: refused by its checksum, naming the file.
    with pytest.raises(StageInputError, match=r"t\.h5: content does not match its checksum"):
        load_target(tmp_path / "t.h5")
    with h5py.File(tmp_path / "t.h5", "a") as f:  # a consistent file without the field (a writer's bug)
        stamp_checksum(f)
    with pytest.raises(StageInputError, match="missing field 'sdt'"):
        load_target(tmp_path / "t.h5")


@pytest.mark.parametrize("damage", ["zeroed surface points", "zero-filled file"])
def test_zeroed_target_is_refused_naming_the_file(tmp_path, damage):
    """Zeroed bytes inside a target used to pass silently (Chamfer off by 0.034): the content
    checksum refuses them, and the morph refuses the target before its first frame."""
    import h5py

    from physmorph.settings.sections import SamplingConfig, TargetConfig
    from physmorph.records.h5io import StageInputError, stored_checksum
    from physmorph.meshes.shapes import ShapeSpec
    from physmorph.meshes.prepare import prepare_mesh
    from physmorph.morph.targets import load_target, rasterize_target

    prepare_mesh(ShapeSpec("iso", "isosphere", size=10.0), None, tmp_path / "iso.h5")
    tc = TargetConfig(cameras=2, width=24, height=16, supersample=1, surface_points=300)
    out = tmp_path / "t.h5"
    rasterize_target(tmp_path / "iso.h5", out, SamplingConfig(16, 1, 1, 75.0, 0.7), tc)
    assert len(stored_checksum(out)) == 64
    data = out.read_bytes()
    if damage == "zero-filled file":
        out.write_bytes(bytes(len(data)))
        match = r"t\.h5: not a readable HDF5 file"
    else:
        with h5py.File(out) as f:
            pts = f["surface_points"][()].tobytes()
        i = data.index(pts[:4096])
        out.write_bytes(data[:i] + bytes(4096) + data[i + 4096:])
        match = r"t\.h5: content does not match its checksum.*zero-filled"
    with pytest.raises(StageInputError, match=match):
        load_target(out)
    with pytest.raises(StageInputError, match=match):
        stored_checksum(out)  # what the morph's resume key reads first


def test_target_carries_its_ceiling(tmp_path):
    """The ceiling is the target's own particle sampling (sigma0 = sigma_scale x mean NN distance,
    as sample_particles) rendered at rest with the config's renderer, against the target alpha."""
    import json

    import h5py

    from physmorph.settings.sections import SamplingConfig
    from physmorph.records.h5io import StageInputError
    from physmorph.meshes.shapes import ShapeSpec
    from physmorph.meshes.prepare import load_mesh, prepare_mesh
    from physmorph.meshes.particles import mean_nn_distance, sample_volume
    from physmorph.morph.quality import ceiling_metrics
    from physmorph.settings.render import RenderConfig
    from physmorph.stages import rasterize_target_stage
    from physmorph.morph.targets import load_target

    prepare_mesh(ShapeSpec("iso", "isosphere", size=20.0), None, tmp_path / "iso.h5")
    sampling = SamplingConfig(16, 1, 1, 75.0, 0.7)
    tcfg = dict(cameras=2, width=72, height=48, supersample=1, surface_points=200)
    out = tmp_path / "t.h5"
    summary = rasterize_target_stage(tmp_path / "iso.h5", out, tmp_path / "t.png", sampling, tcfg, 0)
    t = load_target(out)
    assert t.ceiling_alpha_mse_views.shape == (2,) and t.ceiling_iou_views.shape == (2,)
    assert t.ceiling_alpha_mse == pytest.approx(t.ceiling_alpha_mse_views.mean(), rel=1e-9)
    assert t.ceiling_iou == pytest.approx(t.ceiling_iou_views.mean(), rel=1e-9)
    assert summary["ceiling_alpha_mse"] == pytest.approx(t.ceiling_alpha_mse) and summary["ceiling_iou"] == pytest.approx(t.ceiling_iou)
    # A mesh's own particles render close to its exact coverage: silhouettes overlap well and
    # the alpha MSE is a small fraction of that of an empty image (mean alpha^2).
    assert 0.8 < t.ceiling_iou <= 1.0
    assert 0.0 < t.ceiling_alpha_mse < 0.15 * np.mean(t.alpha**2)
    # Recomputed independently: the same sampling, sigma0 and default renderer.
    x, _, _ = sample_volume(load_mesh(tmp_path / "iso.h5"), Grid(16), 1, 1, 0)
    sigma0 = 0.7 * mean_nn_distance(x)
    ref = ceiling_metrics(x, sigma0, t.cameras, t.alpha, RenderConfig())
    np.testing.assert_allclose(t.ceiling_alpha_mse_views, ref["alpha_mse_views"], rtol=1e-5)
    np.testing.assert_allclose(t.ceiling_iou_views, ref["iou_views"], rtol=1e-9)
    with h5py.File(out) as f:
        assert f.attrs["ceiling_sigma0"] == pytest.approx(sigma0, rel=1e-12)

    # The config's render section reaches the ceiling and the provenance.
    out2 = tmp_path / "t_op.h5"
    rasterize_target_stage(tmp_path / "iso.h5", out2, tmp_path / "t_op.png", sampling, tcfg, 0, render={"opacity": 0.3})
    t2 = load_target(out2)
    ref2 = ceiling_metrics(x, sigma0, t2.cameras, t2.alpha, RenderConfig(opacity=0.3))
    np.testing.assert_allclose(t2.ceiling_alpha_mse_views, ref2["alpha_mse_views"], rtol=1e-5)
    assert abs(t2.ceiling_alpha_mse - t.ceiling_alpha_mse) > 1e-3
    with h5py.File(out2) as f:
        # the provenance holds the renderer's full resolved settings (it always runs on the CPU)
        from physmorph.settings.params import to_plain

        assert json.loads(f.attrs["config"])["render"] == to_plain(RenderConfig(opacity=0.3, device="cpu"))

    # A target without its ceiling (written before it was stored) names the file and the field.
    from physmorph.records.h5io import stamp_checksum

    with h5py.File(out, "a") as f:
        del f.attrs["ceiling_alpha_mse"]
        stamp_checksum(f)
    with pytest.raises(StageInputError, match=r"t\.h5.*'ceiling_alpha_mse'"):
        load_target(out)
    with h5py.File(out2, "a") as f:
        del f["ceiling_iou_views"]
        stamp_checksum(f)
    with pytest.raises(StageInputError, match=r"t_op\.h5.*missing field 'ceiling_iou_views'"):
        load_target(out2)


def test_a_target_cut_off_by_the_image_border_is_named(tmp_path):
    """A shape taller than the cameras frame: the stage warns, naming the file, the shape and the
    views, and records them; a shape inside every view does neither."""
    import h5py

    from physmorph.settings.sections import SamplingConfig, TargetConfig
    from physmorph.meshes.shapes import ShapeSpec
    from physmorph.meshes.prepare import prepare_mesh
    from physmorph.morph.targets import TargetCropWarning, rasterize_target

    tc = TargetConfig(cameras=4, width=24, height=16, supersample=1, surface_points=100)
    sampling = SamplingConfig(16, 1, 1, 75.0, 0.7)
    prepare_mesh(ShapeSpec("small", "isosphere", size=10.0), None, tmp_path / "small.h5")
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error", TargetCropWarning)
        summary = rasterize_target(tmp_path / "small.h5", tmp_path / "ts.h5", sampling, tc)
    assert summary["cropped_views"] == []
    tall = trimesh.creation.box(extents=(2.0, 25.0, 2.0))
    tall.export(tmp_path / "tall.obj")
    prepare_mesh(ShapeSpec("tall", "file", size=25.0, file="tall.obj"), tmp_path / "tall.obj", tmp_path / "tall.h5")
    with pytest.warns(TargetCropWarning, match=r"tall\.h5 \(shape 'tall'\).*views \[0, 1, 2, 3\] of 4"):
        summary = rasterize_target(tmp_path / "tall.h5", tmp_path / "tt.h5", SamplingConfig(32, 1, 1, 75.0, 0.7), tc)
    assert summary["cropped_views"] == [0, 1, 2, 3]
    with h5py.File(tmp_path / "tt.h5") as f:
        assert list(f.attrs["cropped_views"]) == [0, 1, 2, 3]
