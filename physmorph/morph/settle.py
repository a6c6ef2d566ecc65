"""The morph's last phase: the body comes to rest on its target (MorphConfig.settle).

Once a morph has arrived, its frames alternate between two shapes: the restart fires on every
other frame, and a frame started at rest and the frame that coasts after it end on different
sides of the target (docs/study/log.md). Starting every frame at rest does not end it, nor does a
smaller step: the body moves by about the same amount in every frame under the control that holds
it. What ends it is a gate on the frames themselves, a trust region over frames:

- the phase starts when the restart has fired on two frames one apart (frames k - 2 and k: the
  period-two cycle), so a body still on its way is never gated;
- from then on every frame starts at rest, and a frame whose objective (the render loss where the
  method renders, else the physics loss) ends above the last accepted frame's is rejected: the
  body, its control, mask and render gradient go back to the last accepted frame (the body holds
  still for that frame) and the next frame's step is multiplied by ``settle_backoff``.

A rejected frame is committed with the accepted frame's state and metrics, so the run file, the
tables and the video show the body at rest. Resuming needs nothing beyond the checkpoint: after a
settling frame the loop's state is the accepted one, and its metrics are the last committed frame's.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from physmorph.mpm.state import ParticleState
from physmorph.settings.render import LOSS_SCALARS

# MorphConfig.settle_objective -> the frame's scalar the gate compares (physics_then_alpha: the
# physics loss, then the alpha MSE from the hand-over: settle_gate, SettleGate.after_accepted)
OBJECTIVES = {"render": LOSS_SCALARS["total"], "alpha_mse": "alpha_mse", "physics": "physics_loss"}


# the accepted frame's per-particle arrays written by AcceptedFrame.spill (mass and volume stay:
# they are the run's constants, shared with every state)
SPILLED = ("x", "v", "F", "C", "Fp", "mask", "g_F", "g_x")


@dataclass
class AcceptedFrame:
    """What a rejected frame goes back to: the loop's state after the last accepted frame (its
    control is kept by the solver: MPMSolver.keep_control). Its arrays are held in memory or,
    after :meth:`spill`, in files read back by :meth:`arrays`."""

    state: ParticleState | None
    mask: np.ndarray | None  # [N] bool
    g_F: np.ndarray | None  # [N, 3, 3] the pending render gradient
    g_x: np.ndarray | None  # [N, 3]
    injection_scale: float
    scalars: dict  # its committed metrics
    per_view: np.ndarray  # [V] its alpha MSE per view
    objective: float
    spilled: Path | None = None  # the directory of its arrays after spill()
    rest: tuple | None = None  # (mass [N], volume [N]) of a spilled state

    def spill(self, directory: Path) -> "AcceptedFrame":
        """This frame with its arrays written to ``directory`` (replacing what an earlier accepted
        frame left there) and not held: at 471K particles the state and the gradients are 170 MB
        that would otherwise stay resident beside the next frame's."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        held = {name: getattr(self.state, name) for name in SPILLED[:5]}
        held.update(mask=self.mask, g_F=self.g_F, g_x=self.g_x)
        for name, a in held.items():
            path = directory / f"{name}.npy"
            if a is None:
                path.unlink(missing_ok=True)
            else:
                np.save(path, a, allow_pickle=False)
        return replace(self, state=None, mask=None, g_F=None, g_x=None, spilled=directory,
                       rest=(self.state.mass, self.state.volume))

    def arrays(self) -> tuple[ParticleState, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(state, mask, g_F, g_x) of the frame: new arrays where spilled, else the held ones."""
        if self.spilled is None:
            return self.state, self.mask, self.g_F, self.g_x
        got = {name: np.load(self.spilled / f"{name}.npy") if (self.spilled / f"{name}.npy").exists() else None
               for name in SPILLED}
        mass, volume = self.rest
        state = ParticleState(**{name: got[name] for name in SPILLED[:5]}, mass=mass, volume=volume)
        return state, got["mask"], got["g_F"], got["g_x"]


@dataclass
class SettleGate:
    """MorphConfig.settle's state over a run: when the phase starts and the last accepted frame."""

    onset: str  # MorphConfig.settle: "off", "after_cycle" or "after_first_rise"
    objective_key: str
    backoff: float
    start: int | None = None  # the first gated frame (None: not yet)
    last_restart: int = -1
    accepted: AcceptedFrame | None = field(default=None, repr=False)
    # MorphConfig.settle_objective physics_then_alpha: the gate judges the physics loss until an
    # accepted frame lowers it by less than this share, then the alpha MSE (handover_key)
    handover: float = 0.0
    handover_key: str | None = None
    handed_over: int | None = None  # the first frame judged by handover_key (None: not yet)

    def note_restart(self, frame: int, restart: bool) -> bool:
        """Record whether the restart fired at ``frame``; True when this starts the phase (at frame + 1)."""
        cycle = self.last_restart == frame - 2 or self.onset == "after_first_rise"
        starts = bool(self.onset != "off" and restart and self.start is None and cycle)
        if starts:
            self.start = frame + 1
        if restart:
            self.last_restart = frame
        return starts

    def at_rest_after(self, frame: int) -> bool:
        """Whether the frame after ``frame`` starts at rest (the phase has begun by then)."""
        return self.start is not None and frame + 1 >= self.start

    def gates(self, frame: int) -> bool:
        return self.start is not None and frame >= self.start and self.accepted is not None

    def rejects(self, frame: int, scalars: dict) -> bool:
        """Whether ``frame`` (its committed ``scalars``) ends above the last accepted frame's objective
        (and so is undone). Before a hand-over (physics_then_alpha) it is undone only where its alpha
        MSE rose as well: a body thrown toward its target ends the first frame it starts at rest
        above that frame's physics loss however small its step, and would be held there."""
        objective = scalars.get(self.objective_key, np.nan)
        if not (self.gates(frame) and np.isfinite(objective) and objective > self.accepted.objective):
            return False
        if self.handover_key is None or self.handed_over is not None:
            return True
        return bool(scalars.get(self.handover_key, np.nan) > self.accepted.scalars.get(self.handover_key, np.nan))

    def after_accepted(self, frame: int, objective: float) -> bool:
        """An accepted ``frame`` whose objective (the physics loss) fell by less than ``handover`` of
        the last accepted frame's (or rose) hands the gate over to ``handover_key`` from the next
        frame: the body goes on taking shape in 3D while its physics loss still falls, and is then
        held still by its images. True when this frame hands over (call before the frame is kept as
        accepted)."""
        if self.handover_key is None or self.handed_over is not None or not self.gates(frame):
            return False
        before = self.accepted.objective
        if not (np.isfinite(objective) and np.isfinite(before)) or before - objective >= self.handover * abs(before):
            return False
        self.handed_over, self.objective_key = frame + 1, self.handover_key
        return True

    def checkpoint(self) -> dict:
        return {"settle_start": -1 if self.start is None else self.start, "last_restart": self.last_restart,
                "settle_handed_over": -1 if self.handed_over is None else self.handed_over}

    def restore(self, ck: dict) -> None:
        start = int(ck.get("settle_start", -1))
        self.start = None if start < 0 else start
        self.last_restart = int(ck.get("last_restart", -1))
        handed = int(ck.get("settle_handed_over", -1))
        if handed >= 0 and self.handover_key is not None:
            self.handed_over, self.objective_key = handed, self.handover_key


def settle_gate(onset: str, objective: str, renders: bool, backoff: float,
                physics_key: str = "physics_loss", handover: float = 0.0) -> SettleGate:
    """The gate of a run (MorphConfig.settle, settle_objective, settle_backoff, settle_handover); a
    method that does not render (physics_only) is gated only on the physics objective, so it never
    reads the images. ``physics_key``: the frame's scalar the physics objective reads (against the
    target itself where the frames aim at waypoints)."""
    if objective != "physics" and not renders:
        onset = "off"
    if objective == "physics_then_alpha":
        return SettleGate(onset, physics_key, backoff, handover=handover, handover_key=OBJECTIVES["alpha_mse"])
    return SettleGate(onset, physics_key if objective == "physics" else OBJECTIVES[objective], backoff)
