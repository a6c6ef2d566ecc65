# The speed/accuracy study: the base experiment with one resolution knob changed at a time.
from physmorph.tradeoff import point_inputs, tradeoff_points

POINTS = tradeoff_points(PM) if "tradeoff" in PM else {}


rule rasterize_target_image:
    # A target at another image size than the profile's (for the image-size knob).
    input:
        "results/meshes/{shape}.h5",
    output:
        h5="results/targets/{shape}_{res}_{img}.h5",
        png="results/previews/targets/{shape}_{res}_{img}.png",
    wildcard_constraints:
        img=r"\d+x\d+",
    params:
        sampling=lambda wc: SamplingConfig.from_tag(wc.res, PM),
        target=lambda wc: dict(PM["target"], width=int(wc.img.split("x")[0]), height=int(wc.img.split("x")[1])),
        seed=PM.get("seed", 0),
        render=PM.get("render", {}),
    script:
        "../scripts/rasterize_target_image.py"


rule tradeoff_point:
    input:
        particles=lambda wc: point_inputs(PM, POINTS[wc.point])[0],
        target=lambda wc: point_inputs(PM, POINTS[wc.point])[1],
    output:
        "results/tradeoff/runs/{point}.h5",
    wildcard_constraints:
        point=r"[A-Za-z0-9_x-]+",
    benchmark:
        "results/benchmarks/tradeoff/{point}.tsv"
    script:
        "../scripts/tradeoff_point.py"


rule make_tradeoff:
    input:
        runs=expand("results/tradeoff/runs/{point}.h5", point=list(POINTS)),
    output:
        "results/tradeoff/tradeoff.csv",
        "results/tradeoff/tradeoff.md",
        "results/tradeoff/pareto.png",
    params:
        names=list(POINTS),
    script:
        "../scripts/make_tradeoff.py"
