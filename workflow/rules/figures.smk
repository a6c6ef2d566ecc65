# Stage 7: the paper's figures from the runs (PNG under results/{profile}/figures/).
rule make_figures:
    input:
        runs=expand(f"{R}/runs/{{experiment}}.h5", experiment=S.tables.experiments),
        targets=[target_path(s) for s in S.tables.shapes],
        layout="config/paper_results.yaml",  # which runs each figure shows
    output:
        [report(f"{R}/figures/{f}.png", caption=f"../report/captions/{f}.rst", category="Figures",
                labels={"figure": f})
         for f in FIGURES],
    params:
        names=list(S.tables.experiments),
        shapes=list(S.tables.shapes),
        target=params_json(S.target),
        out_dir=f"{R}/figures",
    log:
        f"{R}/logs/make_figures.log",
    benchmark:
        f"{R}/benchmarks/make_figures.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    script:
        "../scripts/make_figures.py"
