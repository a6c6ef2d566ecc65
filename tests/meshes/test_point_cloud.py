"""Point clouds as shapes (physmorph.meshes.point_cloud): points on a closed shape give a watertight
surface through them, of the shape's volume and genus, that the usual repair accepts; points that
enclose nothing are refused in one line naming the file."""

import numpy as np
import pytest
import trimesh

from physmorph.meshes.errors import MeshError
from physmorph.meshes.fit import main
from physmorph.meshes.point_cloud import point_spacing, surface_from_points
from physmorph.meshes.repair import load_raw_mesh, repair_mesh


def _genus(mesh: trimesh.Trimesh) -> float:
    return (2 - (len(mesh.vertices) - len(mesh.edges_unique) + len(mesh.faces))) / 2


def _sphere_points(n: int, seed: int = 0) -> np.ndarray:  # [n, 3] on the unit sphere
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


@pytest.mark.parametrize("n", [500, 3000])
def test_points_on_a_sphere_become_a_closed_sphere_of_its_volume(n):
    points = _sphere_points(n)
    mesh = surface_from_points(points, "sphere")
    assert mesh.is_watertight and _genus(mesh) == 0 and len(mesh.split()) == 1
    assert mesh.volume == pytest.approx(4 / 3 * np.pi, rel=0.06)
    # the surface runs through the points, not a voxel outside them: the sphere within half their spacing
    _, distance, _ = trimesh.proximity.closest_point(mesh, _sphere_points(200, seed=1))
    assert distance.max() < 0.5 * point_spacing(points)


def test_a_torus_keeps_its_hole_and_a_filled_cloud_its_volume():
    torus = trimesh.creation.torus(1.0, 0.35)
    mesh = surface_from_points(torus.sample(4000, seed=0), "torus")
    assert mesh.is_watertight and _genus(mesh) == 1
    assert mesh.volume == pytest.approx(torus.volume, rel=0.08)
    q = np.random.default_rng(2).uniform(-1, 1, (20000, 3))
    solid = surface_from_points(q[np.linalg.norm(q, axis=1) < 1], "ball")
    assert solid.is_watertight and solid.volume == pytest.approx(4 / 3 * np.pi, rel=0.1)


@pytest.mark.parametrize("case", ["hemisphere", "plane", "few"])
def test_points_that_enclose_nothing_are_refused(case):
    p = _sphere_points(2000)
    points = {"hemisphere": p[p[:, 2] > 0], "plane": np.c_[p[:, :2], np.zeros(len(p))], "few": p[:50]}[case]
    with pytest.raises(MeshError, match=r"^cloud: (no closed surface results|no faces and only 50 points)"):
        surface_from_points(points, "cloud")


def test_a_point_cloud_file_is_a_shape_the_repair_and_the_fit_helper_take(tmp_path, capsys):
    """A PLY of points only and an XYZ text file load as their surface; the repair names the step;
    the fit helper prints a size for it."""
    ply, xyz = tmp_path / "ball.ply", tmp_path / "ball.xyz"
    trimesh.PointCloud(_sphere_points(2000) * 5.0).export(ply)
    np.savetxt(xyz, _sphere_points(2000) * 5.0)
    for path in (ply, xyz):
        repaired, steps, _ = repair_mesh(load_raw_mesh(path), str(path))
        assert repaired.is_watertight and any("surface of 2000 points" in s for s in steps), steps
    assert main([str(xyz), "--configfile", "config/config.yaml"]) == 0
    out = capsys.readouterr().out
    assert "surface of 2000 points" in out and "ball: {kind: file" in out
