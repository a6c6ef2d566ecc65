"""The Chamfer-guided plasticity's settings (physmorph.plasticity.step, paper section 3.4)."""

from __future__ import annotations

import math
from typing import Annotated, ClassVar, Literal

from physmorph.settings.base import Bool, Float, Int, Refused, setting, settings_dataclass


@settings_dataclass
class PlasticityConfig:
    """Chamfer-guided plasticity: each particle's rest state pulled toward its destination."""

    # defaults changed since runs were first made (physmorph.settings.params.without_defaults): always in a
    # run's params, so runs made with the old default rerun
    ALWAYS_IN_PARAMS: ClassVar[frozenset[str]] = frozenset({"absorb_control", "absorb_target", "absorb_start_frame",
                                                             "eta", "correspondence", "start_frame", "volume",
                                                             "transport_projection"})
    # the paper's plasticity (section 3.4; eta and start_frame at values of their own, docs/method.md)
    # base rate per frame (the paper: 0.2; config/paper_method.yaml uses it; 0.02 until 2026-11-24,
    # with the nearest-point correspondence, then 0.1; see config/config.yaml)
    eta: Annotated[Float, setting("plasticity rate (the paper: 0.2)", ge=0)] = 0.05
    k_neighbors: Annotated[Int, setting("neighbours of the displacement smoothing", ge=1)] = 64
    smooth_iters: Annotated[Int, setting("passes of neighbour averaging of the displacements", ge=0)] = 3
    damping: Annotated[Float, setting("damping d_p of the Fp update", ge=0, le=1)] = 0.05
    # k0 (the paper: 20 of 90 frames; 10, then 5, until 2026-11-24): transport destinations need
    # no warm-up, and starting early halves the particles torn off thin features (docs/study/log.md findings 104-106)
    start_frame: Annotated[Int, setting(
        "k0: first frame with plasticity; experiments set it with `plasticity_start`", "frame", ge=0)] = 2
    det_bounds: Annotated[tuple[Float, Float], setting("bounds [lo, hi] on det Fp", "",
                                                       "0 < lo <= 1 <= hi")] = (0.5, 2.0)
    max_anisotropy: Annotated[Float, setting("bound on the ratio of Fp's largest to smallest stretch", ge=1)] = 4.0

    # the named departures from the paper (docs/method.md)
    # the particles a neighbourhood is drawn from: at most neighbour_ppc per cell per axis (one per
    # sub-cell of dx / neighbour_ppc, the one nearest its centre at rest; neighbour_pool), so the k
    # neighbours span the same cells at every sampling density: k = 64 from the default sampling
    # (PPC 2/1, which it keeps whole) is about 8 cells. 0: every particle (until 2026-11-26; at
    # the paper's PPC 5 a neighbourhood was half a cell)
    neighbour_ppc: Annotated[Int, setting(
        "the neighbours are drawn from at most this many particles per cell per axis, so k_neighbors spans the "
        "same cells at every sampling density (0 = every particle)", ge=0)] = 2
    # "transport" the default since 2026-11-24; its plan is computed once per run (physmorph.plasticity.transport)
    correspondence: Annotated[Literal["nearest", "transport"], setting(
        "where each particle is pulled: nearest, the nearest target surface point (the paper); transport, its "
        "optimal-transport destination in the target's mass")] = "transport"
    # 1 cell is 1 domain unit at the default grid and 0.5 at mid's and the paper's
    transport_blur: Annotated[Float, setting(
        "blur of the transport plan (correspondence: transport), the entropic scale of its last iterations",
        "grid cells", gt=0)] = 1.0
    # how a particle's destination is read off the plan (physmorph.plasticity.transport,
    # destinations_in_grid_mass): its row's mean rounds a thin target's parts off on a coarse grid
    # (docs/study/log.md part 66)
    transport_projection: Annotated[Literal["barycentric", "sampled"], setting(
        "how a particle's destination is read off the transport plan: barycentric, the mean of its source "
        "node's row; sampled, a target node drawn from that row (seed 0), keeping its offset from the node")] = "sampled"  # history: docs/study/CHANGELOG.md
    # the default, the shape at the last update only, commits the final shape to the rest state
    # without changing the run, so it persists with the control off (docs/study/log.md finding 49)
    absorb_control: Annotated[Bool, setting(
        "commit the achieved shape (or control) to the rest state Fp at the updates absorb_start_frame "
        "picks")] = True
    # "control": a driving stress, which a released body keeps following (the whole update is then
    # re-based); "shape": only that is re-based, the Chamfer step stays a stress unless
    # continuous_stress (docs/study/log.md findings 46-47)
    absorb_target: Annotated[Literal["control", "shape"], setting(
        "what is committed: shape (the stretch of F, stress-free afterwards) or control (its elastic "
        "deformation)")] = "shape"
    # before it the update is the plain one (re-based only with continuous_stress); docs/study/log.md part 9
    absorb_start_frame: Annotated[Int | None, setting(
        "updates that commit: -n the last n, n from frame n on, null every update", "frame", "!= 0")] = -1

    # a target of another volume than its source (not in the paper): the rest state's volume moved
    # toward the target's, so the elastic stress itself takes the body there (rest_volume_ratio);
    # "target" the default since 2026-12-01 (docs/study/log.md finding 242; "keep" before)
    volume: Annotated[Literal["keep", "target"], setting(
        "the rest volume: keep, the source's (MPM keeps volume); target, moved toward the target's volume by at "
        "most volume_rate a frame from plasticity.start_frame on")] = "target"
    volume_rate: Annotated[Float, setting(
        "with volume target: the most the rest volume changes in a frame, as a share of it", gt=0, le=1)] = 0.05

    # the paper's continuous stress as its text describes it (config/paper_method.yaml)
    continuous_stress: Annotated[Bool, setting(
        "re-base the control so an Fp update leaves the elastic Fe unchanged")] = False

    def absorbs_at(self, frame: int, frames: int) -> bool:
        """Whether the update at ``frame`` (1..``frames``) absorbs: absorb_control on and frame past
        absorb_start_frame (counted from the end when negative)."""
        if not self.absorb_control:
            return False
        if self.absorb_start_frame is None:
            return True
        start = self.absorb_start_frame if self.absorb_start_frame >= 0 else frames + 1 + self.absorb_start_frame
        return frame >= start

    def rest_volume_ratio(self, frame: int, target_ratio: float) -> float:
        """The rest volume over the source's after frame ``frame``'s update: 1 with volume keep or
        before start_frame; with volume target, from start_frame on each update moves it by the
        factor 1 + volume_rate toward ``target_ratio`` (the target's volume over the source's), and
        it stays there once reached. A function of the frame alone, so a resumed run follows it."""
        if self.volume == "keep" or frame < self.start_frame or not target_ratio > 0:
            return 1.0
        wanted = math.log(target_ratio)
        reach = (frame - self.start_frame + 1) * math.log1p(self.volume_rate)
        return math.exp(math.copysign(min(abs(wanted), reach), wanted))

    def __post_init__(self) -> None:
        """The checks across a field's parts and its excluded value (each field's range is its declaration's)."""
        lo, hi = self.det_bounds
        if not 0 < lo <= 1 <= hi:
            raise Refused("det_bounds", f"plasticity.det_bounds must satisfy 0 < lo <= 1 <= hi, got {self.det_bounds}")
        if self.absorb_start_frame == 0:
            raise Refused("absorb_start_frame", "plasticity.absorb_start_frame must be a frame >= 1, a count from "
                                                "the end < 0, or null (every update)")
