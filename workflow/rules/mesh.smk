# Labels -> hexahedral mesh -> merged -> smoothed (each mesh read back and checked by `dicer`).


rule mesh:
    input:
        labels=rules.fix.output.labels,
        materials=materials_input,
    output:
        patient_file("mesh.vtu"),
    params:
        settings=settings("mesh"),
        materials=materials_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("mesh"),
        runtime=runtime("mesh"),
    benchmark:
        benchmark_file("mesh"),
    log:
        log_file("mesh"),
    shell:
        "dicer mesh {input.labels:q} -o {output:q} {params.materials} --settings {params.settings:q} > {log:q} 2>&1"


rule merge:
    input:
        rules.mesh.output[0],
    output:
        mesh=patient_file("merged.vtu"),
        report=patient_file("merge.json"),
    params:
        settings=settings("merge"),
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("merge"),
        runtime=runtime("merge"),
    benchmark:
        benchmark_file("merge"),
    log:
        log_file("merge"),
    shell:
        "dicer merge {input:q} -o {output.mesh:q} --report {output.report:q}"
        " --settings {params.settings:q} > {log:q} 2>&1"


rule smooth:
    input:
        unpack(scan_input),
        mesh=rules.merge.output.mesh,
        labels=rules.fix.output.labels,
    output:
        mesh=patient_file("smoothed.vtu"),
        report=patient_file("smooth.json"),
    params:
        settings=settings("smooth"),
        scan=scan_option,
        labels=labels_option,
    conda:
        CONDA_ENV
    threads: 1
    resources:
        mem_mb=mem_mb("smooth"),
        runtime=runtime("smooth"),
    benchmark:
        benchmark_file("smooth"),
    log:
        log_file("smooth"),
    shell:
        "dicer smooth {input.mesh:q} -o {output.mesh:q} --report {output.report:q} {params.labels}"
        " {params.scan}"
        " --settings {params.settings:q} > {log:q} 2>&1"
