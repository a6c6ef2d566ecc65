"""The morph loop (paper Algorithm 1) as a resumable experiment writing one run HDF5.

Per frame k = 1..K, from the state promoted from frame k-1:
A. physics: J optimiser iterations (normalised GD with line search by default) on the control field dFc against the end-layer mass loss, with the
   previous frame's render gradient injected on the final F (gamma * dL/dF; methods f_inject and
   full) or on the final x (gamma_x * dL/dx; the position_inject negative control);
B. render: the surface-masked particles as Gaussians Sigma = sigma0^2 F F^T from V ring cameras;
   losses against the target images; g = dL_render/dF (and dL/dx) kept for frame k+1;
C. plasticity (method full, k >= k0): Chamfer-guided update of Fp (physmorph.plasticity.step); with
   plasticity.continuous_stress the control is re-based so the update leaves Fe unchanged; with
   plasticity.absorb_control the control is first moved into Fp (the achieved shape becomes the
   rest state) and the re-based control keeps only its variation over the substeps.
The state at the end of frame k is the initial state of frame k+1; with morph.momentum_restart
(the default) a frame whose mass loss ended above the previous frame's hands it on at rest.

Methods: physics_only (A without injection), f_inject (A+B), full (A+B+C), position_inject.

Resume (physmorph.records.runfile): every frame is committed all or nothing to ``<out>.partial/`` (its
metrics, then the complete loop state: particles, control field and optimizer moments, mask,
pending render gradient); a run started on an existing partial run continues from its last
committed frame when its settings and the content of its inputs (particles, target) are unchanged,
and with the same config and thread count reproduces the uninterrupted run; otherwise it restarts
and says why. One process writes a run at a time (a lock). The finished file is ``<out>``.
Divergence (non-finite or out-of-bounds F, Fp, x) raises MorphDivergenceError naming frame and
quantity; the partial run keeps every completed frame. For position_inject a divergence is
recorded in the run (status "diverged") instead, since instability is the finding.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from physmorph.morph.frame_measures import frame_strain
from physmorph.morph.frame_state import FrameState, asdict_state
from physmorph.morph.inputs import MorphInputs
from physmorph.records.h5io import stored_identity
from physmorph.morph.injection import frame_calibration
from physmorph.morph.judge import FrameJudge
from physmorph.base.linalg3 import inverse3
from physmorph.base.memory import held_heap
from physmorph.settings.morph import MorphConfig
from physmorph.settings.mpm import MPMError
from physmorph.mpm.solver import MPMSolver
from physmorph.mpm.state import ParticleState
from physmorph.morph.quality import gap_closed
from physmorph.morph.reabsorb import reabsorb_frame
from physmorph.plasticity.step import absorbed_rest, chamfer_plasticity_step, neighbour_pool, rebase_reference
from physmorph.render.api import render_and_grad
from physmorph.settings.render import LOSS_SCALARS
from physmorph.morph.stability import MorphDivergenceError, StabilityMonitor, check_state
from physmorph.records.runfile import RunWriter, summarize_run
from physmorph.records.runkey import RunKey
from physmorph.morph.steering import ControlDecay, StrayPull
from physmorph.morph.surface_mask import update_surface_mask
from physmorph.morph.waypoints import FramePlan


def run_morph(particles_h5: str | Path, target_h5: str | Path, out_h5: str | Path, cfg: MorphConfig,
              name: str = "", config_record: dict | None = None, log=None, target_size: float | None = None) -> dict:
    """Run (or resume) one morph experiment; returns a summary dict. See the module docstring.
    ``target_size``: the target shape's configured size, for the size a volume warning advises."""
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    started = time.time()
    out_h5 = Path(out_h5)
    out_h5.parent.mkdir(parents=True, exist_ok=True)
    record = json.dumps(config_record if config_record is not None else cfg.to_dict(), sort_keys=True, default=str)
    # A partial run resumes only with the same settings and the same input content.
    key = RunKey(record, (("particles", stored_identity(particles_h5)), ("target", stored_identity(target_h5))))
    # one writer per run: a second one is refused; the frames reuse each other's freed heap
    with RunWriter(out_h5, key, started) as run, held_heap():
        MorphRun(particles_h5, target_h5, cfg, name, log, run, target_size).run_frames(record)
    return summarize_run(out_h5)


class MorphRun:
    """One run's frame loop: the policies fixed for the run (its inputs: MorphInputs), the
    FrameState carried from frame to frame, and each frame's phases (physics, mask, render,
    plasticity, measure, steer, commit) as methods."""

    def __init__(self, particles_h5, target_h5, cfg: MorphConfig, name: str, log, run: RunWriter,
                 target_size: float | None = None):
        self.cfg, self.name, self.log, self.run = cfg, name, log, run
        self.inputs = MorphInputs(particles_h5, target_h5, cfg, name, log, target_size)
        self.solver = self.inputs.solver
        self.pool = None  # the plasticity's neighbour pool, chosen at the first update from the positions at rest
        self.nearest_d = self.nearest_i = None  # the state's nearest target surface points, kept from the last frame's end
        self.monitor = StabilityMonitor(cfg.plasticity, log=lambda msg: log(f"[{name}] warning: {msg}"))
        self.judge = FrameJudge(cfg, self.solver, self.inputs, run, log=lambda msg: log(f"[{name}] {msg}"))
        self.decay, self.stray = ControlDecay(cfg), StrayPull(cfg)
        self.plan = FramePlan(cfg, self.inputs)  # the transport plan's destinations, push and waypoints

    # ---------------------------------------------------------------------------- start or resume
    def begin(self) -> int:
        """Frame 0 committed (a new run) or the checkpoint restored: the first frame to run."""
        cfg, run, solver = self.cfg, self.run, self.solver
        checkpoint = run.resume(log=lambda msg: self.log(f"[{self.name}] {msg}"))
        if checkpoint is None:
            self.fs = self.frame_zero()
            start = 1
        else:
            self.fs = FrameState.from_checkpoint(checkpoint.data)
            solver.set_optimizer_state(checkpoint.data)
            self.monitor.restore(checkpoint.data)
            start = checkpoint.frame + 1
            self.log(f"[{self.name}] resuming after frame {checkpoint.frame}/{cfg.frames}")
            self.a0 = run.frame_metric(0, "alpha_mse")
        self.judge.begin(start, self.fs, checkpoint)
        self.inputs.wait_for_walk()  # built beside frame 0: its memory is given back before frame 1's
        return start

    def frame_zero(self) -> FrameState:
        """The unmoved source committed as frame 0: metrics, no physics step (its losses are NaN)."""
        cfg, parts, N, target = self.cfg, self.inputs.parts, self.inputs.N, self.inputs.target
        st = ParticleState(x=parts.x.copy(), v=np.zeros((N, 3)), F=np.tile(np.eye(3), (N, 1, 1)),
                           C=np.zeros((N, 3, 3)), Fp=np.tile(np.eye(3), (N, 1, 1)),
                           mass=parts.mass.copy(), volume=parts.volume.copy())
        mask = (update_surface_mask(st.x, st.volume, self.inputs.tree, cfg.surface, cfg.mpm.domain_lo, cfg.mpm.domain_hi,
                                    search_device=self.inputs.search_device) if self.inputs.need_mask else np.zeros(N, bool))
        fs = FrameState.at_start(st, mask, cfg.mpm.step_size, self.judge.onset.initial_weight())
        self.run.set_meta({"experiment": self.name, "method": cfg.method, "target_mass_ratio": self.inputs.mass_ratio,
                           "target_volume_ratio": float(target.volume) / self.inputs.source_volume, "n_particles": N,
                           "sigma0": parts.sigma0, "views": self.inputs.V, "loss_views": self.inputs.views,
                           "frames_planned": cfg.frames, "ceiling_alpha_mse": self.inputs.ceiling,
                           "ceiling_iou": float(getattr(target, "ceiling_iou", np.nan))})
        m, per_view, _ = self.inputs.measure(st, mask)
        self.a0 = m["alpha_mse"]
        m["gap_closed"] = 0.0
        self.run.commit(0, m, per_view, asdict_state(st), [self.inputs.volume_note] if self.inputs.volume_note else [],
                        fs.checkpoint(self.judge.gate.checkpoint(), self.solver.optimizer_state(by_slots=True), self.monitor.state()))
        return fs

    # ---------------------------------------------------------------------------- the phases
    def physics(self, k: int) -> tuple[dict, ParticleState, float] | None:
        """A. J optimiser iterations on dFc with the last render gradient injected; returns
        (the optimiser's stats, the state at the frame's end, the frame's step), None where a
        position_inject run diverged (recorded: instability is its finding)."""
        cfg, solver, fs = self.cfg, self.solver, self.fs
        fs.state = self.plan.pushed(fs.state, share=self.judge.schedule.step / cfg.mpm.step_size)
        solver.load_state(fs.state)
        if self.stray.on:
            if self.nearest_d is None:
                self.nearest_d, self.nearest_i = self.inputs.nearest_target(fs.state.x)
            self.stray.anchor(solver, fs.state, self.nearest_d, self.nearest_i, self.inputs.target,
                              self.plan.destinations() if self.stray.to_destination else None)
        self.decay.apply(solver)
        self.plan.aim(solver, fs.state)
        try:
            calibration = frame_calibration(cfg, fs, solver, self.inputs.inject_F, self.inputs.inject_x, k,
                                            lambda msg: self.log(f"[{self.name}] {msg}"))
            c = 0.0 if np.isnan(fs.injection_scale) else fs.injection_scale
            frame_step = self.judge.schedule.step
            # the calibration's rollout is current and its two gradients sum to the first
            # iteration's: the optimiser skips that forward and backward (a third of a frame)
            if calibration is not None:
                solver.combine_calibration(c)
            stats = solver.optimize_control(grad_F_final=c * fs.g_F if self.inputs.inject_F else None,
                                            grad_x_final=c * fs.g_x if self.inputs.inject_x else None,
                                            gradient_ready=calibration is not None, learning_rate=frame_step)
            new = solver.state_at(cfg.mpm.substeps)
            check_state(new, k, cfg)
        except (MPMError, MorphDivergenceError) as exc:
            # the state check names its frame; the solver's divergence is named here
            msg = str(exc) if getattr(exc, "frame", None) is not None else f"frame {k}: {exc}"
            if cfg.method == "position_inject":
                self.status = f"diverged: {msg}"
                self.log(f"[{self.name}] {self.status} (recorded; position injection is the negative control)")
                return None
            raise MorphDivergenceError(f"{msg} (completed frames are kept in {self.run.dir})", frame=k) from exc
        return stats, new, frame_step

    def advance(self, new: ParticleState) -> float:
        """The frame's end state becomes the loop's (Fp, m, V0 carried); returns the frame's strain."""
        st = self.fs.state
        strain = frame_strain(st.F, new.F)
        self.fs.state = ParticleState(x=new.x, v=new.v, F=new.F, C=new.C, Fp=st.Fp, mass=st.mass, volume=st.volume)
        return strain

    def mask(self) -> None:
        """Each particle's nearest target surface point, shared by the mask, the plasticity's
        nearest-point map and the Chamfer metric (plasticity changes only Fp), and the surface mask."""
        cfg, fs = self.cfg, self.fs
        self.nearest_d, self.nearest_i = self.inputs.nearest_target(fs.state.x, start=self.nearest_i)
        if self.inputs.need_mask:
            fs.mask = update_surface_mask(fs.state.x, fs.state.volume, self.inputs.tree, cfg.surface, cfg.mpm.domain_lo,
                                          cfg.mpm.domain_hi, previous=fs.mask, target_distance=self.nearest_d,
                                          search_device=self.inputs.search_device)

    def render(self, scal: dict):
        """B. The masked particles rendered against the target; their gradient kept for the next
        frame (only where a method uses it). Returns the render's result (None without one)."""
        if not self.inputs.want_grad:
            return None
        fs, N = self.fs, self.inputs.N
        st, mask = fs.state, fs.mask
        res = render_and_grad(st.x[mask], st.F[mask], self.inputs.parts.sigma0, self.inputs.cams, self.inputs.rtarget, self.cfg.render,
                              want_grad_x=self.inputs.inject_x)
        fs.g_F = np.zeros((N, 3, 3))
        fs.g_F[mask] = res.grad_F
        fs.g_x = np.zeros((N, 3))
        if self.inputs.inject_x and res.grad_x is not None:
            fs.g_x[mask] = res.grad_x
        scal.update({LOSS_SCALARS[term]: value for term, value in res.losses.items()})
        scal.update(grad_F_norm=float(np.linalg.norm(fs.g_F)), grad_x_norm=float(np.linalg.norm(fs.g_x)))
        return res

    def plasticity(self, k: int) -> None:
        """C. The Chamfer-guided update of Fp (method full from plasticity.start_frame), the
        control re-based so the update leaves Fe as continuous_stress / absorb_control say."""
        cfg, solver, fs = self.cfg, self.solver, self.fs
        if not (cfg.method == "full" and k >= cfg.plasticity.start_frame):
            return
        st, N = fs.state, self.inputs.N
        # the control averaged over the substeps: what an absorbing update commits to Fp
        control_mean = solver.control_mean()  # [N, 3, 3]
        absorbing = cfg.plasticity.absorbs_at(k, cfg.frames)
        Fp_from = absorbed_rest(st.F, control_mean, st.Fp, cfg.plasticity) if absorbing else st.Fp
        destination = self.plan.destinations() if cfg.plasticity.correspondence == "transport" else None
        if self.pool is None:
            pool = neighbour_pool(self.inputs.parts.x, self.inputs.target.grid.lo, self.inputs.target.grid.dx, cfg.plasticity.neighbour_ppc)
            self.pool = np.arange(N) if pool is None else pool
        # the rest volume ratio's cube roots before and after the update (1 unless plasticity.volume is target)
        rest_scale = tuple(self.inputs.rest_volume_ratio(j) ** (1.0 / 3.0) for j in (k - 1, k))
        pl = chamfer_plasticity_step(st.x, Fp_from, self.inputs.target.surface_points, cfg.plasticity, self.inputs.tree,
                                     destination=destination, nearest_index=self.nearest_i,
                                     pool=None if len(self.pool) == N else self.pool,
                                     search_device=self.inputs.search_device, rest_scale=rest_scale)
        Fp_old = st.Fp
        fs.state = st = ParticleState(x=st.x, v=st.v, F=st.F, C=st.C, Fp=pl.Fp, mass=st.mass, volume=st.volume)
        try:  # before the re-base: a bad Fp is named as such, not as a bad control
            check_state(st, k, cfg)
        except MorphDivergenceError as exc:
            raise MorphDivergenceError(f"{exc} (completed frames are kept in {self.run.dir})") from exc
        rebase_to = rebase_reference(cfg.plasticity, absorbing, Fp_from, pl.Fp)
        if rebase_to is not None:
            solver.rebase_control(st.F, inverse3(Fp_old) @ rebase_to)

    def frame(self, k: int) -> bool:
        """Frame k's phases, committed; False where the run stops (a position_inject divergence)."""
        if self.judge.holds(k):  # committed as the undone frame it would be, without running
            self.commit(k, *self.judge.held(k, self.fs, self.cfg.progress), [])
            return True
        solver, fs = self.solver, self.fs
        t0 = time.time()
        physics = self.physics(k)
        if physics is None:
            return False
        stats, new, frame_step = physics
        strain = self.advance(new)
        to_target = self.plan.loss_to_target(solver)  # what the frames compare, and the mass loss
        t1 = time.time()
        self.mask()
        t2 = time.time()
        scal = {"physics_loss_to_target": to_target, "injection_scale": fs.injection_scale if self.inputs.want_grad else np.nan,
                "physics_loss_initial": stats["loss_initial"], "physics_loss": stats["loss_final"],
                "mass_loss": solver.mass_loss(), "frame_strain": strain,
                "delta_E_percent": stats["delta_E_percent"], "mpm_grad_norm": stats["grad_norm"], "step_size": frame_step,
                # the normalised step the line search kept (0: none lowered the objective; Adam: NaN)
                "step_accepted": (stats["step"] if stats["iters"] > 0 else 0.0) if "step" in stats else np.nan}
        res = self.render(scal)
        t3 = time.time()
        self.plasticity(k)
        scal["reabsorbed"] = reabsorb_frame(self.fs, self.nearest_d, self.nearest_i, self.inputs, self.cfg)
        scal["plan_distance"] = self.plan.distance(fs.state)
        t4 = time.time()
        every_view = res is not None and len(self.inputs.views) == self.inputs.V
        m, per_view, dm = self.inputs.measure(fs.state, fs.mask, alpha=res.alpha if res is not None and self.inputs.loss_render_is_metric else None,
                                       masked_alpha=res.alpha if every_view else None, target_distance=self.nearest_d)
        m["gap_closed"] = gap_closed(self.a0, m["alpha_mse"], self.inputs.ceiling) if np.isfinite(self.inputs.ceiling) else np.nan
        scal.update(m)
        scal, per_view, m, rejected = self.judge.steer(k, fs, scal, per_view, m, frame_step)
        if rejected:
            self.nearest_d = self.nearest_i = None
        # the det bounds hold the rest state's shape (the plasticity step): det Fp over the rest volume ratio
        rest = self.inputs.rest_volume_ratio(k)
        new_warnings = [] if rejected else self.monitor.update(
            k, fs.state.Fp, m["alpha_mse"], det=dm.det_plastic if rest == 1.0 else dm.det_plastic / rest,
            fp_anisotropy=dm.anisotropy_plastic)
        # the render's images and gradient and the metrics' arrays are done with; their blocks stay
        # in the run's held heap for the next frame (physmorph.base.memory.held_heap)
        res = dm = None
        scal.update(t_physics=t1 - t0, t_mask=t2 - t1, t_render=t3 - t2, t_plasticity=t4 - t3, t_frame=time.time() - t0)
        self.commit(k, scal, per_view, new_warnings)
        self.progress(k, scal, stats, rejected)
        return True

    def commit(self, k: int, scal: dict, per_view: np.ndarray, new_warnings: list) -> None:
        """The frame's metrics and motion, its state where saved, and the checkpoint when due."""
        cfg, fs = self.cfg, self.fs
        save = k % cfg.save_every == 0 or k == cfg.frames
        # the checkpoint's arrays are gathered only when it is due (physmorph.records.runfile)
        self.run.commit(k, scal, per_view, asdict_state(fs.state) if save else None, new_warnings,
                        lambda: fs.checkpoint(self.judge.gate.checkpoint(), self.solver.optimizer_state(by_slots=True), self.monitor.state()),
                        last=k == cfg.frames, motion={"x": fs.state.x, "F": fs.state.F})

    def progress(self, k: int, scal: dict, stats: dict, rejected: bool) -> None:
        self.frame_times.append(scal["t_frame"])
        if self.cfg.progress:
            eta = np.mean(self.frame_times) * (self.cfg.frames - k)
            self.log(f"[{self.name}] frame {k}/{self.cfg.frames}  alpha_mse {scal['alpha_mse']:.4f} "
                     f"(gap closed {100 * scal['gap_closed']:.0f} %)  "
                     f"physics {stats['loss_initial']:.4g}->{stats['loss_final']:.4g}  "
                     f"|gF| {scal.get('grad_F_norm', 0.0):.3g}  {scal['t_frame']:.1f} s/frame  ETA {eta:.0f} s"
                     + ("  (undone: the body holds still)" if rejected else ""))

    def run_frames(self, record: str) -> None:
        """Every frame from the first not committed, then the release curve and the finished file."""
        start = self.begin()
        self.status, self.frame_times = "complete", []
        for k in range(start, self.cfg.frames + 1):
            if not self.frame(k):
                break
        extra = {"injection_scale": self.fs.injection_scale}
        if self.cfg.release_frames and self.status == "complete":
            mask = self.fs.mask
            extra["release_alpha_mse"] = json.dumps(release_curve(self.solver, self.fs.state, self.cfg.release_frames,
                                                                  lambda s: self.inputs.alpha_mse(s, mask),
                                                                  self.log, self.name))
        # The file's provenance also keeps every setting resolved (the key leaves defaults out).
        self.run.finish(self.status, extra, {**json.loads(record), "resolved": self.cfg.to_dict()})


def release_curve(solver: MPMSolver, st: ParticleState, frames: int, alpha_mse, log, name: str,
                  keep_velocity: bool = False) -> list[float]:
    """Alpha MSE of ``st`` and of ``frames`` frames simulated from it with the control off (dFc = 0,
    no optimisation, no plasticity): what the rest state Fp keeps of the morph once nothing holds it
    (the paper's rebound, section 3.4, without the control that hides it here; docs/study/log.md).
    The body is released from rest (v = 0, C = 0) so the curve measures the elastic rebound alone:
    whether the last frame's body was still coasting depends on whether a momentum restart happened
    to fire there, and a stress-free body coasts on (docs/study/log.md finding 112);
    ``keep_velocity`` releases it with its last velocity instead.
    A divergence ends the curve (the remaining frames are NaN)."""
    curve = [alpha_mse(st)]
    if not keep_velocity:
        st = dataclasses.replace(st, v=np.zeros_like(st.v), C=np.zeros_like(st.C))
    solver.reset_control()
    for k in range(frames):
        try:
            solver.load_state(st)
            st = solver.rollout()
        except MPMError as exc:
            log(f"[{name}] release frame {k + 1}/{frames} diverged: {exc}")
            return curve + [float("nan")] * (frames - k)
        curve.append(alpha_mse(st))
    if frames:
        log(f"[{name}] released for {frames} frames: alpha_mse {curve[0]:.4f} -> {curve[-1]:.4f}")
    return curve


def morph_config(settings, experiment_name: str) -> MorphConfig:
    """The MorphConfig of one experiment: the global sections, then the experiment's own keys
    (``settings``: physmorph.settings.workflow.Settings, which owns the resolution and its checks)."""
    return settings.experiment_config(experiment_name)
