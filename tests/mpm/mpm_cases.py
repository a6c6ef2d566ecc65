"""What the MPM solver tests share: a lattice ball state, the small solver configs and the
module-scoped solvers (each instance compiles its Taichi kernels, so a module builds its own once;
a test's own solver comes from solver_for, so configs that differ only in driver settings share
one), and the finite-difference and torch autograd checks of the control gradient."""

from __future__ import annotations

import numpy as np
import torch

from physmorph.base.grid import Grid, splat_mass
from physmorph.settings.mpm import MPMConfig
from physmorph.mpm.solver import MPMSolver, solver_for
from physmorph.mpm.state import ParticleState, total_volume
from physmorph.mpm import reference as ref

RES = 16  # dx = 2 on [-16, 16]^3


def ball_state(radius: float = 3.0, spacing: float = 1.0, center=(0.0, 0.0, 0.0),
               seed: int | None = 0, perturb: bool = True) -> ParticleState:
    """Lattice ball; with perturb, random v, C, F and a non-identity Fp (a generic state)."""
    a = np.arange(-radius, radius + 1e-9, spacing)
    X = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    X = X[np.linalg.norm(X, axis=1) <= radius] + np.asarray(center)
    n = len(X)
    st = ParticleState.at_rest(X, np.full(n, 75.0 * spacing ** 3), np.full(n, spacing ** 3))
    if perturb:
        rng = np.random.default_rng(seed)
        st.x = st.x + 0.1 * rng.normal(size=(n, 3))
        st.v = rng.normal(size=(n, 3))
        st.C = 0.2 * rng.normal(size=(n, 3, 3))
        st.F = np.eye(3) + 0.05 * rng.normal(size=(n, 3, 3))
        st.Fp = np.eye(3) + 0.05 * rng.normal(size=(n, 3, 3))
    return st


def stretched_target(st: ParticleState, cfg: MPMConfig, stretch=(1.15, 0.93, 0.93)) -> np.ndarray:
    return splat_mass(st.x * np.asarray(stretch), st.mass, Grid(cfg.grid_res, cfg.domain_lo, cfg.domain_hi))


def make(cfg: MPMConfig, st: ParticleState, target: bool = True, reuse: bool = False) -> MPMSolver:
    """A solver loaded with st (and the stretched target). reuse: take it from solver_for (for a
    test's own solver; module fixtures take theirs from module_solver or build their own, which no
    later test may reset)."""
    return _loaded(solver_for(cfg, st.n) if reuse else MPMSolver(cfg, st.n), cfg, st, target)


def _loaded(s: MPMSolver, cfg: MPMConfig, st: ParticleState, target: bool = True) -> MPMSolver:
    """s with the stretched target (where ``target``) and st loaded."""
    if target:
        s.set_target_grid_mass(stretched_target(ball_state(perturb=False), cfg))
    s.load_state(st)
    return s


# Module fixtures' solvers by (fixture name, kernel settings, particle count): solver3 is made by each
# module that uses it, and each build compiles ~60 kernels (~8 s on 2 cores with Taichi's cache empty)
_module_solvers: dict = {}


def module_solver(name: str, cfg: MPMConfig, st: ParticleState) -> MPMSolver:
    """The solver of the module fixture ``name``, loaded with st and the stretched target: the one an
    earlier module's fixture of that name built for these kernel settings and this size, reset and
    configured (a reset solver computes what a new one would: test_mpm_solver.py), else a new one.
    Apart from solver_for's, so no test's own solver is this one: no test resets it in its module."""
    key = (name, cfg.kernel_settings(), st.n)
    if key not in _module_solvers:
        _module_solvers[key] = MPMSolver(cfg, st.n)
    s = _module_solvers[key]
    s.reset()
    s.configure(cfg)
    return _loaded(s, cfg, st)


def cfg64(**kw) -> MPMConfig:
    # The solver tests are written for the squared mass loss and Adam, without the step clip, the
    # authors' full step (no volume projection), the paper's F smoothing, no packing term, no
    # blurred level and no volume term (the workflow's defaults are the log loss with overfill
    # weighed twice, a blurred level and a volume term, clipped volume-projected normalised GD and
    # isochoric smoothing, tested where a test names them).
    base = dict(grid_res=RES, precision="float64", substeps=3, mass_loss="squared", log_mass_eps=1e-3,
                optimizer="adam", learning_rate=0.01, step_clip=0.0, smoothing_mode="full", step_volume="full",
                overfill_weight=0.0, mass_loss_blur=0.0, volume_weight=0.0)
    base.update(kw)
    return MPMConfig(**base)


def volume_term_parts(s: MPMSolver, st: ParticleState) -> tuple[float, float, int]:
    """The loss of a forward of s's current control and state st without the volume term, the
    body's volume at its end over the rest volume, V_T / V* = sum V0 det F_T / sum V0 det Fp, and
    the target's filled nodes u (the term's unit): the parts of w u (V_T / V* - 1)^2."""
    plain = s.forward()
    ratio = total_volume(s.state_at(s.cfg.substeps)) / float((st.volume * np.linalg.det(st.Fp)).sum())
    return plain, ratio, int((s.model.target_m.to_numpy() > 0).sum())


def random_control(cfg: MPMConfig, n: int, scale: float = 0.05, seed: int = 3) -> np.ndarray:
    return scale * np.random.default_rng(seed).normal(size=(cfg.n_control_slots, n, 3, 3))




def fd_check(s: MPMSolver, st: ParticleState, gF=None, gx=None, n_checks=6, h=1e-4, seed=0,
              state_names=("x", "v", "F")):
    """Central FD of J = L + <gF, F_T> + <gx, x_T> against the reverse pass, on random entries
    of dFc and of the initial state's state_names (x0, v0, F0). h = 1e-4: the loss sums ~10^3 grid
    nodes (L ~ 300 in the log-loss cases), so its float64 round-off, which moves with the order the
    threads' atomic adds land in, is ~1e-13; divided by 2h = 2e-6 that was ~1e-7 in the quotient,
    as large as the tolerance. At 1e-4 the round-off term is 100x smaller, and the truncation term
    (h^2 times the third derivative) stays far below the tolerance on these smooth losses."""
    def objective():
        L = s.forward()
        end = s.state_at(s.cfg.substeps)
        if gF is not None:
            L += (gF * end.F).sum()
        if gx is not None:
            L += (gx * end.x).sum()
        return L

    s.load_state(st)
    ctrl = s.control()
    objective()
    s.backward(gF, gx)
    g_ctrl = s.control_gradient()
    g0 = s.initial_state_gradients()
    rng = np.random.default_rng(seed)
    pairs = []
    for _ in range(n_checks):
        idx = tuple(rng.integers(0, d) for d in ctrl.shape)
        c = ctrl.copy(); c[idx] += h; s.set_control(c); jp = objective()
        c[idx] -= 2 * h; s.set_control(c); jm = objective()
        s.set_control(ctrl)
        pairs.append((g_ctrl[idx], (jp - jm) / (2 * h)))
    for name in state_names:
        arr = getattr(st, name)
        for _ in range(n_checks // 2):
            idx = tuple(rng.integers(0, d) for d in arr.shape)
            p = st.copy(); getattr(p, name)[idx] += h; s.load_state(p); jp = objective()
            getattr(p, name)[idx] -= 2 * h; s.load_state(p); jm = objective()
            pairs.append((g0[name][idx], (jp - jm) / (2 * h)))
    s.load_state(st)
    an, fd = np.array(pairs).T
    scale = np.abs(an).max()
    assert scale > 0
    np.testing.assert_allclose(an, fd, rtol=2e-5, atol=2e-6 * scale)
    return g_ctrl


def autograd_check(s: MPMSolver, st: ParticleState, ctrl, gF=None, check_x0=True):
    """The solver's gradient of L + <gF, F_T> (squared mass loss) on dFc, and on x0 with check_x0,
    against torch autograd through the reference rollout; returns the reference's states."""
    s.load_state(st)
    s.set_control(ctrl)
    s.forward()
    s.backward(gF, None)
    x0 = ref.as_torch(st.x, True)
    c = ref.as_torch(ctrl, True)
    states = ref.rollout_torch(x0, ref.as_torch(st.v), ref.as_torch(st.C), ref.as_torch(st.F), c,
                               ref.as_torch(st.Fp), ref.as_torch(st.mass), ref.as_torch(st.volume), s.cfg)
    loss = ref.mass_loss_torch(states[-1][0], ref.as_torch(st.mass), ref.as_torch(s.model.target_m.to_numpy()), s.cfg)
    if gF is not None:
        loss = loss + (states[-1][3] * ref.as_torch(gF)).sum()
    loss.backward()
    np.testing.assert_allclose(s.control_gradient(), c.grad.numpy(), rtol=1e-6, atol=1e-8 * c.grad.abs().max().item())
    if check_x0:
        np.testing.assert_allclose(s.initial_state_gradients()["x"], x0.grad.numpy(), rtol=1e-6,
                                   atol=1e-8 * x0.grad.abs().max().item())
    return states
