# Shared helpers. The merged config is turned into typed, frozen settings once (physmorph.config:
# the one validator; every experiment resolved and a memory estimate checked before any job
# runs). Rules get what they depend on as `params` (canonical JSON without the fields at their
# defaults: physmorph.config.params_json), so changing a setting reruns
# exactly the jobs that use it. Every output lives under results/{profile}/.
from physmorph.config import Settings, morph_params, params_json, particle_estimate, without_defaults
from physmorph.config import morph_memory, sampling_memory, target_memory
from physmorph.metrics import TABLE_NAMES as TABLES, FIGURE_NAMES as FIGURES
from physmorph.tradeoff import tradeoff_points

S = Settings.from_mapping(config)
R = f"results/{S.profile}"  # this profile's result tree
RES = S.sampling.tag
POINTS = tradeoff_points(S) if S.tradeoff is not None else {}


wildcard_constraints:
    shape=r"[A-Za-z][A-Za-z0-9]*",
    res=r"\d+x\d+x\d+",
    file=r"[^/]+",
    experiment=r"[A-Za-z0-9_]+",


def raw_mesh_path(shape):
    spec = S.shape(shape)
    if spec.kind != "file":
        return []
    return spec.path if spec.path is not None else f"resources/meshes/{spec.file}"


def particles_path(shape, res=RES):
    return f"{R}/particles/{shape}_{res}.h5"


def target_path(shape, res=RES, image=None):
    return f"{R}/targets/{shape}_{res}{'' if image is None else '_' + image}.h5"


def table_inputs():
    shapes = set(S.tables.shapes)
    for name in S.tables.experiments:
        exp = S.experiment(name)
        shapes.update([exp.source, exp.target])
    runs = [f"{R}/runs/{name}.h5" for name in S.tables.experiments]
    tables = [f"{R}/tables/{t}.md" for t in TABLES] if runs else []
    return [p for s in sorted(shapes) for p in (particles_path(s), target_path(s))] + runs + tables


def figure_outputs():
    return [f"{R}/figures/{f}.png" for f in FIGURES] if S.tables.experiments else []


def mb(estimate):
    return int(estimate.mb) + 1


def morph_runtime_min(n_particles, frames):
    """Minutes for a morph: ~2e-4 s per particle-frame on a CPU (measured 1.4-1.8e-4), x2 margin."""
    return int(10 + 2 * frames * n_particles * 2e-4 / 60)


def experiment_source(name):
    return S.shape(S.experiment(name).source)


def point_target(point):
    p = POINTS[point]
    exp = S.experiment(S.tradeoff.experiment)
    image = None if (p.width, p.height) == (S.target.width, S.target.height) else p.image_tag
    return target_path(exp.target, p.res_tag, image)


def point_settings(point):
    return S.point_config(POINTS[point])
