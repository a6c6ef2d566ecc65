"""The morph loop (paper Algorithm 1) as a resumable experiment writing one run HDF5.

Per frame k = 1..K, from the state promoted from frame k-1:
A. physics: J optimiser iterations (normalised GD with line search by default) on the control field dFc against the end-layer mass loss, with the
   previous frame's render gradient injected on the final F (gamma * dL/dF; methods f_inject and
   full) or on the final x (gamma_x * dL/dx; the position_inject negative control);
B. render: the surface-masked particles as Gaussians Sigma = sigma0^2 F F^T from V ring cameras;
   losses against the target images; g = dL_render/dF (and dL/dx) kept for frame k+1;
C. plasticity (method full, k >= k0): Chamfer-guided update of Fp (physmorph.plasticity); with
   plasticity.continuous_stress the control is re-based so the update leaves Fe unchanged; with
   plasticity.absorb_control the control is first moved into Fp (the achieved shape becomes the
   rest state) and the re-based control keeps only its variation over the substeps.
The state at the end of frame k is the initial state of frame k+1; with morph.momentum_restart
(the default) a frame whose mass loss ended above the previous frame's hands it on at rest.

Methods: physics_only (A without injection), f_inject (A+B), full (A+B+C), position_inject.

Resume (physmorph.runfile): every frame is committed all or nothing to ``<out>.partial/`` (its
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
from scipy.spatial import cKDTree

from physmorph.frame_measures import DeformationMeasures, deformation_measures, frame_strain, grid_mass
from physmorph.grid import grid_average
from physmorph.h5io import stored_checksum
from physmorph.injection import calibrate_injection
from physmorph.linalg3 import det3
from physmorph.memory import release_free_memory
from physmorph.meshes.fit import volume_mismatch
from physmorph.morph_config import METHODS, MorphConfig  # noqa: F401 (re-exported)
from physmorph.mpm import MPMError, MPMSolver, ParticleState, solver_for, kinetic_energy, total_volume
from physmorph.particles import load_particles
from physmorph.quality import gap_closed, silhouette_iou, volume_metrics
from physmorph.plasticity import absorbed_rest, chamfer_plasticity_step, neighbour_pool, rebase_reference
from physmorph.render import RenderTarget, render_and_grad, render_views
from physmorph.stability import MorphDivergenceError, StabilityMonitor, anisotropy, check_state  # noqa: F401 (re-exported)
from physmorph.settle import AcceptedFrame, settle_gate
from physmorph.runfile import SCALARS, RunKey, RunWriter, read_metrics, summarize_run  # noqa: F401 (re-exported)
from physmorph.surface import update_surface_mask
from physmorph.targets import load_target
from physmorph.transport import destinations_in_grid_mass


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
    key = RunKey(record, (("particles", stored_checksum(particles_h5)), ("target", stored_checksum(target_h5))))
    with RunWriter(out_h5, key, started) as run:  # one writer per run: a second one is refused
        _morph_loop(particles_h5, target_h5, cfg, name, record, log, run, target_size)
    return summarize_run(out_h5)


def _morph_loop(particles_h5, target_h5, cfg: MorphConfig, name: str, record: str, log, run: RunWriter,
                target_size: float | None = None) -> None:
    partial = run.dir
    parts = load_particles(particles_h5)
    target = load_target(target_h5)
    if target.grid.res != cfg.mpm.grid_res:
        raise ValueError(f"{target_h5}: target grid {target.grid.res}^3 does not match mpm.grid_res {cfg.mpm.grid_res}")
    # The render loss sees `cfg.cameras` views evenly spaced around the ring; the alpha-MSE metric
    # always uses every target view, so runs with different camera counts stay comparable.
    V = target.cameras.count
    n_loss = V if cfg.cameras is None else min(cfg.cameras, V)
    views = sorted(set(np.linspace(0, V, n_loss, endpoint=False).astype(int).tolist()))
    cams = target.cameras.subset(views)
    rtarget = RenderTarget(target.alpha[views], target.depth[views], target.sdt[views])
    # The best any morph of these particles can render: the target's own sampling at rest.
    ceiling = float(getattr(target, "ceiling_alpha_mse", np.nan))
    # Sliding-midpoint splits (balanced_tree=False): the surface points lie on a 2D sheet, where the
    # median-split tree makes each particle's nearest-point query 3.3x slower (471K particles
    # against 200K points, the paper profile: 5.8 s against 1.75 s a query).
    tree = cKDTree(target.surface_points, balanced_tree=False, compact_nodes=False)
    N = len(parts.x)
    solver = solver_for(cfg.mpm, N)  # a reset solver, reused from the previous run of this config and size
    # MPM conserves mass, so a target of another total mass cannot be matched: the squared loss
    # would then be lowered by smearing the excess thinly. The target's mass distribution is
    # rescaled to the source's total mass (its shape is what is matched).
    mass_ratio = float(parts.mass.sum() / target.grid_mass.sum())
    solver.set_target_grid_mass(target.grid_mass * mass_ratio)
    # a target of another volume is named once in the log and in the run file's warnings
    source_volume = parts.mesh_volume if np.isfinite(parts.mesh_volume) else float(parts.volume.sum())
    volume_note = volume_mismatch(name or str(target_h5), source_volume, float(target.volume), target_size)
    if volume_note:
        log(f"[{name}] warning: {volume_note}")
    lo, hi = cfg.mpm.domain_lo, cfg.mpm.domain_hi

    # The mask is only built where something uses it (a switched-off component costs nothing).
    need_mask = cfg.method != "physics_only" or not cfg.metric_all_particles

    # The loss render of a frame is the metric's render when it draws the same particles (the
    # mask) from every view: plasticity and the momentum restart change neither x nor F.
    loss_render_is_metric = not cfg.metric_all_particles and len(views) == V

    def metrics_for(st: ParticleState, mask: np.ndarray, alpha: np.ndarray | None = None,
                    target_distance: np.ndarray | None = None,
                    masked_alpha: np.ndarray | None = None) -> tuple[dict, np.ndarray, DeformationMeasures]:  # per_view [V]
        sel = slice(None) if cfg.metric_all_particles else mask
        if alpha is None and masked_alpha is not None and cfg.metric_all_particles:
            # The loss rendered the masked particles from every view; coverage composes, 1 - alpha =
            # T_mask T_rest (to within the compositing's early stop, transmittance_min), so only the
            # particles outside the mask (~10 % at the paper's scale) are rendered again.
            rest = ~mask
            alpha = masked_alpha if not rest.any() else 1.0 - (1.0 - masked_alpha) * (
                1.0 - render_views(st.x[rest], st.F[rest], parts.sigma0, target.cameras, cfg.render)[0])
        if alpha is None:
            alpha, _ = render_views(st.x[sel], st.F[sel], parts.sigma0, target.cameras, cfg.render)
        per_view = ((alpha - target.alpha) ** 2).mean(axis=(1, 2))
        iou = silhouette_iou(alpha, target.alpha)
        dm = deformation_measures(st.F, st.Fp)
        d = tree.query(st.x, k=1, workers=-1)[0] if target_distance is None else target_distance
        return {"alpha_mse": float(per_view.mean()), "iou": float(iou.mean()),
                "fp_det_min": float(dm.det_plastic.min()), "fp_det_max": float(dm.det_plastic.max()),
                "fp_anisotropy_max": float(dm.anisotropy_plastic.max()),
                "elastic_energy": dm.elastic_energy(st.volume, cfg.mpm), "kinetic_energy": kinetic_energy(st),
                "total_volume": float(total_volume(st)),
                "mask_size": int(mask.sum()) if need_mask else np.nan,
                "mask_fraction": float(mask.mean()) if need_mask else np.nan,
                "chamfer": float(d.mean()),
                **volume_metrics(st.x, parts.mass, target.grid_mass, target.grid, splat=grid_mass)}, per_view, dm

    destination = None  # correspondence="transport": computed at the first update (a function of the inputs alone)
    pool = None  # the plasticity's neighbour pool, chosen at the first update from the positions at rest
    monitor = StabilityMonitor(cfg.plasticity, log=lambda msg: log(f"[{name}] warning: {msg}"))
    checkpoint = run.resume(log=lambda msg: log(f"[{name}] {msg}"))
    resumed_from = None if checkpoint is None else checkpoint.frame
    if resumed_from is None:
        st = ParticleState(x=parts.x.copy(), v=np.zeros((N, 3)), F=np.tile(np.eye(3), (N, 1, 1)),
                           C=np.zeros((N, 3, 3)), Fp=np.tile(np.eye(3), (N, 1, 1)),
                           mass=parts.mass.copy(), volume=parts.volume.copy())
        mask = update_surface_mask(st.x, st.volume, tree, cfg.surface, lo, hi) if need_mask else np.zeros(N, bool)
        g_F, g_x = np.zeros((N, 3, 3)), np.zeros((N, 3))
        run.set_meta({"experiment": name, "method": cfg.method, "target_mass_ratio": mass_ratio,
                      "target_volume_ratio": float(target.volume) / source_volume, "n_particles": N,
                      "sigma0": parts.sigma0, "views": V, "loss_views": views, "frames_planned": cfg.frames,
                      "ceiling_alpha_mse": ceiling, "ceiling_iou": float(getattr(target, "ceiling_iou", np.nan))})
        m, per_view, _ = metrics_for(st, mask)
        a0 = m["alpha_mse"]
        m["gap_closed"] = 0.0
        # Frame 0 is the unmoved source: it has metrics but no physics step (its losses are NaN).
        run.commit(0, m, per_view, asdict_state(st), [volume_note] if volume_note else [], {**asdict_state(st), "mask": mask, "g_F": g_F, "g_x": g_x,
                                                          "injection_scale": float("nan"), **solver.optimizer_state(),
                                                          **monitor.state()})
        start = 1
    else:
        ck = checkpoint.data
        st = ParticleState(**{k: ck[k] for k in ("x", "v", "F", "C", "Fp", "mass", "volume")})
        mask, g_F, g_x = ck["mask"].astype(bool), ck["g_F"], ck["g_x"]
        solver.set_optimizer_state(ck)
        monitor.restore(ck)
        a0 = run.frame_metric(0, "alpha_mse")
        start = resumed_from + 1
        log(f"[{name}] resuming after frame {resumed_from}/{cfg.frames}")

    scale = float(ck["injection_scale"]) if resumed_from is not None else float("nan")
    restart_on = {"mass_loss": "physics_loss", "alpha_mse": "alpha_mse"}.get(cfg.momentum_restart)
    # the objective whose rise restarts the momentum, and starts the packing term (the mass loss
    # where the restart is off, so the onset does not depend on it)
    rise_on = restart_on or "physics_loss"
    previous = run.frame_metric(start - 1, rise_on)
    before_previous = run.frame_metric(start - 2, rise_on) if start >= 2 else float("nan")
    # the adaptive step (MorphConfig.step_backoff): this frame's step, and the mass loss it is judged against
    step = cfg.mpm.step_size if resumed_from is None else float(ck.get("next_step", cfg.mpm.step_size))
    loss_before = run.frame_metric(start - 1, "physics_loss")
    # MorphConfig.overfill_onset: the packing term waits for the objective's first rise (a
    # resumed run takes the weight its checkpoint was written with; frame 0's has none: 0)
    if cfg.overfill_onset == "first_restart":
        solver.set_overfill_weight(0.0 if resumed_from is None else float(ck.get("overfill_weight", 0.0)))
    inject_F = cfg.method in ("f_inject", "full")
    inject_x = cfg.method == "position_inject"
    want_grad = inject_F or inject_x
    # the stray pull is the Chamfer guidance's (component C, with the plasticity): the full method's
    stray_pull = cfg.stray_pull > 0 and cfg.method == "full"
    # MorphConfig.settle: the last phase's gate over frames (physmorph.settle)
    gate = settle_gate(cfg.settle, cfg.settle_objective, want_grad, cfg.settle_backoff)
    if resumed_from is not None:
        gate.restore(ck)
        if gate.at_rest_after(start - 1):  # the checkpoint's state is the last accepted frame's
            gate.accepted = _accepted_from_run(run, start - 1, st, solver, mask, g_F, g_x, scale, gate.objective_key)
    status = "complete"
    frame_times = []
    nearest_d = nearest_i = None  # the state's nearest target surface points, kept from the last frame's end
    for k in range(start, cfg.frames + 1):
        t0 = time.time()
        # A. physics
        solver.load_state(st)
        if stray_pull:
            if nearest_d is None:
                nearest_d, nearest_i = tree.query(st.x, k=1, workers=-1)
            if cfg.stray_pull_anchor != "nearest" and destination is None:
                destination = destinations_in_grid_mass(parts.x, parts.mass, target.grid_mass, target.grid,
                                                          cfg.plasticity.transport_blur)
            solver.set_position_anchors(*stray_pull_anchors(st.x, st.mass, nearest_d, nearest_i, target, cfg,
                                                            destination))
        if cfg.control_decay < 1.0:
            share = step / cfg.mpm.step_size if cfg.control_decay_follows_step else 1.0
            solver.scale_control(1.0 - (1.0 - cfg.control_decay) * share)
        try:
            recalibrate = np.isnan(scale) or cfg.injection_calibration == "every_frame"
            calibration = None
            if want_grad and cfg.injection_calibration == "absolute":
                scale = cfg.gamma if inject_F else cfg.gamma_x
            elif want_grad and recalibrate and (np.any(g_F) or np.any(g_x)):
                calibration = calibrate_injection(solver, cfg.gamma if inject_F else cfg.gamma_x,
                                                  g_F if inject_F else None, g_x if inject_x else None)
                scale = calibration.scale
                if cfg.injection_calibration == "first_frame":
                    log(f"[{name}] injection scale calibrated at frame {k}: {scale:.4g}")
            c = 0.0 if np.isnan(scale) else scale
            frame_step = step * cfg.step_multiplier(k)  # the bold driver's step on the run's schedule
            # the calibration's rollout is current and its two gradients sum to the first
            # iteration's: the optimiser skips that forward and backward (a third of a frame)
            if calibration is not None:
                solver.combine_calibration(c)
            stats = solver.optimize_control(grad_F_final=c * g_F if inject_F else None,
                                            grad_x_final=c * g_x if inject_x else None,
                                            gradient_ready=calibration is not None,
                                            learning_rate=frame_step)
            new = solver.state_at(cfg.mpm.substeps)
            check_state(new, k, cfg)
        except (MPMError, MorphDivergenceError) as exc:
            msg = str(exc) if str(exc).startswith("frame") else f"frame {k}: {exc}"
            if cfg.method == "position_inject":
                status = f"diverged: {msg}"
                log(f"[{name}] {status} (recorded; position injection is the negative control)")
                break
            raise MorphDivergenceError(f"{msg} (completed frames are kept in {partial})") from exc
        strain = frame_strain(st.F, new.F)
        st = ParticleState(x=new.x, v=new.v, F=new.F, C=new.C, Fp=st.Fp, mass=st.mass, volume=st.volume)
        if cfg.volume_averaging > 0:
            st = dataclasses.replace(st, F=averaged_volume(st.F, grid_average(st.x, st.mass, det3(st.F), target.grid),
                                                           cfg.volume_averaging))
        t1 = time.time()
        # each particle's nearest target surface point, shared by the mask, the plasticity's
        # nearest-point map and the Chamfer metric (x is the same for all: plasticity changes only Fp)
        nearest_d, nearest_i = tree.query(st.x, k=1, workers=-1)
        # Surface mask on the new state.
        if need_mask:
            mask = update_surface_mask(st.x, st.volume, tree, cfg.surface, lo, hi, previous=mask,
                                       target_distance=nearest_d)
        # the physics' and the mask's temporaries go back to the system before the render, the
        # frame's largest transient (physmorph.memory)
        release_free_memory()
        t2 = time.time()
        # B. render (gradients only where a method uses them)
        scal = {"injection_scale": scale if want_grad else np.nan, "physics_loss_initial": stats["loss_initial"], "physics_loss": stats["loss_final"],
                "mass_loss": solver.mass_loss(), "frame_strain": strain,
                "delta_E_percent": stats["delta_E_percent"], "mpm_grad_norm": stats["grad_norm"], "step_size": frame_step,
                # the normalised step the line search kept (0: none lowered the objective; Adam: NaN)
                "step_accepted": (stats["step"] if stats["iters"] > 0 else 0.0) if "step" in stats else np.nan}
        if want_grad:
            res = render_and_grad(st.x[mask], st.F[mask], parts.sigma0, cams, rtarget, cfg.render, want_grad_x=inject_x)
            g_F = np.zeros((N, 3, 3))
            g_F[mask] = res.grad_F
            g_x = np.zeros((N, 3))
            if inject_x and res.grad_x is not None:
                g_x[mask] = res.grad_x
            scal.update(loss_dt=res.losses["dt"], loss_iou=res.losses["iou"], loss_depth=res.losses["depth"],
                        loss_render=res.losses["total"], grad_F_norm=float(np.linalg.norm(g_F)),
                        grad_x_norm=float(np.linalg.norm(g_x)))
        t3 = time.time()
        # C. plasticity
        if cfg.method == "full" and k >= cfg.plasticity.start_frame:
            # The deformation the stress sees is F + dFc (the control enters the stress, see
            # physmorph.mpm.solver): target_rest relaxes Fp toward it, averaged over substeps.
            control_mean = solver.control_mean()  # [N, 3, 3]
            F_stress = st.F + control_mean if cfg.plasticity.update == "target_rest" else None
            absorbing = cfg.plasticity.absorbs_at(k, cfg.frames)
            Fp_from = absorbed_rest(st.F, control_mean, st.Fp, cfg.plasticity) if absorbing else st.Fp
            if cfg.plasticity.correspondence == "transport" and destination is None:
                destination = destinations_in_grid_mass(parts.x, parts.mass, target.grid_mass, target.grid,
                                                          cfg.plasticity.transport_blur)
            if pool is None:
                pool = neighbour_pool(parts.x, target.grid.lo, target.grid.dx, cfg.plasticity.neighbour_ppc)
                pool = np.arange(N) if pool is None else pool
            pl = chamfer_plasticity_step(st.x, Fp_from, target.surface_points, cfg.plasticity, tree, F=F_stress,
                                         destination=destination, nearest_index=nearest_i,
                                         pool=None if len(pool) == N else pool)
            Fp_old = st.Fp
            st = ParticleState(x=st.x, v=st.v, F=st.F, C=st.C, Fp=pl.Fp, mass=st.mass, volume=st.volume)
            try:  # before the re-base: a bad Fp is named as such, not as a bad control
                check_state(st, k, cfg)
            except MorphDivergenceError as exc:
                raise MorphDivergenceError(f"{exc} (completed frames are kept in {partial})") from exc
            rebase_to = rebase_reference(cfg.plasticity, absorbing, Fp_from, pl.Fp)
            if rebase_to is not None:
                solver.rebase_control(st.F, np.linalg.solve(Fp_old, rebase_to))
        t4 = time.time()
        m, per_view, dm = metrics_for(st, mask, alpha=res.alpha if want_grad and loss_render_is_metric else None,
                                  masked_alpha=res.alpha if want_grad and len(views) == V else None,
                                  target_distance=nearest_d)
        m["gap_closed"] = gap_closed(a0, m["alpha_mse"], ceiling) if np.isfinite(ceiling) else np.nan
        scal.update(m)
        rejected = gate.rejects(k, scal.get(gate.objective_key, np.nan))
        if rejected:  # the frame is undone: the body holds still at the last accepted frame
            back = gate.accepted
            st, mask, g_F, g_x, scale = back.state, back.mask, back.g_F, back.g_x, back.injection_scale
            solver.restore_kept_control()
            scal, per_view, m = dict(back.scalars), back.per_view, back.scalars
            nearest_d = nearest_i = None
            scal["step_size"] = frame_step  # the step the undone frame tried
            step *= gate.backoff
            if k == cfg.frames and cfg.method == "full" and cfg.plasticity.absorbs_at(k, cfg.frames):
                st = _absorb_at_rest(st, solver, cfg)  # the last update's absorption, on the accepted body
        if gate.gates(k):
            scal["settling"] = 2.0 if rejected else 1.0
        now = scal[rise_on]
        objective_rose = bool(np.isfinite(previous) and now > previous)
        # MorphConfig.restart_reference: the level a restart is judged against
        reference = before_previous if cfg.restart_reference == "two_back" and np.isfinite(before_previous) else previous
        restart = bool(np.isfinite(reference) and now > reference)
        before_previous, previous = previous, now
        if restart_on:
            # the objective rose over this frame: the state is moving away from the target, so
            # the next frame starts with (most of) that momentum removed
            if gate.note_restart(k, restart):
                log(f"[{name}] frame {k}: the restart fired ({cfg.settle}); from frame {k + 1} every "
                    f"frame starts at rest, and one whose {gate.objective_key} rises is undone")
            if restart or gate.at_rest_after(k):
                st = ParticleState(x=st.x, v=cfg.restart_keep * st.v, F=st.F, C=cfg.restart_keep * st.C, Fp=st.Fp,
                                   mass=st.mass, volume=st.volume)
                if restart and cfg.restart_control_keep < 1.0:  # a restart's, not the settle phase's rest
                    solver.scale_control(cfg.restart_control_keep)
            scal["momentum_restart"] = float(restart)
        if gate.at_rest_after(k) and not rejected:
            solver.keep_control()  # on the device: a host copy of the control costs 340 MB at the paper's scale
            gate.accepted = AcceptedFrame(st, mask, g_F, g_x, scale, dict(scal), per_view,
                                          float(scal.get(gate.objective_key, np.nan)))
        if objective_rose and solver.overfill_weight != cfg.mpm.overfill_weight:
            solver.set_overfill_weight(cfg.mpm.overfill_weight)
            log(f"[{name}] frame {k}: the objective first rose, the packing term acts from frame {k + 1}")
        if np.isfinite(loss_before):  # the bold driver: back off after a rise, regrow after a fall
            rose = scal["physics_loss"] > loss_before
            step = step * cfg.step_backoff if rose else min(step * cfg.step_growth, cfg.mpm.step_size)
        loss_before = scal["physics_loss"]
        if cfg.strain_rate_cap > 0 and strain > 0:  # the body's strain rate steers the next step
            step = min(step * cfg.strain_rate_cap / strain, cfg.mpm.step_size)
        new_warnings = [] if rejected else monitor.update(k, st.Fp, m["alpha_mse"], det=dm.det_plastic,
                                                          fp_anisotropy=dm.anisotropy_plastic)
        # the render's images and gradient and the metrics' arrays are done with: the frame's freed
        # heap goes back to the system, so the checkpoint's buffers do not sit on top of it. Not
        # after every stage: memory returned is faulted in again by the next stage (on the 2-core
        # VM up to ~2 ms per MB), and the stages reuse each other's freed blocks (physmorph.memory)
        res = dm = None
        release_free_memory()
        scal.update(t_physics=t1 - t0, t_mask=t2 - t1, t_render=t3 - t2, t_plasticity=t4 - t3, t_frame=time.time() - t0)
        save = k % cfg.save_every == 0 or k == cfg.frames
        # the checkpoint's arrays are gathered only when it is due (physmorph.runfile)
        run.commit(k, scal, per_view, asdict_state(st) if save else None, new_warnings,
                   lambda: {**asdict_state(st), "mask": mask, "g_F": g_F, "g_x": g_x, "injection_scale": scale,
                            "next_step": step, "overfill_weight": solver.overfill_weight,
                            **gate.checkpoint(),
                            **solver.optimizer_state(), **monitor.state()},
                   last=k == cfg.frames, motion={"x": st.x, "F": st.F})
        frame_times.append(scal["t_frame"])
        if cfg.progress:
            eta = np.mean(frame_times) * (cfg.frames - k)
            log(f"[{name}] frame {k}/{cfg.frames}  alpha_mse {scal['alpha_mse']:.4f} "
                f"(gap closed {100 * scal['gap_closed']:.0f} %)  "
                f"physics {stats['loss_initial']:.4g}->{stats['loss_final']:.4g}  "
                f"|gF| {scal.get('grad_F_norm', 0.0):.3g}  {scal['t_frame']:.1f} s/frame  ETA {eta:.0f} s"
                + ("  (undone: the body holds still)" if rejected else ""))
    extra = {"injection_scale": scale}
    if cfg.release_frames and status == "complete":
        extra["release_alpha_mse"] = json.dumps(release_curve(solver, st, cfg.release_frames,
                                                              lambda s: metrics_for(s, mask)[0]["alpha_mse"], log, name))
    # The file's provenance also keeps every setting resolved (the key leaves defaults out).
    run.finish(status, extra, {**json.loads(record), "resolved": cfg.to_dict()})


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


def stray_pull_anchors(x: np.ndarray,  # [N, 3]
                       mass: np.ndarray,  # [N]
                       nearest_d: np.ndarray,  # [N] distance to the nearest target surface point
                       nearest_i: np.ndarray,  # [N] its index in target.surface_points
                       target, cfg: MorphConfig,
                       destination: np.ndarray | None = None,  # [N, 3] transport destinations
                       ) -> tuple[np.ndarray, np.ndarray]:  # [N, 3], [N]
    """The stray pull's anchors and weights (MorphConfig.stray_pull): a particle whose nearest grid
    node holds no target mass and which lies more than stray_pull_onset cells from the target's
    surface gets the anchor s_p, its nearest surface point (stray_pull_anchor "nearest"), its
    destination T_p (stray_pull_anchor "transport", ``destination`` required) or x_p + d_p (T_p -
    x_p) / |T_p - x_p|, d_p the distance to the nearest surface point ("toward_transport"), and the
    weight stray_pull m_p / (density dx^3) / dx^2 (the solver adds w_p |x_T,p - s_p|^2); every
    other particle weight 0."""
    grid = target.grid
    node = np.clip(np.rint((x - np.asarray(grid.lo)) / grid.dx).astype(np.int64), 0, grid.res - 1)
    outside = target.grid_mass[node[:, 0], node[:, 1], node[:, 2]] <= 0.0
    stray = outside & (nearest_d > cfg.stray_pull_onset * grid.dx)
    cell_mass = cfg.mpm.density * grid.dx ** 3
    weight = np.where(stray, cfg.stray_pull * mass / cell_mass / grid.dx ** 2, 0.0)
    if cfg.stray_pull_anchor != "nearest":
        if destination is None:
            raise ValueError(f"stray_pull_anchor {cfg.stray_pull_anchor!r} needs the particles' destinations")
        destination = np.asarray(destination, dtype=np.float64)
        if cfg.stray_pull_anchor == "transport":
            return destination, weight
        way = destination - x
        length = np.linalg.norm(way, axis=1)
        reach = np.divide(nearest_d, length, out=np.zeros_like(length), where=length > 0)
        return x + way * np.minimum(reach, 1.0)[:, None], weight
    return np.asarray(target.surface_points)[nearest_i], weight


def _accepted_from_run(run: RunWriter, frame: int, st: ParticleState, solver: MPMSolver, mask, g_F, g_x,
                       scale: float, objective_key: str) -> AcceptedFrame:
    """A resumed run's last accepted frame: its loop state is the checkpoint's (after a settling
    frame the state is the accepted one) and its metrics the committed frame's."""
    scalars, per_view = run.frame_metrics(frame)
    solver.keep_control()
    return AcceptedFrame(st, mask, g_F, g_x, scale, scalars, per_view,
                         float(scalars.get(objective_key, np.nan)))


def _absorb_at_rest(st: ParticleState, solver: MPMSolver, cfg: MorphConfig) -> ParticleState:
    """The shape absorbed into the rest state (plasticity.absorb_control) without a Chamfer step: the
    last frame's absorption when that frame was undone, so the run still ends with its shape in Fp."""
    Fp = absorbed_rest(st.F, solver.control_mean(), st.Fp, cfg.plasticity)
    rebase_to = rebase_reference(cfg.plasticity, True, Fp, Fp)
    if rebase_to is not None:
        solver.rebase_control(st.F, np.linalg.solve(st.Fp, rebase_to))
    return dataclasses.replace(st, Fp=Fp)


def averaged_volume(F: np.ndarray,  # [N, 3, 3]
                    J_average: np.ndarray,  # [N] the grid's average of det F at each particle
                    share: float) -> np.ndarray:  # [N, 3, 3]
    """F <- (J' / J)^(1/3) F with J' = (1 - share) J + share J_average (MorphConfig.volume_averaging):
    the volume ratio moves toward the grid's average, the shape (F / J^(1/3)) stays. A particle whose
    J or J' is not positive (an inverted F) keeps its F."""
    J = det3(np.asarray(F, dtype=np.float64))
    J_new = (1.0 - share) * J + share * np.asarray(J_average, dtype=np.float64)
    ok = (J > 0) & (J_new > 0)
    r = np.ones_like(J)
    r[ok] = np.cbrt(J_new[ok] / J[ok])
    return (F * r[:, None, None]).astype(np.asarray(F).dtype)


def asdict_state(st: ParticleState) -> dict:
    return {k: np.asarray(getattr(st, k)) for k in ("x", "v", "F", "C", "Fp", "mass", "volume")}


def morph_config(settings, experiment_name: str) -> MorphConfig:
    """The MorphConfig of one experiment: the global sections, then the experiment's own keys
    (``settings``: physmorph.config.Settings, which owns the resolution and its checks)."""
    return settings.experiment_config(experiment_name)
