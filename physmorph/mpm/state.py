"""Particle state container and NumPy helpers (elastic energy, total volume)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from physmorph.settings.mpm import MPMConfig, MPMStateError
from physmorph.base.linalg3 import det3, signed_singular_values

_SHAPES = {"x": (3,), "v": (3,), "F": (3, 3), "C": (3, 3), "Fp": (3, 3), "mass": (), "volume": ()}


@dataclass
class ParticleState:
    """Per-particle MPM state, NumPy float64 arrays."""

    x: np.ndarray  # [N, 3] positions
    v: np.ndarray  # [N, 3] velocities
    F: np.ndarray  # [N, 3, 3] deformation gradient
    C: np.ndarray  # [N, 3, 3] APIC affine velocity matrix
    Fp: np.ndarray  # [N, 3, 3] plastic deformation (constant within a frame)
    mass: np.ndarray  # [N]
    volume: np.ndarray  # [N] rest volume V0

    @property
    def n(self) -> int:
        return int(np.asarray(self.x).shape[0])

    @classmethod
    def at_rest(cls, x: np.ndarray, mass: np.ndarray, volume: np.ndarray) -> "ParticleState":
        """Undeformed, motionless state: v = 0, C = 0, F = Fp = I.  x: [N, 3], mass/volume: [N]."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        n = x.shape[0]
        eye = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        return cls(x=x.copy(), v=np.zeros((n, 3)), F=eye.copy(), C=np.zeros((n, 3, 3)), Fp=eye,
                   mass=np.asarray(mass, np.float64).reshape(n).copy(),
                   volume=np.asarray(volume, np.float64).reshape(n).copy())

    def copy(self) -> "ParticleState":
        return ParticleState(**{f.name: np.array(getattr(self, f.name), dtype=np.float64, copy=True)
                                for f in fields(self)})

    def validated(self) -> "ParticleState":
        """float64 contiguous copy with shapes checked and every value finite (else MPMStateError)."""
        n = np.asarray(self.x).reshape(-1, 3).shape[0] if np.asarray(self.x).size else 0
        if n == 0:
            raise MPMStateError("x must hold at least one particle, got an empty array")
        out = {}
        for name, tail in _SHAPES.items():
            a = np.ascontiguousarray(np.asarray(getattr(self, name), dtype=np.float64))
            if a.shape != (n, *tail):
                raise MPMStateError(f"{name} must have shape {(n, *tail)}, got {a.shape}")
            if not np.isfinite(a).all():  # one pass; the row is found only when there is one
                bad = ~np.isfinite(a.reshape(n, -1)).all(axis=1)
                raise MPMStateError(f"{name} is not finite (NaN/Inf) at particle {int(np.argmax(bad))}")
            out[name] = a
        if (out["mass"] <= 0).any():
            raise MPMStateError(f"mass must be > 0, particle {int(np.argmax(out['mass'] <= 0))} is not")
        if (out["volume"] <= 0).any():
            raise MPMStateError(f"volume must be > 0, particle {int(np.argmax(out['volume'] <= 0))} is not")
        detp = det3(out["Fp"])
        if (np.abs(detp) < 1e-12).any():
            raise MPMStateError(f"Fp is singular (det ~ 0) at particle {int(np.argmax(np.abs(detp) < 1e-12))}")
        return ParticleState(**out)


def polar_rotation(F: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N, 3, 3]
    """Rotation R of the polar decomposition F = R S with det R = +1 (inversion-safe, via SVD)."""
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    flip = det3(R) < 0
    U[flip, :, 2] *= -1.0
    return U @ Vt


def fixed_corotated_energy_density(Fe: np.ndarray,  # [N, 3, 3]
                                   mu: float, lam: float) -> np.ndarray:  # [N]
    """Psi(Fe) = mu ||Fe - R||_F^2 + Psi_vol(J) (Stomakhin et al. 2012), Psi_vol = lam/2 (J - 1)^2."""
    # ||Fe - R||_F^2 = sum_i (s_i - 1)^2 over the signed singular values (R = U V^T, both rotations)
    shear = mu * ((signed_singular_values(Fe) - 1.0) ** 2).sum(axis=1)
    return shear + volume_energy_density(det3(Fe), lam)


def volume_energy_density(J: np.ndarray, lam: float) -> np.ndarray:  # [N] -> [N]
    """Psi_vol(J) = lam/2 (J - 1)^2, the fixed corotated model's volume term."""
    return 0.5 * lam * (J - 1.0) ** 2


def elastic_energy(state: ParticleState, cfg: MPMConfig) -> float:
    """Total elastic energy sum_p V0_p Psi(F_p Fp_p^-1) (no control field), in J."""
    Fe = np.asarray(state.F) @ np.linalg.inv(np.asarray(state.Fp))
    return float((np.asarray(state.volume) * fixed_corotated_energy_density(Fe, cfg.mu, cfg.lam)).sum())


def total_volume(state: ParticleState) -> float:
    """Current total volume sum_p det(F_p) V0_p."""
    return float((det3(np.asarray(state.F)) * np.asarray(state.volume)).sum())


def kinetic_energy(state: ParticleState) -> float:
    """Translational kinetic energy sum_p m_p |v_p|^2 / 2 (the APIC affine part left out), in J."""
    v = np.asarray(state.v)
    return float(0.5 * (np.asarray(state.mass) * (v * v).sum(axis=1)).sum())
