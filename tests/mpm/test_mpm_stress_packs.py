"""P2G's stress on packs of particles (physmorph.mpm.stress_packs, Transfers.p2g_stress), with the
node loops unrolled as the solver runs them at that scale: the packed forward is the
one-particle-a-thread forward's to round-off, in float64 and float32, its control gradient (and the
paired reverse's) matches central differences at the shipped defaults, and it hands to the SVD
exactly the particles polar_from does."""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest

from physmorph.settings.mpm import MPMConfig
from physmorph.mpm.stress import WARM_GAP_MIN, evaluate_polar
from physmorph.mpm.stress_packs import PACK
from physmorph.mpm.transfer_adjoints import TransferAdjoints
from physmorph.mpm.transfers import Transfers
from mpm_cases import RES, ball_state, fd_check, make, random_control

STORED = ("x", "v", "C", "F", "R_q", "gap_t", "grid_m_t", "grid_mv_t")


def shipped(precision: str) -> MPMConfig:
    """The shipped solver on the tests' small grid, 3 substeps (test_mpm_transfers' shipped solver)."""
    return dataclasses.replace(MPMConfig(), precision=precision, grid_res=RES, substeps=3)


def generic_state():
    """The ball (123 particles: the last pack is part full) with a few inverted F (the SVD's branch)."""
    st = ball_state()
    assert st.n % PACK != 0
    st.F[:6, :, 2] *= -1.0
    return st


# packed transfers per solver: each Transfers instance compiles its kernels (and allocates a field)
_packed: dict = {}


@contextlib.contextmanager
def packed_transfers(s):
    """s's transfers replaced by packed ones for the block, and its transfers' adjoints by unrolled
    ones (the small ball is under the size from which the solver packs and unrolls by itself)."""
    kept = s.transfers, s.transfer_adjoints
    assert not kept[0].packed and not kept[1].unrolled
    if id(s) not in _packed:
        packed = Transfers(s.model, s.trajectory, s.control_field, packed=True)
        assert packed.unrolled
        _packed[id(s)] = (s, packed, TransferAdjoints(s.model, s.trajectory, s.control_field, s.adjoint, unrolled=True))
    s.transfers, s.transfer_adjoints = _packed[id(s)][1:]
    try:
        yield s.transfers
    finally:
        s.transfers, s.transfer_adjoints = kept


def stored(s) -> dict:
    return {name: getattr(s.trajectory, name).to_numpy().astype(np.float64) for name in STORED}


@pytest.mark.parametrize("precision,tol", [("float64", 1e-12), ("float32", 1e-5)])
def test_packed_forward_and_gradient_are_the_scalar_ones(precision, tol):
    """Every stored quantity of a forward (x, v, C, F, the rotations' quaternions and pair sums, the
    P2G grids) and the control gradient of its backward, packed against one particle a thread,
    within tol of each quantity's largest entry."""
    cfg = shipped(precision)
    st = generic_state()
    s = make(cfg, st, reuse=True)
    s.set_control(random_control(cfg, st.n, scale=0.02))
    s.forward()
    s.backward()
    scalar, grad = stored(s), s.control_gradient()
    with packed_transfers(s):
        s.load_state(st)
        s.forward()
        s.backward()
        packed, grad_packed = stored(s), s.control_gradient()
    for name in STORED:
        # the first substep's pair sums: the packs keep the bound a warm start keeps (polar_start)
        # where P2G's SVD keeps the exact sum (either gives the same solve: stress.polar_from)
        first = 1 if name == "gap_t" else 0
        assert np.abs(packed[name][first:] - scalar[name][first:]).max() <= tol * np.abs(scalar[name]).max(), name
    inverted = np.arange(6)  # generic_state's: the packs hand them to the SVD
    np.testing.assert_allclose(packed["gap_t"][0, inverted], scalar["gap_t"][0, inverted], rtol=tol)
    rest = packed["gap_t"][0, 6:]
    assert (rest > 0).all() and (rest < scalar["gap_t"][0, 6:]).all()
    assert np.abs(grad_packed - grad).max() <= tol * np.abs(grad).max()


def test_unrolled_paired_reverse_is_the_scalar_one():
    """backward_pair's two gradients (the mass loss's and an injected adjoint's) with the packed
    forward and the unrolled reverse, float64, against the same from one particle a thread."""
    cfg = shipped("float64")
    st = generic_state()
    s = make(cfg, st, reuse=True)
    s.set_control(random_control(cfg, st.n, scale=0.02))
    gx = np.random.default_rng(6).normal(size=(st.n, 3))
    results = []
    for unrolled in (False, True):
        with packed_transfers(s) if unrolled else contextlib.nullcontext():
            s.load_state(st)
            s.forward()
            n_mass, n_inj = s.backward_pair(None, gx)
            results.append((n_mass, n_inj, s.control_gradient().copy(), s.initial_state_gradients()["x"]))
    for scalar, unrolled in zip(*results):
        np.testing.assert_allclose(unrolled, scalar, rtol=1e-10, atol=1e-12)


def test_the_solver_at_scale_is_the_scalar_one(monkeypatch):
    """A solver built as at the paper's scale (MPMModel.at_scale: P2G's stress on packs, every node
    loop unrolled, the mass loss's splat and its reverse included), float64, against the same
    solver a particle an iteration with its loops: the loss, the control gradient and the initial
    state's gradients, mass loss and injected adjoints."""
    import physmorph.mpm.model as model_module

    cfg = shipped("float64")
    st = generic_state()
    control = random_control(cfg, st.n, scale=0.02)
    rng = np.random.default_rng(8)
    gF, gx = 50.0 * rng.normal(size=(st.n, 3, 3)), 5.0 * rng.normal(size=(st.n, 3))
    results = []
    for at_scale in (False, True):
        if at_scale:
            monkeypatch.setattr(model_module, "PACKED_STRESS_MIN_PARTICLES", 0)
        s = make(cfg, st)
        assert s.model.at_scale == at_scale and s.transfers.unrolled == at_scale
        s.set_control(control)
        loss = s.forward()
        s.backward(gF, gx)
        grads = s.initial_state_gradients()
        results.append((loss, s.control_gradient().copy(), grads["x"], grads["F"]))
    for scalar, scaled in zip(*results):
        np.testing.assert_allclose(scaled, scalar, rtol=1e-10, atol=1e-12 * np.abs(scalar).max())


def test_packed_gradients_at_the_shipped_defaults_match_fd():
    """The control's and the initial state's gradients with the packed forward, float64, against
    central differences (mpm_cases.fd_check), with the injected adjoints."""
    cfg = shipped("float64")
    st = generic_state()
    s = make(cfg, st, reuse=True)
    s.set_control(random_control(cfg, st.n, scale=0.02))
    rng = np.random.default_rng(5)
    with packed_transfers(s):
        fd_check(s, st, gF=50.0 * rng.normal(size=(st.n, 3, 3)), gx=5.0 * rng.normal(size=(st.n, 3)),
                 n_checks=6, seed=25, h=1e-5)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_packs_hand_to_the_svd_what_polar_from_does(precision):
    """From warm rotations 0.01, 0.3 and 2 rad away (Rodrigues' series and its sines; the far
    ones do not converge within polar_from's steps), the packs mark for the SVD exactly the
    particles whose polar_from takes the SVD, and elsewhere give its rotation and pair-sum
    bound; at the first substep (no warm rotation: polar_start's) they mark the inverted
    particles (polar_start's rotation has det -1 there) and give the polar rotation elsewhere."""
    from scipy.spatial.transform import Rotation

    cfg = shipped(precision)
    st = generic_state()
    s = make(cfg, st, reuse=True)
    s.set_control(random_control(cfg, st.n, scale=0.02))
    s.forward()
    t = 2
    x, v, F, C = s.trajectory.export_raw(t)
    Fe = (F.astype(np.float64) + s.control()[t]) @ s.model.Fp_inv.to_numpy().astype(np.float64)
    R_exact, _, _ = evaluate_polar(Fe, None, "float64")
    rng = np.random.default_rng(7)
    atol = 1e-12 if precision == "float64" else 5e-6
    with packed_transfers(s) as packs:
        for angle in (0.01, 0.3, 2.0):
            R0 = R_exact @ Rotation.from_rotvec(angle * rng.standard_normal((st.n, 3)) / np.sqrt(3)).as_matrix()
            R_scalar, S_scalar, gap_scalar = evaluate_polar(Fe, R0, precision)
            svd = np.abs(gap_scalar - WARM_GAP_MIN * np.linalg.norm(S_scalar, axis=(1, 2))) > 1e-5 * np.abs(S_scalar).max()
            assert 0 < svd.sum() < st.n
            s.trajectory.R_prev.from_numpy(R0.astype(s.model.np_dtype))
            packs.p2g_stress(t)
            gap = s.trajectory.gap_t.to_numpy()[t]
            np.testing.assert_array_equal(gap < 0, svd)
            R = s.trajectory.R_prev.to_numpy()
            np.testing.assert_allclose(R[~svd], R_scalar[~svd], atol=atol)
            np.testing.assert_allclose(gap[~svd], gap_scalar[~svd], rtol=atol)
        x, v, F, C = s.trajectory.export_raw(0)
        Fe = (F.astype(np.float64) + s.control()[0]) @ s.model.Fp_inv.to_numpy().astype(np.float64)
        R_exact, _, _ = evaluate_polar(Fe, None, "float64")
        svd = np.linalg.det(Fe) < 0
        assert 0 < svd.sum() < st.n
        s.trajectory.R_prev.from_numpy(np.zeros_like(R_exact).astype(s.model.np_dtype))  # unread: no warm start
        packs.p2g_stress(0)
        gap = s.trajectory.gap_t.to_numpy()[0]
        np.testing.assert_array_equal(gap < 0, svd)
        R = s.trajectory.R_prev.to_numpy()
        np.testing.assert_allclose(R[~svd], R_exact[~svd], atol=10 * atol)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_polar_start_is_the_polar_rotation(precision):
    """At the first substep the packs find Fe's polar rotation without a warm one (polar_start,
    then polar_from's Newton steps) for rotations of any angle up to a half turn, stretches of
    0.3-3 (condition numbers up to ~10) and nearly singular Fe, and hand to the SVD the inverted
    and the singular ones."""
    from scipy.spatial.transform import Rotation

    cfg = shipped(precision)
    st = generic_state()
    rng = np.random.default_rng(11)
    n = st.n
    axes = rng.normal(size=(n, 3))
    rot = Rotation.from_rotvec(np.pi * rng.uniform(0, 1, (n, 1)) * axes / np.linalg.norm(axes, axis=1, keepdims=True))
    basis = Rotation.random(n, random_state=4).as_matrix()
    stretch = np.exp(rng.uniform(np.log(0.3), np.log(3.0), (n, 3)))
    stretch[:4, 2] = 1e-4  # nearly singular
    stretch[4:8, 2] *= -1.0  # inverted
    stretch[8, 2] = 0.0  # singular
    st.F = rot.as_matrix() @ basis @ (stretch[:, :, None] * basis.transpose(0, 2, 1))
    st.Fp = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    s = make(cfg, st, reuse=True)
    s.set_control(np.zeros((cfg.n_control_slots, n, 3, 3)))
    with packed_transfers(s) as packs:
        s.load_state(st)
        packs.p2g_stress(0)
    gap = s.trajectory.gap_t.to_numpy()[0]
    R = s.trajectory.R_prev.to_numpy().astype(np.float64)
    U, sig, Vt = np.linalg.svd(st.F)
    R_exact = U @ Vt
    to_svd = np.zeros(n, dtype=bool)
    to_svd[4:9] = True
    np.testing.assert_array_equal(gap < 0, to_svd)
    atol = 1e-12 if precision == "float64" else 1e-5
    np.testing.assert_allclose(R[~to_svd], R_exact[~to_svd], atol=atol)


def test_pack_quaternion_is_shepperds():
    """pack_quaternion gives MPMModel.quaternion_of's quaternion (the same branch, so the same
    sign) for random rotations, half turns about random axes and the axes (w = 0: every one of
    Shepperd's branches) and the identity, float64."""
    import taichi as ti
    from scipy.spatial.transform import Rotation

    from physmorph.mpm.stress_packs import ENTRIES, pack_quaternion

    s = make(shipped("float64"), generic_state(), reuse=True)
    rng = np.random.default_rng(8)
    axes = rng.normal(size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    half_turns = Rotation.from_rotvec(np.pi * np.vstack([axes, np.eye(3)])).as_matrix()
    rots = np.concatenate([Rotation.random(400, random_state=5).as_matrix(), half_turns, np.eye(3)[None]])
    assert len(rots) % PACK == 0
    r_in = ti.Matrix.field(3, 3, ti.f64, shape=len(rots))
    q_scalar = ti.Vector.field(4, ti.f64, shape=len(rots))
    q_packed = ti.Vector.field(4, ti.f64, shape=len(rots))
    r_in.from_numpy(rots)

    @ti.kernel
    def quaternions():
        for pack in range(len(rots) // PACK):
            R = [ti.Vector([r_in[pack * PACK + lane][i, j] for lane in ti.static(range(PACK))]) for i, j in ti.static(ENTRIES)]
            q = pack_quaternion(R)
            for lane in ti.static(range(PACK)):
                p = pack * PACK + lane
                q_packed[p] = ti.Vector([q[c][lane] for c in ti.static(range(4))])
                q_scalar[p] = s.model.quaternion_of(r_in[p])

    quaternions()
    np.testing.assert_allclose(q_packed.to_numpy(), q_scalar.to_numpy(), rtol=0, atol=1e-15)


def test_pack_helpers_return_variables():
    """The helpers whose rows later rows use return Taichi variables, not expression trees: a tree
    is compiled once per use, so nested helpers' trees would compile exponentially slowly
    (stress_packs.pack_values). Checked while the kernel compiles; the nested product's value
    against NumPy."""
    import taichi as ti

    from physmorph.mpm.stress_packs import pack_cofactor, pack_product, pack_symmetric

    make(shipped("float64"), generic_state(), reuse=True)  # Taichi initialised as the solver does
    rng = np.random.default_rng(9)
    mats = np.eye(3) + 0.3 * rng.normal(size=(PACK, 3, 3))
    a_in = ti.field(ti.f64, shape=(9, PACK))
    a_in.from_numpy(mats.reshape(PACK, 9).T.copy())
    out = ti.field(ti.f64, shape=(9, PACK))
    kinds = []

    def record_pack_kinds(rows: list) -> None:  # at compile time: is each row a variable?
        kinds.append([row.ptr.is_lvalue() for row in rows])

    @ti.kernel
    def nested():
        A = [ti.Vector([a_in[r, lane] for lane in ti.static(range(PACK))]) for r in ti.static(range(9))]
        for rows in ti.static([pack_product(A, A), pack_symmetric(A), pack_cofactor(A)]):
            record_pack_kinds(rows)
        B = pack_product(pack_product(A, A, transpose_a=True), pack_cofactor(A))
        for r in ti.static(range(9)):
            for lane in ti.static(range(PACK)):
                out[r, lane] = B[r][lane]

    nested()
    assert len(kinds) == 3 and all(all(k) for k in kinds)
    cof = np.linalg.det(mats)[:, None, None] * np.linalg.inv(mats).transpose(0, 2, 1)
    expected = np.transpose(mats, (0, 2, 1)) @ mats @ cof  # [PACK, 3, 3]
    np.testing.assert_allclose(out.to_numpy().T.reshape(PACK, 3, 3), expected, rtol=1e-12, atol=1e-12)
