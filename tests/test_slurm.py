"""The workflow through the project's SLURM profile on a real single-node SLURM.

workflow/scripts/slurm-local.sh installs (apt) and starts munged, slurmctld and slurmd on
loopback, without accounting; Snakemake's SLURM plugin submits one job per patient (the
profile's groups) and asks squeue for job states. The cohort: two small phantoms and one
scan that is not an image. Skipped, with the reason, where SLURM cannot be set up (not
root, no apt-get, a real SLURM configured on the machine) or the plugin is not installed.
"""

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from test_workflow import REPO, SNAKEMAKE, _env, _planned_jobs

SCRIPT = REPO / "workflow" / "scripts" / "slurm-local.sh"
PROFILE = REPO / "workflow" / "profiles" / "slurm"
# this test cluster has no accounting database: the plugin asks squeue (slurm-local.sh sets
# MinJobAge=300, >= 3 x the 2 s first-check delay) and guesses no account
NO_ACCOUNTING = ["--slurm-status-command", "squeue", "--slurm-init-seconds-before-status-checks", "2",
                 "--slurm-no-account"]
RUN_SECONDS = 420  # one snakemake run's limit (timeout -k 10)

pytestmark = pytest.mark.slurm


def _why_not() -> str | None:
    if os.geteuid() != 0:
        return "needs root to install and start a single-node SLURM (workflow/scripts/slurm-local.sh)"
    try:
        import snakemake_executor_plugin_slurm  # noqa: F401
    except ImportError:
        return "snakemake-executor-plugin-slurm is not installed (pip install -e '.[slurm]')"
    return None


@pytest.fixture(scope="module")
def slurm():
    """A running single-node SLURM; stopped afterwards if this fixture started it."""
    reason = _why_not()
    if reason:
        pytest.skip(f"SLURM test skipped: {reason}")
    running = subprocess.run([str(SCRIPT), "status"], capture_output=True).returncode == 0
    if not running:
        # 4 CPUs on a 2-core machine: the three patients' jobs start at once (they mostly
        # wait on Python start-up)
        proc = subprocess.run([str(SCRIPT), "start"], capture_output=True, text=True, timeout=600,
                              env={**os.environ, "DICER_SLURM_CPUS": "4"})
        if proc.returncode == 3:  # SLURM cannot be set up on this machine
            pytest.skip(f"SLURM test skipped: {proc.stderr.strip().splitlines()[-1]}")
        assert proc.returncode == 0, proc.stderr
    yield
    if not running:
        proc = subprocess.run([str(SCRIPT), "stop"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr


def _run(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = ["timeout", "-k", "10", str(RUN_SECONDS), *SNAKEMAKE, "-s", str(REPO / "Snakefile"), "-d", str(workdir),
           "--workflow-profile", str(PROFILE), *NO_ACCOUNTING, *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=RUN_SECONDS + 30)
    assert proc.returncode != 124, f"snakemake hung for {RUN_SECONDS} s:\n{proc.stderr[-3000:]}"
    return proc


def _cohort(tmp: Path) -> Path:
    (tmp / "config").mkdir(parents=True)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["workflow"]["exports"] = ["inp"]
    (tmp / "config" / "config.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    (tmp / "data").mkdir()
    for name in ("head", "long_bone"):  # small scans made beforehand: one job fewer per patient
        subprocess.run(["dicer", "phantom", name, "--size", "32", "-o", str(tmp / "data" / f"{name}.nii.gz"), "-q"],
                       check=True, env=_env(), timeout=120)
    (tmp / "data" / "broken.nii.gz").write_bytes(b"this is not a scan\n" * 20)
    (tmp / "config" / "patients.tsv").write_text(
        "patient\timage\toverrides\n"
        "head\tdata/head.nii.gz\t\n"
        "bone\tdata/long_bone.nii.gz\tdownsample.factor=2\n"
        "bad\tdata/broken.nii.gz\t\n"
    )
    return tmp


def _submitted(proc: subprocess.CompletedProcess) -> list[str]:
    """The SLURM job ids Snakemake submitted."""
    return re.findall(r"has been submitted with SLURM jobid (\d+)", proc.stdout + proc.stderr)


def test_cohort_on_slurm_with_a_bad_scan_then_the_rerun(slurm, tmp_path):
    workdir = _cohort(tmp_path)
    start = time.monotonic()
    first = _run(workdir)
    out = first.stdout + first.stderr
    assert first.returncode != 0, out[-3000:]
    # the good patients are complete, with one benchmark line per stage
    for patient in ("head", "bone"):
        folder = workdir / "results" / patient
        report = json.loads((folder / "quality.json").read_text())
        assert report["elements"] > 50 and report["inverted_elements"] == 0
        assert (folder / "model.inp").stat().st_size > 0
        for stage in ("segment", "downsample", "fix", "mesh", "merge", "smooth", "export_inp", "quality"):
            header, values = (workdir / "results" / "benchmarks" / patient / f"{stage}.tsv").read_text().splitlines()[:2]
            assert dict(zip(header.split("\t"), values.split("\t")))["s"] != "NA"
    # the bad scan failed in segment, with its one-line error shown in Snakemake's output
    assert not (workdir / "results" / "bad" / "labels.nii.gz").exists()
    errors = [line for line in (workdir / "results" / "logs" / "bad" / "segment.log").read_text().splitlines()
              if line.startswith("error:")]
    assert len(errors) == 1 and "broken.nii.gz" in errors[0]
    assert errors[0] in out
    # through SLURM, one job per patient, and the failed one once more (the profile's retries: 1)
    assert len(_submitted(first)) == 4, out[-3000:]
    assert out.count("Group job patient") >= 3 and "Error in group patient" in out
    first_seconds = time.monotonic() - start

    mtimes = {p: (workdir / "results" / p / "model.inp").stat().st_mtime_ns for p in ("head", "bone")}
    sheet = workdir / "config" / "patients.tsv"
    sheet.write_text(sheet.read_text().replace("data/broken.nii.gz", "data/head.nii.gz"))
    second = _run(workdir)
    # only the fixed patient's stages ran (Snakemake's job table at the start of the run), then
    # the cohort table, which waited for every patient (a local rule: no SLURM job)
    assert _planned_jobs(second) == {"segment": 1, "downsample": 1, "fix": 1, "mesh": 1, "merge": 1, "smooth": 1, "export": 1,
                       "quality": 1, "cohort": 1, "all": 1}
    assert second.returncode == 0, (second.stdout + second.stderr)[-3000:]
    assert json.loads((workdir / "results" / "bad" / "quality.json").read_text())["elements"] > 50
    assert len(_submitted(second)) == 1
    rows = (workdir / "results" / "cohort.tsv").read_text().splitlines()[1:]
    assert sorted(r.split("\t")[0] for r in rows) == ["bad", "bone", "head"]
    assert {p: (workdir / "results" / p / "model.inp").stat().st_mtime_ns for p in ("head", "bone")} == mtimes
    print(f"SLURM test: first run {first_seconds:.0f} s, rerun {time.monotonic() - start - first_seconds:.0f} s")
