"""Stages 1-2: fetch_mesh (checksums, mirror, atomicity) and prepare_mesh (repair, normalise)."""

import hashlib
import json

import h5py
import numpy as np
import pytest
import trimesh

from physmorph.records.h5io import StageInputError, stamp_checksum
from physmorph.meshes.errors import FetchError, MeshError
from physmorph.meshes.shapes import ShapeSpec
from physmorph.meshes.fetch import fetch_mesh
from physmorph.meshes.prepare import load_mesh, prepare_mesh
from physmorph.meshes.repair import load_raw_mesh, ray_winding_vote, remesh_winding_number, repair_mesh, solid_problem, winding_number


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _leftovers(directory):
    return sorted(p.name for p in directory.iterdir()) if directory.exists() else []


# ---------------------------------------------------------------------------------------- fetch

def test_fetch_file_url_verifies_and_writes(tmp_path):
    data = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    src = tmp_path / "src" / "m.obj"
    src.parent.mkdir()
    src.write_bytes(data)
    dest = fetch_mesh("m.obj", src.as_uri(), _sha(data), tmp_path / "out")
    assert dest == tmp_path / "out" / "m.obj"
    assert dest.read_bytes() == data
    assert _leftovers(tmp_path / "out") == ["m.obj"]


def test_fetch_checksum_mismatch_names_both_and_leaves_nothing(tmp_path):
    src = tmp_path / "m.obj"
    src.write_bytes(b"some bytes")
    wrong = "0" * 64
    with pytest.raises(FetchError) as err:
        fetch_mesh("m.obj", src.as_uri(), wrong, tmp_path / "out")
    msg = str(err.value)
    assert "m.obj" in msg and wrong in msg and _sha(b"some bytes") in msg
    assert _leftovers(tmp_path / "out") == []


def test_fetch_unreachable_url_leaves_nothing(tmp_path):
    with pytest.raises(FetchError, match="could not download"):
        fetch_mesh("x.obj", "http://127.0.0.1:9/x", "0" * 64, tmp_path / "out", timeout=2.0)
    assert _leftovers(tmp_path / "out") == []


def test_fetch_missing_file_in_mirror(tmp_path):
    (tmp_path / "mirror").mkdir()
    with pytest.raises(FetchError, match="not found in mesh mirror"):
        fetch_mesh("absent.obj", "http://127.0.0.1:9/x", "0" * 64, tmp_path / "out", mesh_dir=tmp_path / "mirror")
    assert _leftovers(tmp_path / "out") == []


def test_fetch_replaces_a_corrupt_existing_file(tmp_path):
    data = b"good"
    src = tmp_path / "m.obj"
    src.write_bytes(data)
    out = tmp_path / "out"
    out.mkdir()
    (out / "m.obj").write_bytes(b"truncated")
    fetch_mesh("m.obj", src.as_uri(), _sha(data), out)
    assert (out / "m.obj").read_bytes() == data


def test_fetch_from_mirror_matches_published_checksums(tmp_path, mesh_dir, raw_mesh_sha256):
    for name, sha in raw_mesh_sha256.items():
        dest = fetch_mesh(name, "http://127.0.0.1:9/never-used", sha, tmp_path, mesh_dir=mesh_dir)
        assert dest.read_bytes() == (mesh_dir / name).read_bytes()
    assert sorted(_leftovers(tmp_path)) == sorted(raw_mesh_sha256)


# -------------------------------------------------------------------------------- procedural

def test_isosphere_is_once_subdivided_icosahedron(tmp_path):
    summary = prepare_mesh(ShapeSpec("iso", "isosphere", size=14.0), None, tmp_path / "iso.h5")
    mesh = load_mesh(tmp_path / "iso.h5")
    assert (len(mesh.vertices), len(mesh.faces)) == (42, 80)
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices, axis=1), 7.0, rtol=1e-12)
    assert mesh.is_watertight and summary["watertight"]
    # A polyhedron inscribed in the sphere: less than the ball, but not by much at 80 faces.
    ball = 4.0 / 3.0 * np.pi * 7.0 ** 3
    assert 0.8 * ball < summary["volume"] < ball
    assert summary["repair"] == []


@pytest.mark.parametrize("glyph, genus", [("A", 1), ("S", 0), ("C", 0)])
def test_letters_are_closed_solids_with_right_topology(tmp_path, glyph, genus):
    summary = prepare_mesh(ShapeSpec(glyph, "letter", glyph=glyph, size=16.0), None, tmp_path / f"{glyph}.h5")
    mesh = load_mesh(tmp_path / f"{glyph}.h5")
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert mesh.euler_number == 2 - 2 * genus  # the A's counter is a hole through the solid
    assert len(mesh.split(only_watertight=False)) == 1
    np.testing.assert_allclose(mesh.extents.max(), 16.0, rtol=1e-9)
    np.testing.assert_allclose(mesh.extents[2], 0.3 * 16.0, rtol=1e-9)  # default extrusion depth
    np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-9)  # volume centroid at the origin
    # Curves are drawn finely: the S outline has many segments.
    if glyph == "S":
        assert summary["n_vertices"] > 200


# ---------------------------------------------------------------------------- raw meshes

RAW_SHAPES = [("bunny", "stanford-bunny.obj"), ("spot", "spot.obj"), ("cow", "cow.obj"), ("duck", "Duck.glb")]


def test_all_benchmark_shapes_come_out_watertight(tmp_path, mesh_dir):
    """The four raw meshes (three not watertight as published), the isosphere and A/S/C."""
    specs = [ShapeSpec(n, "file", file=f, size=16.0) for n, f in RAW_SHAPES]
    specs += [ShapeSpec("iso", "isosphere", size=14.0)] + [ShapeSpec(g, "letter", glyph=g) for g in "ASC"]
    for spec in specs:
        raw = mesh_dir / spec.file if spec.file else None
        out = tmp_path / f"{spec.name}.h5"
        summary = prepare_mesh(spec, raw, out)
        mesh = load_mesh(out)
        assert mesh.is_watertight and mesh.is_winding_consistent, spec.name
        assert len(mesh.split(only_watertight=False)) == 1, spec.name  # no component dropped or left over
        np.testing.assert_allclose(mesh.extents.max(), spec.size, rtol=1e-9, err_msg=spec.name)
        np.testing.assert_allclose(mesh.center_mass, 0.0, atol=1e-9, err_msg=spec.name)
        assert abs(mesh.volume - summary["raw_volume"]) <= 0.03 * summary["raw_volume"], spec.name
        with h5py.File(out) as f:
            assert bool(f.attrs["watertight"])
            assert json.loads(f.attrs["repair"]) == summary["repair"]
            assert f["faces"].dtype == np.int64 and f["vertices"].dtype == np.float64
        if spec.name in ("spot", "duck"):
            assert any(s.startswith("merge_vertices") for s in summary["repair"])
        if spec.name == "bunny":
            assert "pymeshfix" in summary["repair"]


def test_duck_node_scale_is_applied(mesh_dir):
    duck = load_raw_mesh(mesh_dir / "Duck.glb")
    # The GLB node carries a 0.01 scale: the duck is ~1.6 units, not ~160.
    assert 1.0 < duck.extents.max() < 2.5


def test_prepare_is_deterministic(tmp_path, mesh_dir):
    spec = ShapeSpec("spot", "file", file="spot.obj")
    prepare_mesh(spec, mesh_dir / "spot.obj", tmp_path / "a.h5")
    prepare_mesh(spec, mesh_dir / "spot.obj", tmp_path / "b.h5")
    a, b = load_mesh(tmp_path / "a.h5"), load_mesh(tmp_path / "b.h5")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


# ------------------------------------------------------------------------------ repair paths

def _holey_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    return sphere, trimesh.Trimesh(sphere.vertices, sphere.faces[12:], process=False)


def test_winding_number_is_one_inside_zero_outside():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    q = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.5], [2.0, 0.0, 0.0], [0.0, -1.5, 0.4]])
    np.testing.assert_allclose(winding_number(sphere, q), [1.0, 1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(ray_winding_vote(sphere, q), [1.0, 1.0, 0.0, 0.0])


@pytest.mark.parametrize("exact_budget", [5e7, 0.0], ids=["winding-number", "ray-vote"])
def test_remesh_fallback_closes_an_open_sphere(exact_budget):
    closed, holey = _holey_sphere()
    assert not holey.is_watertight
    out = remesh_winding_number(holey, resolution=24, exact_budget=exact_budget)
    assert out.is_watertight and out.is_winding_consistent
    assert abs(out.volume - closed.volume) < 0.03 * closed.volume


def _open_shell(centre) -> trimesh.Trimesh:
    """A unit icosphere at ``centre`` with the five faces around its first vertex removed: a hole
    trimesh's fill_holes leaves open."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    return trimesh.Trimesh(sphere.vertices + np.asarray(centre, float), sphere.faces[5:], process=False)


SHELL_CENTRES = ([0.0, 0.0, 0.0], [0.8, 0.3, 0.1])


def _overlapping_open_shells() -> trimesh.Trimesh:
    """Two open spheres passing through each other: open and self-intersecting."""
    return trimesh.util.concatenate([_open_shell(c) for c in SHELL_CENTRES])


def _union_volume() -> float:
    """The volume of the two closed icospheres' union, by Monte Carlo (200k points: ~0.3 %)."""
    closed = [trimesh.creation.icosphere(subdivisions=2, radius=1.0).apply_translation(c) for c in SHELL_CENTRES]
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.8, 1.3, 1.1])
    pts = np.random.default_rng(0).uniform(lo, hi, size=(200_000, 3))
    inside = closed[0].contains(pts) | closed[1].contains(pts)
    return float(inside.mean() * np.prod(hi - lo))


@pytest.mark.parametrize("exact_budget", [5e7, 0.0], ids=["winding-number", "ray-vote"])
def test_remesh_of_overlapping_open_shells_is_their_union(exact_budget):
    """Where the shells overlap a ray crosses both: hit parity called it outside (the old ray vote
    carved the overlap out, 4.9 of 6.5); the signed crossing count is the winding number, 2."""
    out = remesh_winding_number(_overlapping_open_shells(), resolution=32, exact_budget=exact_budget)
    assert solid_problem(out) is None and len(out.split(only_watertight=False)) == 1
    union = _union_volume()
    assert abs(out.volume - union) < 0.03 * union
    # what the raw mesh's volume counts twice: the lens both spheres hold (~1.5)
    assert 1.2 < out.metadata["overlap_volume"] < 1.8


def test_an_open_self_intersecting_shell_is_accepted_by_the_remesh():
    """MeshFix cannot repair it, and the raw (capped) volume counts the overlap twice: the remesh
    is checked against the raw volume less the overlap it measured, and the union is accepted."""
    fixed, steps, volume = repair_mesh(_overlapping_open_shells(), "shells")
    assert steps[-1] == "winding-number remesh (marching cubes)"
    assert solid_problem(fixed) is None and fixed.is_watertight and fixed.is_winding_consistent
    union = _union_volume()
    assert abs(fixed.volume - union) < 0.03 * union
    assert abs(volume - union) < 0.03 * union  # the reported raw volume holds the overlap once


@pytest.mark.parametrize("exact_budget", [5e7, 0.0], ids=["winding-number", "ray-vote"])
@pytest.mark.parametrize("drop", [0, 1], ids=["closed", "open"])
def test_remesh_is_a_solid_where_the_lattice_runs_through_the_faces(exact_budget, drop):
    """A box's sides lie on lattice points, where w = 1/2: marching cubes put vertices on them, and
    merging vertices by position glued the surface into edges of more than two faces (not
    watertight, negative volume). Lattice points on the surface are now on the level, off it by a
    hair, and marching cubes' own vertices are kept: closed, and the box's volume to 0.1 %."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 8.0))
    mesh = trimesh.Trimesh(box.vertices, box.faces[drop:], process=False)
    out = remesh_winding_number(mesh, resolution=64, exact_budget=exact_budget)
    assert solid_problem(out) is None
    assert abs(out.volume - 8.0) < (0.01 if exact_budget else 0.03) * 8.0


def test_remesh_of_a_box_open_on_one_side_does_not_touch_the_lattice():
    """Through the missing side a ray from outside meets one face: the ray vote called points of
    the lattice's own boundary inside, and the surface stayed open there. The lattice is padded
    by a layer held outside."""
    box = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    open_box = trimesh.Trimesh(box.vertices, box.faces[2:], process=False)  # the whole -x side gone
    out = remesh_winding_number(open_box, resolution=64, exact_budget=0.0)
    assert solid_problem(out) is None


@pytest.mark.parametrize("exact_budget", [5e7, 0.0], ids=["winding-number", "ray-vote"])
def test_remesh_turns_an_inside_out_open_mesh_outward(exact_budget):
    """Inside out, w ~ -1 inside: the winding number never reached 1/2 ("encloses no volume")."""
    closed, holey = _holey_sphere()
    inside_out = trimesh.Trimesh(holey.vertices, holey.faces[:, ::-1], process=False)
    out = remesh_winding_number(inside_out, resolution=24, exact_budget=exact_budget)
    assert solid_problem(out) is None
    assert abs(out.volume - closed.volume) < 0.03 * closed.volume


def test_solid_problem_names_the_check():
    box = trimesh.creation.box()
    assert solid_problem(box) is None
    assert solid_problem(trimesh.Trimesh(box.vertices, box.faces[1:], process=False)) == "not watertight: 3 open edges"
    doubled = trimesh.Trimesh(box.vertices, np.vstack([box.faces, box.faces[:1]]), process=False)
    assert solid_problem(doubled) == "not watertight: 3 edges shared by more than two faces"
    one_flipped = box.faces.copy()
    one_flipped[0] = one_flipped[0, ::-1]
    assert solid_problem(trimesh.Trimesh(box.vertices, one_flipped, process=False)) == "inconsistent winding"
    inverted = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    assert solid_problem(inverted).startswith("negative volume")
    assert solid_problem(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int))) == "no faces"


@pytest.mark.parametrize("broken, named", [
    (lambda box: trimesh.Trimesh(box.vertices, box.faces[1:], process=False), "not watertight: 3 open edges"),
    (lambda box: trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False), "negative volume"),
], ids=["open", "inside-out"])
def test_a_refused_repair_names_the_failed_check(monkeypatch, broken, named):
    """Whatever the last repair leaves, the refusal says which check it fails (it said "still not
    watertight" of an inside-out mesh too)."""
    import physmorph.meshes.repair as repair

    monkeypatch.setattr(repair, "remesh_winding_number", lambda mesh: broken(trimesh.creation.box(extents=(2, 2, 2))))
    with pytest.raises(MeshError) as err:
        repair_mesh(_overlapping_open_shells(), "shells.obj")
    msg = str(err.value)
    assert msg.startswith("shells.obj: irreparable, " + named) and "winding-number remesh (marching cubes)" in msg


def test_a_remesh_error_names_the_mesh(monkeypatch):
    import physmorph.meshes.repair as repair

    def no_inside(mesh):
        raise MeshError("winding-number remesh: the surface encloses no volume (inside-ness never crosses 0.5)")

    monkeypatch.setattr(repair, "remesh_winding_number", no_inside)
    with pytest.raises(MeshError, match=r"^shells\.obj: irreparable, winding-number remesh: the surface encloses no volume"):
        repair_mesh(_overlapping_open_shells(), "shells.obj")


def test_a_mesh_whose_volume_overflows_is_too_large():
    box = trimesh.creation.box()
    huge = trimesh.Trimesh(box.vertices * 1e200, box.faces, process=False)
    with pytest.raises(MeshError, match=r"^huge\.obj: too large, coordinates reach 5e\+199"):
        repair_mesh(huge, "huge.obj")


def test_small_holes_are_filled_and_volume_kept():
    box = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    open_box = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    assert not open_box.is_watertight
    fixed, steps, raw_volume = repair_mesh(open_box, "open box")
    assert fixed.is_watertight
    np.testing.assert_allclose(fixed.volume, 24.0, rtol=1e-9)
    assert "fill_holes (trimesh)" in steps


# -------------------------------------------------------------------------------- bad input

def test_corrupt_files_give_mesh_error_and_no_output(tmp_path, mesh_dir):
    bad_glb = tmp_path / "bad.glb"
    bad_glb.write_bytes((mesh_dir / "Duck.glb").read_bytes()[:2000])  # truncated download
    bad_obj = tmp_path / "bad.obj"
    bad_obj.write_bytes(b"\x00\xff garbage \x13\x37" * 50)
    for path in (bad_glb, bad_obj, tmp_path / "absent.obj"):
        out = tmp_path / f"{path.stem}.h5"
        with pytest.raises(MeshError) as err:
            prepare_mesh(ShapeSpec("x", "file", file=path.name), path, out)
        assert str(path) in str(err.value)
        assert not out.exists() and not out.with_name(out.name + ".partial").exists()


def test_raw_mesh_changed_after_fetch_is_named_before_preparation(tmp_path):
    """A raw mesh already in the download directory is verified against its sha256 again."""
    path = tmp_path / "box.obj"
    trimesh.creation.box(extents=(4.0, 5.0, 6.0)).export(path)
    sha = _sha(path.read_bytes())
    spec = ShapeSpec("box", "file", file="box.obj", size=10.0)
    assert prepare_mesh(spec, path, tmp_path / "ok.h5", raw_sha256=sha)["watertight"]
    path.write_bytes(b"\x00" * 64 + path.read_bytes()[64:])  # zeroed bytes in the file, after it was fetched
    with pytest.raises(MeshError, match=rf"box\.obj \(shape 'box'\): no longer matches its checksum \(expected sha256 {sha}"):
        prepare_mesh(spec, path, tmp_path / "bad.h5", raw_sha256=sha)
    assert not (tmp_path / "bad.h5").exists()


def test_empty_mesh_is_rejected(tmp_path):
    path = tmp_path / "empty.obj"
    path.write_text("# only vertices\nv 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(MeshError, match="empty"):
        prepare_mesh(ShapeSpec("e", "file", file="empty.obj"), path, tmp_path / "e.h5")
    assert not (tmp_path / "e.h5").exists()


def test_single_triangle_is_irreparable(tmp_path):
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="tri.obj.*encloses no volume"):
        prepare_mesh(ShapeSpec("t", "file", file="tri.obj"), path, tmp_path / "t.h5")
    assert _leftovers(tmp_path) == ["tri.obj"]


def test_junk_triangle_soup_is_irreparable(tmp_path):
    """Disconnected, mutually crossing triangles: no repair recovers a solid of the raw volume."""
    rng = np.random.default_rng(3)
    soup = trimesh.Trimesh(rng.normal(size=(90, 3)), np.arange(90).reshape(30, 3), process=False)
    path = tmp_path / "soup.obj"
    soup.export(path)
    with pytest.raises(MeshError, match="soup.obj.*irreparable"):
        prepare_mesh(ShapeSpec("s", "file", file="soup.obj"), path, tmp_path / "s.h5")
    assert _leftovers(tmp_path) == ["soup.obj"]


def test_shape_too_big_for_domain(tmp_path):
    with pytest.raises(MeshError, match="does not fit the domain"):
        prepare_mesh(ShapeSpec("big", "isosphere", size=40.0), None, tmp_path / "big.h5")
    assert not (tmp_path / "big.h5").exists()


@pytest.mark.parametrize("kwargs, match", [
    (dict(kind="cube"), "unknown kind"),
    (dict(kind="file"), "needs a 'file'"),
    (dict(kind="letter", glyph="AB"), "single-character"),
    (dict(kind="isosphere", size=-1.0), "size must be"),
])
def test_bad_shape_spec(kwargs, match):
    with pytest.raises(MeshError, match=match):
        ShapeSpec("bad", **kwargs)


def test_load_mesh_reports_missing_and_corrupt_fields(tmp_path):
    with pytest.raises(StageInputError, match="not found"):
        load_mesh(tmp_path / "absent.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(StageInputError, match="not a readable HDF5"):
        load_mesh(tmp_path / "junk.h5")
    with h5py.File(tmp_path / "nofaces.h5", "w") as f:
        f["vertices"] = np.zeros((3, 3))
        f.attrs["shape"] = "x"
    with pytest.raises(StageInputError, match=r"nofaces\.h5: no content checksum"):  # not written by a stage
        load_mesh(tmp_path / "nofaces.h5")
    with h5py.File(tmp_path / "nofaces.h5", "a") as f:
        stamp_checksum(f)
    with pytest.raises(StageInputError, match="'faces'"):
        load_mesh(tmp_path / "nofaces.h5")
    with h5py.File(tmp_path / "badidx.h5", "w") as f:
        f["vertices"] = np.zeros((3, 3))
        f["faces"] = np.array([[0, 1, 7]])
        f.attrs["shape"] = "x"
        stamp_checksum(f)
    with pytest.raises(StageInputError, match="indexes outside"):
        load_mesh(tmp_path / "badidx.h5")
