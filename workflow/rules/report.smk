# The cohort overview: one table row per patient (mesh size, quality, floating parts, volume
# change per material, seconds and peak memory per stage from the benchmark files of the
# stages the model now goes through: an earlier run's file of a dropped stage is left out). A light
# job: it runs where Snakemake runs, not as a cluster job.


localrules:
    cohort,


rule cohort:
    input:
        reports=expand(rules.quality.output.json, patient=PATIENTS),
        # the table shows the exports' seconds: a re-export makes it again
        models=[patient_file(f"model.{ext}").format(patient=p) for p in PATIENTS for ext in CONFIG["workflow"]["exports"]],
    params:
        # read where they exist, not inputs: a deleted benchmark file would re-run its stage
        # (and, through the cohort, every patient's chain) to be made again
        benchmarks=[benchmark_file(stage).format(patient=p) for p in PATIENTS for stage in patient_stages(p)],
    output:
        html=report(
            os.path.join(RESULTS, "cohort.html"),
            caption="../report/cohort.rst",
            category="Cohort",
            labels={"table": "cohort overview"},
        ),
        tsv=os.path.join(RESULTS, "cohort.tsv"),
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=300,
        runtime=5,
    log:
        os.path.join(RESULTS, "logs", "cohort.log"),
    script:
        # dicer cohort with the paths in an argument file: a cohort's would pass a shell
        # command's 128 KB
        "../scripts/cohort.py"
