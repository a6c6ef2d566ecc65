"""Shared pytest fixtures.

mesh_dir: the raw benchmark meshes: env PHYSMORPH_MESH_DIR, else the mirror <repo>/../shared/meshes
(where CI has it), else <repo>/resources/meshes/ (where `make tables` downloads them); when none
holds the four meshes they are downloaded there (config/config.yaml's pinned URLs and checksums).
Tests that need them are skipped, saying where they looked and why the download failed, only when
that fails for want of a network (fetch_or_skip, is_network_failure); a checksum mismatch or any
other error fails the fixture (and so each test that uses it).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mesh_mirror import RAW_MESH_SHA256, fetch_or_skip, find_mesh_dir

REPO_ROOT = Path(__file__).resolve().parents[1]

# The suite builds dozens of small solvers with different settings, each compiling its kernels:
# with Taichi's IR optimisation off they compile in about 60 % of the time (physmorph.base.taichi_runtime).
# The workflow jobs the tests start inherit it; CI's end-to-end run after the suite does not.
os.environ.setdefault("PHYSMORPH_QUICK_COMPILE", "1")


def pytest_configure(config):
    """In each of the suite's worker processes (pytest-xdist, one per core) torch runs on one
    thread: two workers with two OpenMP threads each oversubscribe the cores, and the threads
    waiting at each small op's barrier cost the tests 18-30 % of their time (tests/morph and
    tests/mpm, measured back to back twice). Taichi keeps its threads (the lanes' tests need
    two); the workflow jobs the tests start set their own (the profile's `threads`)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


@pytest.fixture
def checkpoint_every_frame(monkeypatch):
    """A checkpoint every frame: the tests that kill a run or read its checkpoint commit frames
    faster than the checkpoints' wall-time cadence (the cadence's own test sets it)."""
    import physmorph.records.runfile as runfile

    monkeypatch.setattr(runfile, "CHECKPOINT_WALL_SHARE", None)


@pytest.fixture(scope="session")
def mesh_dir() -> Path:
    found = find_mesh_dir()
    if found is None:
        found = fetch_or_skip(REPO_ROOT / "resources" / "meshes")
    return found


@pytest.fixture(scope="session")
def raw_mesh_sha256() -> dict[str, str]:
    return dict(RAW_MESH_SHA256)


@pytest.fixture(scope="session")
def tiny(tmp_path_factory, mesh_dir):
    """iso particles and a bunny target at the test profile's resolution (config/test.yaml), with
    that profile's settings: (settings, the folder holding p_iso.h5 and t_bunny.h5)."""
    from physmorph.settings.workflow import load_settings
    from physmorph.stages import prepare_mesh_stage, rasterize_target_stage, sample_particles_stage

    d = tmp_path_factory.mktemp("tiny")
    cfg = load_settings(REPO_ROOT / "config" / "config.yaml", REPO_ROOT / "config" / "test.yaml")
    s = cfg.sampling
    prepare_mesh_stage("iso", cfg.shapes["iso"], None, d / "iso.h5")
    prepare_mesh_stage("bunny", cfg.shapes["bunny"], mesh_dir / "stanford-bunny.obj", d / "bunny.h5")
    sample_particles_stage(d / "iso.h5", d / "p_iso.h5", d / "p_iso.png", s, 0)
    rasterize_target_stage(d / "bunny.h5", d / "t_bunny.h5", d / "t_bunny.png", s, cfg.target, 0)
    return cfg, d
