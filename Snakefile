# dicer: per-patient hexahedral models from CT/MR scans.
#   snakemake --cores 2 --workflow-profile workflow/profiles/local
# The rules call the `dicer` command; they hold no algorithm.
from snakemake.utils import min_version

min_version("8.0")


configfile: "config/config.yaml"


# the rules call the `dicer` beside this Snakemake: common.smk puts it first on PATH
envvars:
    "PATH",


include: "workflow/rules/common.smk"
include: "workflow/rules/resources.smk"
include: "workflow/rules/segment.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/export.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        all_outputs(),
    default_target: True


onsuccess:
    say_skipped()
    say_stale()


onerror:
    say_skipped()
    say_stale()
    say_cohort_left()
