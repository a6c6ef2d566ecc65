"""The morph loop's one-pass measures against their NumPy references."""

import numpy as np
import pytest

from physmorph.morph.frame_measures import (deformation_measures, frame_strain, frame_strain_reference, grid_mass,
                                           voxel_density)
from physmorph.base.grid import Grid, splat_mass
from physmorph.base.linalg3 import det3, singular_values, signed_singular_values
from physmorph.settings.mpm import MPMConfig
from physmorph.mpm.state import ParticleState, elastic_energy
from physmorph.morph.stability import anisotropy
from physmorph.morph.surface_mask import density_grid


def _matrices(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:  # F, Fp [n, 3, 3]
    rng = np.random.default_rng(seed)
    F = np.eye(3) + 0.4 * rng.standard_normal((n, 3, 3))
    Fp = np.eye(3) + 0.15 * rng.standard_normal((n, 3, 3))
    # the cases the closed form treats apart: F inverted, repeated and vanishing singular values,
    # a rotation, the identity
    F[0] = np.diag([1.0, 1.0, -0.5])
    F[1] = np.diag([2.0, 2.0, 2.0])
    F[2] = np.diag([1.5, 1e-9, 0.7])
    c, s = np.cos(0.7), np.sin(0.7)
    F[3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    Fp[:4] = np.eye(3)
    Fp[4] = np.diag([1.3, 0.9, 1.3])
    return F, Fp


def test_deformation_measures_match_the_numpy_forms():
    F, Fp = _matrices(500)
    dm = deformation_measures(F, Fp)
    Fe = F @ np.linalg.inv(Fp)
    s = signed_singular_values(Fe)
    assert s[0, 2] < 0  # the inverted case is in the sample
    np.testing.assert_allclose(dm.shear, ((s - 1.0) ** 2).sum(axis=1), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(dm.det_elastic, det3(Fe), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(dm.det_plastic, det3(Fp), rtol=1e-12)
    np.testing.assert_allclose(dm.anisotropy_plastic, anisotropy(Fp), rtol=1e-8)
    # and against LAPACK's SVD, not only against the same formula in NumPy
    sv = np.linalg.svd(Fp, compute_uv=False)
    np.testing.assert_allclose(dm.anisotropy_plastic, sv[:, 0] / sv[:, 2], rtol=1e-7)
    np.testing.assert_allclose(singular_values(Fe), np.linalg.svd(Fe, compute_uv=False), rtol=1e-6, atol=1e-9)
    assert dm.shear[3] == pytest.approx(0.0, abs=1e-12)  # a rotation stores no shear energy


def test_elastic_energy_from_the_measures_is_the_states():
    F, Fp = _matrices(300, seed=1)
    F[5] = np.diag([0.05, 1.0, 1.0])  # strongly compressed
    n = len(F)
    rng = np.random.default_rng(2)
    st = ParticleState(x=np.zeros((n, 3)), v=np.zeros((n, 3)), F=F, C=np.zeros((n, 3, 3)), Fp=Fp,
                       mass=np.ones(n), volume=rng.uniform(0.5, 2.0, n))
    cfg = MPMConfig()
    got = deformation_measures(F, Fp).elastic_energy(st.volume, cfg)
    assert got == pytest.approx(elastic_energy(st, cfg), rel=1e-10)


def test_grid_mass_is_the_splat():
    rng = np.random.default_rng(3)
    grid = Grid(16, lo=-2.0, hi=2.0)
    x = rng.uniform(-1.5, 1.5, (2000, 3))
    x[:10] = rng.uniform(-2.1, -1.9, (10, 3))  # stencils that leave the grid: their entries are dropped
    mass = rng.uniform(0.5, 1.5, len(x))
    got = grid_mass(x, mass, grid)
    np.testing.assert_allclose(got, splat_mass(x, mass, grid), rtol=1e-12, atol=1e-14)
    inside = slice(10, None)  # every stencil on the grid: all of the mass arrives
    assert grid_mass(x[inside], mass[inside], grid).sum() == pytest.approx(mass[inside].sum(), rel=1e-12)


def test_voxel_density_is_the_trilinear_splat():
    rng = np.random.default_rng(4)
    x = rng.uniform(-1.0, 1.0, (3000, 3))
    x[:10] = rng.uniform(-1.0, -0.95, (10, 3))  # half a voxel from the face: some corners off the grid
    w = rng.uniform(0.1, 2.0, len(x))
    got = voxel_density(x, w, 20, -1.0, 1.0)
    np.testing.assert_allclose(got, density_grid(x, w, 20, -1.0, 1.0), rtol=1e-12, atol=1e-14)
    assert got.sum() < w.sum() - 1e-6  # the dropped corners carried weight


def test_measures_name_mismatched_inputs():
    F, Fp = _matrices(8)
    with pytest.raises(ValueError, match="F has shape"):
        deformation_measures(F, Fp[:5])
    with pytest.raises(ValueError, match="masses"):
        grid_mass(np.zeros((4, 3)), np.ones(3), Grid(16))


def test_frame_strain_is_the_quantile_of_each_particles_frame_deformation():
    """|F_end F_start^-1 - I|_F per particle, one particle at a time with np.linalg.inv, then the
    quantile; a rotation-free stretch of every F by the same matrix A gives |A - I| whatever F was;
    an unchanged F gives 0."""
    rng = np.random.default_rng(3)
    F0 = np.eye(3) + 0.2 * rng.standard_normal((200, 3, 3))
    F1 = F0 + 0.05 * rng.standard_normal((200, 3, 3))
    per = [np.linalg.norm(F1[p] @ np.linalg.inv(F0[p]) - np.eye(3)) for p in range(len(F0))]
    assert frame_strain(F0, F1) == pytest.approx(np.quantile(per, 0.99), rel=1e-12)
    assert frame_strain(F0, F1, quantile=0.5) == pytest.approx(np.median(per), rel=1e-12)
    A = np.diag([1.1, 0.95, 1.0])
    assert frame_strain(F0, A @ F0) == pytest.approx(np.linalg.norm(A - np.eye(3)), rel=1e-12)
    assert frame_strain(F0, F0) < 1e-12
    with pytest.raises(ValueError, match="must match"):
        frame_strain(F0, F1[:10])
    # the Taichi pass against the NumPy form, and a singular F_start named as inverse3 names it
    for q in (0.99, 0.5, 1.0):
        assert frame_strain(F0, F1, quantile=q) == pytest.approx(frame_strain_reference(F0, F1, quantile=q), rel=1e-12)
    F0[7] = 0.0
    with pytest.raises(np.linalg.LinAlgError, match="matrix 7 of 200"):
        frame_strain(F0, F1)


@pytest.mark.parametrize("name, particle, value, message", [
    ("x", 4, np.nan, "x became non-finite (particle 4)"),
    ("F", 2, -np.inf, "F became non-finite (particle 2)"),
    ("F", 5, -50.5, "|F| = 50.5 exceeds 50 (particle 5)"),
    ("Fp", 1, 10.25, "|Fp| = 10.2 exceeds 10 (particle 1)"),
])
def test_check_state_names_the_quantity_and_particle(name, particle, value, message):
    """A NaN, an infinity or an entry beyond its bound (either sign) stops the frame naming the
    quantity and the first such particle; entries at the bound pass."""
    from physmorph.morph.stability import MorphDivergenceError, check_state
    from physmorph.mpm.state import ParticleState
    from physmorph.settings.morph import MorphConfig

    cfg = MorphConfig()
    n = 8
    st = ParticleState(x=np.zeros((n, 3)), v=np.zeros((n, 3)), F=np.tile(np.eye(3), (n, 1, 1)), C=np.zeros((n, 3, 3)),
                       Fp=np.tile(np.eye(3), (n, 1, 1)), mass=np.ones(n), volume=np.ones(n))
    st.F[3, 0, 1] = -cfg.max_F_norm
    st.Fp[6, 2, 2] = cfg.max_Fp_norm
    check_state(st, 9, cfg)  # at the bounds: passes
    getattr(st, name)[particle].flat[1] = value
    with pytest.raises(MorphDivergenceError) as stop:
        check_state(st, 9, cfg)
    assert str(stop.value) == f"frame 9: {message}"
    assert (stop.value.quantity, stop.value.particle, stop.value.frame) == (name, particle, 9)
