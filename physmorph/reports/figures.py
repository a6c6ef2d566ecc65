"""The paper's figures from run files (PNG): morph sequences, loss curves, gradient coverage.

Sequences render the saved particle states as Phong-shaded Gaussians from one ring camera at
twice the target image size, with the target itself in a last column and the share of the
reachable gap closed (physmorph.morph.quality) over the last frame. Curves read the per-frame metrics
of the runs. Runs that were not made in this profile are left out of a figure (a figure with
none of its runs says so).
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from physmorph.base.cameras import ring_cameras
from physmorph.settings.sections import TargetConfig
from physmorph.reports.layout import PaperLayout
from physmorph.reports.metrics import FIGURE_NAMES
from physmorph.records.runfile import read_metrics
from physmorph.settings.render import LOSS_SCALARS



def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# PNG text key listing the runs a figure draws (empty: none of its runs exist in this profile), so
# a results page can leave out a figure with nothing in it (physmorph.reports.userdocs).
RUNS_KEY = "physmorph runs"


def _save(fig, out_png: Path, runs) -> None:
    fig.savefig(out_png, dpi=110, metadata={RUNS_KEY: ", ".join(runs)})


def figure_runs(png: str | Path) -> list[str] | None:
    """The runs a figure made here draws (from its PNG text); None for a PNG without the record."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(png) as im:
            text = getattr(im, "text", {}) or {}
    except (OSError, UnidentifiedImageError):
        return None
    if RUNS_KEY not in text:
        return None
    return [r for r in text[RUNS_KEY].split(", ") if r]


def _saved_frames(f: h5py.File) -> list[str]:
    return sorted(f["states"]) if "states" in f else []


def figure_cameras(target: TargetConfig | dict, scale: int = 2):
    t = target if isinstance(target, TargetConfig) else TargetConfig(**target)
    return ring_cameras(t.cameras, t.elevation_deg, t.fov_y_deg, t.width * scale, t.height * scale, t.distance,
                        t.elevation_spread_deg)


def _experiment_field(f: h5py.File, key: str) -> str | None:
    """One field of the experiment in a run's config record (None where the run has none)."""
    try:
        return str(json.loads(f.attrs["config_record"])["experiment"][key])
    except (KeyError, TypeError, ValueError):
        return None


def run_method(f: h5py.File) -> str:
    """A run's method from its config record ("" where it has none)."""
    return _experiment_field(f, "method") or ""


def run_target_shape(f: h5py.File, name: str) -> str:
    """The target shape of a run: its config record's experiment, else the name's second part
    (experiments are named {source}_{target}_{method}...)."""
    target = _experiment_field(f, "target")
    if target is not None:
        return target
    parts = name.split("_")
    return parts[1] if len(parts) > 1 else ""


def _share_closed(f: h5py.File, k: int) -> float:
    """Share of the reachable gap closed at frame k (physmorph.morph.quality.gap_closed); nan for a run
    file without the ceiling."""
    from physmorph.morph.quality import gap_closed

    ceiling = float(f.attrs.get("ceiling_alpha_mse", np.nan))
    if "metrics" not in f or "alpha_mse" not in f["metrics"] or not np.isfinite(ceiling):
        return np.nan
    a = f["metrics"]["alpha_mse"][()]
    return gap_closed(float(a[0]), float(a[min(k, len(a) - 1)]), ceiling) if len(a) else np.nan


def target_image(target_h5: Path, view: int) -> np.ndarray:
    """The target's own coverage alpha of ``view`` as a grey silhouette on white, [H, W, 3]."""
    with h5py.File(target_h5) as f:
        alpha = f["alpha"][view].astype(np.float64)
    return 1.0 - 0.55 * alpha[..., None] * np.ones(3)


def sequence_figure(runs: dict[str, Path], target_cfg: dict, out_png: Path, view: int = 1, columns: int = 6,
                    frames: list[int] | None = None, targets: dict[str, Path] | None = None) -> list[list[str]]:
    """One row per run: ``columns`` saved frames from the first to the last (or the saved frames
    nearest to ``frames``), shaded Gaussians. With ``targets`` (target shape -> target HDF5) a last
    column shows each run's target (its exact coverage alpha in the same view) and the last frame's
    title gives the share of the reachable gap closed there (physmorph.morph.quality). Returns the panel
    titles, one list per row."""
    from physmorph.settings.render import RenderConfig
    from physmorph.render.api import shade

    plt = _plt()
    cams = figure_cameras(target_cfg)
    rows = [(n, p) for n, p in runs.items() if p is not None and Path(p).exists()]
    ncols = columns + (targets is not None)
    fig, axes = plt.subplots(max(len(rows), 1), ncols, figsize=(2.2 * ncols, 1.4 * max(len(rows), 1) + 0.3), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for r, (name, path) in enumerate(rows):
        with h5py.File(path) as f:
            saved = _saved_frames(f)
            if frames is None:
                pick = [saved[i] for i in np.unique(np.linspace(0, len(saved) - 1, columns).round().astype(int))]
            else:
                numbers = np.array([int(fr.replace("frame_", "")) for fr in saved])
                pick = list(dict.fromkeys(saved[int(np.argmin(np.abs(numbers - k)))] for k in frames))
            sigma0 = float(f.attrs["sigma0"])
            for c, fr in enumerate(pick):
                g = f["states"][fr]
                img = shade(g["x"][()].astype(np.float64), g["F"][()].astype(np.float64), sigma0, cams, view, RenderConfig())
                axes[r, c].imshow(img)
                k = int(fr.replace("frame_", ""))
                title = f"{name}  k={k}" if c == 0 else f"k={k}"
                if targets is not None and c == len(pick) - 1 and c > 0:
                    closed = _share_closed(f, k)
                    if np.isfinite(closed):
                        title += f"  {100 * closed:.0f}% of gap"
                axes[r, c].set_title(title, fontsize=7)
            shape = run_target_shape(f, name) if targets is not None else ""
        if targets is not None:
            t_h5 = targets.get(shape)
            if t_h5 is not None and Path(t_h5).exists():
                axes[r, -1].imshow(target_image(Path(t_h5), view), interpolation="bilinear")
                axes[r, -1].set_title(f"target ({shape})", fontsize=7)
            else:
                axes[r, -1].set_title(f"target ({shape}): not made", fontsize=7)
    if not rows:
        axes[0, 0].text(0, 0.5, "no runs of this figure in this profile", fontsize=8)
    fig.tight_layout()
    _save(fig, out_png, [n for n, _ in rows])
    titles = [[ax.get_title() for ax in row] for row in axes]
    plt.close(fig)
    return titles


def curves_figure(runs: dict[str, Path], panels: list[tuple[str, str]], out_png: Path, title: str,
                  logy: tuple[str, ...] = ()) -> None:
    """One panel per (metric key, label); one line per run. Metrics are indexed by frame."""
    plt = _plt()
    data = {n: read_metrics(p) for n, p in runs.items() if p is not None and Path(p).exists()}
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.0), squeeze=False)
    for ax, (key, label) in zip(axes[0], panels):
        for name, m in data.items():
            if key == "fp_det_range":
                ax.fill_between(np.arange(len(m["fp_det_min"])), m["fp_det_min"], m["fp_det_max"], alpha=0.3, label=name)
                continue
            y = m[key] if key in m else None
            if y is not None:
                ax.plot(np.arange(len(y)), y, label=name, lw=1.4)
        ax.set_xlabel("frame")
        ax.set_title(label, fontsize=9)
        if key in logy:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    if data:
        axes[0, 0].legend(fontsize=7)
    fig.suptitle(title if data else f"{title} (no runs of this figure in this profile)", fontsize=10)
    fig.tight_layout()
    _save(fig, out_png, list(data))
    plt.close(fig)


def coverage_figure(run: Path | None, target_h5: Path | None, out_png: Path, camera_counts=(1, 4, 8)) -> None:
    """Per-particle |dL/dF| (log colour) on the run's last saved state with 1, 4 and 8 cameras."""
    from physmorph.settings.render import RenderConfig
    from physmorph.render.containers import RenderTarget
    from physmorph.render.api import render_and_grad
    from physmorph.morph.targets import load_target

    plt = _plt()
    fig, axes = plt.subplots(1, len(camera_counts), figsize=(3.6 * len(camera_counts), 3.2), squeeze=False)
    if run is None or not Path(run).exists() or target_h5 is None:
        axes[0, 0].text(0, 0.5, "run not made in this profile", fontsize=8)
        _save(fig, out_png, [])
        plt.close(fig)
        return
    t = load_target(target_h5)
    with h5py.File(run) as f:
        last = _saved_frames(f)[-1]
        x = f["states"][last]["x"][()].astype(np.float64)
        F = f["states"][last]["F"][()].astype(np.float64)
        sigma0 = float(f.attrs["sigma0"])
    V = t.cameras.count
    uv, _ = t.cameras.project(x)
    for ax, n in zip(axes[0], camera_counts):
        views = list(np.linspace(0, V, n, endpoint=False).astype(int)) if n < V else list(range(V))
        res = render_and_grad(x, F, sigma0, t.cameras.subset(views), RenderTarget(t.alpha[views], t.depth[views], t.sdt[views]), RenderConfig())
        g = np.linalg.norm(res.grad_F.reshape(len(x), -1), axis=1)
        order = np.argsort(g)
        sc = ax.scatter(uv[2, order, 0], uv[2, order, 1], c=np.log10(g[order] + 1e-12), s=3, cmap="turbo")
        ax.set_xlim(0, t.cameras.width)
        ax.set_ylim(t.cameras.height, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{n} camera{'s' if n > 1 else ''}: {100 * np.mean(g > 1e-3 * g.max()):.0f}% of particles guided", fontsize=8)
        ax.axis("off")
        fig.colorbar(sc, ax=ax, fraction=0.04, label="log10 |dL/dF|")
    fig.suptitle(f"render-gradient coverage on {Path(run).stem} ({last})", fontsize=9)
    fig.tight_layout()
    _save(fig, out_png, [Path(run).stem])
    plt.close(fig)


SEQUENCE_FIGURES = ("sequences_main", "sequences_cross_shape", "sequences_letters", "sequences_other")


def other_sequence_runs(runs: dict[str, Path], sel: dict[str, dict[str, Path]]) -> dict[str, Path]:
    """The full-method runs whose target no other sequence figure shows, in ``runs``' order: a
    profile's own targets (held-out shapes, a user's mesh) get their picture too."""
    def existing(d):
        return {n: p for n, p in d.items() if p is not None and Path(p).exists()}

    shown = set()
    for name in SEQUENCE_FIGURES[:-1]:
        for n, p in existing(sel.get(name, {})).items():
            with h5py.File(p) as f:
                shown.add(run_target_shape(f, n))
    out = {}
    for n, p in existing(runs).items():
        with h5py.File(p) as f:
            if run_method(f) == "full" and run_target_shape(f, n) not in shown:
                out[n] = p
    return out


def build_figures(runs: dict[str, Path], targets: dict[str, Path], target_cfg: dict, out_dir: Path,
                  layout: PaperLayout, names: tuple[str, ...] = FIGURE_NAMES) -> list[Path]:
    """The figures ``names`` (default: every one of FIGURE_NAMES) as out_dir/{name}.png; ``layout``
    (physmorph.reports.layout) names the runs of each figure."""
    unknown = sorted(set(names) - set(FIGURE_NAMES))
    if unknown:
        raise ValueError(f"unknown figures {unknown} (known: {', '.join(FIGURE_NAMES)})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sel = {name: {r: runs.get(r) for r in layout.figures.get(name, ())} for name in FIGURE_NAMES}
    sel["sequences_other"] = other_sequence_runs(runs, sel)

    def coverage(png: Path) -> None:
        name = next(iter(layout.figures.get("gradient_coverage", ())), None)
        run = runs.get(name) if name else None
        target = None
        if run is not None and Path(run).exists():
            with h5py.File(run, "r") as f:
                target = targets.get(run_target_shape(f, name))
        coverage_figure(run, target, png)

    makers = {
        **{name: (lambda png, name=name: sequence_figure(sel[name], target_cfg, png, targets=targets))
           for name in SEQUENCE_FIGURES},
        "drag_ablation": lambda png: curves_figure(sel["drag_ablation"], [("alpha_mse", "alpha MSE")], png,
                                                   "drag ablation: iso -> bunny"),
        "trajectory_divergence": lambda png: curves_figure(
            sel["trajectory_divergence"], [("physics_loss", "physics loss"), ("alpha_mse", "alpha MSE")],
            png, "trajectory divergence: iso -> duck", logy=("physics_loss",)),
        # The paper shows frames 10, 15 and 19 side by side; the saved frames nearest to them.
        "trajectory_frames": lambda png: sequence_figure(sel["trajectory_frames"], target_cfg, png, columns=3,
                                                         frames=[10, 15, 19]),
        "plasticity_effect": lambda png: curves_figure(
            sel["plasticity_effect"], [("alpha_mse", "alpha MSE"), ("physics_loss", "physics loss"),
                                       ("fp_det_range", "det Fp range")], png,
            "Chamfer plasticity: with (full) and without (f_inject)", logy=("physics_loss",)),
        "optimization_traces": lambda png: curves_figure(
            sel["optimization_traces"], [("alpha_mse", "alpha MSE"), ("grad_F_norm", "|dL/dF|"),
                                         (LOSS_SCALARS["total"], "render loss"), ("physics_loss", "physics loss")],
            png, "optimization traces: iso -> bunny (full)", logy=("grad_F_norm", "physics_loss")),
        "gradient_coverage": coverage,
    }
    for name in names:
        makers[name](out / f"{name}.png")
    return [out / f"{n}.png" for n in names]
