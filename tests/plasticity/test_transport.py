"""Tests of the optimal-transport correspondences (physmorph.plasticity.transport) and their use by the
plasticity step (plasticity.correspondence = "transport")."""

from __future__ import annotations

import numpy as np
import pytest

from physmorph.base.grid import Grid, splat_mass
from physmorph.settings.plasticity import PlasticityConfig
from physmorph.plasticity.step import chamfer_plasticity_step, displacement_jacobian, nearest_neighbours
from physmorph.plasticity.transport import destinations_in_grid_mass, transport_destinations


def test_destinations_of_a_translated_cloud_are_the_translation():
    """For the squared cost the optimal map between a cloud and its translate is the translation
    (whatever order the target samples come in): the barycentric projection recovers it."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(60, 3))
    shift = np.array([2.0, -1.0, 0.5])
    y = (x + shift)[rng.permutation(60)]
    T = transport_destinations(x, np.ones(60), y, np.ones(60), blur=0.05)
    np.testing.assert_allclose(T, x + shift, atol=1e-3)


def test_destinations_share_the_source_mass_as_the_target_holds_it():
    """Two target points holding 3/4 and 1/4 of the mass, a source blob nearer the small one: the
    nearest-point map sends everything to the near one; the transport plan moves 3/4 of the mass
    to the far one, so the mass-weighted mean of the destinations is the target's mean."""
    rng = np.random.default_rng(1)
    x = rng.normal(scale=0.5, size=(200, 3))
    a = rng.uniform(0.5, 1.5, size=200)
    y = np.array([[6.0, 0.0, 0.0], [-3.0, 0.0, 0.0]])
    b = np.array([3.0, 1.0])
    T = transport_destinations(x, a, y, b, blur=0.5)
    assert (np.abs(T[:, 1:]) < 0.1).all()  # on the segment between the two points
    far_share = (a * (T[:, 0] - y[1, 0]) / (y[0, 0] - y[1, 0])).sum() / a.sum()
    assert far_share == pytest.approx(0.75, abs=0.015)


def test_destinations_in_grid_mass_fill_the_target_and_refuse_bad_input():
    grid = Grid(16)  # dx = 2
    rng = np.random.default_rng(2)
    src = rng.uniform(-3, 3, size=(300, 3)) + [-4.0, 0.0, 0.0]
    tgt = rng.uniform(-2, 2, size=(300, 3)) * [2.0, 1.0, 1.0] + [5.0, 0.0, 0.0]
    gm = splat_mass(tgt, np.ones(300), grid)
    T = destinations_in_grid_mass(src, np.ones(300), gm, grid)
    # every destination lies inside the target's hull of non-empty nodes, and their spread
    # follows the target's (twice as long along x)
    nodes = grid.lo + grid.dx * np.argwhere(gm > 0)
    assert (T >= nodes.min(0) - 1e-9).all() and (T <= nodes.max(0) + 1e-9).all()
    assert T[:, 0].std() > 1.5 * T[:, 1].std()
    with pytest.raises(ValueError, match="grid mass has shape"):
        destinations_in_grid_mass(src, np.ones(300), gm[:8], grid)
    with pytest.raises(ValueError, match="positive source masses"):
        transport_destinations(src, np.zeros(300), nodes, np.ones(len(nodes)), blur=1.0)


def test_plasticity_step_uses_the_destinations_given():
    """With destinations x + A x the step's displacement is that affine field (before smoothing,
    which keeps an affine field), so every particle's update is the one eq. 4 gives that field
    (the reference Jacobian, A M_i); the nearest-surface displacement would not be affine."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-3, 3, size=(400, 3))
    A = np.array([[0.2, 0.05, 0.0], [0.05, -0.1, 0.0], [0.0, 0.0, 0.1]])
    cfg = PlasticityConfig(eta=0.5, k_neighbors=16, smooth_iters=0, damping=0.0,
                           det_bounds=(0.1, 10.0), max_anisotropy=100.0, correspondence="transport")
    Fp = np.tile(np.eye(3), (len(x), 1, 1))
    res = chamfer_plasticity_step(x, Fp, np.zeros((1, 3)), cfg, destination=x + x @ A.T)
    np.testing.assert_allclose(res.displacement, x @ A.T, atol=1e-12)
    J = displacement_jacobian(x, x @ A.T, nearest_neighbours(x, np.arange(len(x)), 16)[0])
    want = np.eye(3) + res.eta[:, None, None] * 0.5 * (J + J.transpose(0, 2, 1))
    np.testing.assert_allclose(res.Fp, want, atol=1e-9)
    with pytest.raises(ValueError, match="correspondence"):
        PlasticityConfig(correspondence="closest")


def test_softmin_equals_the_dense_formula():
    """The blocked expansion -eps logsumexp_k(h_k + p_k.q_l / eps) + |q_l|^2 / 2 against the direct
    -eps logsumexp_k(log w_k + (potential_k - |p_k - q_l|^2 / 2) / eps), in float64, blocks smaller
    than the problem."""
    import torch

    from physmorph.plasticity import transport

    rng = np.random.default_rng(4)
    P = torch.from_numpy(rng.normal(size=(70, 3)))
    Q = torch.from_numpy(rng.normal(size=(50, 3)) + 0.5)
    log_w = torch.from_numpy(np.log(rng.uniform(0.1, 1.0, size=70)))
    pot = torch.from_numpy(rng.normal(scale=0.3, size=70))
    for eps in (0.005, 0.05, 1.0, 30.0):  # at 0.005 most exponents are under EXP_FLOOR
        C = 0.5 * ((Q[:, None, :] - P[None, :, :]) ** 2).sum(-1)
        want = -eps * torch.logsumexp(log_w[None, :] + (pot[None, :] - C) / eps, dim=1)
        old = transport.BLOCK_ENTRIES
        try:
            transport.BLOCK_ENTRIES = 7 * 70  # 7 rows per block: 8 blocks, the last one short
            got = transport._softmin(P, log_w, pot, Q, eps)
        finally:
            transport.BLOCK_ENTRIES = old
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-12, atol=1e-12 * eps)


def test_floored_exponents_give_torchs_logsumexp_and_softmax_in_float32():
    """The kernel's rows at the finest blur: entries spread over thousands below their row's
    maximum, most of them under EXP_FLOOR. The floored exp gives torch.logsumexp and torch.softmax
    to float32 rounding."""
    import torch

    from physmorph.plasticity import transport

    g = torch.Generator().manual_seed(0)
    B = torch.rand(40, 3000, generator=g) * 3000.0 - 2500.0
    B[:, 7] = B.amax(1) + 50.0  # one dominant entry a row
    B[::2, 11] = B[::2, 7] - 3.0  # and a second close to it in every other row
    assert (B - B.amax(1, keepdim=True) < transport.EXP_FLOOR).float().mean() > 0.9
    shifted, top = transport._exp_shifted(B.clone())
    np.testing.assert_allclose((shifted.sum(1).log() + top).numpy(), torch.logsumexp(B, 1).numpy(), rtol=1e-7)
    np.testing.assert_allclose((shifted / shifted.sum(1, keepdim=True)).numpy(), torch.softmax(B, 1).numpy(),
                               rtol=1e-6, atol=1e-30)


def test_the_plan_of_the_same_grid_masses_is_computed_once(monkeypatch):
    """destinations_in_grid_mass keeps the node plan of the last inputs: the same particles and
    target give the same destinations without a new plan; another target makes a new one."""
    from physmorph.plasticity import transport

    grid = Grid(16)
    rng = np.random.default_rng(6)
    src = rng.uniform(-3, 3, size=(200, 3))
    gm = splat_mass(rng.uniform(-2, 2, size=(200, 3)) + [4.0, 0.0, 0.0], np.ones(200), grid)
    calls = []
    real = transport.transport_destinations
    monkeypatch.setattr(transport, "transport_destinations", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(transport, "_PLANS", {})
    first = destinations_in_grid_mass(src, np.ones(200), gm, grid)
    again = destinations_in_grid_mass(src.copy(), np.ones(200), gm.copy(), grid)
    assert len(calls) == 1
    np.testing.assert_array_equal(again, first)
    other = destinations_in_grid_mass(src, np.ones(200), np.roll(gm, 1, axis=1), grid)  # the target moved a cell
    assert len(calls) == 2 and np.abs(other - first).max() > 0.5
    np.testing.assert_allclose(destinations_in_grid_mass(src + 1e-3, np.ones(200), gm, grid), first + 1e-3, atol=0.05)
    assert len(calls) == 3  # moved particles: a new plan


def test_coarse_to_fine_plan_equals_the_single_scale_plan(monkeypatch):
    """Grid-node clouds of two different blobs, 2,018 and 2,687 nodes: the iterations run on coarse
    cell centroids while the blur is large (checked: Sinkhorn sees fewer points), and the
    destinations equal the single-scale plan's (coarse_switch=0) to 2 % of the blur."""
    from physmorph.plasticity import transport

    rng = np.random.default_rng(5)
    grid = Grid(32)
    src = splat_mass(rng.normal(scale=[3.0, 1.5, 1.5], size=(3000, 3)) + [-6.0, 0.0, 0.0], np.ones(3000), grid)
    tgt = splat_mass(rng.normal(scale=[1.5, 3.0, 2.25], size=(3000, 3)) + [5.0, 2.0, 0.0], np.ones(3000), grid)
    x, a = grid.lo + grid.dx * np.argwhere(src > 0), src[src > 0]
    y, b = grid.lo + grid.dx * np.argwhere(tgt > 0), tgt[tgt > 0]
    assert len(x) > 2000 and len(y) > 2000
    sizes = []
    real = transport.sinkhorn_potentials

    def counting(X, Y, *args, **kwargs):
        sizes.append((len(X), len(Y), len(args[2])))
        return real(X, Y, *args, **kwargs)

    monkeypatch.setattr(transport, "sinkhorn_potentials", counting)
    fine = transport_destinations(x, a, y, b, blur=grid.dx, coarse_switch=0)
    assert sizes == [(len(x), len(y), 50)]
    sizes.clear()
    multi = transport_destinations(x, a, y, b, blur=grid.dx)
    assert len(sizes) >= 3 and sizes[-1][:2] == (len(x), len(y)) and sum(s[2] for s in sizes) == 50
    assert all(n < len(x) / 4 and m < len(y) / 4 for n, m, _ in sizes[:-2])  # 2 and more levels up
    err = np.linalg.norm(multi - fine, axis=1) / grid.dx
    print(f"levels {sizes}; |T_multi - T_single| / dx: mean {err.mean():.4f} max {err.max():.4f}")
    assert err.max() < 0.02
    assert np.linalg.norm(fine - x, axis=1).mean() > 5 * grid.dx  # the plan moves mass far


def test_the_plans_blur_is_counted_in_grid_cells(monkeypatch):
    """plasticity.transport_blur reaches the plan as blur_cells x dx, each blur keeps its own plan,
    and a wider blur draws the destinations toward the target's mean (the entropic plan's
    barycentric projection averages over more of the target)."""
    from physmorph.plasticity import transport

    grid = Grid(16)  # dx = 2
    rng = np.random.default_rng(7)
    src = rng.uniform(-3, 3, size=(300, 3)) + [-4.0, 0.0, 0.0]
    gm = splat_mass(rng.uniform(-2, 2, size=(300, 3)) * [3.0, 1.0, 1.0] + [5.0, 0.0, 0.0], np.ones(300), grid)
    blurs = []
    real = transport.transport_destinations
    monkeypatch.setattr(transport, "transport_destinations", lambda *a, **k: blurs.append(k["blur"]) or real(*a, **k))
    monkeypatch.setattr(transport, "_PLANS", {})
    sharp = destinations_in_grid_mass(src, np.ones(300), gm, grid)
    wide = destinations_in_grid_mass(src, np.ones(300), gm, grid, blur_cells=4.0)
    assert blurs == [2.0, 8.0]
    np.testing.assert_array_equal(destinations_in_grid_mass(src, np.ones(300), gm, grid, blur_cells=1.0), sharp)
    assert len(blurs) == 2  # the first plan was kept, not overwritten by the second
    assert wide[:, 0].std() < 0.8 * sharp[:, 0].std()
    with pytest.raises(ValueError, match="transport_blur must be > 0"):
        PlasticityConfig(transport_blur=0.0)


def test_sampled_destinations_give_each_target_node_its_share(monkeypatch):
    """projection "sampled" (PlasticityConfig.transport_projection): each particle goes to a target
    node with mass drawn from its nearest source node's plan row, plus its offset from that node;
    the same on every call; and the mass the target's nodes receive is the target's, where the
    barycentric projection sends the rows that split between two thin slabs to the gap between them."""
    from physmorph.plasticity import transport

    grid = Grid(16)  # dx = 2
    rng = np.random.default_rng(11)
    n = 4000
    src = rng.uniform(-4, 4, size=(n, 3)) + [-6.0, 0.0, 0.0]
    mass = np.ones(n)
    slabs = rng.uniform(-1, 1, size=(n, 3)) * [0.6, 6.0, 6.0]
    slabs[: n // 2, 0] += 9.0  # two thin slabs, 6 units apart, side by side
    slabs[n // 2:, 0] += 3.0
    gm = splat_mass(slabs, mass, grid)
    monkeypatch.setattr(transport, "_PLANS", {})
    drawn = destinations_in_grid_mass(src, mass, gm, grid, projection="sampled")
    monkeypatch.setattr(transport, "_PLANS", {})
    np.testing.assert_array_equal(destinations_in_grid_mass(src, mass, gm, grid, projection="sampled"), drawn)
    nearest = np.rint((src - grid.lo) / grid.dx)
    node = (drawn - (src - (grid.lo + grid.dx * nearest)) - grid.lo) / grid.dx
    np.testing.assert_allclose(node, np.rint(node), atol=1e-9)  # a node, plus the particle's offset
    node = np.rint(node).astype(int)
    assert (gm[node[:, 0], node[:, 1], node[:, 2]] > 0).all()  # a target node with mass

    def received(d):  # each target node's share of the mass sent to it (by nearest node)
        idx = np.rint((d - grid.lo) / grid.dx).astype(int)
        got = np.zeros_like(gm)
        np.add.at(got, tuple(idx.T), mass)
        return got / got.sum()

    bary = destinations_in_grid_mass(src, mass, gm, grid)
    want = gm / gm.sum()
    err_drawn = 0.5 * np.abs(received(drawn) - want).sum()
    err_bary = 0.5 * np.abs(received(bary) - want).sum()
    print(f"total variation from the target's mass: sampled {err_drawn:.3f}, barycentric {err_bary:.3f}")
    assert err_drawn < 0.15 and err_bary > 2 * err_drawn
    with pytest.raises(ValueError, match="projection must be"):
        destinations_in_grid_mass(src, mass, gm, grid, projection="nearest")


def test_transport_draws_take_each_rows_count():
    """transport_draws: draws_i target points for source point i, in order, rows with none skipped;
    a source point next to one of two targets draws (almost) only that one at a small blur."""
    from physmorph.plasticity.transport import transport_draws

    x = np.array([[-5.0, 0, 0], [5.0, 0, 0], [0.0, 0, 0]])
    y = np.array([[-5.0, 0, 0], [5.0, 0, 0]])
    out = transport_draws(x, np.array([1.0, 1.0, 1e-9]), y, np.array([1.0, 1.0]), blur=0.5,
                          draws=np.array([7, 3, 0]))
    assert out.shape == (10, 3)
    np.testing.assert_array_equal(out[:7], np.repeat(y[:1], 7, axis=0))
    np.testing.assert_array_equal(out[7:], np.repeat(y[1:], 3, axis=0))
    with pytest.raises(ValueError, match="draw counts"):
        transport_draws(x, np.ones(3), y, np.ones(2), blur=0.5, draws=np.array([1, 2]))
