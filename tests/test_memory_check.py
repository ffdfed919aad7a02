"""dicer run estimates its peak memory from the scan's header before any stage allocates."""

from __future__ import annotations

import numpy as np
import pytest
import dicer.resources as resources
from dicer.cli import main


def test_peak_estimate_grows_with_voxels_and_elements_and_shrinks_with_downsampling():
    # before any stage: the stages that read the scan (the 512^3 CT's segment peaks near 3 GB)
    scan = resources.run_peak_mb(512**3)
    assert 2_000 < scan < 5_000
    # with the mesh's size: dicer run on the 512^3 CT (51.2 M elements) measured 17.7 GB
    full = resources.run_peak_mb(512**3, elements=51_200_000)
    assert 17.7 * 1024 < full < 1.1 * 17.7 * 1024
    assert resources.run_peak_mb(512**3, 2, elements=51_200_000 // 8) < full / 5  # a factor 2 leaves 1/8
    # per-axis factors count by the voxels they leave: (2, 2, 1) as (4, 1, 1), between factors 1 and 2
    assert resources.voxel_reduction((2, 2, 1)) == resources.voxel_reduction((4, 1, 1)) == 4
    assert resources.voxel_reduction(2) == 8 and resources.voxel_reduction(1) == 1
    assert resources.run_peak_mb(512**3, (2, 2, 1)) == resources.run_peak_mb(512**3, (4, 1, 1)) <= scan
    small = resources.run_peak_mb(48**3, elements=48**3 // 2)
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


def test_the_hint_names_a_factor_that_fits(tmp_path, monkeypatch):
    from dicer.cli import _check_memory
    from dicer.config import default_config
    from dicer.errors import DicerError

    # a 512^3 scan whose labels fill the box (134 M elements) on a 24 GB machine
    monkeypatch.setattr(resources, "scan_header", lambda path: (512**3, (1.0, 1.0, 1.0)))
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: 24_000)
    _check_memory("scan.nii.gz", default_config())                  # its segment, downsample and fix fit
    with pytest.raises(DicerError) as err:
        _check_memory("scan.nii.gz", default_config(), elements=512**3)
    assert "134,217,728 elements" in str(err.value) and "downsample.factor: 2" in str(err.value)
    _check_memory("scan.nii.gz", default_config(), elements=51_200_000)  # the CT phantom's 38 % fits


def test_run_refuses_a_mesh_too_big_after_fix_and_writes_nothing(tmp_path, monkeypatch, capsys):
    labels = np.zeros((64, 64, 64), np.uint8)
    labels[16:48, 16:48, 16:48] = 1
    np.save(tmp_path / "labels.npy", labels)
    scan, mesh = resources.run_peak_mb(labels.size), resources.run_peak_mb(labels.size, elements=32**3)
    assert scan < mesh
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: (scan + mesh) // 2)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "labels.npy" in err[0]
    assert "32,768 elements" in err[0] and "--skip-memory-check" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels.npy"]  # no out, .partial or .failed


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


def test_an_order_2_run_counts_the_quadratic_mesh(tmp_path, monkeypatch, capsys):
    """export.order 2 holds the quadratic mesh besides the run's own (the head CT's labels with
    curved mid-edge nodes peaked at 4.07-4.35 GB against 1.7-1.8 GB at order 1): a machine that
    fits the linear run refuses the quadratic one before any stage writes."""
    from dicer.resources import COEFFICIENTS, RUN_MESH

    linear = resources.run_peak_mb(10**6, elements=2_280_000)
    quadratic = resources.run_peak_mb(10**6, elements=2_280_000, order=2)
    assert quadratic - linear == pytest.approx(COEFFICIENTS["export_inp_order2"][1] * 2.28, abs=1)
    assert 4_000 < quadratic < 2 * 4_350 and RUN_MESH[1] < COEFFICIENTS["export_inp_order2"][1]
    labels = np.zeros((64, 64, 64), np.uint8)
    labels[16:48, 16:48, 16:48] = 1
    np.save(tmp_path / "labels.npy", labels)
    one, two = (resources.run_peak_mb(labels.size, elements=32**3, order=k) for k in (1, 2))
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: (one + two) // 2)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out), "--set", "export.order=2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "32,768 elements" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels.npy"]
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out), "-q"]) == 0  # order 1 fits
