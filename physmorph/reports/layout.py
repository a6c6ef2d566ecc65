"""Which experiments each of the paper's tables and figures compares, and the paper's numbers.

The layout lives in a YAML file (config/paper_results.yaml in the repository), typed here once with
the config's own validator (physmorph.settings.workflow.build): an error names the file and the key. The
tables and figures stages read experiments by these names (docs/outputs.md: what each compares).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from physmorph.settings.errors import ConfigError
from physmorph.settings.build import build
from physmorph.reports.metrics import CHOSEN_FIGURES, FIGURE_NAMES


@dataclass(frozen=True)
class MainComparison:
    """One target of the main table: physics-only vs full at matched convergence."""

    physics_only: str
    full: str
    paper_physics_only: float
    paper_full: float
    paper_improvement_percent: float


@dataclass(frozen=True)
class ComponentReference:
    """The component ablation's final alpha MSE and Delta E % in the paper."""

    alpha_mse: float
    delta_e_percent: float


@dataclass(frozen=True)
class DragReference:
    """The drag ablation's best and final alpha MSE in the paper."""

    best: float
    final: float


@dataclass(frozen=True)
class PlasticityPair:
    """The run with plasticity, the one without, and the paper's rebound with it (text)."""

    with_: str
    without: str
    paper_rebound: str = ""


@dataclass(frozen=True)
class InjectionPair:
    """The F-injection run and the position-injection run (same source, target and gain) that
    the directions table compares, and the paper's claim about them (text)."""

    f_inject: str
    position_inject: str
    paper: str = ""


@dataclass(frozen=True)
class TableLayout:
    main: dict[str, MainComparison] = field(default_factory=dict)  # target shape -> comparison
    components: dict[str, ComponentReference] = field(default_factory=dict)  # experiment -> paper
    drag: dict[str, DragReference] = field(default_factory=dict)  # experiment -> paper
    source_invariance: dict[str, float] = field(default_factory=dict)  # experiment -> paper best alpha MSE
    plasticity: PlasticityPair | None = None
    injection: InjectionPair | None = None  # the directions table's F vs position pair
    shapes: tuple[str, ...] = ()


@dataclass(frozen=True)
class PaperLayout:
    tables: TableLayout = field(default_factory=TableLayout)
    figures: dict[str, tuple[str, ...]] = field(default_factory=dict)  # figure -> experiments

    def __post_init__(self) -> None:
        unknown = sorted(set(self.figures) - set(FIGURE_NAMES))
        if unknown:
            raise ValueError(f"figures: unknown figure {unknown[0]!r} (known: {', '.join(FIGURE_NAMES)})")
        chosen = sorted(set(self.figures) & set(CHOSEN_FIGURES))
        if chosen:
            raise ValueError(f"figures: {chosen[0]!r} takes no list: its runs are chosen from the profile's runs "
                             "(the full runs whose target no other sequence figure shows)")

    def experiments(self) -> set[str]:
        """Every experiment name the layout refers to."""
        t = self.tables
        names = {n for c in t.main.values() for n in (c.physics_only, c.full)}
        names |= set(t.components) | set(t.drag) | set(t.source_invariance) | set(t.shapes)
        if t.plasticity is not None:
            names |= {t.plasticity.with_, t.plasticity.without}
        if t.injection is not None:
            names |= {t.injection.f_inject, t.injection.position_inject}
        return names | {n for runs in self.figures.values() for n in runs}

    def paper_alpha_mse(self, name: str) -> tuple[float, str]:
        """The paper's alpha MSE for experiment ``name`` and which one it is, or (nan, "")."""
        t = self.tables
        if name in t.drag:
            return t.drag[name].best, "best (drag ablation)"
        if name in t.source_invariance:
            return t.source_invariance[name], "best (source invariance)"
        for c in t.main.values():
            if name == c.physics_only:
                return c.paper_physics_only, "matched frame (main)"
            if name == c.full:
                return c.paper_full, "matched frame (main)"
        if name in t.components:
            return t.components[name].alpha_mse, "final (component ablation)"
        return float("nan"), ""


def load_layout(path: str | Path) -> PaperLayout:
    """The layout of ``path`` (YAML); ConfigError naming the file and the key on bad content."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the table/figure layout ({exc})") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    plasticity = ((data or {}).get("tables") or {}).get("plasticity") if isinstance(data, dict) else None
    if isinstance(plasticity, dict) and "with" in plasticity:  # `with` is a Python keyword
        plasticity["with_"] = plasticity.pop("with")
    try:
        return build(PaperLayout, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}".replace("with_", "with")) from exc
