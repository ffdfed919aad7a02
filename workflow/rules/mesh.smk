# Labels -> hexahedral mesh (read back and checked by `dicer` before the rule succeeds).


rule mesh:
    input:
        patient_file("labels_ds.nii.gz"),
    output:
        patient_file("mesh.vtu"),
    params:
        settings=settings("mesh"),
    conda:
        CONDA_ENV
    log:
        "logs/{patient}/mesh.log",
    shell:
        "dicer mesh {input:q} -o {output:q} --settings {params.settings:q} > {log:q} 2>&1"
