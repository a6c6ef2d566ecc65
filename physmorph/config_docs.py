"""What every config key means: (meaning, unit, range) by dotted key, ``<name>`` for a mapping's
entries. The type, allowed values and default come from the schema (physmorph.config.json_schema);
``config_reference()`` (physmorph.userdocs) joins the two into config/README.md, and a test checks
that every schema key has an entry here and in that file. "" as unit: a plain number or a choice.
"""

from __future__ import annotations

# Sections, in the order of config/config.yaml, with one line each.
SECTIONS = {
    "": "Run-wide settings.",
    "raw_meshes": "Raw meshes fetched from a pinned URL and checked against their SHA-256.",
    "shapes": "The shapes experiments morph from and to; each is repaired, normalised to `size` and centred "
              "on its volume centroid.",
    "sampling": "Particle sampling on the simulation grid (file tag {grid_res}x{ppc_surface}x{ppc_interior}).",
    "target": "The target's images (cameras on a ring around the origin), grid mass and surface points.",
    "mpm": "The differentiable MPM solver and the optimiser of its control field (physmorph.mpm.MPMConfig).",
    "render": "The differentiable Gaussian splatting renderer and its losses (physmorph.render.RenderConfig).",
    "plasticity": "Chamfer-guided plasticity: each particle's rest state pulled toward its destination "
                  "(physmorph.plasticity.PlasticityConfig).",
    "surface": "The surface mask: which particles the render loss sees (physmorph.surface.SurfaceMaskConfig).",
    "morph": "The frame loop of one run (physmorph.morph_config.MorphConfig).",
    "experiments": "The experiments: one morph run each; unset keys take the sections' values.",
    "tradeoff": "The speed/accuracy study: the base experiment rerun with one knob changed at a time.",
    "tables": "What `snakemake tables` (and `figures`) builds.",
    "export": "Videos, surface meshes and Gaussian-splat files of the full-method runs (`snakemake export`; "
              "physmorph.export.settings.ExportConfig).",
}

R01 = "[0, 1]"
POS = "> 0"

FIELD_DOCS: dict[str, tuple[str, str, str]] = {
    # run-wide
    "profile": ("name of the results tree: outputs go to results/{profile}/", "", "letters, digits, _ . -"),
    "device": ("where Taichi and torch run; auto picks CUDA when present", "", ""),
    "threads": ("threads per job (Taichi and torch); changing it reruns nothing", "", ">= 1"),
    "mesh_dir": ("a local folder holding the raw meshes (read instead of downloading); null downloads into "
                 "resources/meshes/", "path", ""),
    "seed": ("random seed of the particle sampling and the target surface points", "", ">= 0"),
    "domain": ("the simulation cube [lo, hi]^3", "domain units", "lo < hi"),
    "max_memory_mb": ("refuse a config whose estimated stage memory exceeds this; null: this machine's memory",
                      "MB", POS),
    "morph_gpus": ("GPUs a morph job asks a cluster scheduler for (resources.gpu)", "", ">= 0"),
    "raw_meshes": ("raw mesh files by file name", "", ""),
    "raw_meshes.<name>.url": ("where the file is downloaded from (pin a commit)", "URL", ""),
    "raw_meshes.<name>.sha256": ("SHA-256 of the file; a mismatch stops the run", "", "64 lowercase hex digits"),
    "shapes": ("the shapes, by name", "", ""),
    "shapes.<name>.kind": ("file: a mesh; isosphere: a once-subdivided icosahedron; letter: an extruded glyph",
                           "", ""),
    "shapes.<name>.file": ("kind file: a raw_meshes entry (fetched and checked)", "", "exactly one of file, path"),
    "shapes.<name>.path": ("kind file: a mesh on disk (OBJ, PLY, STL, GLB, ...); its SHA-256 is recorded",
                           "path", "exactly one of file, path"),
    "shapes.<name>.glyph": ("kind letter: the character", "", "one character"),
    "shapes.<name>.size": ("longest extent after normalisation; choose it so the shape holds ~1170 units^3 "
                           "like the benchmark shapes (MPM keeps volume); python -m physmorph.meshes.fit MESH prints it", "domain units", POS),
    "shapes.<name>.depth": ("kind letter: extrusion depth", "domain units", POS),
    # sampling
    "sampling.grid_res": ("MPM grid cells per axis (also the sampling grid)", "cells", ">= 8"),
    "sampling.ppc_surface": ("particles per cell per axis in the two-cell surface shell", "", ">= 1"),
    "sampling.ppc_interior": ("particles per cell per axis inside", "", ">= 1"),
    "sampling.density": ("material density rho", "mass / domain unit^3", POS),
    "sampling.sigma_scale": ("Gaussian size sigma0 as a multiple of the mean nearest-neighbour distance", "", POS),
    # target
    "target.cameras": ("views of the target, evenly spaced on the ring", "", ">= 1"),
    "target.elevation_deg": ("camera elevation above the horizontal", "degrees", "[-89, 89]"),
    "target.fov_y_deg": ("vertical field of view", "degrees", "(0, 180)"),
    "target.distance": ("camera distance from the origin", "domain units", POS),
    "target.width": ("image width", "pixels", ">= 4"),
    "target.height": ("image height", "pixels", ">= 4"),
    "target.supersample": ("rays per pixel per axis for the target's exact coverage alpha", "", "[1, 8]"),
    "target.surface_points": ("target surface samples for Chamfer distances and plasticity", "", ">= 100"),
    # mpm
    "mpm.dt": ("MPM time step of one substep (a frame is substeps x dt); refused above the stable step "
               "cfl dx / c", "s", "> 0, <= cfl dx / c"),
    "mpm.substeps": ("MPM substeps per frame (T)", "", ">= 1"),
    "mpm.youngs_modulus": ("Young's modulus E", "Pa", POS),
    "mpm.poisson_ratio": ("Poisson's ratio nu", "", "(-1, 0.5)"),
    "mpm.drag": ("velocity drag d; experiments set it with `drag`", "1/s", "0 <= drag dt <= 1"),
    "mpm.smoothing": ("F smoothing s: the share of F kept from before each substep", "", "[0, 1)"),
    "mpm.smoothing_mode": ("full: the paper's blend (also smooths the volume); isochoric: the blend rescaled so "
                           "det F follows the motion", "", ""),
    "mpm.control": ("per_substep: one control dFc per particle per substep (the paper's code); per_frame: one "
                    "per frame", "", ""),
    "mpm.control_in_F": ("carry dFc in F as the authors' code does (otherwise it enters the stress only)", "", ""),
    "mpm.learning_rate": ("step size: per-entry RMS of each normalised step (normalized_gd) or Adam's lr, "
                          "at a one-unit cell with step_scales_with_dx", "", POS),
    "mpm.step_scales_with_dx": ("the step is learning_rate x dx (domain units): the same distance per frame "
                                "at every grid resolution", "", ""),
    "mpm.optimizer": ("normalized_gd: the authors' normalised descent with line search; adam: the paper's text",
                      "", ""),
    "mpm.line_search_iters": ("normalized_gd: halvings of the step tried before a step is undone", "", ">= 1"),
    "mpm.sufficient_decrease": ("normalized_gd: Armijo constant c of the line search (a step must lower the "
                                "objective by c alpha <g, d>; 0: any decrease)", "", "[0, 1)"),
    "mpm.step_clip": ("normalized_gd: clamp of each entry of the normalised step, in multiples of its RMS; "
                      "0 = off", "", ">= 0"),
    "mpm.step_per_volume": ("normalized_gd: the step direction is the gradient per unit of particle volume "
                            "(a shell-biased sampling's surface particles are driven as hard as its interior ones)",
                            "", ""),
    "mpm.step_volume_power": ("with step_per_volume: the exponent of the per-volume weight, "
                              "g_p (V_max / V_p)^power (1: per unit volume; 0: the plain step)", "", "[0, 1]"),
    "mpm.step_rms": ("what the normalised step's RMS is taken over: every particle once (particles) or each "
                     "by its volume (volume: the same for every sampling of a body)", "", "particles | volume"),
    "mpm.step_smoothing": ("grid: the weighted gradient replaced by its share on the MPM grid (P2G, then G2P) "
                           "before the step is normalised; none: each particle's own", "", "none | grid"),
    "mpm.step_volume": ("what the step may do to the volume the stress sees: particle (each particle's step "
                        "loses its change of volume), body (only the body's total change is removed), full "
                        "(the authors' step)", "", "particle | body | full"),
    "mpm.step_volume_share": ("with step_volume particle: the share of each particle's change of volume removed "
                              "from its step (1: all, 0: the full step)", "", "[0, 1]"),
    "mpm.grad_iters": ("optimiser iterations per frame (J); experiments set it with `grad_iters`", "", ">= 1"),
    "mpm.adam_beta1": ("Adam's first-moment decay", "", "[0, 1)"),
    "mpm.adam_beta2": ("Adam's second-moment decay", "", "[0, 1)"),
    "mpm.adam_eps": ("Adam's epsilon", "", POS),
    "mpm.mass_loss": ("form of the grid-mass loss: squared difference, log difference, sqrt (Hellinger), "
                      "log below the target and sqrt above, or log continued linearly where it turns concave "
                      "(log_convex)", "", ""),
    "mpm.log_mass_eps": ("eps of the log and sqrt losses, in mean particle masses", "particle masses", POS),
    "mpm.mass_loss_levels": ("levels of a grid-mass pyramid the loss is summed over; 1 = the grid alone", "",
                             ">= 1, 2^(levels-1) divides grid_res"),
    "mpm.mass_loss_blur": ("sigma of a Gaussian-blurred level of the mass loss, reaching material several cells from "
                           "the target; 0 = off", "cells", "[0, 16]"),
    "mpm.mass_loss_blur_weight": ("weight of the blurred level (the grid's own is 1)", "", ">= 0"),
    "mpm.overfill_weight": ("weight of a packing term on nodes holding more than the target (or than overfill_ratio x "
                            "density, where that is more); 1 with ratio 0.001: overfill weighed twice; 0 = off", "",
                            ">= 0"),
    "mpm.volume_law": ("volume term of the elastic energy: fixed_corotated (the paper's) or barrier (grows "
                       "without bound as det F -> 0)", "", ""),
    "mpm.overfill_ratio": ("density ratio of the packing term's cap (0.001: the target's own node mass)", "", POS),
    "mpm.warm_start": ("keep the control (and Adam's moments) from frame to frame", "", ""),
    "mpm.volume_stiffness": ("K of a pressure against packing measured from the particles' density; 0 = off",
                             "Pa", ">= 0"),
    "mpm.volume_onset": ("density ratio above which volume_stiffness acts", "", POS),
    "mpm.min_volume_ratio": ("floor on det F under isochoric smoothing; 0 = off (the paper)", "", "[0, 1)"),
    "mpm.control_clip": ("clamp of every dFc entry after each step; 0 = off", "", ">= 0"),
    "mpm.cfl": ("CFL number: dt above cfl dx / c (c the P-wave speed) is refused", "", "(0, 1]"),
    "mpm.cfl_warn_fraction": ("warn when dt is above this share of the stable step", "", "(0, 1]"),
    "mpm.precision": ("floating-point type of the solver", "", ""),
    # render
    "render.opacity": ("peak opacity of every Gaussian (particles carry no learned opacity)", "", "(0, 1]"),
    "render.low_pass": ("added to the diagonal of every 2D covariance (EWA low-pass)", "pixels^2", ">= 0"),
    "render.tile_size": ("side of the screen tiles Gaussians are binned into", "pixels", ">= 1"),
    "render.cutoff_sigma": ("a Gaussian is evaluated within this 2D Mahalanobis distance", "sigma", POS),
    "render.alpha_min": ("per-Gaussian alpha below this is skipped", "", "[0, alpha_max)"),
    "render.alpha_max": ("per-Gaussian alpha is clamped to this", "", "(0, 1)"),
    "render.transmittance_min": ("compositing stops below this transmittance; 0 composites all", "", "[0, 1)"),
    "render.iou_fraction": ("soft-IoU gradient scaled to this share of the distance-transform gradient's norm",
                            "", ">= 0"),
    "render.depth_fraction": ("depth gradient scaled to this share of the distance-transform gradient's norm",
                              "", ">= 0"),
    "render.depth_min_alpha": ("the depth loss uses pixels whose rendered alpha exceeds this", "", R01),
    "render.dtype": ("floating-point type of the renderer (float64 for gradient checks)", "", ""),
    "render.kernel": ("rasterizer loop order: tile (faster on CPU), pixel (CUDA), auto by device", "", ""),
    # plasticity
    "plasticity.eta": ("plasticity rate (the paper: 0.2)", "", ">= 0"),
    "plasticity.k_neighbors": ("neighbours of the displacement smoothing", "", ">= 1"),
    "plasticity.neighbour_ppc": ("the neighbours are drawn from at most this many particles per cell per axis, "
                                 "so k_neighbors spans the same cells at every sampling density (0 = every particle)",
                                 "", ">= 0"),
    "plasticity.transport_blur": ("blur of the transport plan (correspondence: transport), the entropic scale of its "
                                  "last iterations", "grid cells", "> 0"),
    "plasticity.smooth_iters": ("passes of neighbour averaging of the displacements", "", ">= 0"),
    "plasticity.damping": ("damping d_p of the Fp update", "", R01),
    "plasticity.start_frame": ("k0: first frame with plasticity; experiments set it with `plasticity_start`",
                               "frame", ">= 0"),
    "plasticity.det_bounds": ("bounds [lo, hi] on det Fp", "", "0 < lo <= 1 <= hi"),
    "plasticity.max_anisotropy": ("bound on the ratio of Fp's largest to smallest stretch", "", ">= 1"),
    "plasticity.jacobian": ("paper: eq. 4 as printed; least_squares: exact for affine displacement fields", "",
                            ""),
    "plasticity.update": ("incremental: eq. 4 as printed; target_rest: relax toward the rest state on the "
                          "target", "", ""),
    "plasticity.correspondence": ("where each particle is pulled: nearest, the nearest target surface point (the "
                                  "paper); transport, its optimal-transport destination in the target's mass", "", ""),
    "plasticity.continuous_stress": ("re-base the control so an Fp update leaves the elastic Fe unchanged", "",
                                     ""),
    "plasticity.absorb_control": ("commit the achieved shape (or control) to the rest state Fp at the updates "
                                  "absorb_start_frame picks", "", ""),
    "plasticity.absorb_rate": ("share moved into Fp per absorbing update", "", "(0, 1]"),
    "plasticity.absorb_target": ("what is committed: shape (the stretch of F, stress-free afterwards) or "
                                 "control (its elastic deformation)", "", ""),
    "plasticity.absorb_start_frame": ("updates that commit: -n the last n, n from frame n on, null every update",
                                      "frame", "!= 0"),
    # surface
    "surface.voxels": ("voxels per axis of the density grid the mask is built on", "", ">= 8"),
    "surface.blur_sigma": ("Gaussian blur of the density grid", "voxels", ">= 0"),
    "surface.level": ("iso level, as a share of the 95th-percentile blurred density", "", "(0, 1)"),
    "surface.band": ("particles within this distance of the reconstructed surface are rendered", "voxels", POS),
    "surface.target_band": ("and those within this distance of the target surface", "domain units", ">= 0"),
    "surface.enabled": ("false renders every particle", "", ""),
    # morph
    "morph.frames": ("frames per run; experiments set it with `frames`", "", ">= 1"),
    "morph.gamma": ("gain of the render gradient injected on F, relative to the mass gradient", "", ">= 0"),
    "morph.gamma_x": ("position_inject only: gain of the render gradient injected on positions", "", ">= 0"),
    "morph.injection_calibration": ("every_frame: gain re-measured each frame; first_frame: once; absolute: "
                                    "no calibration (eq. 3 as printed)", "", ""),
    "morph.cameras": ("views the render loss uses (evenly spaced); null: all target.cameras", "", "<= cameras"),
    "morph.save_every": ("store x, F, Fp every this many frames (and the first and last)", "frames", ">= 1"),
    "morph.metric_all_particles": ("alpha MSE from all particles (false: the masked subset)", "", ""),
    "morph.max_F_norm": ("a run stops when an entry of F exceeds this (divergence)", "", POS),
    "morph.max_Fp_norm": ("a run stops when an entry of Fp exceeds this", "", POS),
    "morph.release_frames": ("frames with the control off after the run (how much of the morph persists)",
                             "frames", ">= 0"),
    "morph.progress": ("log a line per frame; changing it reruns nothing", "", ""),
    "morph.momentum_restart": ("start the next frame at rest when the frame's physics loss (the mass loss, with the full method's stray pull) or alpha MSE rose; "
                               "off: the paper's loop", "", ""),
    "morph.restart_keep": ("share of the velocity a restart keeps", "", R01),
    "morph.restart_reference": ("what a frame's objective must rise above for a restart: the previous frame's "
                                "(previous) or the one before it (two_back)", "", "previous or two_back"),
    "morph.settle": ("the last phase: from the frame after the objective first rose (after_first_rise) or after the "
                     "restart fired twice one frame apart (after_cycle) every frame starts at rest, and one whose "
                     "settle_objective rises is undone (the body holds still); off: the restart alone", "",
                     "off, after_cycle or after_first_rise"),
    "morph.settle_backoff": ("step multiplier after a frame the settle phase undid", "", "(0, 1]"),
    "morph.settle_objective": ("what the settle phase judges a frame by: its alpha MSE (every view), its render loss, "
                               "or its physics loss; physics_only is gated on the physics loss only", "",
                               "render, alpha_mse or physics"),
    "morph.step_backoff": ("step multiplier after a frame whose physics loss rose; 1 = fixed step", "", "(0, 1]"),
    "morph.step_growth": ("step multiplier after a frame whose loss fell, up to learning_rate", "", ">= 1"),
    "morph.step_first": ("the step at the first frame, in learning rates (linear to step_last); 1 = fixed step", "", "> 0"),
    "morph.step_last": ("the step at the last frame, in learning rates", "", "> 0"),
    "morph.restart_control_keep": ("share of the carried control a restart keeps", "", R01),
    "morph.control_decay": ("share of the control each frame starts with (1: carried whole)", "", R01),
    "morph.control_decay_follows_step": ("the leak (1 - control_decay) scales with the bold driver's step over mpm's step", "", ""),
    "morph.overfill_onset": ("when mpm.overfill_weight's packing term starts: start, or first_restart (the frame after the "
                             "objective first rose, the first momentum restart)", "", ""),
    "morph.stray_pull": ("method full: weight of a pull on particles outside the target toward their nearest target "
                         "surface point (a cell of material one cell out costs this; 0: off)", "", ">= 0"),
    "morph.strain_rate_cap": ("the next frame's step is scaled by this over the frame's strain (99th percentile of "
                              "|F_T F_0^-1 - I|), up to learning_rate; 0: off", "per frame", ">= 0"),
    "morph.stray_pull_anchor": ("where the stray pull draws a stray particle: its nearest target surface point, "
                                "its optimal-transport destination in the target's mass, or toward that destination as far "
                                "as the nearest surface point", "", ""),
    "morph.stray_pull_onset": ("the stray pull acts on particles more than this far from the target's surface", "cells", ">= 0"),
    "morph.volume_averaging": ("share of each particle's det F moved to its grid average between frames (0: off)", "", R01),
    # experiments
    "experiments": ("the experiments, by name (run one: results/{profile}/runs/{name}.h5)", "", ""),
    "experiments.<name>.source": ("shape the particles are sampled from", "", "a shapes key"),
    "experiments.<name>.target": ("shape to morph into", "", "a shapes key"),
    "experiments.<name>.method": ("physics_only: mass loss alone; f_inject: + render gradient on F; full: + "
                                  "plasticity; position_inject: render gradient on positions", "", ""),
    "experiments.<name>.drag": ("sets mpm.drag", "1/s", "as mpm.drag"),
    "experiments.<name>.frames": ("sets morph.frames", "", ">= 1"),
    "experiments.<name>.cameras": ("sets morph.cameras", "", "<= target.cameras"),
    "experiments.<name>.gamma": ("sets morph.gamma", "", ">= 0"),
    "experiments.<name>.gamma_x": ("sets morph.gamma_x", "", ">= 0"),
    "experiments.<name>.grad_iters": ("sets mpm.grad_iters", "", ">= 1"),
    "experiments.<name>.plasticity_start": ("sets plasticity.start_frame", "frame", ">= 0"),
    "experiments.<name>.release_frames": ("sets morph.release_frames", "frames", ">= 0"),
    # tradeoff, tables
    "tradeoff.experiment": ("the base experiment", "", "an experiments key"),
    "tradeoff.frames": ("frames of the base point (the frames knob changes them)", "", ">= 1"),
    "tradeoff.knobs": ("values tried per knob: grid_res, ppc_surface, ppc_interior, image ([w, h]), cameras, "
                       "grad_iters, learning_rate, frames, precision (float32 | float64), threads", "", ""),
    "tradeoff.threads": ("threads of the base point (the threads knob changes them); the workflow's `threads` "
                         "does not reach the study", "", ">= 1"),
    "tables.shapes": ("shapes whose particles and targets are built", "", "shapes keys"),
    "tables.experiments": ("experiments run for the tables and figures", "", "experiments keys"),
    "export.width": ("width of each video panel (the body's, then the target's)", "pixels", "even, >= 16"),
    "export.height": ("height of the video", "pixels", "even, >= 16"),
    "export.fps": ("video frames per second (one per morph frame)", "1/s", "[1, 120]"),
    "export.orbit_deg": ("how far the video's camera turns around the body over the whole run", "degrees", ""),
    "export.max_particles": ("above this many particles the video shows the body by an even subsample, each "
                             "Gaussian widened to keep it closed", "", ">= 1000"),
    "export.crf": ("H.264 constant rate factor (lower: better and larger)", "", "[0, 51]"),
    "export.refine": ("surface grid cells per MPM cell (the exported meshes' resolution)", "", POS),
    "export.smooth_iterations": ("Taubin smoothing passes of the exported surface (0: none)", "", ">= 0"),
    "export.frame": ("coordinates of the exported meshes and splats: domain (the simulation's) or target (the "
                     "target's input mesh frame and units, to overlay it)", "", ""),
}
