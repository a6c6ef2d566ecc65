# Stage 7: the paper's figures from the runs (PNG under results/figures/).
rule make_figures:
    input:
        runs=expand("results/runs/{experiment}.h5", experiment=PM["tables"].get("experiments", [])),
        targets=[f"results/targets/{s}_{RES}.h5" for s in PM["tables"].get("shapes", [])],
    output:
        expand("results/figures/{figure}.png", figure=FIGURES),
    params:
        names=PM["tables"].get("experiments", []),
        shapes=PM["tables"].get("shapes", []),
    script:
        "../scripts/make_figures.py"
