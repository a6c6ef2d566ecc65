"""The GPU bundle's builder (benchmarks/gpu_bundle.py) and the device's check script
(benchmarks/gpu_check.sh), offline: the builder's pins, its stripping and packing, its meshes, and
the check's refusals before it runs anything. pip's download for the device's Python needs the
package index and is not run here."""

from __future__ import annotations

import hashlib
import os
import subprocess
import tarfile
from pathlib import Path

import pytest

from benchmark_scripts import load_benchmark

bundle = load_benchmark("gpu_bundle")
REPO = Path(__file__).resolve().parents[2]


def test_every_bundled_package_is_pinned_by_the_lock():
    """Each package the bundle carries at the lock's version; pip's spellings (case, - and _) alike."""
    pins = bundle.lock_pins(REPO / "environment.lock")
    assert [p.split("==")[0].lower().replace("_", "-") for p in pins] == [bundle._key(n) for n in bundle.BUNDLED]
    lock = (REPO / "environment.lock").read_text()
    assert all(f"\n{p}\n" in lock for p in pins)
    assert any(p.startswith("taichi==") for p in pins)


def test_a_package_the_lock_lacks_is_named(tmp_path):
    lock = tmp_path / "lock.txt"
    lock.write_text("# pins\nTaichi==1.7.4\npydantic_core==2.50.4\n")
    assert bundle.lock_pins(lock, ("taichi", "pydantic-core")) == ["Taichi==1.7.4", "pydantic_core==2.50.4"]
    with pytest.raises(SystemExit, match="no pin for trimesh"):
        bundle.lock_pins(lock, ("taichi", "trimesh"))


def test_the_site_is_stripped_and_packed_whole(tmp_path):
    """strip_site removes exactly the listed paths and counts their bytes; the archive unpacks to
    the stripped tree, file for file."""
    site = tmp_path / "site"
    files = {"taichi/__init__.py": b"x" * 10, "taichi/_lib/core/core.so": b"c" * 100,
             "taichi/_lib/c_api/lib/capi.so": b"a" * 1000, "taichi/assets/logo.png": b"p" * 50,
             "bin/ti": b"b" * 7, "pydantic/main.py": b"m" * 20}
    for rel, data in files.items():
        (site / rel).parent.mkdir(parents=True, exist_ok=True)
        (site / rel).write_bytes(data)
    assert bundle.strip_site(site) == 1000 + 50 + 7
    kept = {rel: data for rel, data in files.items() if rel.split("/")[0] != "bin" and "/c_api/" not in rel
            and "/assets/" not in rel}
    assert {str(p.relative_to(site)) for p in site.rglob("*") if p.is_file()} == set(kept)
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "bunny.obj").write_bytes(b"v 0 0 0\n")
    archive = tmp_path / "bundle.tar.xz"
    bundle.pack([site, meshes], archive)
    out = tmp_path / "unpacked"
    with tarfile.open(archive, "r:xz") as tar:
        tar.extractall(out, filter="data")
    got = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert got == {**{f"site/{rel}": data for rel, data in kept.items()}, "meshes/bunny.obj": b"v 0 0 0\n"}


def test_the_meshes_are_copied_with_their_checksums(tmp_path, mesh_dir, raw_mesh_sha256):
    names = bundle.copy_meshes(mesh_dir, tmp_path / "meshes")
    assert sorted(names) == sorted(raw_mesh_sha256)
    for name in names:
        assert hashlib.sha256((tmp_path / "meshes" / name).read_bytes()).hexdigest() == raw_mesh_sha256[name]


def test_a_damaged_mirror_is_refused(tmp_path, mesh_dir):
    from physmorph.meshes.errors import FetchError

    mirror = tmp_path / "mirror"
    mirror.mkdir()
    for p in mesh_dir.iterdir():
        if p.is_file():
            (mirror / p.name).write_bytes(p.read_bytes())
    (mirror / "cow.obj").write_bytes(b"v 0 0 0\n")
    with pytest.raises(FetchError, match="cow.obj"):
        bundle.copy_meshes(mirror, tmp_path / "meshes")


def _check(tmp_path, **env) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(REPO / "benchmarks" / "gpu_check.sh")], capture_output=True, text=True,
                          env={**os.environ, "OUT": str(tmp_path / "out"), **env}, timeout=60)


def test_the_check_refuses_a_missing_bundle_in_one_line(tmp_path):
    res = _check(tmp_path, GPU_BUNDLE=str(tmp_path / "none"))
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "make gpu-bundle" in res.stderr
    assert "===" not in res.stdout  # no step ran


def test_the_check_refuses_a_bundle_for_another_python(tmp_path):
    b = tmp_path / "b"
    b.mkdir()
    (b / "bundle.tar.xz").write_bytes(b"")
    (b / "MANIFEST.txt").write_text("python 2.7\nplatform manylinux_2_28_x86_64\n")
    res = _check(tmp_path, GPU_BUNDLE=str(b))
    assert res.returncode == 2
    assert "built for Python 2.7" in res.stderr and "PYTHON_DEVICE=" in res.stderr
    assert "===" not in res.stdout


def test_a_missing_mirror_is_named_in_one_line_before_any_download(tmp_path, monkeypatch):
    """The meshes are checked first: a mirror without them stops the builder with the mesh and the
    folder named, before pip runs and without leaving a bundle."""
    monkeypatch.setattr(bundle, "install_site", lambda *a: pytest.fail("pip ran before the meshes were checked"))
    monkeypatch.setattr("sys.argv", ["gpu_bundle.py", "--mesh-dir", str(tmp_path / "none"), "--out", str(tmp_path / "b")])
    with pytest.raises(SystemExit, match=r"stanford-bunny.obj: not found in mesh mirror .*none.*--mesh-dir"):
        bundle.main()
    assert not (tmp_path / "b").exists()
    assert not list(tmp_path.glob(".gpu_bundle_build*"))
