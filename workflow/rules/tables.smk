# Stage 6: the paper's tables from the runs (CSV + Markdown + LaTeX, paper figures beside ours).
rule make_tables:
    input:
        runs=expand(f"{R}/runs/{{experiment}}.h5", experiment=S.tables.experiments),
        layout="config/paper_results.yaml",  # which runs each table compares, the paper's numbers
        # the full runs' exported surfaces: the convergence table's stray and surface columns
        exported=[f"{R}/meshes/{n}" for n in S.tables.experiments if n in FULL_RUNS],
    output:
        csv=[report(f"{R}/tables/{t}.csv", caption=f"../report/captions/{t}.rst", category="Tables",
                    labels={"table": t})
             for t in TABLES],
        md=expand(f"{R}/tables/{{table}}.md", table=TABLES),
        tex=expand(f"{R}/tables/{{table}}.tex", table=TABLES),
    params:
        names=list(S.tables.experiments),
        full=FULL_RUNS,
        noise=list(S.tables.noise),
        out_dir=folder_of_first_output,
    log:
        f"{R}/logs/make_tables.log",
    benchmark:
        f"{R}/benchmarks/make_tables.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../scripts/make_tables.py"


# The same tables from the main table's runs alone (`snakemake paper_main`): at the paper's scale
# the six runs take a few hours on 2 cores (each run's time: docs/paper_scale.md).
rule make_main_tables:
    input:
        runs=expand(f"{R}/runs/{{experiment}}.h5", experiment=MAIN_EXPERIMENTS),
        layout="config/paper_results.yaml",
        exported=[f"{R}/meshes/{n}" for n in MAIN_EXPERIMENTS if n in FULL_RUNS],
    output:
        md=expand(f"{R}/main_tables/{{table}}.md", table=TABLES),
        csv=expand(f"{R}/main_tables/{{table}}.csv", table=TABLES),
        tex=expand(f"{R}/main_tables/{{table}}.tex", table=TABLES),
    params:
        names=MAIN_EXPERIMENTS,
        full=FULL_RUNS,
        out_dir=folder_of_first_output,
    log:
        f"{R}/logs/make_main_tables.log",
    benchmark:
        f"{R}/benchmarks/make_main_tables.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../scripts/make_tables.py"
