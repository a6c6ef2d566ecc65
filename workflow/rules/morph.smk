# Stage 5: one morph experiment (paper Algorithm 1) -> results/runs/{experiment}.h5.
# A killed run resumes from its last committed frame in results/runs/{experiment}.h5.partial/.
rule morph:
    input:
        particles=lambda wc: f"results/particles/{experiment(PM, wc.experiment)['source']}_{RES}.h5",
        target=lambda wc: f"results/targets/{experiment(PM, wc.experiment)['target']}_{RES}.h5",
    output:
        "results/runs/{experiment}.h5",
    benchmark:
        "results/benchmarks/morph/{experiment}.tsv"
    script:
        "../scripts/morph.py"
