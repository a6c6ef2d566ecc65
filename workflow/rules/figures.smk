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
        out_dir=folder_of_first_output,
    log:
        f"{R}/logs/make_figures.log",
    benchmark:
        f"{R}/benchmarks/make_figures.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../scripts/make_figures.py"


# The main table's figures from its six runs alone (`snakemake paper_main`), results/{profile}/main_figures/.
rule make_main_figures:
    input:
        runs=expand(f"{R}/runs/{{experiment}}.h5", experiment=MAIN_EXPERIMENTS),
        targets=[target_path(s) for s in MAIN_TARGETS],
        layout="config/paper_results.yaml",
    output:
        [report(f"{R}/main_figures/{f}.png", caption=f"../report/captions/{f}.rst", category="Main table",
                labels={"figure": f})
         for f in MAIN_FIGURES],
    params:
        names=MAIN_EXPERIMENTS,
        shapes=MAIN_TARGETS,
        target=params_json(S.target),
        out_dir=folder_of_first_output,
        figures=list(MAIN_FIGURES),
    log:
        f"{R}/logs/make_main_figures.log",
    benchmark:
        f"{R}/benchmarks/make_main_figures.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    conda:
        CONDA_ENV
    script:
        "../scripts/make_figures.py"
