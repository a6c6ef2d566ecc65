"""The points of the speed/accuracy study, as the config's ``tradeoff`` section asks for them.

A point is the base experiment with one knob changed (``TRADEOFF_KNOBS``): a resolution
(``grid_res``, ``ppc_surface``, ``ppc_interior``, ``image`` as [width, height], ``cameras``), the
optimiser's work (``grad_iters``, ``learning_rate``, ``frames``), the arithmetic (``precision``) or
the machine (``threads``). Its name is ``{knob}-{value}`` (``base`` for the unchanged base). The
config checks the points when it is built (physmorph.settings.workflow), the workflow makes one run per point
and the study (physmorph.studies.tradeoff) judges them; so the points live below all three.
"""

from __future__ import annotations

from dataclasses import dataclass

from physmorph.settings.errors import ConfigError

TRADEOFF_KNOBS = ("grid_res", "ppc_surface", "ppc_interior", "image", "cameras", "grad_iters", "learning_rate",
                  "frames", "precision", "threads")
PRECISIONS = ("float32", "float64")


@dataclass(frozen=True)
class TradeoffPoint:
    name: str
    knob: str  # "" for the base point
    value: str
    grid_res: int
    ppc_surface: int
    ppc_interior: int
    width: int
    height: int
    cameras: int
    grad_iters: int
    learning_rate: float
    frames: int
    precision: str
    threads: int

    @property
    def res_tag(self) -> str:
        return f"{self.grid_res}x{self.ppc_surface}x{self.ppc_interior}"

    @property
    def image_tag(self) -> str:
        return f"{self.width}x{self.height}"


def _knob_value(knob: str, v):
    """(the point's field changes, its label) of one knob value; ValueError names what it expects."""
    if knob == "image":
        if not isinstance(v, (list, tuple)) or len(v) != 2:
            raise ValueError("[width, height]")
        w, h = int(v[0]), int(v[1])
        return {"width": w, "height": h}, f"{w}x{h}"
    if knob == "precision":
        if v not in PRECISIONS:
            raise ValueError(" or ".join(PRECISIONS))
        return {"precision": v}, v
    if knob == "learning_rate":
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ValueError("a positive number")
        return {"learning_rate": float(v)}, f"{float(v):g}"
    if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v or int(v) < 1:
        raise ValueError("a positive integer")
    return {knob: int(v)}, str(int(v))


def tradeoff_points(settings) -> dict[str, TradeoffPoint]:
    """Every point of the study (base first), from the settings' ``tradeoff`` section
    (``settings``: physmorph.settings.workflow.Settings). A knob or value it cannot take is a ConfigError
    naming its key."""
    t = settings.tradeoff
    exp = settings.experiment(t.experiment)
    s, tg = settings.sampling, settings.target
    base = dict(grid_res=s.grid_res, ppc_surface=s.ppc_surface, ppc_interior=s.ppc_interior,
                width=tg.width, height=tg.height, cameras=exp.cameras or tg.cameras,
                grad_iters=exp.grad_iters or settings.mpm.grad_iters,
                learning_rate=float(settings.mpm.learning_rate), frames=t.frames,
                precision=settings.mpm.precision, threads=t.threads)
    points = {"base": TradeoffPoint("base", "", "", **base)}
    for knob, values in t.knobs.items():
        if knob not in TRADEOFF_KNOBS:
            raise ConfigError.for_key(f"tradeoff.knobs.{knob}", f"unknown knob (known: {', '.join(TRADEOFF_KNOBS)})")
        for i, v in enumerate(values):
            try:
                change, label = _knob_value(knob, v)
            except (TypeError, ValueError) as exc:
                raise ConfigError.for_key(f"tradeoff.knobs.{knob}[{i}]", f"expected {exc}, got {v!r}") from None
            p = {**base, **change}
            if p == base:
                continue
            if knob == "cameras" and p["cameras"] > tg.cameras:
                raise ConfigError.for_key("tradeoff.knobs.cameras",
                                          f"{p['cameras']} exceeds target.cameras {tg.cameras}")
            name = f"{knob}-{label}"
            points[name] = TradeoffPoint(name, knob, label, **p)
    return points
