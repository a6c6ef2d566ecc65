"""What the solver's stored results belong to: one explicit record instead of flags spread over
the solver.

The solver keeps one trajectory (the last forward's per-substep state), the loss of it, and the
gradients of the last backward. Anything that changes the loaded state, dFc or the loss (a new
state, target, control, anchors, overfill weight, optimiser state) makes the stored trajectory
stale: ``rollout()`` then runs a forward again, ``backward()`` refuses. The injection
calibration's two gradients and their combination belong to one rollout, named by its count.
"""

from dataclasses import dataclass


@dataclass
class Currency:
    loaded: bool = False  # a frame's initial state is loaded (load_state)
    has_target: bool = False  # a target grid mass is set (set_target_grid_mass)
    rollout: int = 0  # forwards run so far: the stored trajectory is rollout number `rollout`
    trajectory_current: bool = False  # the stored trajectory is that of the current state, dFc and loss
    calibrated_for: int = -1  # the rollout whose calibration gradients the solver holds (-1: none)
    combined_for: int = -1  # the rollout whose combined gradient is in place (-1: none)

    def clear(self) -> None:
        """Back to a freshly built solver's record (in place: the solver's parts share it)."""
        for name, value in vars(Currency()).items():
            setattr(self, name, value)

    def stale(self) -> None:
        """The state, dFc or loss changed: the stored trajectory no longer belongs to them."""
        self.trajectory_current = False

    def new_rollout(self) -> None:
        """A forward begins: until it completes, no trajectory is current."""
        self.rollout += 1
        self.trajectory_current = False

    def gradients_overwritten(self) -> None:
        """A backward overwrites the control gradient: the calibration's pair is gone."""
        self.calibrated_for = self.combined_for = -1
