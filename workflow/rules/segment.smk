# Image -> label volumes: phantoms for the demo cohort, segment, downsample.


rule phantom:
    output:
        PHANTOM_DIR + "/{name}.nii.gz",
    params:
        size=phantom_size_option,
    log:
        "logs/phantoms/{name}.log",
    shell:
        "dicer phantom {wildcards.name} -o {output:q} {params.size} > {log:q} 2>&1"


rule segment:
    input:
        patient_image,
    output:
        RESULTS + "/{patient}/labels.nii.gz",
    params:
        settings=settings("segment"),
    log:
        "logs/{patient}/segment.log",
    shell:
        "dicer segment {input:q} -o {output:q} --settings {params.settings:q} > {log:q} 2>&1"


rule downsample:
    input:
        RESULTS + "/{patient}/labels.nii.gz",
    output:
        RESULTS + "/{patient}/labels_ds.nii.gz",
    params:
        settings=settings("downsample"),
    log:
        "logs/{patient}/downsample.log",
    shell:
        "dicer downsample {input:q} -o {output:q} --settings {params.settings:q} > {log:q} 2>&1"
