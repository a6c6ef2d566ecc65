"""What a dry run says of a user's own meshes before any job (physmorph.meshes.user_shapes): each
mesh the run would refuse is refused in one line naming the file and the reason (a too large size
with the largest that fits, which the sampler indeed accepts); two bodies are warned; the volume
advice never names a size that does not fit."""

import numpy as np
import pytest
import trimesh

from physmorph.meshes.errors import MeshError
from physmorph.meshes.fit import region_size, target_cameras, volume_mismatch
from physmorph.meshes.mesh_record import mesh_record
from physmorph.meshes.particles import sample_volume
from physmorph.meshes.prepare import normalize_mesh
from physmorph.meshes.repair import load_raw_mesh, repair_mesh
from physmorph.meshes.user_shapes import check_user_shape, user_shape_report
from physmorph.settings.workflow import load_settings
from physmorph.base.grid import Grid


def _write(directory, case):
    path = directory / f"{case}.obj"
    if case == "garbage":
        path.write_bytes(b"\x00\xff garbage \x13\x37" * 50)
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "folder":
        path.mkdir()
    elif case == "flat":
        trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False).export(path)
    elif case == "open":  # a hemisphere: closing it is no repair
        s = trimesh.creation.icosphere(3)
        trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0]).export(path)
    elif case == "long":
        trimesh.creation.capsule(height=30, radius=1).export(path)
    elif case == "two":
        a = trimesh.creation.icosphere(2)
        trimesh.util.concatenate([a, a.copy().apply_translation([3, 0, 0])]).export(path)
    return path


def _settings(path, size):
    return load_settings("config/config.yaml", overrides={"shapes": {"mine": {"kind": "file", "path": str(path),
                                                                              "size": size}}})


REFUSALS = [("garbage", "cannot be read as a mesh"), ("empty", "cannot be read as a mesh (no vertices or faces in its 0 bytes)"),
            ("folder", "is a folder, not a mesh file"), ("flat", "mesh is flat"),
            ("open", "the mesh is open (48 edges on a hole's rim), and closing it changed the volume"),
            ("long", "size 30 does not fit grid 32's particle region [-13, 13]^3: the largest size that fits is 26.0")]


@pytest.mark.parametrize("case, reason", REFUSALS, ids=[c for c, _ in REFUSALS])
def test_a_mesh_the_run_would_refuse_is_refused_in_one_line(tmp_path, case, reason):
    path = _write(tmp_path, case)
    settings = _settings(path, 30.0 if case == "long" else 18.0)
    with pytest.raises(MeshError) as refused:
        check_user_shape(settings, "mine", target_cameras(settings))
    line = str(refused.value)
    assert "\n" not in line and str(path) in line and reason in line, line
    if case == "open":  # says what to do, and never to delete anything
        assert "close its holes in a mesh editor" in line and "delete" not in line
    assert user_shape_report(settings, target_cameras(settings)) == ([], line)


def test_the_largest_size_named_is_one_the_sampler_accepts(tmp_path):
    path = _write(tmp_path, "long")
    record = mesh_record(path)
    largest = region_size(record.unit_lo, record.unit_hi, 32)
    repaired, _, _ = repair_mesh(load_raw_mesh(path), str(path))
    grid = Grid(32, -16.0, 16.0)
    assert len(sample_volume(normalize_mesh(repaired, largest)[0], grid, 1, 1, seed=0, name="long")[0]) > 0
    with pytest.raises(MeshError, match="do not fit the grid's particle region"):
        sample_volume(normalize_mesh(repaired, largest + 0.2)[0], grid, 1, 1, seed=0, name="long")
    settings = _settings(path, largest)
    assert check_user_shape(settings, "mine", target_cameras(settings)) == []


def test_separate_bodies_are_warned(tmp_path):
    path = _write(tmp_path, "two")
    settings = _settings(path, 12.0)
    warnings = check_user_shape(settings, "mine", target_cameras(settings))
    assert len(warnings) == 1 and "2 separate bodies" in warnings[0] and str(path) in warnings[0]


def test_the_volume_advice_never_exceeds_the_largest_size_that_fits():
    # a target at 50 % of the source's volume: 18 * 2^(1/3) = 22.7 holds it; with 21.0 the largest, a smaller source
    assert "a target size of 22.7 (now 18) would hold" in volume_mismatch("x", 2000.0, 1000.0, 18.0)
    capped = volume_mismatch("x", 2000.0, 1000.0, 18.0, largest=21.0)
    assert "22.7" not in capped and "the largest target size that fits the grid, 21.0, holds 79 % of it" in capped
    assert np.isclose(100 * 0.5 * (21.0 / 18.0) ** 3, 79.4, atol=0.05)
