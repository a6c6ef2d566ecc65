"""Names declared once: the run file's scalars (physmorph.records.runfile.SCALARS: a frame with
any other is refused, so a misspelt name cannot vanish), the render loss's terms and their
scalars (physmorph.settings.render.LOSS_SCALARS) and the export jobs' keys (each field of
physmorph.settings.export.ExportConfig names the job that reads it)."""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest

from physmorph.records.runfile import SCALARS, RunWriter
from physmorph.records.runkey import RunKey
from physmorph.settings.base import fields_of_job
from physmorph.settings.export import ExportConfig
from physmorph.settings.render import LOSS_SCALARS, LOSS_TERMS

KEY = RunKey(json.dumps({"frames": 1}), (("particles", "aa" * 32), ("target", "bb" * 32)))


def test_a_frame_with_an_undeclared_scalar_is_refused_and_nothing_is_committed(tmp_path):
    out = tmp_path / "run.h5"
    with RunWriter(out, KEY) as w:
        assert w.resume(log=lambda m: None) is None
        w.set_meta({"experiment": "hand", "views": 2})
        with pytest.raises(ValueError, match="alpha_mes"):
            w.commit(0, {"alpha_mes": 0.5}, np.full(2, 0.5), None, [], {})
        assert w.resume(log=lambda m: None) is None  # no frame was committed
        w.commit(0, {"alpha_mse": 0.5}, np.full(2, 0.5), None, [], {})


def test_the_render_loss_scalars_come_from_its_terms_in_the_run_files_order():
    assert set(LOSS_SCALARS) == set(LOSS_TERMS) | {"total"}
    names = list(LOSS_SCALARS.values())
    assert names == ["loss_dt", "loss_iou", "loss_depth", "loss_render"]  # the run files' datasets
    start = SCALARS.index(names[0])
    assert list(SCALARS[start:start + len(names)]) == names


def test_every_export_setting_names_the_one_job_that_reads_it():
    video, mesh = fields_of_job(ExportConfig, "video"), fields_of_job(ExportConfig, "mesh")
    plan = fields_of_job(ExportConfig, "plan")  # read where the workflow plans the export, by no job
    assert set(video) | set(mesh) | set(plan) == {f.name for f in fields(ExportConfig)}
    assert not set(video) & set(mesh) and plan == ("experiments",)
    cfg = ExportConfig()
    assert list(cfg.video()) == list(video) and list(cfg.mesh()) == list(mesh)
    assert {"width", "fps", "crf"} <= set(video) and {"refine", "smooth_iterations"} <= set(mesh)
