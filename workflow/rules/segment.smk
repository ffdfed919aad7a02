# Image -> label volumes: phantoms for the demo cohort, segment, downsample.


rule phantom:
    output:
        os.path.join(PHANTOM_DIR, "{name}.nii.gz"),
    params:
        size=phantom_size_option,
    conda:
        CONDA_ENV
    log:
        "logs/phantoms/{name}.log",
    shell:
        "dicer phantom {wildcards.name} -o {output:q} {params.size} > {log:q} 2>&1"


rule segment:
    input:
        patient_image,
    output:
        labels=patient_file("labels.nii.gz"),
        overlay=patient_file("segmentation.png"),
        info=patient_file("segmentation.json"),
    params:
        settings=settings("segment"),
    conda:
        CONDA_ENV
    log:
        "logs/{patient}/segment.log",
    shell:
        "dicer segment {input:q} -o {output.labels:q} --overlay {output.overlay:q} --info {output.info:q}"
        " --settings {params.settings:q} > {log:q} 2>&1"


rule downsample:
    input:
        patient_file("labels.nii.gz"),
    output:
        patient_file("labels_ds.nii.gz"),
    params:
        settings=settings("downsample"),
    conda:
        CONDA_ENV
    log:
        "logs/{patient}/downsample.log",
    shell:
        "dicer downsample {input:q} -o {output:q} --settings {params.settings:q} > {log:q} 2>&1"


rule fix:
    input:
        patient_file("labels_ds.nii.gz"),
    output:
        labels=patient_file("labels_fixed.nii.gz"),
        report=patient_file("fix.json"),
    params:
        settings=settings("fix"),
    conda:
        CONDA_ENV
    log:
        "logs/{patient}/fix.log",
    shell:
        "dicer fix {input:q} -o {output.labels:q} --report {output.report:q}"
        " --settings {params.settings:q} > {log:q} 2>&1"
