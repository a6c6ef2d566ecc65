# Stage 8: the profile's results page, results/{profile}/results.md, from its tables and figures
# (physmorph.reports.userdocs; docs/results.md is the default profile's, `python -m physmorph.reports.userdocs results`).
rule results_doc:
    input:
        tables=expand(f"{R}/tables/{{table}}.csv", table=TABLES),
        figures=figure_outputs(),
    output:
        f"{R}/results.md",
    params:
        tables_dir=folder_of_input("tables"),
        figures_dir=folder_of_input("figures"),
        profile=S.profile,
    log:
        f"{R}/logs/results_doc.log",
    benchmark:
        f"{R}/benchmarks/results_doc.tsv"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=5,
    conda:
        CONDA_ENV
    script:
        "../scripts/results_doc.py"
