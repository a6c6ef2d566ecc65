# Shared helpers: validate the merged config once and name the files each target needs.
from physmorph.config import SamplingConfig, validate_config, experiment, shape_entry

PM = validate_config(config)
from physmorph.metrics import TABLE_NAMES as TABLES, FIGURE_NAMES as FIGURES
RES = SamplingConfig.from_config(PM).tag


wildcard_constraints:
    shape=r"[A-Za-z][A-Za-z0-9]*",
    res=r"\d+x\d+x\d+",
    file=r"[^/]+",
    experiment=r"[A-Za-z0-9_]+",


def raw_mesh_path(shape):
    spec = shape_entry(PM, shape)
    return f"resources/meshes/{spec['file']}" if spec["kind"] == "file" else []


def shape_data(shape, res=RES):
    return [f"results/particles/{shape}_{res}.h5", f"results/targets/{shape}_{res}.h5"]


def table_inputs():
    shapes = set(PM["tables"].get("shapes", []))
    for name in PM["tables"].get("experiments", []):
        exp = experiment(PM, name)
        shapes.update([exp["source"], exp["target"]])
    runs = [f"results/runs/{name}.h5" for name in PM["tables"].get("experiments", [])]
    tables = [f"results/tables/{t}.md" for t in TABLES] if runs else []
    return [p for s in sorted(shapes) for p in shape_data(s)] + runs + tables


def figure_outputs():
    return [f"results/figures/{f}.png" for f in FIGURES] if PM["tables"].get("experiments") else []
