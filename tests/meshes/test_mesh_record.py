"""The mesh record cache (physmorph.meshes.mesh_record): one small file a record, read back equal,
measured again when its file is damaged or the mesh changed; a letter's volume from the cache
equal to its mesh's."""

import trimesh

import physmorph.meshes.mesh_record as mr
from physmorph.meshes.shapes import letter_mesh


def _records(cache):
    return sorted((cache / "physmorph" / "mesh_records").glob("*.json"))


def test_each_record_is_its_own_file_read_back_equal(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(mr, "_KNOWN", {})
    paths = []
    for i, radius in enumerate((1.0, 2.0)):
        path = tmp_path / f"ball{i}.obj"
        trimesh.creation.icosphere(2, radius).export(path)
        paths.append(path)
    first = [mr.mesh_record(p) for p in paths]
    assert len(_records(cache)) == 2 and first[0].unit_volume > 0
    # a new process (no memo) reads the files, not the meshes
    monkeypatch.setattr(mr, "_KNOWN", {})
    monkeypatch.setattr(mr, "_measure", lambda path: (_ for _ in ()).throw(AssertionError(f"measured {path}")))
    assert [mr.mesh_record(p) for p in paths] == first
    # a damaged record is measured again; so is a changed mesh (another key)
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(mr, "_KNOWN", {})
    _records(cache)[0].write_text("{not json")
    assert [mr.mesh_record(p) for p in paths] == first
    trimesh.creation.box((1.0, 2.0, 3.0)).export(paths[0])
    changed = mr.mesh_record(paths[0])
    assert changed.unit_volume != first[0].unit_volume and len(_records(cache)) == 3


def test_a_letters_volume_is_its_meshes_and_is_kept(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    volume = mr.letter_volume("S", 18.0, None)
    assert volume == float(letter_mesh("S", 18.0, None).volume)
    assert len(_records(cache)) == 1
    import physmorph.meshes.shapes as shapes

    monkeypatch.setattr(shapes, "letter_mesh", lambda *a: (_ for _ in ()).throw(AssertionError("built again")))
    assert mr.letter_volume("S", 18.0, None) == volume
