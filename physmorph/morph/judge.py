"""The morph loop's judgement of each frame (physmorph.morph.loop): the settle phase's gate
(physmorph.morph.settle: a frame whose objective rose after the body came to rest is undone, the
body held at the last accepted frame and the step backed off), the momentum restart, the step
schedule and the packing term's onset (physmorph.morph.steering): what the next frame starts from.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from physmorph.base.linalg3 import inverse3
from physmorph.morph.frame_state import FrameState
from physmorph.morph.inputs import MorphInputs
from physmorph.morph.settle import AcceptedFrame, settle_gate
from physmorph.morph.waypoints import physics_objective
from physmorph.morph.steering import MomentumRestart, OverfillOnset, StepSchedule
from physmorph.mpm.solver import MPMSolver
from physmorph.mpm.state import ParticleState
from physmorph.plasticity.step import absorbed_rest, rebase_reference
from physmorph.records.runfile import STAGE_TIMES, RunWriter
from physmorph.settings.morph import MorphConfig


class FrameJudge:
    """The policies over the frames that judge a frame and set up the next; ``log`` takes a line."""

    def __init__(self, cfg: MorphConfig, solver: MPMSolver, inputs: MorphInputs, run: RunWriter, log):
        self.cfg, self.solver, self.inputs, self.run, self.log = cfg, solver, inputs, run, log
        # MorphConfig.settle: the last phase's gate over frames (physmorph.morph.settle)
        self.gate = settle_gate(cfg.settle, cfg.settle_objective, inputs.want_grad, cfg.settle_backoff,
                                physics_key=physics_objective(cfg), handover=cfg.settle_handover)
        self.onset = OverfillOnset(cfg)
        self.holding = False  # a frame has been held (MorphConfig.settle_hold_below): said once

    def begin(self, start: int, fs: FrameState, checkpoint) -> None:
        """The policies at the run's first frame to run: from the committed frames and the
        checkpoint where the run resumes (None: a new run)."""
        cfg, solver = self.cfg, self.solver
        self.restart = MomentumRestart(cfg)
        rise_on = self.restart.rise_on
        self.restart.previous = self.run.frame_metric(start - 1, rise_on)
        self.restart.before_previous = self.run.frame_metric(start - 2, rise_on) if start >= 2 else float("nan")
        # the step the next frame takes (backed off by MorphConfig.settle_backoff after an undone frame)
        self.schedule = StepSchedule(fs.next_step)
        self.onset.begin(solver, fs.overfill_weight)
        if checkpoint is not None:
            self.gate.restore(checkpoint.data)
            if self.gate.at_rest_after(start - 1):  # the checkpoint's state is the last accepted frame's
                scalars, per_view = self.run.frame_metrics(start - 1)
                self.gate.accepted = self.keep_accepted(AcceptedFrame(
                    fs.state, fs.mask, fs.g_F, fs.g_x, fs.injection_scale, scalars, per_view,
                    float(scalars.get(self.gate.objective_key, np.nan))))

    def keep_accepted(self, frame: AcceptedFrame) -> AcceptedFrame:
        """The settle gate's last accepted frame, with the solver's control kept beside it. On the CPU
        both go to files in the partial run (removed with it): in memory they would add ~510 MB to
        every later frame's peak at the paper's scale (the control 340 MB, the state and gradients
        170 MB), and the page cache holds them instead; on a GPU the control stays on the device."""
        if self.inputs.device != "cpu":
            self.solver.keep_control()
            return frame
        scratch = self.run.dir / "settle"  # removed with the partial run
        frame = frame.spill(scratch)  # makes the directory
        self.solver.keep_control(spill=scratch / "control.bin")
        return frame

    def holds(self, k: int) -> bool:
        """Whether frame k is held, not run (MorphConfig.settle_hold_below): the settle phase gates it
        and its step has backed off under that share of mpm's."""
        share = self.cfg.settle_hold_below
        return share > 0 and self.gate.gates(k) and self.schedule.step < share * self.cfg.mpm.step_size

    def held(self, k: int, fs: FrameState, progress: bool) -> tuple[dict, np.ndarray]:
        """Frame k held (``holds``): the undone frame's record (scalars, per-view α MSE) without running
        it, its stage times NaN; the log says so at the first held frame (and at each with ``progress``)."""
        back, frame_step = self.gate.accepted, self.schedule.step
        scal, per_view, _, _ = self.steer(k, fs, dict(back.scalars), back.per_view, back.scalars, frame_step, held=True)
        scal.update(dict.fromkeys(STAGE_TIMES, np.nan))
        if not self.holding:
            self.holding = True
            self.log(f"frame {k}: the settle phase's step {frame_step:.3g} is under settle_hold_below of mpm's; "
                     f"from here on the frames are held, the body still, without running")
        if progress:
            self.log(f"frame {k}/{self.cfg.frames}  alpha_mse {scal['alpha_mse']:.4f} "
                     f"(gap closed {100 * scal['gap_closed']:.0f} %)  held")
        return scal, per_view

    def steer(self, k: int, fs: FrameState, scal: dict, per_view: np.ndarray, m: dict, frame_step: float,
              held: bool = False):
        """The frame judged: the settle gate may undo it (the body holds still at the last accepted
        frame, and the step backs off), the momentum restart and the packing term's onset act on
        what the next frame starts from; a ``held`` frame (``holds``) is undone as such. Returns
        (scal, per_view, m, undone) to commit."""
        cfg, solver, gate = self.cfg, self.solver, self.gate
        rejected = held or gate.rejects(k, scal)
        if rejected:  # the frame is undone: the body holds still at the last accepted frame
            back = gate.accepted
            fs.state, fs.mask, fs.g_F, fs.g_x = back.arrays()
            fs.injection_scale = back.injection_scale
            solver.restore_kept_control()
            scal, per_view, m = dict(back.scalars), back.per_view, back.scalars
            scal["step_size"] = frame_step  # the step the undone frame tried
            self.schedule.back_off(gate.backoff)
            if k == cfg.frames and cfg.method == "full" and cfg.plasticity.absorbs_at(k, cfg.frames):
                fs.state = absorb_at_rest(fs.state, solver, cfg)  # the last update's absorption, on the accepted body
        if gate.gates(k):
            scal["settling"] = 2.0 if rejected else 1.0
            if cfg.settle_regrow and not rejected:
                self.schedule.regrow(gate.backoff, cfg.mpm.step_size)
        objective_rose, restart = self.restart.observe(scal[self.restart.rise_on])
        if self.restart.on:
            # the objective rose over this frame: the state is moving away from the target, so
            # the next frame starts with (most of) that momentum removed
            if gate.note_restart(k, restart):
                self.log(f"frame {k}: the restart fired ({cfg.settle}); from frame {k + 1} every "
                         f"frame starts at rest, and one whose {gate.objective_key} rises is undone")
            if restart or gate.at_rest_after(k):
                fs.state = self.restart.at_rest(fs.state)
                if restart and self.restart.control_keep < 1.0:  # a restart's, not the settle phase's rest
                    solver.scale_control(self.restart.control_keep)
            scal["momentum_restart"] = float(restart)
        if not rejected and gate.after_accepted(k, scal.get(gate.objective_key, np.nan)):
            self.log(f"frame {k}: the physics loss fell by less than {cfg.settle_handover:g} of the frame "
                     f"before; from frame {k + 1} a frame whose {gate.objective_key} rises is undone")
        if gate.at_rest_after(k) and not rejected:
            gate.accepted = self.keep_accepted(AcceptedFrame(fs.state, fs.mask, fs.g_F, fs.g_x, fs.injection_scale,
                                                             dict(scal), per_view, float(scal.get(gate.objective_key, np.nan))))
        if self.onset.after_frame(solver, objective_rose):
            self.log(f"frame {k}: the objective first rose, the packing term acts from frame {k + 1}")
        fs.next_step, fs.overfill_weight = self.schedule.step, solver.overfill_weight
        return scal, per_view, m, rejected


def absorb_at_rest(st: ParticleState, solver: MPMSolver, cfg: MorphConfig) -> ParticleState:
    """The shape absorbed into the rest state (plasticity.absorb_control) without a Chamfer step: the
    last frame's absorption when that frame was undone, so the run still ends with its shape in Fp."""
    Fp = absorbed_rest(st.F, solver.control_mean(), st.Fp, cfg.plasticity)
    rebase_to = rebase_reference(cfg.plasticity, True, Fp, Fp)
    if rebase_to is not None:
        solver.rebase_control(st.F, inverse3(st.Fp) @ rebase_to)
    return dataclasses.replace(st, Fp=Fp)
