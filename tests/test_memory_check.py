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
    # with the mesh's size: dicer run on the 512^3 CT (51.2 M elements, 1.45 M surface faces)
    # measured 20.2 GB (17.9 GB before the pillow layer was on by default)
    full = resources.run_peak_mb(512**3, elements=51_229_208, faces=1_445_136)
    assert 20_237 < full < 1.15 * 20_237
    # a factor 2 leaves 1/8 of the elements, 1/4 of the faces
    assert resources.run_peak_mb(512**3, 2, elements=51_229_208 // 8, faces=1_445_136 // 4) < full / 5
    # per-axis factors count by the voxels they leave: (2, 2, 1) as (4, 1, 1), between factors 1 and 2
    assert resources.voxel_reduction((2, 2, 1)) == resources.voxel_reduction((4, 1, 1)) == 4
    assert resources.voxel_reduction(2) == 8 and resources.voxel_reduction(1) == 1
    assert resources.run_peak_mb(512**3, (2, 2, 1)) == resources.run_peak_mb(512**3, (4, 1, 1)) <= scan
    small = resources.run_peak_mb(48**3, elements=48**3 // 2)
    assert 150 < small < 400                            # the interpreter's baseline dominates


def _run_memory_rows():
    import csv
    from pathlib import Path

    lines = [line for line in (Path(__file__).parents[1] / "docs" / "run-memory.tsv").read_text().splitlines()
             if not line.startswith("#")]
    return list(csv.DictReader(lines, delimiter="\t"))


def test_the_run_estimate_bounds_every_measured_run_closely():
    """RUN_MESH against dicer run's measured peaks on phantoms and the head CT: never below
    (the check would let through a run the kernel kills), at most 35 % above (it would refuse
    runs that fit)."""
    rows = _run_memory_rows()
    assert len(rows) >= 24 and {r["scan"].split()[0] for r in rows} >= {"shell", "head", "long_bone", "block"}
    ratios = {1: [], 2: []}
    for r in rows:
        need = resources.run_peak_mb(int(r["voxels"]), int(r["factor"]), int(r["elements"]), int(r["order"]),
                                     faces=int(r["faces"]), relaxed="labels" in r["scan"])
        ratios[int(r["order"])].append(need / float(r["peak_mb"]))
    # order 2 (curved C3D20 decks) reads the long-bone and block phantoms' runs 1.6 and 1.75 times
    # over (their few faces per element: the slopes are the thin-walled scans')
    assert min(ratios[1] + ratios[2]) >= 1.0 and max(ratios[1]) <= 1.35 and max(ratios[2]) <= 1.8, ratios
    # without the faces the thin-walled head CT is not underestimated either
    ct = next(r for r in rows if r["scan"] == "head CT" and r["factor"] == "1")
    assert resources.run_peak_mb(int(ct["voxels"]), 1, int(ct["elements"])) >= float(ct["peak_mb"])


def test_the_run_counts_the_surface_thin_walls_need(tmp_path, monkeypatch, capsys):
    """As many elements in 16 plates two voxels thick (which fix leaves as they are) as in one
    cube: six times the surface faces. A machine with memory for the cube's run refuses the
    plates' before any stage of the mesh writes, naming their size."""
    cube = np.zeros((64, 40, 40), np.uint8)
    cube[16:48, 4:36, 4:36] = 1
    plates = np.zeros((64, 40, 40), np.uint8)
    for k in range(0, 64, 4):
        plates[k:k + 2, 4:36, 4:36] = 1
    assert np.count_nonzero(cube) == np.count_nonzero(plates) == 32**3
    assert resources.surface_faces(plates) == 6 * resources.surface_faces(cube) == 36_864
    need = {name: resources.run_peak_mb(a.size, elements=32**3, faces=resources.surface_faces(a))
            for name, a in (("cube", cube), ("plates", plates))}
    assert need["plates"] - need["cube"] > 50
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: (need["cube"] + need["plates"]) // 2)
    for name, a in (("cube", cube), ("plates", plates)):
        np.save(tmp_path / f"{name}.npy", a)
    assert main(["run", "--labels", str(tmp_path / "plates.npy"), "-o", str(tmp_path / "p"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "32,768 elements" in err[0]
    assert not (tmp_path / "p").exists()
    assert main(["run", "--labels", str(tmp_path / "cube.npy"), "-o", str(tmp_path / "c"), "-q"]) == 0


def test_surface_faces_counts_exterior_and_interface_faces():
    labels = np.zeros((4, 5, 6), np.uint8)
    assert resources.surface_faces(labels) == 0
    labels[1, 1, 1] = 1
    assert resources.surface_faces(labels) == 6                        # one voxel: its six faces
    labels[1, 1, 2] = 2
    assert resources.surface_faces(labels) == 11                       # two voxels: 10 outside, 1 between
    labels[1, 1, 3] = 2
    assert resources.surface_faces(labels) == 15                       # the same label meets itself: no face
    labels[:] = 3
    assert resources.surface_faces(labels) == 2 * (20 + 24 + 30)       # the volume's edges
    assert resources.surface_faces(np.ones((3, 4), np.uint8)) == 14    # 2D: the perimeter
    rng = np.random.default_rng(5)
    lab = rng.integers(0, 3, (6, 7, 8))
    padded = np.pad(lab, 1)
    brute = sum(int(np.count_nonzero(np.diff(padded, axis=a) != 0)) for a in range(3))
    assert resources.surface_faces(lab) == brute


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
    # (its faces unknown, taken as 0.35 per element: factor 2's 19.3 GB is over 80 % of 24 GB)
    assert "134,217,728 elements" in str(err.value) and "downsample.factor: 3" in str(err.value)
    _check_memory("scan.nii.gz", default_config(), elements=51_200_000, faces=1_445_136)  # the CT phantom's 38 % fits
    with pytest.raises(DicerError, match="51,200,000 elements"):  # as many elements, thin walls: 35 % faces
        _check_memory("scan.nii.gz", default_config(), elements=51_200_000, faces=18_000_000)


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
    curved mid-edge nodes peaked at 3.75-3.86 GB against 1.6-1.7 GB at order 1): a machine that
    fits the linear run refuses the quadratic one before any stage writes."""
    from dicer.resources import RUN_MESH_ORDER2

    linear = resources.run_peak_mb(10**6, elements=2_278_516, faces=425_260)
    quadratic = resources.run_peak_mb(10**6, elements=2_278_516, order=2, faces=425_260)
    assert quadratic - linear == pytest.approx(RUN_MESH_ORDER2[0] * 2.278516 + RUN_MESH_ORDER2[1] * 0.42526, abs=1)
    assert 3_856 <= quadratic < 1.05 * 3_856
    labels = np.zeros((64, 64, 64), np.uint8)
    labels[16:48, 16:48, 16:48] = 1
    np.save(tmp_path / "labels.npy", labels)
    faces = resources.surface_faces(labels)
    one, two = (resources.run_peak_mb(labels.size, elements=32**3, order=k, faces=faces) for k in (1, 2))
    assert two - one > 10
    monkeypatch.setattr(resources, "machine_memory_mb", lambda: (one + two) // 2)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out), "--set", "export.order=2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "32,768 elements" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["labels.npy"]
    assert main(["run", "--labels", str(tmp_path / "labels.npy"), "-o", str(out), "-q"]) == 0  # order 1 fits
