# Image -> label volumes: phantoms for the demo cohort, segment (or labels: a label volume
# made elsewhere, mapped to materials), downsample, fix.


rule phantom:
    output:
        os.path.join(PHANTOM_DIR, "{name}.nii.gz"),
    params:
        size=phantom_size_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("phantom"),
        runtime=runtime("phantom"),
    benchmark:
        os.path.join("benchmarks", "phantoms", "{name}.tsv"),
    log:
        "logs/phantoms/{name}.log",
    shell:
        "dicer phantom {wildcards.name} -o {output:q} {params.size} > {log:q} 2>&1"


rule segment:
    input:
        patient_image,
    output:
        labels=patient_file("labels.nii.gz"),
        overlay=report(
            patient_file("segmentation.png"),
            caption="../report/segmentation.rst",
            category="Patients",
            subcategory="{patient}",
            labels={"patient": "{patient}", "figure": "segmentation"},
        ),
        info=patient_file("segmentation.json"),
    params:
        settings=settings("segment"),
        files=image_fingerprint,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("segment"),
        runtime=runtime("segment"),
    benchmark:
        benchmark_file("segment"),
    log:
        log_file("segment"),
    wildcard_constraints:
        patient=IMAGE_PATIENTS,
    shell:
        "dicer segment {input:q} -o {output.labels:q} --overlay {output.overlay:q} --info {output.info:q}"
        " --settings {params.settings:q} > {log:q} 2>&1"


rule labels:
    input:
        patient_labels,
    output:
        labels=patient_file("labels.nii.gz"),
        materials=patient_file("materials.json"),
    params:
        settings=settings("labels"),
        files=labels_fingerprint,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("labels"),
        runtime=runtime("labels"),
    benchmark:
        benchmark_file("labels"),
    log:
        log_file("labels"),
    wildcard_constraints:
        patient=LABELS_PATIENTS,
    shell:
        "dicer labels {input:q} -o {output.labels:q} --materials {output.materials:q}"
        " --settings {params.settings:q} > {log:q} 2>&1"


rule downsample:
    input:
        labels=patient_file("labels.nii.gz"),
        materials=materials_input,
    output:
        patient_file("labels_ds.nii.gz"),
    params:
        settings=settings("downsample"),
        materials=materials_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("downsample"),
        runtime=runtime("downsample"),
    benchmark:
        benchmark_file("downsample"),
    log:
        log_file("downsample"),
    shell:
        "dicer downsample {input.labels:q} -o {output:q} {params.materials} --settings {params.settings:q}"
        " > {log:q} 2>&1"


rule fix:
    input:
        labels=fix_input,
        materials=materials_input,
    output:
        labels=patient_file("labels_fixed.nii.gz"),
        report=patient_file("fix.json"),
    params:
        settings=settings("fix"),
        materials=materials_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("fix"),
        runtime=runtime("fix"),
    benchmark:
        benchmark_file("fix"),
    log:
        log_file("fix"),
    shell:
        "dicer fix {input.labels:q} -o {output.labels:q} --report {output.report:q} {params.materials}"
        " --settings {params.settings:q} > {log:q} 2>&1"
