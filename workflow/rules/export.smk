# Mesh -> solver decks and viewer files; quality report per patient.


rule export:
    input:
        RESULTS + "/{patient}/mesh.vtu",
    output:
        RESULTS + "/{patient}/model.{ext}",
    params:
        settings=settings("export"),
    log:
        "logs/{patient}/export_{ext}.log",
    wildcard_constraints:
        ext="inp|vtu|out|neu|k",
    shell:
        "dicer export {input:q} -o {output:q} --settings {params.settings:q} > {log:q} 2>&1"


rule quality:
    input:
        mesh=RESULTS + "/{patient}/model.vtu",
        labels=RESULTS + "/{patient}/labels_ds.nii.gz",
    output:
        json=RESULTS + "/{patient}/quality.json",
        html=report(
            RESULTS + "/{patient}/report.html",
            caption="../report/quality.rst",
            category="Mesh quality",
            labels={"patient": "{patient}"},
        ),
    params:
        settings=settings("quality"),
    log:
        "logs/{patient}/quality.log",
    shell:
        "dicer quality {input.mesh:q} --labels {input.labels:q} -o {output.json:q} --html {output.html:q}"
        " --settings {params.settings:q} > {log:q} 2>&1"
