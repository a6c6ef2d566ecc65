"""Divergence checks and stability warnings of the morph loop (docs/study/log.md: what a run
that leaves the stable region looks like)."""

from __future__ import annotations

import numpy as np

from physmorph.base.linalg3 import det3, singular_values

from physmorph.settings.mpm import MPMDivergenceError
from physmorph.mpm.state import ParticleState
from physmorph.settings.plasticity import PlasticityConfig


class MorphDivergenceError(RuntimeError):
    """A run diverged at ``frame``: ``quantity`` (x, F, Fp, or what the solver names, e.g. the dFc
    gradient) became non-finite or passed its bound, at ``particle`` where one is known. The
    message says the same in words; code reads the attributes. Raised from another divergence
    (``raise MorphDivergenceError(...) from exc``: a MorphDivergenceError, or the solver's
    MPMDivergenceError), it takes what it is not given from that one."""

    def __init__(self, message: str, frame: int | None = None, quantity: str | None = None,
                 particle: int | None = None):
        super().__init__(message)
        self._frame, self._quantity, self._particle = frame, quantity, particle

    def _given_or_cause(self, name: str):
        own = getattr(self, f"_{name}")
        if own is None and isinstance(self.__cause__, (MorphDivergenceError, MPMDivergenceError)):
            return getattr(self.__cause__, name, None)
        return own

    @property
    def frame(self) -> int | None:
        return self._given_or_cause("frame")

    @property
    def quantity(self) -> str | None:
        return self._given_or_cause("quantity")

    @property
    def particle(self) -> int | None:
        return self._given_or_cause("particle")


def anisotropy(M: np.ndarray) -> np.ndarray:  # [N, 3, 3] -> [N]
    """Largest over smallest singular value of each M."""
    s = singular_values(M)
    return s[:, 0] / np.maximum(s[:, 2], 1e-12)


def check_state(st: ParticleState, frame: int, cfg) -> None:
    """Raise MorphDivergenceError naming frame, quantity and particle when x, F or Fp is non-finite
    or beyond its bound (cfg: physmorph.settings.morph.MorphConfig, its max_F_norm and max_Fp_norm)."""
    for name, arr, bound in (("x", st.x, 1e6), ("F", st.F, cfg.max_F_norm), ("Fp", st.Fp, cfg.max_Fp_norm)):
        # two reductions, no temporaries, decide the usual case (NaN propagates through both); the
        # particle is found only where something is wrong (0.3 s a paper-scale frame the other way)
        hi, lo = float(arr.max()), float(arr.min())
        if np.isfinite(hi) and np.isfinite(lo) and max(hi, -lo) <= bound:
            continue
        if not np.isfinite(arr).all():
            p = int(np.argwhere(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1))[0, 0])
            raise MorphDivergenceError(f"frame {frame}: {name} became non-finite (particle {p})", frame=int(frame),
                                       quantity=name, particle=p)
        big = np.abs(arr).reshape(len(arr), -1).max(axis=1)
        if big.max() > bound:
            p = int(np.argmax(big))
            raise MorphDivergenceError(f"frame {frame}: |{name}| = {big[p]:.3g} exceeds {bound:g} (particle {p})",
                                       frame=int(frame), quantity=name, particle=p)


class StabilityMonitor:
    """Warns (once per streak) when a run leaves the stable region: many particles' Fp pinned at
    a clamp bound of the isochoric projection (det bounds or anisotropy) for ``pinned_frames``
    frames in a row, or alpha MSE rising for ``rising_frames`` frames in a row."""

    def __init__(self, plasticity: PlasticityConfig, log, pinned_share: float = 0.01, pinned_frames: int = 5,
                 rising_frames: int = 8):
        self.cfg, self.log = plasticity, log
        self.pinned_share, self.pinned_frames, self.rising_frames = pinned_share, pinned_frames, rising_frames
        self.pinned_streak = self.rising_streak = 0
        self.last_alpha = None

    def update(self, frame: int, Fp: np.ndarray, alpha_mse: float,  # Fp [N, 3, 3]
               det: np.ndarray | None = None,  # [N] det Fp, where the caller has it
               fp_anisotropy: np.ndarray | None = None) -> list[str]:  # [N] anisotropy(Fp), the same
        out = []
        lo, hi = self.cfg.det_bounds
        det = det3(Fp) if det is None else det
        aniso = anisotropy(Fp) if fp_anisotropy is None else fp_anisotropy
        tol = 1e-3
        pinned = (det <= lo * (1 + tol)) | (det >= hi * (1 - tol)) | (aniso >= self.cfg.max_anisotropy * (1 - tol))
        share = float(pinned.mean())
        self.pinned_streak = self.pinned_streak + 1 if share >= self.pinned_share else 0
        if self.pinned_streak == self.pinned_frames:
            out.append(f"frame {frame}: {100 * share:.1f} % of particles have Fp pinned at a clamp bound "
                       f"(det in [{lo:g}, {hi:g}], anisotropy <= {self.cfg.max_anisotropy:g}) for "
                       f"{self.pinned_frames} frames; plasticity.eta may be too large")
        rising = self.last_alpha is not None and alpha_mse > self.last_alpha
        self.last_alpha = alpha_mse
        self.rising_streak = self.rising_streak + 1 if rising else 0
        if self.rising_streak == self.rising_frames:
            out.append(f"frame {frame}: alpha MSE rose for {self.rising_frames} frames in a row (now {alpha_mse:.4g})")
        for msg in out:
            self.log(msg)
        return out

    def state(self) -> dict:
        """The streaks, for a checkpoint (a resumed run warns as the uninterrupted one would)."""
        return {"monitor_pinned_streak": self.pinned_streak, "monitor_rising_streak": self.rising_streak,
                "monitor_last_alpha": np.nan if self.last_alpha is None else float(self.last_alpha)}

    def restore(self, state: dict) -> None:
        self.pinned_streak = int(state["monitor_pinned_streak"])
        self.rising_streak = int(state["monitor_rising_streak"])
        last = float(state["monitor_last_alpha"])
        self.last_alpha = None if np.isnan(last) else last
