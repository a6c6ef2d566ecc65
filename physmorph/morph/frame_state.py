"""The morph loop's state between frames: what frame k hands frame k + 1, and the checkpoint's
only format (physmorph.records.runfile CHECKPOINT_FORMAT; the solver's control and optimiser state, the
stability monitor's and the settle gate's are written beside it by their owners)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physmorph.mpm.state import ParticleState

STATE_KEYS = ("x", "v", "F", "C", "Fp", "mass", "volume")


def asdict_state(st: ParticleState) -> dict:
    return {k: np.asarray(getattr(st, k)) for k in STATE_KEYS}


@dataclass
class FrameState:
    state: ParticleState  # the particles at the frame's end (the next frame's start)
    mask: np.ndarray  # [N] bool: the surface mask the render draws
    g_F: np.ndarray  # [N, 3, 3] the render's gradient on F, injected into the next frame's physics
    g_x: np.ndarray  # [N, 3] the render's gradient on x (position_inject)
    injection_scale: float  # the calibrated injection scale (NaN: not yet calibrated)
    next_step: float  # the optimiser's step the next frame starts from (StepSchedule)
    overfill_weight: float  # the packing term's weight in use (OverfillOnset)

    @classmethod
    def at_start(cls, st: ParticleState, mask: np.ndarray, step: float, overfill_weight: float) -> "FrameState":
        n = st.n
        return cls(st, mask, np.zeros((n, 3, 3)), np.zeros((n, 3)), float("nan"), step, overfill_weight)

    def checkpoint(self, *owners: dict) -> dict:
        """The checkpoint's content: this state, then each owner's own (solver, monitor, gate)."""
        out = {**asdict_state(self.state), "mask": self.mask, "g_F": self.g_F, "g_x": self.g_x,
               "injection_scale": self.injection_scale, "next_step": self.next_step,
               "overfill_weight": self.overfill_weight}
        for own in owners:
            out.update(own)
        return out

    @classmethod
    def from_checkpoint(cls, ck: dict) -> "FrameState":
        st = ParticleState(**{k: ck[k] for k in STATE_KEYS})
        return cls(st, ck["mask"].astype(bool), ck["g_F"], ck["g_x"], float(ck["injection_scale"]),
                   float(ck["next_step"]), float(ck["overfill_weight"]))
