"""Build .gpu_bundle/, what a lent GPU machine needs to run the GPU check (benchmarks/gpu_check.sh).

Such a machine reaches no package index, has its own Python (3.12) with PyTorch's CUDA build,
NumPy, SciPy, h5py, scikit-image, pandas, matplotlib and pytest, and receives the working tree
(tracked files and what is carried) up to 64 MiB. The bundle holds what it lacks:

- bundle.tar.xz, one xz-compressed tar (xz: a third smaller than the wheels' deflate) of
  - site/: the packages of environment.lock that the GPU check imports and that image lacks
    (BUNDLED below, at the lock's versions), installed by pip for the device's Python and platform
    (binary wheels only, no dependencies resolved: each is named), less Taichi's C API library,
    its C headers and its GUI assets, which Python never loads (55 MB of its 163);
  - meshes/: the raw benchmark meshes of config/config.yaml's raw_meshes, copied from a local
    mirror and checked against their SHA-256;
- MANIFEST.txt: the Python version and platform it was built for, the packages, the meshes and
  the commit.

Left out for its size: shapely, which only the letter shapes' outlines need (the GPU check morphs
the isosphere into the bunny).

    .venv/bin/python benchmarks/gpu_bundle.py [--python 3.12] [--mesh-dir ../shared/meshes]
    make gpu-bundle

then, with the device tool, the command `bash benchmarks/gpu_check.sh` carrying `.gpu_bundle`
(docs/cluster.md). The builder refuses a bundle that would not travel: the tracked and untracked
files that git does not ignore plus the bundle over TRAVEL_LIMIT.
"""

from __future__ import annotations

import argparse
import hashlib
import lzma
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# The GPU check's run-time imports the device image lacks, and what they need that it lacks too
# (Taichi: dill; pydantic: its core, annotated-types, typing-inspection; trimesh's inside tests:
# Embree's rays through embreex, which take the paper profile's preparation from minutes to
# seconds, and rtree where they fall back).
BUNDLED = ("taichi", "dill", "pydantic", "pydantic_core", "annotated-types", "typing-inspection", "trimesh",
           "embreex", "rtree", "pymeshfix", "plyfile")
# Parts of the installed packages that Python never loads (paths relative to the site directory).
DROPPED = ("taichi/_lib/c_api", "taichi/assets", "taichi/examples", "bin", "include", "share")
# What the device tool carries at most: the working tree and the carried paths together.
TRAVEL_LIMIT = 64 * 2**20
# The manylinux tags a wheel for the device may carry (pip matches them exactly).
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux_2_5_x86_64", "manylinux1_x86_64")


def _key(name: str) -> str:
    return name.lower().replace("_", "-")


def lock_pins(lock: Path, names: tuple[str, ...] = BUNDLED) -> list[str]:
    """name==version of each of ``names`` as environment.lock pins it (names compared as pip does:
    case and - / _ alike). Raises SystemExit naming any the lock lacks."""
    pins = {}
    for line in lock.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" in line:
            name, version = line.split("==", 1)
            pins[_key(name)] = f"{name}=={version.lstrip('=')}"
    missing = [n for n in names if _key(n) not in pins]
    if missing:
        raise SystemExit(f"{lock}: no pin for {', '.join(missing)} (the bundle takes the lock's versions)")
    return [pins[_key(n)] for n in names]


def install_site(pins: list[str], python: str, site: Path) -> None:
    """pip install --target ``site`` of ``pins`` for CPython ``python`` on x86-64 Linux."""
    cmd = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-compile", "--only-binary=:all:",
           "--python-version", python, "--implementation", "cp", "--target", str(site)]
    for platform in PLATFORMS:
        cmd += ["--platform", platform]
    result = subprocess.run(cmd + pins, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"pip could not fetch the wheels for Python {python}:\n{result.stderr.strip()}")


def strip_site(site: Path, dropped: tuple[str, ...] = DROPPED) -> int:
    """Remove the ``dropped`` paths from ``site``; returns the bytes removed."""
    removed = 0
    for rel in dropped:
        path = site / rel
        if path.is_dir():
            removed += sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
            shutil.rmtree(path)
        elif path.exists():
            removed += path.stat().st_size
            path.unlink()
    return removed


def pack(folders: list[Path], archive: Path) -> None:
    """The ``folders`` (each under its own name) as one xz-compressed tar."""
    tmp = archive.with_name(archive.name + ".partial")
    with lzma.open(tmp, "wb", preset=6) as xz, tarfile.open(fileobj=xz, mode="w") as tar:
        for folder in folders:
            tar.add(folder, arcname=folder.name)
    os.replace(tmp, archive)


def copy_meshes(mesh_dir: Path, dest: Path) -> list[str]:
    """The raw meshes of config/config.yaml into ``dest``, checksums verified; their names. Raises
    FetchError naming the mesh a mirror lacks or holds with another checksum."""
    from physmorph.meshes.fetch import fetch_mesh
    from physmorph.settings.workflow import load_settings

    raw = load_settings(REPO / "config" / "config.yaml").raw_meshes
    for name, spec in raw.items():
        fetch_mesh(name, spec.url, spec.sha256, dest, mesh_dir=mesh_dir)
    return sorted(raw)


def travelling_bytes(repo: Path = REPO) -> int:
    """Bytes of the files git does not ignore (tracked and untracked): what the device tool sends
    besides the carried paths."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=repo,
                         capture_output=True, check=True).stdout
    files = [repo / p for p in out.decode().split("\0") if p]
    return sum(f.stat().st_size for f in files if f.is_file() and not f.is_symlink())


def tree_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def commit() -> str:
    out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    return out.stdout.strip() or "unknown"


def build(out: Path, python: str, mesh_dir: Path) -> dict:
    """The bundle in ``out`` (replaced whole); returns its sizes."""
    pins = lock_pins(REPO / "environment.lock")
    parent = out.parent
    parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=parent, prefix=".gpu_bundle_build") as tmp:
        staging = Path(tmp) / "bundle"
        site = Path(tmp) / "site"
        meshes = copy_meshes(mesh_dir, Path(tmp) / "meshes")  # first: a bad mirror is named before the download
        install_site(pins, python, site)
        removed = strip_site(site)
        staging.mkdir()
        pack([site, Path(tmp) / "meshes"], staging / "bundle.tar.xz")
        digest = hashlib.sha256((staging / "bundle.tar.xz").read_bytes()).hexdigest()
        (staging / "MANIFEST.txt").write_text(
            f"python {python}\nplatform {PLATFORMS[0]}\ncommit {commit()}\nbundle.tar.xz sha256 {digest}\n"
            + "".join(f"package {p}\n" for p in pins) + "".join(f"mesh {m}\n" for m in meshes))
        sizes = {"site_installed": tree_bytes(site), "site_removed": removed, "bundle": tree_bytes(staging)}
        if out.exists():
            shutil.rmtree(out)
        os.replace(staging, out)
    return sizes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--python", default="3.12", help="the device's Python, major.minor (default 3.12)")
    ap.add_argument("--mesh-dir", type=Path, default=Path(os.environ.get("PHYSMORPH_MESH_DIR", REPO.parent / "shared" / "meshes")),
                    help="a local mirror of the raw meshes (default: $PHYSMORPH_MESH_DIR, else ../shared/meshes)")
    ap.add_argument("--out", type=Path, default=REPO / ".gpu_bundle")
    args = ap.parse_args()
    from physmorph.meshes.errors import FetchError

    try:
        sizes = build(args.out, args.python, args.mesh_dir)
    except FetchError as exc:
        raise SystemExit(f"{exc} (--mesh-dir names a local mirror of the raw meshes)") from None
    tree = travelling_bytes()
    total = tree + sizes["bundle"]
    mib = 2.0**20
    print(f"{args.out}: {sizes['bundle'] / mib:.1f} MiB (packages {sizes['site_installed'] / mib:.0f} MiB installed, "
          f"{sizes['site_removed'] / mib:.0f} MiB of Taichi's C API, headers and assets left out); the working tree "
          f"{tree / mib:.1f} MiB; together {total / mib:.1f} of the {TRAVEL_LIMIT / mib:.0f} MiB the device tool carries")
    if total > TRAVEL_LIMIT:
        raise SystemExit(f"{args.out} would not travel: {total / mib:.1f} MiB with the working tree, over "
                         f"{TRAVEL_LIMIT / mib:.0f} MiB")
    print("on the device: the command `bash benchmarks/gpu_check.sh`, carrying .gpu_bundle")


if __name__ == "__main__":
    main()
