# The cohort overview: one table row per patient (mesh size, quality, floating parts, volume
# change per material, seconds and peak memory per stage from the benchmark files). A light
# job: it runs where Snakemake runs, not as a cluster job.


localrules:
    cohort,


rule cohort:
    input:
        reports=expand(rules.quality.output.json, patient=PATIENTS),
        benchmarks=[benchmark_file(stage).format(patient=p) for p in PATIENTS for stage in patient_stages(p)],
    output:
        html=report(
            os.path.join(RESULTS, "cohort.html"),
            caption="../report/cohort.rst",
            category="Cohort",
            labels={"table": "cohort overview"},
        ),
        tsv=os.path.join(RESULTS, "cohort.tsv"),
    params:
        # the benchmark folder: benchmarks/<patient>/<stage>.tsv
        benchmarks=lambda wildcards, input: os.path.dirname(os.path.dirname(input.benchmarks[0])),
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=300,
        runtime=5,
    log:
        "logs/cohort.log",
    shell:
        "dicer cohort {input.reports:q} -o {output.html:q} --tsv {output.tsv:q} --benchmarks {params.benchmarks:q}"
        " > {log:q} 2>&1"
