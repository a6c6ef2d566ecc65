"""Tests of the differentiable MPM solver (physmorph.mpm): the solver as a whole: extreme states stay finite, a divergence names its quantity and substep, the injected adjoints, a small optimisation, the optimiser state and the kept control, solver reuse and what configure may change."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from physmorph.base.grid import Grid, splat_mass
from physmorph.settings.mpm import CFLWarning, MPMConfig, MPMConfigError, MPMDivergenceError, MPMStateError
from physmorph.mpm.solver import MPMSolver, solver_for
from physmorph.mpm.state import ParticleState, elastic_energy, fixed_corotated_energy_density, total_volume
from physmorph.mpm import reference as ref
from physmorph.mpm.stress import evaluate_stress
from mpm_cases import (RES, autograd_check, ball_state, cfg64, fd_check, make, random_control,  # noqa: F401
                        stretched_target)


# ----------------------------------------------------------------------------- extremes
@pytest.mark.parametrize("case", ["near_singular", "inverted", "compressed", "extreme_Fp", "faces"])
def test_extreme_states_stay_finite(solver20, case):
    s = solver20
    st = ball_state(perturb=False)
    n = st.n
    rng = np.random.default_rng(1)
    if case == "near_singular":
        st.F = np.broadcast_to(np.diag([1.0, 1.0, 1e-4]), (n, 3, 3)).copy()
    elif case == "inverted":
        st.F = np.eye(3) + 0.1 * rng.normal(size=(n, 3, 3))
        st.F[::2, :, 0] *= -1.0
    elif case == "compressed":
        st.F = np.broadcast_to(0.05 ** (1 / 3) * np.eye(3), (n, 3, 3)).copy()  # J = 0.05
    elif case == "extreme_Fp":
        st.Fp = np.broadcast_to(np.diag([4.0, 2.0, 0.05]), (n, 3, 3)).copy()  # det 0.4, anisotropic
        st.Fp[1::2] = np.diag([10.0, 10.0, 10.0])  # det 1000
    elif case == "faces":
        # particles pressed against all six faces, moving outward fast
        lo, hi = s.model.x_min, s.model.x_max
        x = rng.uniform(lo, hi, size=(n, 3))
        for i in range(n):
            x[i, i % 3] = lo if (i // 3) % 2 == 0 else hi
        st.x = x
        st.v = np.sign(x) * 30.0
    s.reset_control()
    s.load_state(st)
    s.forward()
    end = s.state_at(20)
    for name in ("x", "v", "F", "C"):
        assert np.isfinite(getattr(end, name)).all(), name
    assert (end.x >= s.model.x_min).all() and (end.x <= s.model.x_max).all()
    s.backward()
    assert np.isfinite(s.control_gradient()).all()
    assert np.isfinite(s.initial_state_gradients()["x"]).all()
    s.reset_control()


def test_max_drag_and_near_one_smoothing_stay_finite():
    cfg = cfg64(substeps=20, drag=240.0, smoothing=0.999)  # d = 1/dt: P2G momentum factor 0
    st = ball_state()
    s = make(cfg, st)
    s.set_control(random_control(cfg, st.n))
    s.forward()
    end = s.state_at(20)
    assert np.isfinite(end.F).all() and np.isfinite(end.x).all()
    # all the incoming momentum is removed: only stress moves material
    s.backward()
    assert np.isfinite(s.control_gradient()).all()


def test_stiff_material_near_cfl_limit_stays_finite():
    base = cfg64(substeps=20, drag=0.0, smoothing=0.0)
    e_lim = base.density * (base.cfl * base.dx / base.dt) ** 2 * (1 + 0.2) * (1 - 0.4) / (1 - 0.2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CFLWarning)
        cfg = cfg64(substeps=20, drag=0.0, smoothing=0.0, youngs_modulus=0.95 * e_lim)
    st = ball_state(seed=2)
    st.F = np.eye(3) + 0.2 * np.random.default_rng(0).normal(size=(st.n, 3, 3))  # strongly stressed
    s = make(cfg, st, target=False)
    s.forward()
    end = s.state_at(20)
    assert np.isfinite(end.F).all() and np.abs(end.F).max() < 10.0


def test_divergence_raises_naming_quantity_and_substep(solver20):
    st = ball_state(perturb=False)
    solver20.load_state(st)
    solver20.set_control(np.full((20, st.n, 3, 3), 1e7))
    with pytest.raises(MPMDivergenceError, match=r"(x|v|F) became non-finite .* at substep \d+ \(particle \d+\)"):
        solver20.forward()
    solver20.reset_control()


def test_injected_adjoint_validation(solver3, state):
    solver3.load_state(state)
    solver3.set_control(random_control(solver3.cfg, state.n))
    with pytest.raises(RuntimeError, match="forward"):
        solver3.backward()  # no trajectory of this dFc yet
    solver3.forward()
    assert np.array_equal(solver3.state_at(0).Fp, state.Fp)
    with pytest.raises(MPMStateError, match="grad_F_final"):
        solver3.backward(np.zeros((state.n, 3)))
    g = np.zeros((state.n, 3))
    g[0, 0] = np.inf
    with pytest.raises(MPMStateError, match="grad_x_final is not finite"):
        solver3.backward(None, g)


# ----------------------------------------------------------------------------- optimization
def test_optimization_reduces_mass_loss_by_half(solver20):
    """Sphere -> slightly stretched sphere: Adam on dFc reduces the end-layer mass loss > 50 %."""
    s = solver20
    st = ball_state(perturb=False)
    s.set_target_grid_mass(stretched_target(st, s.cfg, stretch=(1.06, 0.97, 0.97)))
    s.reset_control()
    s.load_state(st)
    stats = s.optimize_control(iters=40)
    assert stats["iters"] == 40
    assert stats["loss_final"] < 0.5 * stats["loss_initial"]
    assert stats["loss_final"] == pytest.approx(s.mass_loss())
    end = s.rollout()
    assert s.mass_loss() == pytest.approx(stats["loss_final"], rel=1e-12)
    # the stretch is real: the extent grew along x and shrank along y, z
    ext = end.x.max(0) - end.x.min(0)
    ext0 = st.x.max(0) - st.x.min(0)
    assert ext[0] > ext0[0] and ext[1] < ext0[1]
    s.reset_control()
    assert np.abs(s.control()).max() == 0.0
    s.set_target_grid_mass(stretched_target(ball_state(perturb=False), s.cfg))


def test_injected_adjoint_alone_is_the_difference(solver3, state):
    """backward(g, include_mass_loss=False) pulls back the injected adjoints alone: by linearity
    it equals backward(g) - backward(None) (float64); backward_pair gives both gradients, and the
    injected one's initial-state adjoints, in one sweep."""
    s = solver3
    s.load_state(state)
    s.set_control(random_control(s.cfg, s.n))
    rng = np.random.default_rng(5)
    gF, gx = rng.normal(size=(s.n, 3, 3)), rng.normal(size=(s.n, 3))
    s.forward()
    s.backward(None, None)
    g_mass = s.control_gradient()
    s.backward(gF, gx)
    g_both = s.control_gradient()
    s.backward(gF, gx, include_mass_loss=False)
    g_inj = s.control_gradient()
    assert np.linalg.norm(g_inj) > 0 and np.linalg.norm(g_mass) > 0
    np.testing.assert_allclose(g_inj, g_both - g_mass, rtol=1e-8, atol=1e-10 * np.abs(g_both).max())
    initial_inj = s.initial_state_gradients()
    # backward_pair: the two in one reverse sweep (mass into the base field, injected into the gradient)
    n_mass, n_inj = s.backward_pair(gF, gx)
    np.testing.assert_allclose(s.control_gradient(), g_inj, rtol=1e-10, atol=1e-14 * np.abs(g_inj).max())
    np.testing.assert_allclose(s.control_field.ctrl_base.to_numpy(), g_mass, rtol=1e-10, atol=1e-14 * np.abs(g_mass).max())
    assert (n_mass, n_inj) == pytest.approx((np.linalg.norm(g_mass), np.linalg.norm(g_inj)), rel=1e-10)
    for key, ref in initial_inj.items():
        np.testing.assert_allclose(s.initial_state_gradients()[key], ref, rtol=1e-10, atol=1e-14 * np.abs(ref).max())


def test_optimizer_state_round_trip(solver3, state):
    """Saving and restoring dFc + Adam moments reproduces the next optimization step exactly."""
    s = solver3
    s.reset_control()
    s.load_state(state)
    s.optimize_control(iters=2)
    saved = s.optimizer_state()
    after_a = s.optimize_control(iters=1)["loss_final"]
    ctrl_a = s.control()
    s.reset_control()
    s.set_optimizer_state(saved)
    s.load_state(state)
    after_b = s.optimize_control(iters=1)["loss_final"]
    assert after_b == after_a
    np.testing.assert_array_equal(s.control(), ctrl_a)
    with pytest.raises(MPMStateError, match="adam_m"):
        s.set_optimizer_state({**saved, "adam_m": saved["adam_m"][:, :1]})


@pytest.mark.parametrize("spill", [False, True])
def test_kept_control_restores_the_next_step(solver3, state, spill, tmp_path):
    """keep_control / restore_kept_control (the settle phase's undo, on the device or in a file) put
    back the control and Adam's moments: the next optimization step is the one taken from the kept point."""
    s = solver3
    s.reset_control()
    s.load_state(state)
    s.optimize_control(iters=2)
    s.keep_control(spill=tmp_path / "kept.bin" if spill else None)
    after_a = s.optimize_control(iters=1)["loss_final"]
    ctrl_a = s.control()
    s.optimize_control(iters=2)  # moves the control and the moments on
    assert not np.array_equal(s.control(), ctrl_a)
    s.restore_kept_control()
    s.load_state(state)
    after_b = s.optimize_control(iters=1)["loss_final"]
    assert after_b == after_a
    np.testing.assert_array_equal(s.control(), ctrl_a)


def test_reused_solver_computes_what_a_new_one_does(state):
    """solver_for hands back the previous solver for an equal config and size, reset: after a
    run that moved dFc and the Adam moments, it optimizes exactly as a freshly built solver; given
    other driver settings (optimiser, learning rate, line search, log eps, ...) it optimizes as a
    solver built with them. Slow: it builds two solvers, each compiling its kernels (solver_for's
    and a fresh one to compare with), and runs four optimisations of three iterations each."""
    cfg = cfg64(substeps=2, mass_loss="log")
    target = stretched_target(ball_state(perturb=False), cfg)

    def optimize(s):
        s.set_target_grid_mass(target)
        s.load_state(state)
        stats = s.optimize_control(iters=3)
        return stats["loss_final"], s.control(), s.optimizer_state().get("adam_v")  # None: Adam never ran

    first = solver_for(cfg, state.n)
    loss_a, ctrl_a, v_a = optimize(first)
    assert np.abs(ctrl_a).max() > 0 and np.abs(v_a).max() > 0  # the run left state behind
    again = solver_for(cfg, state.n)
    assert again is first
    assert np.abs(again.control()).max() == 0.0
    with pytest.raises(RuntimeError, match="target"):  # the old target is gone too
        again.optimize_control(iters=1)
    loss_b, ctrl_b, v_b = optimize(again)
    assert loss_b == loss_a
    np.testing.assert_array_equal(ctrl_b, ctrl_a)
    np.testing.assert_array_equal(v_b, v_a)
    # every driver field changed; the kernels compiled above (with cfg) are kept
    driver = dict(optimizer="normalized_gd", learning_rate=3e-3, line_search_iters=4, step_clip=2.0,
                  grad_iters=2, frame_end="last_forward", log_mass_eps=0.05, cfl=0.6, cfl_warn_fraction=0.9,
                  step_scales_with_dx=False, step_per_volume=True, step_volume="particle",
                  step_volume_share=0.5, volume_weight=0.5)
    from physmorph.settings.mpm import DRIVER_FIELDS
    assert set(driver) == DRIVER_FIELDS
    other = cfg64(substeps=2, mass_loss="log", **driver)
    swapped = solver_for(other, state.n)
    assert swapped is first and swapped.cfg is other
    loss_c, ctrl_c, _ = optimize(swapped)
    loss_d, ctrl_d, _ = optimize(MPMSolver(other, state.n))
    assert loss_c == loss_d and loss_c != loss_a
    np.testing.assert_array_equal(ctrl_c, ctrl_d)
    with pytest.raises(MPMConfigError, match="drag"):
        swapped.configure(cfg64(substeps=2, mass_loss="log", drag=0.5))


def test_no_kernel_reads_a_driver_field():
    """What lets configure change DRIVER_FIELDS on a built solver: no Taichi kernel or function,
    and nothing __init__ turns into a compile-time constant, reads them (a static check of the
    solver and stress sources; the test above checks the behaviour)."""
    import ast
    import inspect

    import importlib

    from physmorph.settings.mpm import DRIVER_FIELDS

    def compiled_or_init(fn: ast.FunctionDef) -> bool:
        names = {ast.unparse(d) for d in fn.decorator_list}
        return (fn.name in ("__init__", "make_stress_funcs") or fn.name.startswith("_allocate")
                or bool(names & {"ti.kernel", "ti.func"}))

    read = set()
    kernels = ("solver", "stress", "model", "trajectory", "adjoint", "transfers", "transfer_adjoints",
               "physics_loss", "control", "step_kernels", "optimiser")
    for module in (importlib.import_module(f"physmorph.mpm.{name}") for name in kernels):
        for node in ast.walk(ast.parse(inspect.getsource(module))):
            if isinstance(node, ast.FunctionDef) and compiled_or_init(node):
                read |= {a.attr for a in ast.walk(node) if isinstance(a, ast.Attribute)
                         and isinstance(a.value, (ast.Attribute, ast.Name))
                         and getattr(a.value, "attr", getattr(a.value, "id", None)) == "cfg"}
    assert "substeps" in read and "dt" in read  # the walk does see the kernels' settings
    assert not read & DRIVER_FIELDS, read & DRIVER_FIELDS


def test_solver_for_reuses_only_an_equal_config_and_size(monkeypatch):
    """Other kernel settings or particle count get their own solver, other driver settings the
    same one; every one built is kept, so alternating settings build each once (checked with a
    stand-in class: building real solvers would only add compile time)."""
    import physmorph.mpm.solver as solver_module

    class Recorder:
        def __init__(self, cfg, n):
            self.cfg, self.n, self.resets = cfg, n, 0

        def reset(self):
            self.resets += 1

        def configure(self, cfg):
            self.cfg = cfg

    monkeypatch.setattr(solver_module, "MPMSolver", Recorder)
    monkeypatch.setattr(solver_module, "_reusable", [])
    a = solver_module.solver_for(cfg64(), 10)
    assert solver_module.solver_for(cfg64(), 10) is a and a.resets == 1
    faster = cfg64(learning_rate=0.5, optimizer="normalized_gd")  # driver settings only
    assert solver_module.solver_for(faster, 10) is a and a.cfg is faster and a.resets == 2
    b = solver_module.solver_for(cfg64(drag=0.5), 10)
    assert b is not a and (b.cfg.drag, b.n) == (0.5, 10)
    c = solver_module.solver_for(cfg64(drag=0.5), 11)
    assert c is not b and c.n == 11
    again = solver_module.solver_for(cfg64(), 10)
    assert again is a and a.cfg == cfg64() and a.resets == 3  # reset and given the caller's settings
    assert solver_module.solver_for(cfg64(drag=0.5), 11) is c and solver_module.solver_for(cfg64(drag=0.5), 10) is b
    assert len(solver_module._reusable) == 3


def test_a_lone_particles_control_cannot_move_it():
    """The control acts through the particle's stress, whose forces on its grid nodes sum to zero
    (APIC P2G, paper eq. 6): a particle sharing no node with another stays where it is under any
    control, while its F follows the control. So material torn off the body (the spray) cannot be
    steered back by any loss through the control (docs/study/log.md finding 229)."""
    cfg = cfg64()
    st = ParticleState.at_rest(np.array([[0.3, -0.2, 0.1]]), np.array([75.0]), np.array([1.0]))
    s = make(cfg, st, reuse=True)
    for scale in (0.05, 0.2):
        s.load_state(st)
        c = np.zeros((cfg.n_control_slots, 1, 3, 3))
        c[:, 0] = scale * np.array([[1.0, 0.3, 0.0], [0.0, -0.5, 0.2], [0.1, 0.0, 0.4]])
        s.set_control(c)
        s.forward()
        out = s.state_at(cfg.substeps)
        np.testing.assert_allclose(out.x, st.x, rtol=0, atol=1e-12)
        assert np.abs(out.F[0] - np.eye(3)).max() > 1e-4
