"""The GPU path: the MPM solver and the renderer on arch=cuda against the CPU (`make gpu-check`).

The test profile's iso -> bunny runs (full: solver, render gradient injected through F,
plasticity) twice from the same inputs, once with `device: cpu` and once with `device: cuda`,
each in its own process (Taichi picks its arch once per process). The GPU run must really be on
CUDA (Taichi falls back to the CPU without a word: the arch each process ended on is checked)
and follow the CPU run: the same frames, the metrics to 3 digits, the particles to 1e-3 of the
domain. Float32 atomics add in another order on a GPU than on CPU threads, so the runs are not
bit-identical; the tolerances are those of a deterministic solver, far below what any wrong
kernel gives. Skips, saying why, where no CUDA device is usable.

The plasticity's and the mask's nearest-point searches, the transport plan (torch on CUDA) and the
neighbourhood kernels (Taichi on arch=cuda) are also compared piece by piece with their CPU
references, to the tolerances of tests/plasticity/test_plasticity_device.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from physmorph.settings.workflow import load_settings
from physmorph.records.runfile import read_metrics
from physmorph.stages import prepare_mesh_stage, rasterize_target_stage, sample_particles_stage

pytestmark = pytest.mark.gpu

REPO = Path(__file__).resolve().parent.parent

PROBE = """
import taichi as ti, torch
assert torch.version.cuda, f"torch {torch.__version__} is a CPU build: install its CUDA build (make venv DEVICE=cuda)"
assert torch.cuda.is_available(), "torch sees no CUDA device"
ti.init(arch=ti.cuda, log_level=ti.ERROR)
arch = str(ti.lang.impl.current_cfg().arch)
assert arch.endswith("cuda"), f"Taichi fell back to {arch}"
print(torch.cuda.get_device_name(0))
"""

RUN = """
import dataclasses, json, sys
from physmorph.settings.workflow import load_settings
from physmorph.morph.loop import morph_config, run_morph
from physmorph.render.api import torch_device
from physmorph.base.taichi_runtime import taichi_state
device, d = sys.argv[1], sys.argv[2]
cfg = load_settings("config/config.yaml", "config/test.yaml", overrides={"device": device})
mc = dataclasses.replace(morph_config(cfg, "iso_bunny_full"), progress=False)
run_morph(f"{d}/p_iso.h5", f"{d}/t_bunny.h5", f"{d}/{device}.h5", mc, name=device)
print(json.dumps({"taichi": taichi_state()["arch"], "torch": str(torch_device(mc.render))}))
"""


DEVICE_CHECK = """
import json, sys
sys.path.insert(0, "tests/plasticity")
import taichi as ti
from physmorph.base.taichi_runtime import init_taichi
from test_plasticity_device import check_deviations, device_deviations
init_taichi("cuda")
arch = str(ti.lang.impl.current_cfg().arch)
dev = device_deviations("cuda")
print(json.dumps({"taichi": arch, **dev}), flush=True)
check_deviations(dev)
"""


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code, *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=1800)


@pytest.fixture(scope="module")
def cuda() -> str:
    probe = _python(PROBE)
    if probe.returncode != 0:
        why = (probe.stderr.strip().splitlines() or ["no output"])[-1]
        pytest.skip(f"no usable CUDA device here ({why}): the GPU check needs a machine with an NVIDIA GPU")
    return probe.stdout.strip()


@pytest.fixture(scope="module")
def pair(cuda, tmp_path_factory, mesh_dir):
    d = tmp_path_factory.mktemp("gpu")
    cfg = load_settings("config/config.yaml", "config/test.yaml")
    prepare_mesh_stage("iso", cfg.shapes["iso"], None, d / "iso.h5")
    prepare_mesh_stage("bunny", cfg.shapes["bunny"], mesh_dir / "stanford-bunny.obj", d / "bunny.h5")
    sample_particles_stage(d / "iso.h5", d / "p_iso.h5", d / "p_iso.png", cfg.sampling, 0)
    rasterize_target_stage(d / "bunny.h5", d / "t_bunny.h5", d / "t_bunny.png", cfg.sampling, cfg.target, 0)
    used = {}
    for device in ("cpu", "cuda"):
        out = _python(RUN, device, str(d))
        assert out.returncode == 0, f"{device} run failed:\n{out.stderr[-4000:]}"
        used[device] = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"GPU check on {cuda}: {used}")
    return d, used


def test_gpu_run_is_on_cuda(pair):
    _, used = pair
    assert used["cpu"] == {"taichi": "cpu", "torch": "cpu"}
    assert used["cuda"]["taichi"] == "cuda" and used["cuda"]["torch"].startswith("cuda")


def test_solver_and_renderer_on_cuda_follow_the_cpu(pair):
    d, _ = pair
    a, b = read_metrics(d / "cpu.h5"), read_metrics(d / "cuda.h5")
    assert b["attrs"]["status"] == a["attrs"]["status"] == "complete"
    assert len(b["alpha_mse"]) == len(a["alpha_mse"]) == 13
    # frame 1: one physics step and one render from the same state
    for key in ("physics_loss", "alpha_mse", "iou", "total_volume"):
        np.testing.assert_allclose(b[key][:2], a[key][:2], rtol=1e-4, err_msg=f"{key}, frames 0-1")
    # the whole run (solver, render gradient injected through F, plasticity)
    for key in ("alpha_mse", "iou", "physics_loss", "chamfer", "total_volume", "fp_det_max"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-3, err_msg=key)
    with h5py.File(d / "cpu.h5") as fa, h5py.File(d / "cuda.h5") as fb:
        assert sorted(fb["states"]) == sorted(fa["states"])
        last = sorted(fa["states"])[-1]
        for k in ("x", "F", "Fp"):
            np.testing.assert_allclose(fb["states"][last][k][()], fa["states"][last][k][()], rtol=1e-3, atol=1e-3,
                                       err_msg=f"{k} at {last}")


def test_plasticity_searches_transport_and_neighbourhoods_on_cuda_follow_the_cpu(cuda):
    out = _python(DEVICE_CHECK)
    print(out.stdout.strip())
    assert out.returncode == 0, f"the device comparison failed:\n{out.stderr[-4000:]}"
    assert json.loads(out.stdout.strip().splitlines()[-1])["taichi"].endswith("cuda")
