"""dicer run estimates its peak memory from the scan's header before any stage allocates."""

from __future__ import annotations

import numpy as np
import dicer.resources as resources
from dicer.cli import main


def test_peak_estimate_grows_with_voxels_and_shrinks_with_downsampling():
    full = resources.run_peak_mb(512**3)
    # the 512^3 ball's stage processes peak at 10.5-15.6 GB (docs/benchmark.md); dicer run
    # holds about 1.25 times its largest stage (2.5 against 2.0 GB at 256^3)
    assert 1.25 * 15_644 < full < 40_000
    assert resources.run_peak_mb(512**3, 2) < full / 6  # about 1/8 of the elements
    # per-axis factors count by the voxels they leave: (2, 2, 1) as (4, 1, 1), between factors 1 and 2
    assert resources.run_peak_mb(512**3, (2, 2, 1)) == resources.run_peak_mb(512**3, (4, 1, 1))
    assert resources.run_peak_mb(512**3, 2) < resources.run_peak_mb(512**3, (2, 2, 1)) < full
    small = resources.run_peak_mb(48**3)
    assert 150 < small < 400                            # the interpreter's baseline dominates


def test_machine_memory_is_read():
    have = resources.machine_memory_mb()
    assert have is None or have > 100


def test_run_refuses_a_scan_too_big_for_the_machine(tmp_path, monkeypatch, capsys):
    labels = np.zeros((64, 64, 64), np.uint8)
    labels[16:48, 16:48, 16:48] = 1
    np.save(tmp_path / "labels.npy", labels)
    need = resources.run_peak_mb(labels.size)
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: need - 1)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "labels.npy" in err[0]
    assert f"{labels.size:,} voxels" in err[0] and "--skip-memory-check" in err[0]
    assert not out.exists() and not (tmp_path / ".out.partial").exists()


def test_the_hint_names_a_factor_that_fits(tmp_path, monkeypatch, capsys):
    labels = np.zeros((64, 64, 64), np.uint8)
    labels[8:56, 8:56, 8:56] = 1
    np.save(tmp_path / "labels.npy", labels)
    # pretend the scan is 512^3 on a 24 GB machine
    monkeypatch.setattr(resources, "scan_header", lambda path: (512**3, (1.0, 1.0, 1.0)))
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: 24_000)
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "downsample.factor: 2" in err


def test_skip_memory_check_runs_anyway(tmp_path, monkeypatch):
    labels = np.zeros((12, 12, 12), np.uint8)
    labels[3:9, 3:9, 3:9] = 1
    np.save(tmp_path / "labels.npy", labels)
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: 1)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out), "--skip-memory-check"]) == 0
    assert (out / "model.inp").exists()


def test_a_missing_input_is_named_by_the_stage_not_the_memory_check(tmp_path, capsys):
    for args in (["run", str(tmp_path / "nope.nii.gz")], ["run", "--labels", str(tmp_path / "nope.npy")]):
        assert main(args + ["-o", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and "nope." in err[0]
        assert not (tmp_path / "out").exists()
