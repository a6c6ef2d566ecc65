"""Shared pytest fixtures.

mesh_dir: the raw benchmark meshes: env PHYSMORPH_MESH_DIR, else the mirror <repo>/../shared/meshes
(where CI has it), else <repo>/resources/meshes/ (where `make tables` downloads them). Tests that
need them are skipped, saying where they looked, when none of these holds the four meshes.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

# Published SHA-256 of the raw benchmark meshes (../shared/meshes/SOURCES.md).
RAW_MESH_SHA256 = {
    "stanford-bunny.obj": "1eb35d1e21ce99e5ce911353b6be278990713448dd9e8f5c9387f9de39b32205",
    "spot.obj": "0738b5e8608fed74e5e8c7aa8dd0af97b4b74f9f6cbf7aac84cd7e40b2e44a75",
    "cow.obj": "69afce548640bc2beb0c44894d1a24d5766cc9cd3fd74f3ec55b4e229104b23f",
    "Duck.glb": "49e23fa9faead02dd9b8ae45bc63b945bce068c1361dc00485596f4ba723b27d",
}


def mesh_dir_candidates() -> list[Path]:
    env = os.environ.get("PHYSMORPH_MESH_DIR")
    return ([Path(env)] if env else []) + [REPO_ROOT.parent / "shared" / "meshes", REPO_ROOT / "resources" / "meshes"]


def find_mesh_dir() -> Path | None:
    for candidate in mesh_dir_candidates():
        if all((candidate / name).is_file() for name in RAW_MESH_SHA256):
            return candidate
    return None


@pytest.fixture(scope="session")
def mesh_dir() -> Path:
    found = find_mesh_dir()
    if found is None:
        looked = ", ".join(str(p) for p in mesh_dir_candidates())
        pytest.skip(f"raw benchmark meshes not found (looked in {looked}; set PHYSMORPH_MESH_DIR or run "
                    "`make tables` once to download them into resources/meshes/)")
    return found


@pytest.fixture(scope="session")
def raw_mesh_sha256() -> dict[str, str]:
    return dict(RAW_MESH_SHA256)
