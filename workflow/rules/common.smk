# Config validation, the cohort sheet and per-stage settings. No algorithm here.
import functools
import json
import os
import re
import shlex
import sys
from pathlib import Path

from snakemake.exceptions import WorkflowError

from dicer.config import (deep_merge, downsample_applies, for_label_volume, load_config, parse_set,
                          smoothing_reads_scan, stage_kwargs, stage_settings, workflow_config)
from dicer.errors import DicerError
from dicer.io.images import check_input_kind
from dicer.phantoms import PHANTOMS
from dicer.sheet import beside_sheet, read_sheet, scan_files, unknown_priorities, unread_settings

def _stop(message):
    """End the run on a bad config or sheet with one line, as dicer's commands end (a
    WorkflowError printed the rule file's name and line and Snakemake's traceback lines)."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(1)


# the rules call the `dicer` installed beside this Snakemake
os.environ["PATH"] = os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", "")


def _as_dicer_reads():
    """The config files Snakemake read (this workflow's, unless --replace-workflow-config, then
    --configfile's) and its --config items, read again as dicer reads them: Snakemake's YAML 1.1
    gave labels.map key 041 to label 33 and kept the last of a key given twice, without a word."""
    given = workflow.config_settings
    cli = [str(path) for path in given.configfiles or ()]
    # Snakemake replaces the workflow's own file only when a --configfile or --config is given
    replaced = given.replace_workflow_config and bool(cli or given.config)
    own = [] if replaced else [str(path) for path in workflow.configfiles
                               if os.path.abspath(path) not in map(os.path.abspath, cli)]
    return workflow_config(own + cli, dict(given.config or {}))


try:
    _read = _as_dicer_reads()
    config.clear()
    config.update(_read)
    CONFIG = load_config(settings=config, properties_used=True)
except DicerError as exc:
    _stop(str(exc) if str(exc).startswith("config") else f"config: {exc}")

# one spelling per folder: Snakemake keys its records of past runs by the path as written, so
# "results" and its absolute path would not share them (a later change would leave stale models)
RESULTS = os.path.normpath(CONFIG["workflow"]["results"])
if os.path.isabs(RESULTS) and os.path.relpath(RESULTS).split(os.sep)[0] != os.pardir:
    RESULTS = os.path.relpath(RESULTS)
if RESULTS == os.curdir:
    _stop(f"config: key 'workflow.results': {CONFIG['workflow']['results']!r} is the working folder "
          "itself; give a folder for the results (default: results)")
PHANTOM_DIR = "resources/phantoms"
# the environment every rule runs in (used with --software-deployment-method conda); its
# post-deploy script installs dicer from this checkout, found through DICER_SOURCE
CONDA_ENV = "../../environment.yml"
os.environ.update(DICER_SOURCE=str(Path(workflow.basedir).resolve()))


def patient_file(name):
    """Path pattern of one per-patient output."""
    return os.path.join(RESULTS, "{patient}", name)


def _read_patients(path):
    """The sheet's rows with their line numbers, checked (dicer.sheet)."""
    import yaml

    schema = yaml.safe_load((Path(workflow.basedir) / "workflow" / "schemas" / "patients.schema.yaml").read_text())
    try:
        return read_sheet(path, schema)
    except DicerError as exc:
        _stop(str(exc))


def _available(row, number, sheet):
    """Phantoms are made by the workflow; other images must exist, unless workflow.skip_missing."""
    image = row.get("image") or row["labels"]
    where = f"{sheet}, line {number}: patient {row['patient']!r}"
    if Path(image).parent == Path(PHANTOM_DIR):
        name = Path(image).name
        if not name.endswith(".nii.gz") or name[: -len(".nii.gz")] not in PHANTOMS:
            _stop(f"{where}: {image}: the workflow makes {PHANTOM_DIR}/<name>.nii.gz for the phantoms "
                  f"{', '.join(sorted(PHANTOMS))}; name one of them")
        return True
    other = beside_sheet(image, sheet)
    if Path(image).exists():
        try:  # a file of another kind: said here, naming the line, not in the patient's first job
            check_input_kind(image, labels=not row.get("image"))
        except DicerError as exc:
            _stop(f"{where}: {exc}")
        if other is not None:
            print(f"dicer workflow: {where}: reading {image} from the working folder, not {other} beside the sheet "
                  "(paths in the sheet are taken from the working folder)", file=sys.stderr)
        return True
    hint = f" ({other} beside the sheet exists: paths in the sheet are taken from the working folder)" if other else ""
    if not CONFIG["workflow"]["skip_missing"]:
        _stop(f"{where}: {image} not found{hint}; fix the path, or set workflow.skip_missing: true to "
              "skip such rows")
    print(f"dicer workflow: skipping patient {row['patient']}: {image} not found{hint}", file=sys.stderr)
    SKIPPED.append(f"{row['patient']} ({image}, line {number})")
    return False


SKIPPED = []  # patients left out by workflow.skip_missing, said again when the run ends


def say_skipped():
    """onsuccess/onerror: the patients left out, so a mistyped path is not lost in the run's
    first lines (the cohort table has no row for them)."""
    if SKIPPED:
        print(f"dicer workflow: {len(SKIPPED)} patient(s) skipped, their input not found: {', '.join(SKIPPED)}; "
              "fix the paths, or set workflow.skip_missing: false to stop on them", file=sys.stderr)


def stale_models():
    """Model files in a patient's results folder of a format workflow.exports no longer names:
    the workflow does not update them, so after a change of the config they describe an older
    model (dicer run, which writes its folder afresh, leaves none)."""
    from dicer.config import schema

    nameable = schema()["properties"]["workflow"]["properties"]["exports"]["items"]["enum"]
    made = set(CONFIG["workflow"]["exports"])
    return [path for patient in PATIENTS for suffix in (f".{ext}" for ext in nameable if ext not in made)
            for path in [os.path.join(RESULTS, patient, f"model{suffix}")] if os.path.exists(path)]


def say_cohort_left():
    """onerror: a cohort table of an earlier run stays where this run stopped before making it
    again (a failed patient's old row, other patients' old figures): said, not silent."""
    left = [p for p in (os.path.join(RESULTS, "cohort.html"), os.path.join(RESULTS, "cohort.tsv"))
            if os.path.exists(p)]
    if left:
        print(f"dicer workflow: {' and '.join(left)} were not made again and show the cohort as an earlier run left "
              "it (rows of failed patients and figures of older settings among them); they are made again when "
              "every patient's run finishes", file=sys.stderr)


def say_stale():
    """At the start (the main process: not each cluster job) and at the end of a run: the model
    files the workflow no longer updates."""
    stale = stale_models()
    if stale:
        shown = ", ".join(stale[:5]) + (f" and {len(stale) - 5} more" if len(stale) > 5 else "")
        print(f"dicer workflow: {shown}: not among workflow.exports ({', '.join(CONFIG['workflow']['exports'])}), so "
              "the workflow no longer updates them and they may describe an older model; delete them, or name their "
              "formats in workflow.exports again", file=sys.stderr)


SHEET = _read_patients(CONFIG["workflow"]["patients"])
PATIENTS = {row["patient"]: row for number, row in SHEET if _available(row, number, CONFIG["workflow"]["patients"])}
if SHEET and not PATIENTS:  # a run that makes nothing would end as a success
    _stop(f"{CONFIG['workflow']['patients']}: every patient was skipped, their input not found: "
          f"{', '.join(SKIPPED)}; fix the paths (taken from the working folder, not the sheet's)")


def _one_of(names):
    """A wildcard regex matching exactly these patients (none: a regex that never matches)."""
    return "|".join(re.escape(n) for n in sorted(names)) or "(?!)"


# patients with a label volume made elsewhere skip segment: rule labels makes their labels.nii.gz
LABEL_PATIENTS = {p for p, row in PATIENTS.items() if row.get("labels")}
IMAGE_PATIENTS = _one_of(set(PATIENTS) - LABEL_PATIENTS)
LABELS_PATIENTS = _one_of(LABEL_PATIENTS)


@functools.lru_cache(maxsize=None)
def patient_config(patient):
    """The workflow config with the patient's overrides applied, validated (once per patient and
    run: callers must not change the returned dict)."""
    overrides = [item.strip() for item in PATIENTS[patient].get("overrides", "").split(";") if item.strip()]
    merged = config
    for item in overrides:
        merged = deep_merge(merged, parse_set(item, source=f"patients.tsv overrides of {patient}"))
    try:
        # the materials a patient's overrides list are said of (the workflow's own once, above)
        loaded = load_config(settings=merged, properties_used=any(item.startswith("materials") for item in overrides))
    except DicerError as exc:
        raise WorkflowError(f"patient {patient}: {exc}")
    label_volume = bool(PATIENTS[patient].get("labels"))
    loaded = for_label_volume(loaded) if label_volume else loaded
    for key, why in unread_settings(overrides, loaded, label_volume):
        raise WorkflowError(f"patient {patient!r}: override {key!r} {why}, so it would change nothing: remove it")
    unknown = None if label_volume else unknown_priorities(loaded)
    if unknown:
        raise WorkflowError(f"patient {patient!r}: {unknown}")
    return loaded


def _check_overrides():
    """Every patient's overrides, validated as the sheet is read: a bad one stops the run
    naming its line of the sheet (found later, inside a rule's input function, it came with
    Snakemake's traceback)."""
    sheet = CONFIG["workflow"]["patients"]
    lines = {row["patient"]: number for number, row in SHEET}
    for patient in PATIENTS:
        try:
            patient_config(patient)
        except (WorkflowError, DicerError) as exc:
            _stop(f"{sheet}, line {lines[patient]}: {exc}")


_check_overrides()
if workflow.is_main_process:
    say_stale()


# what smooth reads of the scan's settings, which a label-volume patient's smoothing (no scan) does not
# (so a change of them re-runs no such patient; its log then has no "image_sigma is not used")
SCAN_KEYS = {"segment": ("method", "thresholds"), "image": ("crop", "allow_irregular_slices"),
             "smooth": ("fit_to_scan", "image_sigma")}


def settings(stage):
    """params: the config sections `stage` reads, as JSON; a change re-runs only that stage and later ones."""

    def of(wildcards):
        part = stage_settings(patient_config(wildcards.patient), stage)
        if stage == "smooth" and wildcards.patient in LABEL_PATIENTS:
            for section, keys in SCAN_KEYS.items():
                for key in keys:
                    part.get(section, {}).pop(key, None)
            part = {k: v for k, v in part.items() if v != {}}
        return json.dumps(part, sort_keys=True)

    return of


def phantom_size_option(wildcards):
    size = CONFIG["workflow"]["phantom_size"]
    return f"--size {size}" if size else ""


def patient_image(wildcards):
    return PATIENTS[wildcards.patient]["image"]


def input_fingerprint(path):
    """params: a patient's scan or label volume by the size and modification time of each of
    its files (a folder's files, a header's data file beside it). Snakemake compares the
    modification times of the input itself only: a slice rewritten inside a DICOM folder
    leaves the folder's own time, and a file copied in with its older time (cp -p, rsync -a,
    tar) looks older than the results; both left a stale model. Phantoms are the workflow's
    own outputs and need none."""
    import hashlib

    path = Path(path)
    if path.parent == Path(PHANTOM_DIR):
        return ""
    files = scan_files(path)
    base = path if path.is_dir() else path.parent  # a header's data file may lie elsewhere
    entries = [[os.path.relpath(f, base), f.stat().st_size, f.stat().st_mtime_ns] for f in files]
    return hashlib.sha256(json.dumps(entries).encode()).hexdigest()[:16]


def image_fingerprint(wildcards):
    return input_fingerprint(patient_image(wildcards))


def labels_fingerprint(wildcards):
    return input_fingerprint(PATIENTS[wildcards.patient]["labels"])


def patient_labels(wildcards):
    return PATIENTS[wildcards.patient]["labels"]


def fix_input(wildcards):
    """labels_ds.nii.gz; for a label-volume patient labels.nii.gz unless downsample.factor or
    voxel_size asks for coarser voxels (dicer run --labels does the same)."""
    if wildcards.patient in LABEL_PATIENTS and not downsample_applies(patient_config(wildcards.patient)):
        return patient_file("labels.nii.gz").format(patient=wildcards.patient)
    return patient_file("labels_ds.nii.gz").format(patient=wildcards.patient)


def materials_input(wildcards):
    """The materials file of a label-volume patient (written by rule labels); none otherwise."""
    if wildcards.patient in LABEL_PATIENTS:
        return [patient_file("materials.json").format(patient=wildcards.patient)]
    return []


def materials_option(wildcards, input):
    """params: --materials FILE for a label-volume patient, else nothing."""
    return " ".join(f"--materials {shlex.quote(path)}" for path in getattr(input, "materials", []))


def scan_input(wildcards):
    """The scan and its segmentation.json for a segmented patient (the smooth stage places
    the labels' faces by it, smooth.fit_to_scan, or the surface on its iso-surfaces,
    smooth.surface_from_image); none for a label-volume patient."""
    if wildcards.patient in LABEL_PATIENTS:
        return {}
    return {"image": patient_image(wildcards),
            "thresholds": patient_file("segmentation.json").format(patient=wildcards.patient)}


def scan_option(wildcards, input):
    """params: --image SCAN --thresholds segmentation.json for a segmented patient whose
    smoothing reads the scan (smooth.surface_from_image, or fit_to_scan with the labels' fit),
    else nothing."""
    if "image" not in input.keys():
        return ""
    smooth = stage_kwargs(patient_config(wildcards.patient), "smooth")
    if not smoothing_reads_scan(smooth):
        return ""
    return f"--image {shlex.quote(input.image)} --thresholds {shlex.quote(input.thresholds)}"


def labels_option(wildcards, input):
    """params: --labels labels_fixed.nii.gz where the smoothing fits the labels' staircase
    (smooth.surface_from_labels, not beside the scan's surface), else nothing."""
    smooth = stage_kwargs(patient_config(wildcards.patient), "smooth")
    beside_scan = "image" in input.keys() and smooth["surface_from_image"]
    return f"--labels {shlex.quote(input.labels)}" if smooth["surface_from_labels"] and not beside_scan else ""


def pictures(wildcards):
    """The segmentation overlay shown in the quality page (label-volume patients have none)."""
    if wildcards.patient in LABEL_PATIENTS:
        return []
    return [patient_file("segmentation.png").format(patient=wildcards.patient)]


def picture_options(wildcards, input):
    return " ".join(f"--picture {shlex.quote(path)}" for path in getattr(input, "pictures", []))


def all_outputs():
    outputs = []
    for patient in PATIENTS:
        names = [f"model.{ext}" for ext in CONFIG["workflow"]["exports"]] + ["quality.json", "report.html"]
        outputs += [os.path.join(RESULTS, patient, name) for name in names]
    if PATIENTS:
        outputs.append(os.path.join(RESULTS, "cohort.html"))
    return outputs


def patient_stages(patient):
    """The stages a patient's model goes through, as named in <results>/benchmarks/<patient>/<stage>.tsv."""
    first = ["labels"] if patient in LABEL_PATIENTS else ["segment"]
    if patient not in LABEL_PATIENTS or downsample_applies(patient_config(patient)):
        first.append("downsample")
    exports = [f"export_{ext}" for ext in CONFIG["workflow"]["exports"]]
    return first + ["fix", "mesh", "merge", "smooth"] + exports + ["quality"]


wildcard_constraints:
    patient="[A-Za-z0-9][A-Za-z0-9_.-]*",
    name="[A-Za-z_]+",
