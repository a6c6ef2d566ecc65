"""Size advice for a user's mesh (physmorph.meshes.fit): the volume of the source, inside the
particles' region, with the source shrunk where a long mesh cannot hold it."""

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from physmorph.settings.workflow import load_settings
from physmorph.base.grid import BOUNDARY_CELLS, Grid
from physmorph.meshes.errors import MeshError
from physmorph.meshes.prepare import normalize_mesh
from physmorph.meshes.fit import (SIZE_STEP, VIEW_MARGIN_PX, VOLUME_SLACK, advise_size, isosphere_size_for_volume,
                                  isosphere_volume, main, shape_name)
from physmorph.meshes.particles import sample_volume

REPO = Path(__file__).resolve().parents[2]


def _cone() -> trimesh.Trimesh:
    """Its volume centroid sits a quarter of the height from the base: bounds are not symmetric about it."""
    return trimesh.creation.cone(radius=1.0, height=5.0, sections=32)


def test_a_compact_mesh_keeps_the_source_and_holds_its_volume():
    a = advise_size(trimesh.creation.box(extents=(1.0, 2.0, 1.5)), volume=1170.0, grid_res=32)
    assert a.keeps_source and a.source_size is None
    assert a.size == a.size_for_volume
    mesh, _, _ = normalize_mesh(trimesh.creation.box(extents=(1.0, 2.0, 1.5)), a.size)
    # rounded down to SIZE_STEP: at most one step's worth of volume short, never over
    assert 1170.0 * (1 - 3 * SIZE_STEP / a.size) <= mesh.volume <= 1170.0


def test_a_long_mesh_gets_the_largest_size_that_fits_and_a_source_of_its_volume():
    box = trimesh.creation.box(extents=(1.0, 1.0, 6.0))
    a = advise_size(box, volume=1170.0, grid_res=32)
    assert a.size_for_volume == pytest.approx((1170.0 * 36) ** (1 / 3), abs=SIZE_STEP)
    # the region is 3 cells of dx = 1 from each face of [-16, 16]: the box's half-length is 13
    assert a.region == (-13.0, 13.0) and a.max_size == pytest.approx(26.0)
    assert not a.keeps_source and a.size == a.max_size
    assert a.target_volume == pytest.approx(26.0 ** 3 / 36)
    assert isosphere_volume(a.source_size) == pytest.approx(a.target_volume, rel=3 * SIZE_STEP / a.source_size)


def test_the_largest_size_is_where_sampling_starts_to_refuse(tmp_path):
    """The advice places the mesh as prepare_mesh does (volume centroid at the origin), so its
    largest size is accepted by particle sampling and one step more is not."""
    cone = _cone()
    a = advise_size(cone, volume=5000.0, grid_res=32)
    assert not a.keeps_source
    grid = Grid(res=32)
    mesh, _, _ = normalize_mesh(cone, a.max_size)
    x, _, _ = sample_volume(mesh, grid, ppc_surface=1, ppc_interior=1, seed=0)
    assert len(x) > 0
    too_big, _, _ = normalize_mesh(cone, a.max_size + 2 * SIZE_STEP)
    with pytest.raises(MeshError, match="particle region"):
        sample_volume(too_big, grid, ppc_surface=1, ppc_interior=1, seed=0)
    # the centroid is off the bounding box's centre, so a symmetric bound would be wrong
    assert a.max_size < 2 * 13.0 - SIZE_STEP


def test_a_finer_grid_leaves_more_room():
    box = trimesh.creation.box(extents=(1.0, 1.0, 6.0))
    coarse, fine = advise_size(box, 1170.0, grid_res=24), advise_size(box, 1170.0, grid_res=64)
    assert coarse.max_size == pytest.approx(2 * (16 - BOUNDARY_CELLS * 32 / 24), abs=SIZE_STEP)
    assert fine.max_size == pytest.approx(2 * (16 - BOUNDARY_CELLS * 32 / 64), abs=SIZE_STEP)


@pytest.mark.parametrize("need, keeps", [(26.2, True), (27.0, False)])
def test_a_few_percent_short_keeps_the_source(need, keeps):
    """A box whose size for 1170 units^3 is ``need``: at the 26 that fits it holds 97.7 % of the
    volume (inside VOLUME_SLACK: the source stays) or 89 % (the source shrinks)."""
    length = np.sqrt(need ** 3 / 1170.0)
    a = advise_size(trimesh.creation.box(extents=(1.0, 1.0, length)), volume=1170.0, grid_res=32)
    assert a.max_size == pytest.approx(26.0) and a.size_for_volume > a.max_size
    assert a.keeps_source == keeps
    assert a.keeps_source == (a.target_volume >= (1 - VOLUME_SLACK) * 1170.0)
    assert a.size == a.max_size


def test_shape_names_are_valid():
    assert shape_name("rocker-arm") == "rockerarm"
    assert shape_name("3d_model") == "mesh3dmodel"
    assert shape_name("bunny", taken={"bunny", "iso"}) == "bunnymine"
    assert shape_name("bunny", taken={"bunny", "bunnymine"}) == "bunnymine2"


@pytest.mark.parametrize("file_name, name, expected", [
    ("bunny.obj", None, "bunnymine"),  # the stem is a shipped shape's name
    ("suz.obj", "my_suz", "mysuz"),  # a name asked for with an underscore the workflow refuses
    ("a, b #1.obj", None, "ab1"),  # a path YAML must quote (',' and '#')
])
def test_the_printed_config_is_one_the_workflow_accepts(tmp_path, capsys, monkeypatch, file_name, name, expected):
    """The helper's whole output, redirected to a file, is a config the workflow loads with the
    shipped one: the shape named validly and apart from the config's, the path as given."""
    trimesh.creation.icosphere(2, 1.0).export(tmp_path / file_name)
    monkeypatch.chdir(tmp_path)
    args = [file_name, "--configfile", str(REPO / "config/config.yaml")] + (["--name", name] if name else [])
    assert main(args) == 0
    out = capsys.readouterr().out
    (tmp_path / "mine.yaml").write_text(out)
    s = load_settings(REPO / "config/config.yaml", tmp_path / "mine.yaml")
    (experiment,) = yaml.safe_load(out)["experiments"]
    assert s.experiment(experiment).target == expected
    assert s.shape(expected).path == file_name and s.shape("bunny").kind == "file"  # the shipped bunny kept
    if expected != (name or file_name.rsplit(".", 1)[0]):
        assert f"# the shape is named {expected}" in out


def test_isosphere_size_for_volume_inverts_isosphere_volume():
    for s in (8.0, 13.7, 20.0):
        assert isosphere_size_for_volume(isosphere_volume(s)) == pytest.approx(s)


def test_the_printed_config_is_valid_and_matches_volumes(tmp_path, capsys, monkeypatch):
    """As a user runs it: an open mesh file (repaired as prepare_mesh repairs it), the YAML pasted
    into a config that the workflow's loader accepts, source and target of one volume."""
    open_box = trimesh.creation.box(extents=(1.0, 1.0, 8.0))
    open_box = trimesh.Trimesh(open_box.vertices, open_box.faces[:-1], process=False)  # one triangle missing
    path = tmp_path / "long.obj"
    open_box.export(path)
    monkeypatch.chdir(tmp_path)
    assert main([str(path.name), "--configfile", str(REPO / "config/config.yaml")]) == 0
    out = capsys.readouterr().out
    assert "repaired" in out
    (tmp_path / "mine.yaml").write_text(out)  # `fit mesh > mine.yaml`: the advice is its comments
    snippet = yaml.safe_load(out)
    assert set(snippet) == {"shapes", "experiments"}
    s = load_settings(REPO / "config/config.yaml", tmp_path / "mine.yaml")
    (exp,) = snippet["experiments"].values()
    src, tgt = s.shapes[exp["source"]], s.shapes[exp["target"]]
    assert src.kind == "isosphere" and tgt.path == "long.obj"
    assert tgt.size == pytest.approx(26.0)
    assert isosphere_volume(src.size) == pytest.approx(26.0 ** 3 / 64, rel=0.02)


def test_a_source_that_is_not_an_isosphere_is_refused(tmp_path, capsys):
    path = tmp_path / "b.obj"
    trimesh.creation.box().export(path)
    with pytest.raises(SystemExit):
        main([str(path), "--configfile", str(REPO / "config/config.yaml"), "--source", "A"])
    assert "isosphere" in capsys.readouterr().err


def test_the_size_also_keeps_the_target_whole_in_every_view():
    """A tall mesh at the default grid: the 26-unit particle region would take it, but the target's
    cameras (fov 40 degrees at distance 36, from 21 degrees above) cut off its ends, and the render
    loss would never see them. The advice stops where the last vertex leaves a view."""
    from physmorph.base.cameras import ring_cameras

    cams = ring_cameras(8, 21.0, 40.0, 160, 90, 36.0)
    tall = trimesh.creation.box(extents=(1.0, 6.0, 1.0))
    a = advise_size(tall, volume=1170.0, grid_res=32, cameras=cams)
    assert a.max_size == pytest.approx(26.0) and a.view_size < a.max_size
    assert a.size == a.view_size == a.largest and not a.keeps_source

    def inside(size):
        mesh, _, _ = normalize_mesh(tall, size)
        uv, z = cams.project(mesh.vertices)
        m = VIEW_MARGIN_PX
        return bool(np.all(z > 0) and np.all((uv >= m) & (uv <= [cams.width - m, cams.height - m])))

    assert inside(a.view_size) and not inside(a.view_size + 2 * SIZE_STEP)
    # a compact mesh holds the volume well inside the views
    cube = advise_size(trimesh.creation.box(), 1170.0, 32, cameras=cams)
    assert cube.keeps_source and cube.size == cube.size_for_volume < cube.view_size


def test_at_the_advised_size_the_target_stage_sees_no_crop(tmp_path):
    """The fit and the target stage agree: at the advised size the silhouette keeps off the image
    edge in every view (no TargetCropWarning); half a unit larger it reaches it."""
    import warnings

    from physmorph.base.cameras import ring_cameras
    from physmorph.settings.sections import SamplingConfig, TargetConfig
    from physmorph.meshes.shapes import ShapeSpec
    from physmorph.meshes.prepare import prepare_mesh
    from physmorph.morph.targets import TargetCropWarning, rasterize_target

    tc = TargetConfig(surface_points=100)  # the default views: 8 x 160x90
    cams = ring_cameras(tc.cameras, tc.elevation_deg, tc.fov_y_deg, tc.width, tc.height, tc.distance)
    tall = trimesh.creation.box(extents=(1.0, 6.0, 1.0))
    tall.export(tmp_path / "tall.obj")
    size = advise_size(tall, volume=1170.0, grid_res=32, cameras=cams).size
    sampling = SamplingConfig(32, 1, 1, 75.0, 0.7)
    for s, cropped in ((size, False), (size + 0.5, True)):
        spec = ShapeSpec("tall", "file", size=s, file="tall.obj")
        prepare_mesh(spec, tmp_path / "tall.obj", tmp_path / f"tall_{s}.h5")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            summary = rasterize_target(tmp_path / f"tall_{s}.h5", tmp_path / f"t_{s}.h5", sampling, tc)
        assert bool(summary["cropped_views"]) == cropped, (s, summary["cropped_views"])
        assert any(issubclass(w.category, TargetCropWarning) for w in caught) == cropped


def test_two_targets_get_their_own_shrunk_sources(tmp_path, capsys, monkeypatch):
    """Two long meshes of different volumes: each one's advice shrinks the source to its volume.
    Named after the target, the sources do not collide when both blocks go into one config (both
    were `isosmall`, and the second block's size overwrote the first's)."""
    monkeypatch.chdir(tmp_path)
    blocks = []
    for length in (8.0, 10.0):
        box = trimesh.creation.box(extents=(1.0, 1.0, length))
        box.export(tmp_path / f"long{length:.0f}.obj")
        assert main([f"long{length:.0f}.obj", "--configfile", str(REPO / "config/config.yaml")]) == 0
        out = capsys.readouterr().out
        blocks.append(yaml.safe_load(out[out.index("shapes:"):]))
    (a,), (b,) = (list(block["experiments"].values()) for block in blocks)
    for i, block in enumerate(blocks):
        (tmp_path / f"block{i}.yaml").write_text(yaml.safe_dump(block))
    s = load_settings(REPO / "config/config.yaml", tmp_path / "block0.yaml", tmp_path / "block1.yaml")
    for exp, length in ((a, 8.0), (b, 10.0)):
        src, tgt = s.shapes[exp["source"]], s.shapes[exp["target"]]
        target_volume = tgt.size ** 3 / length ** 2  # the box 1 x 1 x length at longest extent tgt.size
        assert isosphere_volume(src.size) == pytest.approx(target_volume, rel=0.02)
    assert {name for block in blocks for name in block["experiments"]} <= set(s.experiments)
    assert (a["source"], b["source"]) == ("isolong8", "isolong10")  # valid shape names: letters and digits


def test_the_isospheres_volume_without_its_mesh_is_its_meshs():
    """fit.isosphere_unit_volume (numpy only, for the workflow's volume warnings) is the volume of
    the mesh physmorph.meshes.shapes.isosphere builds, at any size."""
    from physmorph.meshes.fit import isosphere_unit_volume, isosphere_volume
    from physmorph.meshes.shapes import isosphere

    assert isosphere_unit_volume() == pytest.approx(isosphere(radius=0.5).volume, rel=1e-12)
    assert isosphere_volume(13.7) == pytest.approx(isosphere(radius=6.85).volume, rel=1e-12)
