# Stage 6: the paper's tables from the runs (CSV + Markdown + LaTeX, paper figures beside ours).
rule make_tables:
    input:
        runs=expand("results/runs/{experiment}.h5", experiment=PM["tables"].get("experiments", [])),
    output:
        expand("results/tables/{table}.{ext}", table=TABLES, ext=["csv", "md", "tex"]),
    params:
        names=PM["tables"].get("experiments", []),
    script:
        "../scripts/make_tables.py"
