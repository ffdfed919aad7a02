# Smoothed mesh -> solver decks and viewer files; quality report per patient.


rule export:
    input:
        mesh=rules.smooth.output.mesh,
        materials=materials_input,
    output:
        patient_file("model.{ext}"),
    params:
        settings=settings("export"),
        materials=materials_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("export"),
        runtime=runtime("export"),
    benchmark:
        benchmark_file("export_{ext}"),
    log:
        log_file("export_{ext}"),
    wildcard_constraints:
        ext="inp|vtu|out|neu|k|msh|exo|e|feb",
    shell:
        "dicer export {input.mesh:q} -o {output:q} {params.materials} --settings {params.settings:q} > {log:q} 2>&1"


rule quality:
    input:
        mesh=rules.smooth.output.mesh,
        labels=rules.fix.output.labels,
        original=patient_file("labels.nii.gz"),
        pictures=pictures,
        materials=materials_input,
        reports=[rules.fix.output.report, rules.merge.output.report, rules.smooth.output.report],
    output:
        json=patient_file("quality.json"),
        html=report(
            patient_file("report.html"),
            caption="../report/quality.rst",
            category="Patients",
            subcategory="{patient}",
            labels={"patient": "{patient}", "figure": "quality report"},
        ),
        histogram=report(
            patient_file("jacobian.png"),
            caption="../report/jacobian.rst",
            category="Patients",
            subcategory="{patient}",
            labels={"patient": "{patient}", "figure": "scaled Jacobian"},
        ),
        model=report(
            patient_file("model.png"),
            caption="../report/model.rst",
            category="Patients",
            subcategory="{patient}",
            labels={"patient": "{patient}", "figure": "model"},
        ),
        node_classes=report(
            patient_file("node_classes.png"),
            caption="../report/node_classes.rst",
            category="Patients",
            subcategory="{patient}",
            labels={"patient": "{patient}", "figure": "node classes"},
        ),
    params:
        settings=settings("quality"),
        pictures=picture_options,
        materials=materials_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("quality"),
        runtime=runtime("quality"),
    benchmark:
        benchmark_file("quality"),
    log:
        log_file("quality"),
    shell:
        "dicer quality {input.mesh:q} --labels {input.labels:q} --original {input.original:q} -o {output.json:q}"
        " --html {output.html:q} --histogram {output.histogram:q} --model-picture {output.model:q}"
        " --node-classes {output.node_classes:q} {params.pictures} {params.materials}"
        " --stage-report {input.reports[0]:q} --stage-report {input.reports[1]:q}"
        " --stage-report {input.reports[2]:q} --settings {params.settings:q} > {log:q} 2>&1"
