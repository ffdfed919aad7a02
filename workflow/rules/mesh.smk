# Labels -> hexahedral mesh (read back and checked by `dicer` before the rule succeeds).


rule mesh:
    input:
        RESULTS + "/{patient}/labels_ds.nii.gz",
    output:
        RESULTS + "/{patient}/mesh.vtu",
    params:
        settings=settings("mesh"),
    log:
        "logs/{patient}/mesh.log",
    shell:
        "dicer mesh {input:q} -o {output:q} --settings {params.settings:q} > {log:q} 2>&1"
