"""The Snakemake workflow on a tiny cohort: a real run, then dry runs for the rerun rules."""

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = [sys.executable, "-m", "snakemake"]


def _env():
    env = dict(os.environ)
    env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
    # the rules' `dicer` commands run this checkout's package, not another installed copy
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


def _snakemake(workdir: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    cmd = SNAKEMAKE + ["-s", str(REPO / "Snakefile"), "-d", str(workdir), "--cores", "2", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def _cohort(tmp: Path, config_extra: dict | None = None) -> Path:
    (tmp / "config").mkdir(parents=True, exist_ok=True)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["workflow"]["phantom_size"] = 48
    config["downsample"]["factor"] = 1
    for key, value in (config_extra or {}).items():
        config.setdefault(key, {}).update(value)
    (tmp / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    (tmp / "config" / "patients.tsv").write_text(
        "patient\timage\toverrides\n"
        "head\tresources/phantoms/head.nii.gz\t\n"
        "bone\tresources/phantoms/long_bone.nii.gz\tdownsample.factor=2\n"
        "absent\tno/such/scan.nii.gz\t\n"
    )
    return tmp


def _planned_jobs(proc: subprocess.CompletedProcess) -> dict[str, int]:
    """Rule -> job count from a dry run's job table."""
    text = proc.stdout + proc.stderr
    table = text[text.find("Job stats:"):]
    jobs = {}
    for line in table.splitlines()[3:]:
        match = re.match(r"^(\w+)\s+(\d+)$", line.strip())
        if not match:
            if jobs:
                break
            continue
        jobs[match.group(1)] = int(match.group(2))
    jobs.pop("total", None)
    return jobs


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    workdir = _cohort(tmp_path_factory.mktemp("cohort"))
    first = _snakemake(workdir)
    (workdir.parent / "first_run.err").write_text(first.stderr)
    return workdir


def test_every_output_per_patient(cohort):
    for patient in ("head", "bone"):
        for picture in ("segmentation.png", "jacobian.png", "model.png", "node_classes.png"):
            assert (cohort / "results" / patient / picture).read_bytes().startswith(b"\x89PNG"), (patient, picture)
        folder = cohort / "results" / patient
        for name in ("labels.nii.gz", "labels_ds.nii.gz", "labels_fixed.nii.gz", "mesh.vtu", "merged.vtu",
                     "smoothed.vtu", "model.inp", "model.vtu", "quality.json", "report.html"):
            assert (folder / name).stat().st_size > 0, name
        report = json.loads((folder / "quality.json").read_text())
        assert report["elements"] > 100
        assert report["inverted_elements"] == 0
        assert set(report["materials"]) == {"soft_tissue", "bone"}
        assert set(report["stages"]) == {"fix", "merge", "smooth"}
        for rule in ("segment", "downsample", "fix", "mesh", "merge", "smooth", "export_inp", "export_vtu", "quality"):
            assert (cohort / "results" / "logs" / patient / f"{rule}.log").exists()
    assert not (cohort / "results" / "absent").exists()


def test_a_results_folder_holds_its_own_logs_and_one_spelling_of_it_its_records(cohort):
    """Logs and benchmarks lay in the working folder, so a second results folder overwrote the
    first's (and the cohort table then showed the other run's seconds); the absolute path of the
    results folder was a folder of its own to Snakemake, with no record of past runs."""
    assert not (cohort / "logs" / "head").exists() and not (cohort / "benchmarks" / "head").exists()
    same = _snakemake(cohort, "-n", "--config", f"workflow={{results: {cohort / 'results'}}}")
    assert "Nothing to be done" in same.stdout + same.stderr
    other = _snakemake(cohort, "-n", "-p", "--config", "workflow={results: elsewhere}")
    assert "elsewhere/logs/head/mesh.log" in other.stdout and " logs/head/" not in other.stdout
    refused = _snakemake(cohort, "-n", "--config", "workflow={results: .}", check=False)
    assert refused.returncode != 0
    assert "config: key 'workflow.results': '.' is the working folder itself; give a folder for the results" in (
        refused.stdout + refused.stderr)


def test_skipped_patients_are_said_again_when_the_run_ends(cohort):
    """With workflow.skip_missing a mistyped path dropped its patient, said only in the run's
    first lines."""
    said = (cohort.parent / "first_run.err").read_text().splitlines()
    summary = ("dicer workflow: 1 patient(s) skipped, their input not found: absent (no/such/scan.nii.gz, line 4); "
               "fix the paths, or set workflow.skip_missing: false to stop on them")
    assert summary in said and said.index(summary) > len(said) - 5  # at the end, after the jobs


def test_model_files_the_exports_no_longer_name_are_said_when_the_run_ends(cohort):
    """A model.feb left from a run with feb among workflow.exports is not updated after a change
    of the config (it kept the old stiffness) and was left without a word."""
    stale = cohort / "results" / "head" / "model.feb"
    stale.write_text("<febio_spec/>\n")
    try:
        proc = _snakemake(cohort)
        assert ("dicer workflow: results/head/model.feb: not among workflow.exports (inp, vtu), so the workflow no "
                "longer updates them and they may describe an older model; delete them, or name their formats in "
                "workflow.exports again") in proc.stderr
    finally:
        stale.unlink()
    assert "not among workflow.exports" not in _snakemake(cohort).stderr


def test_patient_overrides_apply(cohort):
    from dicer.io.images import read_labels

    for patient, factor in (("head", 1), ("bone", 2)):
        fine = read_labels(cohort / "results" / patient / "labels.nii.gz")
        coarse = read_labels(cohort / "results" / patient / "labels_ds.nii.gz")
        assert coarse.spacing == pytest.approx(tuple(s * factor for s in fine.spacing))


def test_nothing_to_do_after_a_run(cohort):
    proc = _snakemake(cohort, "-n")
    assert _planned_jobs(proc) == {}


def test_changing_export_settings_reruns_only_export_and_later(cohort):
    config_path = cohort / "config" / "config.yaml"
    original = config_path.read_text()
    try:
        config = yaml.safe_load(original)
        config["export"]["element_type"] = "C3D8R"
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        jobs = _planned_jobs(_snakemake(cohort, "-n"))
        # both patients: the .inp and .vtu exports and the quality report (a 2D deck's element type
        # gives its time step plane stress or strain); nothing upstream; the cohort table
        assert jobs == {"export": 4, "quality": 2, "cohort": 1, "all": 1}

        config = yaml.safe_load(original)
        config["segment"]["closing_radius"] = 2
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        jobs = _planned_jobs(_snakemake(cohort, "-n"))
        assert jobs.get("segment") == 2 and jobs.get("mesh") == 2 and "phantom" not in jobs

        # a material's stiffness: the exports and the quality report (its explicit time step)
        # alone (the stages before read only the names)
        config = yaml.safe_load(original)
        config["materials"][1]["youngs_modulus"] = 12000.0
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        jobs = _planned_jobs(_snakemake(cohort, "-n"))
        assert jobs == {"export": 4, "quality": 2, "cohort": 1, "all": 1}

        config = yaml.safe_load(original)
        config["smooth"] = {"coefficient": 0.8}
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        jobs = _planned_jobs(_snakemake(cohort, "-n"))
        assert jobs == {"smooth": 2, "export": 4, "quality": 2, "cohort": 1, "all": 1}

        # a preset (smooth and export settings) in the config file, its keys left to it: the cohort
        # takes it; with the file's own keys at their defaults beside it, they win and it says so
        config = yaml.safe_load(original)
        config["preset"] = "explicit-dynamics"
        for section, keys in (("smooth", ("pillow", "label_samples", "label_surface_radius")),
                              ("export", ("midside_nodes",))):
            for key in keys:
                config.get(section, {}).pop(key, None)
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        jobs = _planned_jobs(_snakemake(cohort, "-n"))
        assert jobs == {"smooth": 2, "export": 4, "quality": 2, "cohort": 1, "all": 1}
        config = yaml.safe_load(original)
        config["preset"] = "explicit-dynamics"
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        proc_kept = _snakemake(cohort, "-n")
        said = [line for line in (proc_kept.stdout + proc_kept.stderr).splitlines()
                if "preset explicit-dynamics" in line]
        assert len(said) == 1 and "the configuration's own smooth.pillow: true" in said[0]
        assert "smooth.label_surface_radius: 7, export.midside_nodes: \"curved\" override it" in said[0]
    finally:
        config_path.write_text(original)


def test_bad_config_key_stops_the_run_naming_it(tmp_path):
    workdir = _cohort(tmp_path, {"segment": {"closing_radiuss": 1}})
    proc = _snakemake(workdir, "-n", check=False)
    assert proc.returncode != 0
    assert "segment.closing_radiuss" in proc.stdout + proc.stderr
    assert "config: config" not in proc.stdout + proc.stderr  # the prefix was doubled


def test_bad_override_names_the_patient(tmp_path):
    workdir = _cohort(tmp_path)
    sheet = workdir / "config" / "patients.tsv"
    sheet.write_text(sheet.read_text().replace("downsample.factor=2", "downsample.factor=zero"))
    proc = _snakemake(workdir, "-n", check=False)
    assert proc.returncode != 0
    out = proc.stdout + proc.stderr
    assert "bone" in out and "downsample.factor" in out


def test_missing_image_stops_the_run_unless_skipped(tmp_path):
    workdir = _cohort(tmp_path, {"workflow": {"skip_missing": False}})
    proc = _snakemake(workdir, "-n", check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "patients.tsv, line 4: patient 'absent': no/such/scan.nii.gz not found" in out
    assert "workflow.skip_missing" in out


def test_a_sheet_whose_every_patient_is_skipped_stops_the_run(tmp_path):
    """With workflow.skip_missing (the default) a sheet of mistyped paths made nothing and
    ended as a success (exit 0)."""
    workdir = _cohort(tmp_path)
    (workdir / "config" / "patients.tsv").write_text("patient\timage\nabsent\tno/such/scan.nii.gz\n"
                                                     "gone\tno/such/other.nii.gz\n")
    proc = _snakemake(workdir, "-n", check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert ("config/patients.tsv: every patient was skipped, their input not found: absent (no/such/scan.nii.gz, "
            "line 2), gone (no/such/other.nii.gz, line 3); fix the paths") in out


def test_a_failed_run_says_the_cohort_table_left_from_an_earlier_one_is_not_current(tmp_path):
    """A patient's failed run left results/cohort.tsv of an earlier run (its old row and the
    others' figures of older settings) in place without a word."""
    workdir = _cohort(tmp_path)
    (workdir / "broken.nii.gz").write_bytes(b"\x1f\x8b\x08\x00" + bytes(40))  # a truncated gzip
    (workdir / "config" / "patients.tsv").write_text("patient\timage\nbroken\tbroken.nii.gz\n")
    (workdir / "results").mkdir()
    for name in ("cohort.html", "cohort.tsv"):
        (workdir / "results" / name).write_text("an earlier run's\n")
    proc = _snakemake(workdir, check=False)
    assert proc.returncode != 0
    assert ("dicer workflow: results/cohort.html and results/cohort.tsv were not made again and show the cohort as "
            "an earlier run left it") in proc.stderr


def test_sheet_with_a_byte_order_mark_and_a_bad_column(tmp_path):
    workdir = _cohort(tmp_path)
    sheet = workdir / "config" / "patients.tsv"
    sheet.write_bytes(b"\xef\xbb\xbf" + sheet.read_bytes())
    assert _snakemake(workdir, "-n", check=False).returncode == 0
    sheet.write_text(sheet.read_text(encoding="utf-8-sig").replace("patient\timage", "patient\tscan"))
    proc = _snakemake(workdir, "-n", check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "line 1: unknown column 'scan'" in out


@pytest.mark.skipif(shutil.which("snakemake") is None and not (Path(sys.executable).parent / "snakemake").exists(),
                    reason="snakemake not installed")
def test_lint_is_clean():
    proc = subprocess.run(SNAKEMAKE + ["-s", str(REPO / "Snakefile"), "-d", str(REPO), "--lint"],
                          capture_output=True, text=True, env=_env(), timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]


def test_labels_column_meshes_a_label_volume(tmp_path):
    """A cohort row with a labels file skips segment (and downsample at factor 1)."""
    from test_label_input import CONFIG, affine, seven_labels, write_nifti

    workdir = _cohort(tmp_path, {"labels": CONFIG["labels"]})
    (workdir / "data").mkdir()
    write_nifti(workdir / "data" / "aseg.nii.gz", seven_labels())
    (workdir / "config" / "patients.tsv").write_text(
        "patient\timage\tlabels\toverrides\n"
        "brain\t\tdata/aseg.nii.gz\t\n"
        "coarse\t\tdata/aseg.nii.gz\tdownsample.factor=2\n"
    )
    _snakemake(workdir)
    brain = workdir / "results" / "brain"
    assert affine(brain / "labels.nii.gz") == affine(workdir / "data" / "aseg.nii.gz")
    assert not (brain / "labels_ds.nii.gz").exists() and not (brain / "segmentation.png").exists()
    assert (workdir / "results" / "coarse" / "labels_ds.nii.gz").exists()
    deck = (brain / "model.inp").read_text()
    assert re.findall(r"^\*ELEMENT, TYPE=C3D8, ELSET=(\w+)$", deck, flags=re.M) == [
        "white_matter", "grey_matter", "label_4", "cerebellum"]
    report = json.loads((brain / "quality.json").read_text())
    assert set(report["materials"]) == {"white_matter", "grey_matter", "label_4", "cerebellum"}
    assert _planned_jobs(_snakemake(workdir, "-n")) == {}
    # a stiffness study re-runs the exports and the quality report alone (the labels stage wrote
    # the properties into materials.json, and every stage after it ran again), and the deck
    # takes the new value
    config_path = workdir / "config" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["materials"].append({"name": "cerebellum", "youngs_modulus": 0.002, "poissons_ratio": 0.49})
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    _snakemake(workdir)
    config["materials"][-1]["youngs_modulus"] = 4321.5
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    assert _planned_jobs(_snakemake(workdir, "-n")) == {"export": 4, "quality": 2, "cohort": 1, "all": 1}
    _snakemake(workdir)
    listed = json.loads((brain / "materials.json").read_text())["materials"]
    assert listed == [{"name": n} for n in ("white_matter", "grey_matter", "label_4", "cerebellum")]
    deck = (brain / "model.inp").read_text()
    block = deck[deck.index("*MATERIAL, NAME=cerebellum"):]
    assert block.split("*ELASTIC\n", 1)[1].startswith("4321.5,")
    # the scan's smoothing settings: a label volume's smoothing reads no scan, so nothing re-runs
    config.setdefault("smooth", {}).update({"image_sigma": 0.7, "fit_to_scan": False})
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    assert _planned_jobs(_snakemake(workdir, "-n")) == {}


def test_the_scan_goes_to_smooth_where_its_settings_read_it(tmp_path):
    """A segmented patient's smooth rule is given the scan (the labels' faces placed by it, the
    default), also with label_samples: relaxed (the staircase relaxed through the faces' places);
    with smooth.fit_to_scan: false it is not."""
    workdir = _cohort(tmp_path)
    (workdir / "config" / "patients.tsv").write_text(
        "patient\timage\toverrides\n"
        "head\tresources/phantoms/head.nii.gz\t\n"
        "relaxed\tresources/phantoms/head.nii.gz\tsmooth.label_samples=relaxed\n"
        "off\tresources/phantoms/head.nii.gz\tsmooth.fit_to_scan=false\n"
    )
    text = _snakemake(workdir, "-n", "-p").stdout
    smooth = {m.group(1): m.group(0) for m in re.finditer(r"dicer smooth \S*results/(\w+)/merged\.vtu.*", text)}
    assert set(smooth) == {"head", "relaxed", "off"}
    for patient, given in (("head", True), ("relaxed", True), ("off", False)):
        assert ("--image" in smooth[patient]) is given, smooth[patient]
        assert "--labels" in smooth[patient]


def test_the_workflow_reads_its_config_files_as_dicer_does(tmp_path):
    """Snakemake reads config files as YAML 1.1: labels.map key 041 went to label 33 (the model
    then differed from dicer run's with the same file, exit 0), a section given twice kept its
    last (a pasted `smooth: {pillow: true}` dropped smooth.coefficient), and --config's nested
    values came as text ("0.5" refused)."""
    from test_label_input import seven_labels, write_nifti

    workdir = _cohort(tmp_path)
    (workdir / "data").mkdir()
    labels = seven_labels()
    labels[labels == 4] = 41
    write_nifti(workdir / "data" / "aseg.nii.gz", labels)
    (workdir / "config" / "patients.tsv").write_text("patient\timage\tlabels\nbrain\t\tdata/aseg.nii.gz\n")
    (workdir / "extra.yaml").write_text("labels:\n  map: {041: bone, 2: soft_tissue, 3: soft_tissue}\n"
                                         "  drop: [7, 8, 98, 99]\n")
    files = [str(workdir / "config" / "config.yaml"), str(workdir / "extra.yaml")]
    proc = _snakemake(workdir, "-n", "-p", "--configfile", *files, "--config", "smooth={coefficient: 0.5}")
    out = proc.stdout + proc.stderr
    commands = [shlex.split(line.partition("Shell command: ")[2]) for line in out.splitlines()
                if line.startswith("Shell command: dicer ")]
    settings = [json.loads(args[args.index("--settings") + 1]) for args in commands if "--settings" in args]
    labels_settings = next(s for s in settings if "labels" in s)
    assert labels_settings["labels"]["map"] == {"2": "soft_tissue", "3": "soft_tissue", "41": "bone"}
    assert next(s for s in settings if "smooth" in s)["smooth"]["coefficient"] == 0.5
    # --replace-workflow-config alone replaces nothing (Snakemake's rule): the file's 0.7 holds
    config_path = workdir / "config" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["smooth"]["coefficient"] = 0.7
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    out = _snakemake(workdir, "-n", "-p", "--replace-workflow-config").stdout
    smooth = next(json.loads(args[args.index("--settings") + 1]) for args in (
        shlex.split(line.partition("Shell command: ")[2]) for line in out.splitlines()
        if line.startswith("Shell command: dicer smooth")))
    assert smooth["smooth"]["coefficient"] == 0.7
    (workdir / "extra.yaml").write_text("smooth:\n  coefficient: 0.6\nsmooth:\n  pillow: true\n")
    proc = _snakemake(workdir, "-n", "--configfile", *files, check=False)
    assert proc.returncode != 0
    assert f"{files[1]}: key 'smooth' is given twice (lines 1 and 3) in one section; keep one" in \
        proc.stdout + proc.stderr


def test_an_override_no_stage_of_the_patient_reads_stops_the_run(tmp_path):
    """segment.keep=largest on a label volume's row (not downsampled) dropped no floating part,
    and was accepted without a word."""
    from test_label_input import seven_labels, write_nifti

    workdir = _cohort(tmp_path)
    (workdir / "data").mkdir()
    write_nifti(workdir / "data" / "aseg.nii.gz", seven_labels())
    sheet = workdir / "config" / "patients.tsv"
    sheet.write_text("patient\timage\tlabels\toverrides\nbrain\t\tdata/aseg.nii.gz\tsegment.keep=largest\n")
    proc = _snakemake(workdir, "-n", check=False)
    assert proc.returncode != 0
    assert ("config/patients.tsv, line 2: patient 'brain': override 'segment.keep' acts when the labels are "
            "downsampled, and these are not (downsample.factor 1, no downsample.voxel_size), so it would change "
            "nothing: remove it") in proc.stdout + proc.stderr
    sheet.write_text(sheet.read_text().replace("segment.keep=largest", "downsample.factor=2"))
    assert _snakemake(workdir, "-n", check=False).returncode == 0


def test_row_with_image_and_labels_is_refused(tmp_path):
    workdir = _cohort(tmp_path)
    (workdir / "config" / "patients.tsv").write_text(
        "patient\timage\tlabels\toverrides\nboth\tresources/phantoms/head.nii.gz\tx.nii.gz\t\n")
    proc = _snakemake(workdir, "-n", check=False)
    assert proc.returncode != 0
    assert "give either an image or a labels file" in proc.stdout + proc.stderr


def test_workflow_heading_equals_the_stage_commands(cohort, tmp_path):
    # the workflow's export rule gets only the export sections; the heading depends on
    # nothing else, so exporting the same mesh by hand gives the same heading
    folder = cohort / "results" / "head"
    again = tmp_path / "again.inp"
    proc = subprocess.run(["dicer", "export", str(folder / "smoothed.vtu"), "-o", str(again), "-q",
                           "--config", str(cohort / "config" / "config.yaml")],
                          capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr
    head = (folder / "model.inp").read_text().split("*NODE")[0]
    assert head == again.read_text().split("*NODE")[0] and "mesh sha256 " in head


def test_model_heading_is_the_same_from_the_workflow_dicer_run_and_the_stage(cohort, tmp_path):
    # one settings path. The workflow (export sections as --settings JSON), dicer run
    # (the whole config) and the stage command (--config) all reach export_mesh through
    # dicer.config.stage_kwargs, so the same settings give the same heading, byte for byte
    from dicer.config import load_config
    from dicer.export import settings_hash

    config = cohort / "config" / "config.yaml"
    image = cohort / "resources" / "phantoms" / "head.nii.gz"
    run = subprocess.run(["dicer", "run", str(image), "-o", str(tmp_path / "run"), "-q", "--config", str(config)],
                         capture_output=True, text=True, env=_env(), timeout=600)
    assert run.returncode == 0, run.stderr
    stage = tmp_path / "stage.inp"
    proc = subprocess.run(["dicer", "export", str(tmp_path / "run" / "smoothed.vtu"), "-o", str(stage), "-q",
                           "--config", str(config)], capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr
    heads = {name: path.read_text().split("*NODE")[0] for name, path in (
        ("workflow", cohort / "results" / "head" / "model.inp"), ("run", tmp_path / "run" / "model.inp"),
        ("stage", stage))}
    assert heads["workflow"] == heads["run"] == heads["stage"], heads
    # the same smoothed mesh (its checksum is in the heading) and the settings' hash
    assert (cohort / "results" / "head" / "smoothed.vtu").read_bytes() == (tmp_path / "run" / "smoothed.vtu").read_bytes()
    assert f"config sha256/16 {settings_hash(load_config(config))}" in heads["workflow"]
    # and every file both make, the report with its pictures among them
    both = sorted({p.name for p in (cohort / "results" / "head").iterdir()} & {p.name for p in (tmp_path / "run").iterdir()})
    assert "report.html" in both and len(both) >= 15
    for name in both:
        assert (cohort / "results" / "head" / name).read_bytes() == (tmp_path / "run" / name).read_bytes(), name


def _requested(proc: subprocess.CompletedProcess) -> dict[tuple[str, str], int]:
    """(patient, stage) -> mem_mb from a dry run's job listing."""
    requests = {}
    for block in re.split(r"\n(?=\[.*\]\n\s*rule \w+:)", proc.stdout + proc.stderr):
        rule = re.search(r"rule (\w+):", block)
        wildcards = re.search(r"wildcards: (.*)", block)
        mem = re.search(r"resources: .*?\bmem_mb=(\d+)", block)
        if not (rule and wildcards and mem):
            continue
        values = dict(item.split("=", 1) for item in wildcards.group(1).split(", "))
        stage = rule.group(1) + (f"_{values['ext']}" if "ext" in values else "")
        requests[values.get("patient", values.get("name")), stage] = int(mem.group(1))
    return requests


def test_benchmarks_and_resources_per_stage(cohort):
    """Each stage leaves a benchmark line per patient; the rules ask for the formula's memory
    (dicer.resources.estimate from the scan's and mesh's headers), which covers Snakemake's
    measured peak. (Its samples, about once a second, miss most of a 1 s stage's peak: the
    2x bound is checked on exact peaks in test_resources.py.)"""
    from dicer.resources import estimate, mesh_elements, scan_voxels

    requests = _requested(_snakemake(cohort, "-n", "--forceall"))
    stages = ("segment", "downsample", "fix", "mesh", "merge", "smooth", "export_inp", "export_vtu", "quality")
    for patient, factor in (("head", 1), ("bone", 2)):
        voxels = scan_voxels(cohort / "resources" / "phantoms" / f"{'head' if patient == 'head' else 'long_bone'}.nii.gz")
        coarse = voxels // factor // factor // factor  # the downsampled grid, from the scan's header and the factor
        elements = mesh_elements(cohort / "results" / patient / "mesh.vtu")
        for stage in stages:
            header, values = (cohort / "results" / "benchmarks" / patient / f"{stage}.tsv").read_text().splitlines()[:2]
            bench = dict(zip(header.split("\t"), values.split("\t")))
            assert float(bench["s"]) > 0
            # both patients are segmented scans: smooth reads the scan too
            assert requests[patient, stage] == estimate(stage, voxels, coarse, elements, scan=True)[0], (patient, stage)
            assert bench["max_rss"] == "NA" or float(bench["max_rss"]) <= requests[patient, stage], (patient, stage)


def test_exports_of_order_2_ask_for_the_quadratic_mesh(cohort):
    """export.order 2: the export rules ask by the _order2 rows (a quadratic deck holds two to
    three times an order-1 export's memory); the other stages as before."""
    from dicer.resources import estimate, mesh_elements, scan_voxels

    linear = _requested(_snakemake(cohort, "-n", "--forceall"))
    quadratic = _requested(_snakemake(cohort, "-n", "--forceall", "--config", "export={order: 2}"))
    voxels = scan_voxels(cohort / "resources" / "phantoms" / "head.nii.gz")
    elements = mesh_elements(cohort / "results" / "head" / "mesh.vtu")
    for stage in ("export_inp", "export_vtu"):
        assert quadratic["head", stage] == estimate(stage, voxels, voxels, elements, scan=True, order=2)[0]
        assert quadratic["head", stage] > 1.3 * linear["head", stage]  # a small phantom: the baseline counts
    assert quadratic["head", "smooth"] == linear["head", "smooth"]


def test_the_cohort_table_leaves_out_a_stage_the_model_no_longer_goes_through(cohort):
    """An earlier run's benchmark file of a stage since dropped (say downsample, after its
    override went) showed in the table as if the model went through it."""
    stale = cohort / "results" / "benchmarks" / "head" / "export_feb.tsv"
    stale.write_text("s\tmax_rss\n7.5\t100\n")
    try:
        _snakemake(cohort, "--forcerun", "cohort")
        header = (cohort / "results" / "cohort.tsv").read_text().splitlines()[0].split("\t")
        assert "seconds:export_feb" not in header and "seconds:export_inp" in header and "seconds:mesh" in header
        arguments = (cohort / "results" / "logs" / "cohort.args").read_text().splitlines()
        assert arguments[:2] == ["results/head/quality.json", "results/bone/quality.json"]
        assert "results/benchmarks/head/mesh.tsv" in arguments and "results/benchmarks/head/export_feb.tsv" not in arguments
    finally:
        stale.unlink()


def _embedded(text: str) -> dict[str, list[bytes]]:
    """The files embedded in a page as data URIs: file name (or mime type) -> decoded contents."""
    import base64

    files: dict[str, list[bytes]] = {}
    for match in re.finditer(r"data:([\w/+.-]+)((?:;[\w-]+=[^;,\"']*)*);base64,([A-Za-z0-9+/=]+)", text):
        name = re.search(r";filename=([^;]+)", match.group(2))
        files.setdefault(name.group(1) if name else match.group(1), []).append(base64.b64decode(match.group(3)))
    return files


def _images_resolve(page: str) -> list[str]:
    """Every <img> source of an HTML page; each must be an embedded PNG (relative links break
    inside snakemake --report, which shows a page from a data URI)."""
    sources = re.findall(r"<img[^>]*\ssrc=['\"]([^'\"]+)['\"]", page)
    for src in sources:
        assert src.startswith("data:image/png;base64,"), src[:80]
        assert list(_embedded(src).values())[0][0].startswith(b"\x89PNG\r\n\x1a\n")
    return sources


_IMAGE_CHECK = """<script>window.addEventListener('load', function () {
  var imgs = Array.from(document.images);
  var shown = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; });
  document.body.setAttribute('data-images', imgs.length + '/' + shown.length);
});</script>"""


def _chromium(path: Path, budget_ms: int = 5000) -> str:
    """The DOM of a page after headless Chromium loaded it (scripts run)."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    proc = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", f"--virtual-time-budget={budget_ms}",
                           "--dump-dom", path.as_uri()], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_snakemake_report_shows_the_cohort_table_and_every_picture(cohort, tmp_path):
    """snakemake --report: the cohort table and, per patient, the quality page and its pictures
    (segmentation, scaled Jacobian, model, node classes), each embedded, every <img> resolving."""
    _snakemake(cohort, "--report", str(tmp_path / "report.html"))
    text = (tmp_path / "report.html").read_text()
    files = _embedded(text)
    for name, count in (("cohort.html", 1), ("report.html", 2), ("segmentation.png", 2), ("jacobian.png", 2),
                        ("model.png", 2), ("node_classes.png", 2)):
        assert len(files.get(name, [])) == count, (name, sorted(files))
    for name in ("segmentation.png", "jacobian.png", "model.png", "node_classes.png"):
        assert all(png.startswith(b"\x89PNG\r\n\x1a\n") for png in files[name])
    cohort_page = files["cohort.html"][0].decode()
    assert "<h1>Cohort overview</h1>" in cohort_page
    for patient in ("head", "bone"):
        assert f"<td>{patient}</td>" in cohort_page
    table = (cohort / "results" / "cohort.tsv").read_text().splitlines()
    header = table[0].split("\t")
    rows = {line.split("\t")[0]: dict(zip(header, line.split("\t"))) for line in table[1:]}
    assert set(rows) == {"head", "bone"}
    for patient, row in rows.items():
        report = json.loads((cohort / "results" / patient / "quality.json").read_text())
        assert int(row["elements"]) == report["elements"] and int(row["parts"]) == report["parts"]["model"]["parts"]
        assert float(row["min_scaled_jacobian"]) == report["scaled_jacobian"]["min"]
        bone = report["materials"]["bone"]
        assert float(row["original_volume_change_percent:bone"]) == bone["original_volume_change_percent"]
        for stage in ("segment", "fix", "mesh", "quality"):
            assert float(row[f"seconds:{stage}"]) > 0
    # the bone patient is downsampled by 2: its volume against the original differs from that
    # against the downsampled labels; the head (factor 1) differs only by the fixes
    assert rows["bone"]["original_volume_change_percent:bone"] != rows["bone"]["volume_change_percent:bone"]
    for page in files["report.html"]:
        assert len(_images_resolve(page.decode())) == 4  # segmentation, histogram, model, node classes
        assert "<h2>Floating parts</h2>" in page.decode() and "<h2>Volume</h2>" in page.decode()
    if not (shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")):
        pytest.skip("no Chromium here (apt-get install chromium): the report's files were checked by parsing only")
    # in the browser: the report's app shows its categories, and every embedded page its pictures
    dom = _chromium(tmp_path / "report.html", 15000)
    assert ">Cohort<" in dom and ">Patients<" in dom
    for i, page in enumerate(files["report.html"] + files["cohort.html"]):
        path = tmp_path / f"page{i}.html"
        path.write_text(page.decode().replace("</body>", _IMAGE_CHECK + "</body>"))
        shown = re.search(r'data-images="(\d+)/(\d+)"', _chromium(path))
        expected = 0 if i == len(files["report.html"]) else 4
        assert shown and shown.group(1) == shown.group(2) == str(expected), (i, shown and shown.group(0))


def test_pictures_are_the_same_on_a_rerun(cohort, tmp_path):
    folder = cohort / "results" / "head"
    before = {n: (folder / n).read_bytes() for n in ("jacobian.png", "model.png", "node_classes.png", "report.html")}
    _snakemake(cohort, "--forcerun", "quality", "--allowed-rules", "quality", "cohort")
    for name, data in before.items():
        assert (folder / name).read_bytes() == data, name


def test_bad_override_stops_the_run_naming_the_sheet_line_without_traceback(tmp_path):
    workdir = _cohort(tmp_path)
    sheet = workdir / "config" / "patients.tsv"
    sheet.write_text(sheet.read_text().replace("downsample.factor=2", "fix.colour=1"))
    proc = _snakemake(workdir, "-n", check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "patients.tsv, line 3: patient bone: config: unknown key 'fix.colour'" in out
    assert "Traceback" not in out and "InputFunctionException" not in out
    # one line, as dicer's commands end (Snakemake's WorkflowError added the rule file's lines)
    said = [line for line in proc.stderr.splitlines() if "fix.colour" in line]
    assert len(said) == 1 and said[0].startswith("error: config/patients.tsv, line 3: patient bone:")
    assert "common.smk" not in out


def test_a_rows_file_of_another_kind_stops_the_run_naming_the_sheet_line(tmp_path):
    """A text file as the image, or a folder as the label volume, was found inside the patient's
    first job, named by its path alone."""
    workdir = _cohort(tmp_path)
    (workdir / "notes.txt").write_text("not a scan\n")
    (workdir / "seg").mkdir()
    for column, path, said in (("image", "notes.txt", "notes.txt: unknown image format '.txt'; supported inputs"),
                               ("labels", "seg", "seg: label volumes must be one of .nii, .nii.gz")):
        (workdir / "config" / "patients.tsv").write_text(f"patient\t{column}\toverrides\np1\t{path}\t\n")
        proc = _snakemake(workdir, "-n", check=False)
        out = proc.stdout + proc.stderr
        assert proc.returncode != 0
        assert f"patients.tsv, line 2: patient 'p1': {said}" in out
        assert "Traceback" not in out


def test_a_cropped_patient_pulled_onto_its_scan_matches_dicer_run(tmp_path):
    """The smooth rule was given the smooth section only: the pull read the uncropped scan
    against the cropped mesh (nodes up to 7.6 mm from dicer run's, exit 0)."""
    workdir = _cohort(tmp_path)
    sets = ["image.crop={unit: voxels, min: [6, 6, 4], max: [34, 40, 28]}", "smooth.surface_from_image=true"]
    (workdir / "config" / "patients.tsv").write_text(
        f"patient\timage\toverrides\ncut\tresources/phantoms/head.nii.gz\t{';'.join(sets)}\n")
    _snakemake(workdir, "results/cut/smoothed.vtu")
    args = [sys.executable, "-m", "dicer", "run", str(workdir / "resources" / "phantoms" / "head.nii.gz"), "-o",
            str(tmp_path / "run"), "--config", str(workdir / "config" / "config.yaml"), "-q"]
    for item in sets:
        args += ["--set", item]
    subprocess.run(args, check=True, env=_env(), timeout=600)
    made = (workdir / "results" / "cut" / "smoothed.vtu").read_bytes()
    assert made == (tmp_path / "run" / "smoothed.vtu").read_bytes()


def test_deleted_benchmarks_rerun_nothing_and_a_rewritten_input_reruns_its_patient(cohort):
    """Deleting benchmarks/ made the next change re-run every patient's chain (the cohort took the
    files as inputs); a scan rewritten with an older modification time (cp -p, rsync -a) or a
    file changed inside a scan folder left a stale model (Snakemake compares the input's own
    time only)."""
    saved = cohort.parent / (cohort.name + "_benchmarks")
    shutil.copytree(cohort / "results" / "benchmarks", saved)
    try:
        shutil.rmtree(cohort / "results" / "benchmarks")
        assert _planned_jobs(_snakemake(cohort, "-n")) == {}
        # and a change of the exports re-runs them alone, as with the files there
        test_changing_export_settings_reruns_only_export_and_later(cohort)
    finally:
        shutil.rmtree(cohort / "results" / "benchmarks", ignore_errors=True)
        shutil.copytree(saved, cohort / "results" / "benchmarks")
        shutil.rmtree(saved)
    # a label patient whose volume is replaced by one of the same name with an older time
    work = cohort.parent / (cohort.name + "_labels")
    shutil.copytree(cohort / "config", work / "config")
    import numpy as np

    from dicer.image import Volume
    from dicer.io.images import write_image

    labels = np.zeros((12, 12, 12), np.uint8)
    labels[2:10, 2:10, 2:10] = 1
    scans = work / "scans"
    scans.mkdir()
    write_image(Volume(labels, (1.0, 1.0, 1.0)), scans / "cube.nii.gz")
    (work / "config" / "patients.tsv").write_text("patient\tlabels\toverrides\ncube\tscans/cube.nii.gz\t\n")
    _snakemake(work)
    assert _planned_jobs(_snakemake(work, "-n")) == {}
    # the scan's settings that smooth reads for a segmented patient: nothing to do for a label volume
    config = yaml.safe_load((work / "config" / "config.yaml").read_text())
    config["segment"].update(method="manual", thresholds=[-200, 300])
    config["image"]["crop"] = {"unit": "voxels", "min": [0, 0, 0], "max": [12, 12, 12]}
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    assert _planned_jobs(_snakemake(work, "-n")) == {"labels": 1, "fix": 1, "mesh": 1, "merge": 1, "smooth": 1,
                                                     "export": 2, "quality": 1, "cohort": 1, "all": 1}
    config["image"]["crop"] = None  # the crop is the labels stage's; the segment keys read by smooth alone
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    assert _planned_jobs(_snakemake(work, "-n")) == {}
    old = (scans / "cube.nii.gz").stat()
    labels[2:10, 2:10, 2:6] = 0
    write_image(Volume(labels, (1.0, 1.0, 1.0)), scans / "cube.nii.gz")
    os.utime(scans / "cube.nii.gz", ns=(old.st_atime_ns, old.st_mtime_ns - 10**9))  # older than before
    jobs = _planned_jobs(_snakemake(work, "-n"))
    assert jobs.get("labels") == 1 and jobs.get("mesh") == 1 and jobs.get("export") == 2
