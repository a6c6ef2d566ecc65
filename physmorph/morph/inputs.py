"""What one morph run reads and never changes (physmorph.morph.loop's MorphRun holds one): the
particles, the target and the views the render loss sees, the solver built for them, the device
of the searches, what the method uses; and the measures of a state against the target (the
frame's metrics, each particle's nearest target surface point).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from physmorph.base.taichi_runtime import resolve_device
from physmorph.meshes.fit import volume_mismatch
from physmorph.meshes.particles import load_particles
from physmorph.morph.frame_measures import DeformationMeasures, deformation_measures, grid_mass
from physmorph.morph.quality import silhouette_iou, view_alpha_mse, volume_metrics
from physmorph.morph.targets import load_target
from physmorph.mpm.solver import solver_for
from physmorph.mpm.state import ParticleState, kinetic_energy, total_volume
from physmorph.plasticity.surface_walk import WALK_MIN_QUERIES, build_in_background
from physmorph.render.api import coverage_behind, render_views
from physmorph.render.containers import RenderTarget
from physmorph.settings.morph import MorphConfig

# points per leaf of the target's KD tree: the paper profile's nearest-target query (511K particles
# against 200K surface points, one thread) 1.29 s at 64 against 1.66 s at scipy's 16, 1.40 at 128
# (docs/study/performance_history.md); any size gives the same nearest points
TARGET_TREE_LEAFSIZE = 64

class MorphInputs:
    """The run's particles, target, views and solver, and the measures against the target."""

    def __init__(self, particles_h5, target_h5, cfg: MorphConfig, name: str, log, target_size: float | None = None):
        self.cfg = cfg
        self.parts = parts = load_particles(particles_h5)
        self.target = target = load_target(target_h5)
        if target.grid.res != cfg.mpm.grid_res:
            raise ValueError(f"{target_h5}: target grid {target.grid.res}^3 does not match mpm.grid_res {cfg.mpm.grid_res}")
        # The render loss sees `cfg.cameras` views evenly spaced around the ring; the alpha-MSE metric
        # always uses every target view, so runs with different camera counts stay comparable.
        self.V = V = target.cameras.count
        n_loss = V if cfg.cameras is None else min(cfg.cameras, V)
        self.views = views = sorted(set(np.linspace(0, V, n_loss, endpoint=False).astype(int).tolist()))
        self.cams = target.cameras.subset(views)
        # in the render's float type, converted once (at the paper's 8 x 960x540 float32 50 MB, not 100,
        # and no copy at each frame's render)
        self.rtarget = RenderTarget(target.alpha[views], target.depth[views], target.sdt[views]).in_float(cfg.render.dtype)
        # The best any morph of these particles can render: the target's own sampling at rest.
        self.ceiling = float(getattr(target, "ceiling_alpha_mse", np.nan))
        # Sliding-midpoint splits (balanced_tree=False): the surface points lie on a 2D sheet, where the
        # median-split tree makes each particle's nearest-point query 3.3x slower (471K particles
        # against 200K points, the paper profile: 5.8 s against 1.75 s a query); leaves of
        # TARGET_TREE_LEAFSIZE points: fewer nodes to descend for the particles deep inside the body.
        self.tree = cKDTree(target.surface_points, leafsize=TARGET_TREE_LEAFSIZE, balanced_tree=False,
                            compact_nodes=False)
        self.N = N = len(parts.x)
        self.solver = solver_for(cfg.mpm, N)  # a reset solver, reused from the previous run of this config and size
        # the device of the solver's Taichi runtime, and the torch device of the transport plan; on
        # "cuda" also of the nearest-target and the mask's distance searches (physmorph.plasticity.nearest), the
        # target points held there; on the CPU those are KD-tree queries (search_device None)
        self.device = resolve_device(cfg.mpm.device)
        self.search_device = None if self.device == "cpu" else self.device
        self.target_on_device = None
        if self.search_device is not None:
            from physmorph.plasticity.nearest import DevicePoints

            self.target_on_device = DevicePoints(target.surface_points, self.search_device)
        # From WALK_MIN_QUERIES particles on the CPU a frame's nearest points are walked to from the
        # last frame's (physmorph.plasticity.surface_walk); its graph is built beside frame 0
        self._walk_pending = (build_in_background(target.surface_points)
                              if self.search_device is None and N >= WALK_MIN_QUERIES else None)
        self.walk = None
        # MPM conserves mass, so a target of another total mass cannot be matched: the squared loss
        # would then be lowered by smearing the excess thinly. The target's mass distribution is
        # rescaled to the source's total mass (its shape is what is matched).
        self.mass_ratio = float(parts.mass.sum() / target.grid_mass.sum())
        self.target_mass = target.grid_mass * self.mass_ratio  # [R, R, R] what the physics matches
        self.solver.set_target_grid_mass(self.target_mass)
        # a target of another volume is named once in the log and in the run file's warnings
        self.source_volume = parts.mesh_volume if np.isfinite(parts.mesh_volume) else float(parts.volume.sum())
        self.target_volume_ratio = float(target.volume) / self.source_volume
        self.volume_note = volume_mismatch(name or str(target_h5), self.source_volume, float(target.volume), target_size,
                                           volume_setting=cfg.rest_volume_setting())
        if self.volume_note:
            log(f"[{name}] warning: {self.volume_note}")
        # The mask is only built where something uses it (a switched-off component costs nothing).
        self.need_mask = cfg.method != "physics_only" or not cfg.metric_all_particles
        # The loss render of a frame is the metric's render when it draws the same particles (the
        # mask) from every view: plasticity and the momentum restart change neither x nor F.
        self.loss_render_is_metric = not cfg.metric_all_particles and len(views) == V
        self.inject_F = cfg.method in ("f_inject", "full")
        self.inject_x = cfg.method == "position_inject"
        self.want_grad = self.inject_F or self.inject_x

    def rest_volume_ratio(self, frame: int) -> float:
        """The rest volume over the source's the plasticity holds after frame ``frame``
        (PlasticityConfig.rest_volume_ratio toward this target's volume; 1 without plasticity)."""
        if self.cfg.rest_volume_setting() is None:
            return 1.0
        return self.cfg.plasticity.rest_volume_ratio(frame, self.target_volume_ratio)

    # ---------------------------------------------------------------------------- the measures
    def measure(self, st: ParticleState, mask: np.ndarray, alpha: np.ndarray | None = None,
                target_distance: np.ndarray | None = None,
                masked_alpha: np.ndarray | None = None) -> tuple[dict, np.ndarray, DeformationMeasures]:  # per_view [V]
        """The frame's metrics: α MSE and IoU over every target view, the deformation measures,
        the energies, the Chamfer distance and the volume metrics."""
        cfg, target = self.cfg, self.target
        if alpha is None and masked_alpha is not None and cfg.metric_all_particles:
            # The loss rendered the masked particles from every view; coverage composes, 1 - alpha =
            # T_mask T_rest (to within the compositing's early stop, transmittance_min), so only the
            # particles outside the mask (~10 % at the paper's scale) are rendered again, behind the
            # mask's transmittance (inside the body's outline nearly every pixel is opaque already).
            rest = ~mask
            alpha = masked_alpha if not rest.any() else coverage_behind(
                st.x[rest], st.F[rest], self.parts.sigma0, target.cameras, 1.0 - masked_alpha, cfg.render)
        if alpha is None:
            alpha = self.rendered_alpha(st, mask)
        per_view = view_alpha_mse(alpha, target.alpha)
        iou = silhouette_iou(alpha, target.alpha)
        dm = deformation_measures(st.F, st.Fp)
        d = self.nearest_target(st.x)[0] if target_distance is None else target_distance
        return {"alpha_mse": float(per_view.mean()), "iou": float(iou.mean()),
                "fp_det_min": float(dm.det_plastic.min()), "fp_det_max": float(dm.det_plastic.max()),
                "fp_anisotropy_max": float(dm.anisotropy_plastic.max()),
                "elastic_energy": dm.elastic_energy(st.volume, cfg.mpm), "kinetic_energy": kinetic_energy(st),
                "total_volume": float(total_volume(st)),
                "rest_volume": float((st.volume * dm.det_plastic).sum() / st.volume.sum()),
                "mask_size": int(mask.sum()) if self.need_mask else np.nan,
                "mask_fraction": float(mask.mean()) if self.need_mask else np.nan,
                "chamfer": float(d.mean()),
                **volume_metrics(st.x, self.parts.mass, target.grid_mass, target.grid, splat=grid_mass)}, per_view, dm

    def rendered_alpha(self, st: ParticleState, mask: np.ndarray) -> np.ndarray:  # mask [N] -> [V, H, W]
        """The coverage of every target view by the particles the metric counts (every particle with
        metric_all_particles, else the mask's)."""
        sel = slice(None) if self.cfg.metric_all_particles else mask
        return render_views(st.x[sel], st.F[sel], self.parts.sigma0, self.target.cameras, self.cfg.render)[0]

    def alpha_mse(self, st: ParticleState, mask: np.ndarray) -> float:  # mask [N]
        """The α MSE that :meth:`measure` reports for ``st`` without the rest of its measures (the
        release curve's: there the nearest-target search and the deformation measures would cost
        as much as the views' rendering, for numbers nobody reads)."""
        return float(view_alpha_mse(self.rendered_alpha(st, mask), self.target.alpha).mean())

    def wait_for_walk(self) -> None:
        """The surface walk's graph, where one is being built, ready (or None: Qhull could not)."""
        if self._walk_pending is not None:
            self.walk, self._walk_pending = self._walk_pending(), None

    def nearest_target(self, x: np.ndarray,  # [N, 3]
                       start: np.ndarray | None = None,  # [N] indices: each x's nearest a little before
                       ) -> tuple[np.ndarray, np.ndarray]:  # [N] distances, [N] indices
        """Each x's nearest target surface point: on the CPU the KD tree, or with ``start`` and a
        walk built the surface walk from there (the same points); the exhaustive search of
        physmorph.plasticity.nearest on the device."""
        if self.target_on_device is not None:
            return self.target_on_device.query(x)
        if start is not None and self.walk is not None:
            return self.walk.query(x, start)
        return self.tree.query(x, k=1, workers=-1)
