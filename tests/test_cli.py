"""The `dicer` command: every form runs, and bad input ends in one `error:` line, exit 2, no file."""

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from dicer.cli import main


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.err


@pytest.fixture(scope="module")
def head(tmp_path_factory):
    path = tmp_path_factory.mktemp("img") / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(path), "--size", "32", "-q"]) == 0
    return path


def test_help_for_every_command():
    for command in ("run", "segment", "downsample", "fix", "mesh", "merge", "smooth", "export", "quality", "surface", "phantom"):
        proc = subprocess.run([sys.executable, "-m", "dicer", command, "--help"], capture_output=True, text=True)
        assert proc.returncode == 0 and "usage: dicer " + command in proc.stdout


def test_stage_by_stage(tmp_path, capsys, head):
    labels, coarse, mesh = tmp_path / "labels.nii.gz", tmp_path / "ds.nii.gz", tmp_path / "mesh.vtu"
    assert run_cli(capsys, "segment", head, "-o", labels)[0] == 0
    assert run_cli(capsys, "downsample", labels, "-o", coarse, "--set", "downsample.factor=2")[0] == 0
    assert run_cli(capsys, "mesh", coarse, "-o", mesh)[0] == 0
    for name in ("model.inp", "model.vtu"):
        assert run_cli(capsys, "export", mesh, "-o", tmp_path / name)[0] == 0
    code, err = run_cli(capsys, "quality", tmp_path / "model.vtu", "-o", tmp_path / "q.json",
                        "--labels", coarse, "--html", tmp_path / "q.html")
    assert code == 0, err
    report = json.loads((tmp_path / "q.json").read_text())
    assert report["elements"] == sum(m["voxels"] for m in report["materials"].values())
    assert report["inverted_elements"] == 0
    assert (tmp_path / "q.html").read_text().startswith("<!DOCTYPE html>")
    assert "*ELEMENT" in (tmp_path / "model.inp").read_text()


def test_run_writes_everything_and_is_reproducible(tmp_path, capsys, head):
    for out in ("a", "b"):
        code, err = run_cli(capsys, "run", head, "-o", tmp_path / out)
        assert code == 0, err
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    from dicer.cli import RUN_OUTPUTS

    # materials.json: run --labels only; of the models, those of workflow.exports (inp, vtu)
    others = {"materials.json"} | {n for n in RUN_OUTPUTS if n.startswith("model.")} - {"model.inp", "model.vtu", "model.png"}
    assert names == sorted(set(RUN_OUTPUTS) - others)
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


def test_mesh_from_npy_labels(tmp_path, capsys):
    labels = np.zeros((3, 4, 5), np.int16)
    labels[1:, 1:3, :4] = 2
    np.save(tmp_path / "l.npy", labels)
    assert run_cli(capsys, "mesh", tmp_path / "l.npy", "-o", tmp_path / "m.vtu")[0] == 0
    from dicer.io.meshes import read_mesh

    mesh = read_mesh(tmp_path / "m.vtu")
    assert mesh.n_cells == 16 and set(mesh.material.tolist()) == {2}
    assert np.allclose(mesh.spacing, 1.0)


def _write(path, array, spacing=(1.0, 1.0, 1.0)):
    image = sitk.GetImageFromArray(array)
    image.SetSpacing(spacing)
    sitk.WriteImage(image, str(path))


def _bad_cases(tmp_path, head):
    truncated = tmp_path / "truncated.nii.gz"
    truncated.write_bytes(head.read_bytes()[:2000])
    air = tmp_path / "air.nii.gz"
    _write(air, np.full((8, 8, 8), -1000, np.int16))
    four_d = tmp_path / "four_d.nii.gz"
    sitk.WriteImage(sitk.JoinSeries([sitk.GetImageFromArray(np.zeros((4, 4, 4), np.int16))] * 2), str(four_d))
    import meshio

    from dicer.io.meshes import write_mesh
    from dicer.mesh.voxel import voxel_mesh

    good = voxel_mesh(np.ones((3, 3, 3), np.uint8))
    good_vtu = tmp_path / "good.vtu"
    write_mesh(good, good_vtu)
    foreign = tmp_path / "foreign.vtu"
    meshio.write(foreign, meshio.Mesh(good.points, [("hexahedron", good.cells)], cell_data={"material": [good.material]}))
    empty = tmp_path / "empty.vtu"
    meshio.write(empty, meshio.Mesh(good.points, [("hexahedron", np.zeros((0, 8), np.int64))]))
    smoothed = tmp_path / "out" / "smoothed.vtu"
    a_file = tmp_path / "plain.txt"
    a_file.write_text("x")
    out = tmp_path / "out" / "labels.nii.gz"
    return {
        "missing file": (["segment", tmp_path / "missing.nii.gz", "-o", out], "missing.nii.gz", out),
        "truncated image": (["segment", truncated, "-o", out], "truncated.nii.gz", out),
        "no voxel in any class": (["segment", air, "-o", out], "air.nii.gz", out),
        "4D image": (["segment", four_d, "-o", out], "four_d.nii.gz", out),
        "unknown config key": (["segment", head, "-o", out, "--set", "segment.colour=red"], "segment.colour", out),
        "wrong config type": (["segment", head, "-o", out, "--set", "segment.opening_radius=wide"],
                              "segment.opening_radius", out),
        "unwritable output folder": (["segment", head, "-o", a_file / "labels.nii.gz"], "plain.txt",
                                     a_file / "labels.nii.gz"),
        "run into unwritable folder": (["run", head, "-o", a_file / "sub"], "plain.txt", a_file / "sub"),
        "run with no voxel in any class": (["run", air, "-o", tmp_path / "run_out"], "air.nii.gz",
                                           tmp_path / "run_out"),
        "smoothing coefficient of 1": (["smooth", good_vtu, "-o", smoothed, "--set", "smooth.coefficient=1.0"],
                                       "smooth.coefficient", smoothed),
        "negative class coefficient": (["smooth", good_vtu, "-o", smoothed, "--set", "smooth.coefficients.D=-0.1"],
                                       "smooth.coefficients.D", smoothed),
        "mesh without lattice": (["smooth", foreign, "-o", smoothed], "foreign.vtu", smoothed),
        "empty mesh": (["merge", empty, "-o", smoothed], "empty.vtu", smoothed),
        "fix of a missing file": (["fix", tmp_path / "none.nii.gz", "-o", out], "none.nii.gz", out),
    }


CASES = ["missing file", "truncated image", "no voxel in any class", "4D image", "unknown config key",
         "wrong config type", "unwritable output folder", "run into unwritable folder",
         "run with no voxel in any class", "smoothing coefficient of 1", "negative class coefficient",
         "mesh without lattice", "empty mesh", "fix of a missing file"]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_one_error_line_exit_2_no_output(tmp_path, capsys, head, case):
    argv, named, output = _bad_cases(tmp_path, head)[case]
    code, err = run_cli(capsys, *argv)
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("dicer ")]
    assert code == 2
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert named in lines[0]
    assert not output.exists()
    leftovers = [p for p in tmp_path.rglob("*") if p.name.startswith(".") and ".tmp" in p.name]
    assert leftovers == []


def test_console_script_exit_status(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dicer", "mesh", str(tmp_path / "none.npy"), "-o",
                           str(tmp_path / "m.vtu")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: ") and "none.npy" in proc.stderr
    assert not (tmp_path / "m.vtu").exists()


def test_model_heading_is_the_same_from_run_and_from_the_stage(tmp_path):
    # the provenance heading depends on the exported mesh and the export settings only,
    # so dicer run and dicer export (and the workflow's export rule) write the same lines
    from dicer.cli import main

    image = tmp_path / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(image), "-q"]) == 0
    out = tmp_path / "out"
    assert main(["run", str(image), "-o", str(out), "-q", "--set", "downsample.factor=4"]) == 0
    assert main(["export", str(out / "smoothed.vtu"), "-o", str(tmp_path / "again.inp"), "-q"]) == 0
    head = (out / "model.inp").read_text().split("*NODE")[0]
    assert head == (tmp_path / "again.inp").read_text().split("*NODE")[0]
    assert "mesh sha256 " in head and "head.nii" not in head


def test_fix_warns_of_a_material_it_leaves_without_voxels(tmp_path, capsys, caplog):
    """A material that the fixes or the floating-part filter remove whole would be missing from
    the model and the deck: a warning names it (shown with -q), fix.json lists it."""
    from dicer.image import Volume
    from dicer.io.images import write_image

    lab = np.ones((16, 16, 16), np.uint8)
    lab[8, 8, 8] = 2  # the only voxel of material 2 (bone), inside the block: taken over by its neighbour
    write_image(Volume(lab, (1.0, 1.0, 1.0)), tmp_path / "l.nii.gz")
    code, err = run_cli(capsys, "fix", tmp_path / "l.nii.gz", "-o", tmp_path / "f.nii.gz", "--report",
                        tmp_path / "fix.json", "-q")
    assert code == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("1 material(s) have no voxels left and no elements in the model: bone (" in m for m in warned)
    assert json.loads((tmp_path / "fix.json").read_text())["lost_materials"] == ["bone"]
    fixed = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "f.nii.gz")))
    assert np.unique(fixed).tolist() == [1]
    # nothing lost, nothing said
    lab[6:10, 6:10, 6:10] = 2
    caplog.clear()
    write_image(Volume(lab, (1.0, 1.0, 1.0)), tmp_path / "l.nii.gz")
    code, err = run_cli(capsys, "fix", tmp_path / "l.nii.gz", "-o", tmp_path / "f.nii.gz", "--report",
                        tmp_path / "fix.json", "-q")
    assert code == 0 and not any("no voxels left" in r.getMessage() for r in caplog.records)
    assert json.loads((tmp_path / "fix.json").read_text())["lost_materials"] == []


def test_smooth_warns_when_the_guard_undoes_most_of_the_smoothing(tmp_path, capsys, caplog):
    """A quality floor the staircase cannot keep made the guard back off 1,072 of 1,204 boundary
    nodes (mean move 0.017 mm, 0.287 at defaults), exit 0 without a word."""
    g = np.indices((20, 20, 20)).astype(float) - 9.5
    r = np.sqrt((g ** 2).sum(0))
    a = np.zeros((20, 20, 20), np.uint8)
    a[r < 8] = 1
    a[r < 4.5] = 2
    np.save(tmp_path / "in.npy", a)
    assert main(["mesh", str(tmp_path / "in.npy"), "-o", str(tmp_path / "m.vtu"), "-q"]) == 0
    for floor, warned in ((0.2, False), (0.9, True)):
        caplog.clear()
        code, err = run_cli(capsys, "smooth", tmp_path / "m.vtu", "-o", tmp_path / "s.vtu", "--report",
                            tmp_path / "s.json", "-q", "--set", f"smooth.min_scaled_jacobian={floor}")
        report = json.loads((tmp_path / "s.json").read_text())
        said = [m.getMessage() for m in caplog.records if "the quality guard backed off" in m.getMessage()]
        assert code == 0 and len(said) == int(warned)
        share = report["backed_off_nodes"] / report["boundary_nodes"]
        assert (share > 0.5) if warned else (share < 0.1)
        if warned:
            assert said[0].startswith(f"smooth: the quality guard backed off {report['backed_off_nodes']} of the "
                                      f"{report['boundary_nodes']} boundary nodes")
            assert "smooth.min_scaled_jacobian=0.9" in said[0]


def test_smooth_says_when_the_mesh_it_was_given_is_under_its_floor(tmp_path, capsys, caplog):
    """A merged mesh's elements under smooth.min_scaled_jacobian (merging's floor is 0.2) are
    kept no worse by the guard, not raised: quality.json then read under the floor the README
    promises with no message (thick slices, downsample.factor=[4,4,1]: 0.242)."""
    g = np.indices((20, 20, 20)).astype(float) - 9.5
    a = (np.sqrt((g ** 2).sum(0)) < 8).astype(np.uint8)
    np.save(tmp_path / "in.npy", a)
    assert main(["mesh", str(tmp_path / "in.npy"), "-o", str(tmp_path / "m.vtu"), "-q"]) == 0
    assert main(["merge", str(tmp_path / "m.vtu"), "-o", str(tmp_path / "merged.vtu"), "-q"]) == 0
    for mesh, floor, warned in (("m.vtu", 0.6, False), ("merged.vtu", 0.6, True), ("merged.vtu", 0.2, False)):
        caplog.clear()
        code, err = run_cli(capsys, "smooth", tmp_path / mesh, "-o", tmp_path / "s.vtu", "--report",
                            tmp_path / "s.json", "-q", "--set", f"smooth.min_scaled_jacobian={floor}")
        lowest = json.loads((tmp_path / "s.json").read_text())["min_scaled_jacobian"]
        said = [m.getMessage() for m in caplog.records if "the smallest scaled Jacobian is" in m.getMessage()]
        assert code == 0 and len(said) == int(warned) and (lowest < floor) == warned, (mesh, floor, lowest)
        if warned:
            assert said[0].startswith(f"smooth: the smallest scaled Jacobian is {lowest:.3f}, under "
                                      f"smooth.min_scaled_jacobian={floor:g}: elements already under it in merged.vtu")
            assert said[0].endswith(f"set merge.min_scaled_jacobian={floor:g} too to keep every element at the floor")


def test_run_says_each_warning_once(tmp_path, caplog):
    """Both exports of dicer run (model.inp and model.vtu) met the same things and each
    warned of them: the same line twice. Within a run a repeated line is dropped; a later
    command says it again."""
    from dicer.cli import _each_warning_once

    log = logging.getLogger("dicer")
    with caplog.at_level("WARNING"):
        with _each_warning_once():
            for text in ("export: one thing", "export: another", "export: one thing"):
                log.warning(text)
        log.warning("export: one thing")
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert said == [("WARNING", "export: one thing"), ("WARNING", "export: another"), ("WARNING", "export: one thing")]


def test_fix_warns_of_a_volume_it_changes_and_names_the_rounds_that_left_nothing(tmp_path, capsys, caplog):
    """A one-voxel plate near a block was filled away by the majority rounds (-6.7 %, exit 0,
    no word), and a plate alone ended in 'smaller than fix.min_component_voxels=0; lower it'."""
    a = np.zeros((12, 12, 12), np.uint8)
    a[1:11, 1:11, 1:6] = 1
    a[3:9, 3:9, 8] = 1  # a plate one voxel thin, apart from the block
    np.save(tmp_path / "a.npy", a)
    assert run_cli(capsys, "fix", tmp_path / "a.npy", "-o", tmp_path / "a.nii.gz", "-q",
                   "--set", "fix.min_component_voxels=0")[0] == 0
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("fix: material volume")]
    assert len(warned) == 1 and "(soft_tissue -6.7 %)" in warned[0] and "fix.majority_rounds=0" in warned[0]
    b = np.zeros((10, 10, 10), np.uint8)
    b[2:8, 2:8, 5] = 1  # the plate alone
    np.save(tmp_path / "b.npy", b)
    code, err = run_cli(capsys, "fix", tmp_path / "b.npy", "-o", tmp_path / "b.nii.gz", "-q",
                        "--set", "fix.min_component_voxels=0")
    assert code == 2 and "the connectivity fixes left no voxel" in err and "fix.majority_rounds=0" in err
    caplog.clear()
    assert run_cli(capsys, "fix", tmp_path / "b.npy", "-o", tmp_path / "b.nii.gz", "-q", "--set",
                   "fix.min_component_voxels=0", "--set", "fix.majority_rounds=0")[0] == 0
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("fix: material volume")]
    assert len(warned) == 1 and "(soft_tissue +100.0 %)" in warned[0] and "thicken" in warned[0]
    # at the scan's own voxels there is no downsampling to lower: the advice is a finer scan
    assert "a scan of finer voxels keeps them" in warned[0] and "lower downsample.factor" not in warned[0]
    caplog.clear()
    assert run_cli(capsys, "fix", tmp_path / "b.npy", "-o", tmp_path / "b.nii.gz", "-q", "--set",
                   "fix.min_component_voxels=0", "--set", "fix.majority_rounds=0", "--set", "downsample.factor=2")[0] == 0
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("fix: material volume")]
    assert len(warned) == 1 and "lower downsample.factor" in warned[0]
    # the fixes that changed the volume are named: the type A fix alone (type C off) ...
    c = np.zeros((10, 10, 10), np.uint8)
    c[1:5, 1:5, 1:5] = 1
    c[5:9, 5:9, 1:5] = 2  # two blocks touching along an edge only
    np.save(tmp_path / "c.npy", c)
    caplog.clear()
    assert run_cli(capsys, "fix", tmp_path / "c.npy", "-o", tmp_path / "c.nii.gz", "-q", "--set", "fix.type_c=false",
                   "--set", "fix.min_component_voxels=0")[0] == 0
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("fix: material volume")]
    assert len(warned) == 1 and "the type A and B fixes added voxels where parts touched along an edge" in warned[0]
    assert "type C" not in warned[0]
    # ... and a floating part removed, no majority round changing anything
    d = np.zeros((12, 12, 12), np.uint8)
    d[1:7, 1:7, 1:7] = 1
    d[8:11, 8:11, 8:11] = 1  # 27 voxels apart from the block
    np.save(tmp_path / "d.npy", d)
    caplog.clear()
    assert run_cli(capsys, "fix", tmp_path / "d.npy", "-o", tmp_path / "d.nii.gz", "-q",
                   "--set", "fix.min_component_voxels=30")[0] == 0
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("fix: material volume")]
    assert len(warned) == 1 and "(soft_tissue -11.1 %)" in warned[0], warned
    assert warned[0].endswith("; floating parts smaller than fix.min_component_voxels=30 were removed: lower it to "
                              "keep them")


def test_fix_warns_of_parts_it_joins_and_of_a_model_grown_to_the_image_faces(tmp_path, capsys, caplog):
    """A brain inside a skull shell one voxel apart was welded to the skull by the fixes, and a
    downsampled shell grew by two thirds to the image's faces, each with only a per-material
    volume warning ("segment more finely") and exit 0."""
    n = 40
    x, y, z = np.mgrid[:n, :n, :n].astype(float)
    r = np.sqrt((x - 19.3) ** 2 + (y - 20.1) ** 2 + (z - 19.7) ** 2)
    config = tmp_path / "c.yaml"
    config.write_text("labels:\n  map: {1: soft_tissue, 2: bone}\n")
    for gap, joined in ((1.0, 1), (2.0, 0)):
        lab = np.zeros((n, n, n), np.uint8)
        lab[r < 17] = 1
        lab[r < 14] = 0
        lab[r < 14 - gap] = 2
        np.save(tmp_path / "gap.npy", lab)
        caplog.clear()
        assert run_cli(capsys, "fix", tmp_path / "gap.npy", "-o", tmp_path / "g.nii.gz", "-q", "--config", config,
                       "--report", tmp_path / "fix.json")[0] == 0
        report = json.loads((tmp_path / "fix.json").read_text())
        assert report["joined_parts"] == joined
        warned = [r.getMessage() for r in caplog.records if "separate part(s)" in r.getMessage()]
        assert len(warned) == joined
        if joined:
            assert warned[0].startswith("fix: 1 separate part(s) of the labels were joined") and "two voxels" in warned[0]
    lab = np.zeros((n, n, n), np.uint8)  # shells: 2, 1 and 14 voxels, downsampled by 2 as the next stage sees it
    lab[r < 17] = 1
    lab[r < 15] = 2
    lab[r < 14] = 1
    np.save(tmp_path / "shells.npy", lab[::2, ::2, ::2])
    caplog.clear()
    assert run_cli(capsys, "fix", tmp_path / "shells.npy", "-o", tmp_path / "s.nii.gz", "-q", "--config", config,
                   "--report", tmp_path / "fix.json")[0] == 0
    report = json.loads((tmp_path / "fix.json").read_text())
    grown = 100 * (report["solid_voxels"]["after"] / report["solid_voxels"]["before"] - 1)
    warned = [r.getMessage() for r in caplog.records if r.getMessage().startswith("fix: the model grew")]
    assert grown > 5 and len(warned) == 1 and f"grew by {grown:.1f} %" in warned[0]
    assert report["faces_reached"] == ["Y1", "Z1"]  # the off-centre shell, 0.5 voxel from those faces
    assert "faces Y1, Z1 (" in warned[0]


def test_merge_warns_when_it_grows_a_material_across_thick_slices(tmp_path, capsys, caplog):
    """Chamfers fill whole voxel steps: across 3 mm slices of 0.5 mm pixels a ball grows by
    far more than its in-plane merging would; the stage says so and which passes avoid it."""
    from dicer.image import Volume
    from dicer.io.images import write_image

    g = np.indices((14, 60, 60)) + 0.5
    ball = ((g[0] * 3 - 21) / 18) ** 2 + ((g[1] * 0.5 - 15) / 12) ** 2 + ((g[2] * 0.5 - 15) / 12) ** 2 < 1
    write_image(Volume(ball.astype(np.uint8), (3.0, 0.5, 0.5)), tmp_path / "l.nii.gz")
    assert run_cli(capsys, "mesh", tmp_path / "l.nii.gz", "-o", tmp_path / "m.vtu")[0] == 0
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]  # the mesh stage's, before merging
    assert len(said) == 1 and "6 times longer" in said[0] and "merge.passes [0, 1, 1]" in said[0]
    caplog.clear()
    code, _ = run_cli(capsys, "merge", tmp_path / "m.vtu", "-o", tmp_path / "g.vtu", "--report", tmp_path / "g.json")
    assert code == 0
    change = json.loads((tmp_path / "g.json").read_text())["volume"]["1"]["change_percent"]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert change > 5 and len(warned) == 1
    assert f"soft_tissue {change:+.1f} %" in warned[0] and "set merge.passes=[0, 1, 1] to merge in-plane only" in warned[0]
    caplog.clear()
    code, _ = run_cli(capsys, "merge", tmp_path / "m.vtu", "-o", tmp_path / "g.vtu", "--report", tmp_path / "g.json",
                      "--set", "merge.passes=[0,1,1]")
    assert code == 0 and json.loads((tmp_path / "g.json").read_text())["volume"]["1"]["change_percent"] < 5
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_a_run_says_which_merge_the_fit_to_the_labels_does_not_take_back(tmp_path, capsys, caplog):
    """The fit to the labels takes merging's chamfers back where its window (5 voxels of the
    finest axis) reaches across a voxel: a 1 mm ball's +6 % is said at INFO, and the run warns of
    nothing. On 0.5 mm pixels with 3 mm slices it cannot: merge and smooth both warn, the smooth
    stage of the volume left and of the passes that avoid it (it had blamed small parts)."""
    from dicer.image import Volume
    from dicer.io.images import write_image

    import logging

    caplog.set_level(logging.INFO, logger="dicer")
    g = np.indices((40, 40, 40)) + 0.5
    ball = ((g - 20) ** 2).sum(axis=0) < 15 ** 2
    write_image(Volume(ball.astype(np.uint8), (1.0, 1.0, 1.0)), tmp_path / "ball.nii.gz")
    assert run_cli(capsys, "run", "--labels", tmp_path / "ball.nii.gz", "-o", tmp_path / "ball")[0] == 0
    merged = json.loads((tmp_path / "ball" / "merge.json").read_text())["volume"]["1"]["change_percent"]
    assert merged > 5
    said = [r for r in caplog.records if r.getMessage().startswith("merge: material volume changed")]
    assert len(said) == 1 and said[0].levelname == "INFO" and "takes the surface back" in said[0].getMessage()
    assert not [r for r in caplog.records if r.levelname == "WARNING" and "volume" in r.getMessage()]
    caplog.clear()
    g = np.indices((14, 60, 60)) + 0.5
    ball = ((g[0] * 3 - 21) / 18) ** 2 + ((g[1] * 0.5 - 15) / 12) ** 2 + ((g[2] * 0.5 - 15) / 12) ** 2 < 1
    write_image(Volume(ball.astype(np.uint8), (3.0, 0.5, 0.5)), tmp_path / "thick.nii.gz")
    assert run_cli(capsys, "run", "--labels", tmp_path / "thick.nii.gz", "-o", tmp_path / "thick")[0] == 0
    left = 100 * json.loads((tmp_path / "thick" / "smooth.json").read_text())[
        "volume_change_from_labels_by_material"]["1"]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "volume changed" in r.getMessage()]
    assert left > 5 and len(warned) == 2
    assert warned[0].startswith("merge:") and "takes back little of it" in warned[0]
    assert warned[1].startswith(f"smooth: material volume changed by more than 5 % (label_1 {left:+.1f} %)")
    assert "merge in-plane only (merge.passes=[0, 1, 1])" in warned[1] and "small" not in warned[1]


def test_smooth_warns_when_it_shrinks_a_small_part(tmp_path, capsys, caplog):
    """A 6-voxel bone box merged into 3-voxel elements and smoothed loses almost half its
    volume; the stage says so (and nothing for a part it keeps)."""
    from dicer.image import Volume
    from dicer.io.images import write_image

    lab = np.ones((24, 24, 24), np.uint8)
    lab[9:15, 9:15, 9:15] = 2
    write_image(Volume(lab, (1.0, 1.0, 1.0)), tmp_path / "l.nii.gz")
    for argv in (["mesh", tmp_path / "l.nii.gz", "-o", tmp_path / "m.vtu"],
                 ["merge", tmp_path / "m.vtu", "-o", tmp_path / "g.vtu"],
                 ["smooth", tmp_path / "g.vtu", "-o", tmp_path / "s.vtu", "--report", tmp_path / "s.json",
                  "--set", "preset=explicit-dynamics"]):
        assert run_cli(capsys, *argv)[0] == 0
    change = 100 * json.loads((tmp_path / "s.json").read_text())["volume_change_by_material"]["2"]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert change < -20 and len(warned) == 1
    assert warned[0].startswith(f"smooth: material volume changed by more than 5 % (bone {change:+.1f} %)")
    caplog.clear()
    assert run_cli(capsys, "smooth", tmp_path / "m.vtu", "-o", tmp_path / "s.vtu", "--report", tmp_path / "s.json",
                   "--set", "smooth.coefficient=0.5", "--set", "smooth.surface_from_labels=false")[0] == 0
    assert abs(json.loads((tmp_path / "s.json").read_text())["volume_change_by_material"]["2"]) < 0.05
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


def test_a_relaxed_staircase_keeps_a_thin_rods_volume_as_the_faces_do(tmp_path, capsys):
    """A rod 2 x 2 voxels across, smoothed with its staircase relaxed (the static-stress preset's
    samples on a label volume): the fairing drew its section to a third (-64.7 % against the
    faces' -17.9 %); each sheet of the relaxed staircase now keeps the labels' volume to first
    order, and so does the rod (measured +3.0 % against the faces' -17.9 %: the rod reaches the
    image's ends, mirrors, so it is an endless rod, whose section relaxes to +3.3 % as
    tests/test_labelnet.py's does; +1.0 % while the mirrors were 8 voxels of reflected labels)."""
    rod = np.zeros((12, 12, 12), np.uint8)
    rod[5:7, 5:7, :] = 1
    np.save(tmp_path / "rod.npy", rod)
    assert run_cli(capsys, "mesh", tmp_path / "rod.npy", "-o", tmp_path / "m.vtu")[0] == 0
    change = {}
    for samples in ("relaxed", "faces"):
        assert run_cli(capsys, "smooth", tmp_path / "m.vtu", "--labels", tmp_path / "rod.npy", "-o",
                       tmp_path / "s.vtu", "--report", tmp_path / "s.json", "--set",
                       f"smooth.label_samples={samples}")[0] == 0
        change[samples] = 100 * json.loads((tmp_path / "s.json").read_text())[
            "volume_change_from_labels_by_material"]["1"]
    assert abs(change["relaxed"]) < 4 and change["faces"] < -15, change


def test_stages_warn_when_labels_map_numbers_materials_otherwise_than_the_config(tmp_path, capsys, caplog):
    """dicer labels numbers an atlas's materials by smallest value (map {2: soft, 5: bone}:
    soft 1, bone 2); a config listing bone first gave the mapped soft tissue bone's name and
    properties in 'dicer mesh' without --materials: said, and --materials or a config in
    the map's order is quiet."""
    from dicer.io.meshes import read_mesh

    atlas = np.zeros((6, 6, 6), np.uint8)
    atlas[1:5, 1:5, 1:5] = 2
    atlas[2:4, 2:4, 2:4] = 5
    np.save(tmp_path / "atlas.npy", atlas)
    config = tmp_path / "c.yaml"
    config.write_text("labels:\n  map: {2: soft, 5: bone}\nmaterials:\n  - {name: bone, youngs_modulus: 15000}\n"
                      "  - {name: soft, youngs_modulus: 1}\n")
    assert run_cli(capsys, "labels", tmp_path / "atlas.npy", "-o", tmp_path / "l.nii.gz", "--config", config,
                   "--materials", tmp_path / "materials.json")[0] == 0
    caplog.clear()
    for stage in ("mesh", "fix", "downsample"):
        out = tmp_path / ("m.vtu" if stage == "mesh" else f"{stage}.nii.gz")
        assert run_cli(capsys, stage, tmp_path / "l.nii.gz", "-o", out, "--config", config)[0] == 0
        warned = [r.getMessage() for r in caplog.records if "labels.map numbers" in r.getMessage()]
        assert len(warned) == 1 and warned[0].startswith(f"{stage}: ") and "soft, bone" in warned[0]
        caplog.clear()
    assert read_mesh(tmp_path / "m.vtu").names == ["bone", "soft"]  # what the warning is about
    assert run_cli(capsys, "mesh", tmp_path / "l.nii.gz", "-o", tmp_path / "m.vtu", "--config", config,
                   "--materials", tmp_path / "materials.json")[0] == 0
    assert read_mesh(tmp_path / "m.vtu").names == ["soft", "bone"]
    config.write_text("labels:\n  map: {2: soft, 5: bone}\nmaterials:\n  - {name: soft}\n  - {name: bone}\n")
    assert run_cli(capsys, "mesh", tmp_path / "l.nii.gz", "-o", tmp_path / "m.vtu", "--config", config)[0] == 0
    assert not [r for r in caplog.records if "labels.map numbers" in r.getMessage()]


def test_export_warns_when_the_mesh_names_other_materials_than_the_config(tmp_path, capsys, caplog):
    """A mesh of label_1/label_2 (dicer run --labels) exported with the default config would get
    soft tissue's and bone's names and properties: said, and --materials gives its own."""
    from dicer.io.meshes import write_mesh
    from dicer.mesh.voxel import voxel_mesh

    lab = np.ones((6, 6, 6), np.uint8)
    lab[2:4, 2:4, 2:4] = 2
    mesh = voxel_mesh(lab)
    mesh.names = ["label_1", "label_2"]
    write_mesh(mesh, tmp_path / "m.vtu")
    assert run_cli(capsys, "export", tmp_path / "m.vtu", "-o", tmp_path / "m.inp")[0] == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "names its materials label_1, label_2, the config soft_tissue, bone" in warned[0]
    materials = {"materials": [{"name": "label_1"}, {"name": "label_2"}]}
    (tmp_path / "materials.json").write_text(json.dumps(materials))
    caplog.clear()
    assert run_cli(capsys, "export", tmp_path / "m.vtu", "-o", tmp_path / "m.inp", "--materials",
                   tmp_path / "materials.json")[0] == 0
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    assert "ELSET=label_2" in (tmp_path / "m.inp").read_text()


def test_a_materials_file_that_does_not_match_the_mesh_is_refused_or_warned_of(tmp_path, capsys, caplog):
    """quality and surface took the mesh's own names and said nothing of a --materials file
    naming others; export failed naming the output and 'the config'. A file shorter than the
    mesh's labels is refused naming the file, by every command; other names are warned of."""
    from dicer.io.meshes import write_mesh
    from dicer.mesh.voxel import voxel_mesh

    lab = np.ones((6, 6, 6), np.uint8)
    lab[2:4, 2:4, 2:4] = 2
    mesh = voxel_mesh(lab)
    mesh.names = ["label_1", "label_2"]
    write_mesh(mesh, tmp_path / "m.vtu")
    short, other = tmp_path / "short.json", tmp_path / "other.json"
    short.write_text(json.dumps({"materials": [{"name": "bone"}]}))
    other.write_text(json.dumps({"materials": [{"name": "bone"}, {"name": "label_2"}]}))
    outputs = {"quality": tmp_path / "q.json", "surface": tmp_path / "stl", "export": tmp_path / "m.inp"}
    for stage, out in outputs.items():
        code, err = run_cli(capsys, stage, tmp_path / "m.vtu", "-o", out, "--materials", short)
        assert code == 2 and err.count("\n") == 1, (stage, err)
        assert err.startswith(f"error: {short}: lists 1 material(s) but ") and "labels 1..2" in err, err
        assert not out.exists()
    for stage, out in outputs.items():
        caplog.clear()
        assert run_cli(capsys, stage, tmp_path / "m.vtu", "-o", out, "--materials", other)[0] == 0
        warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert len(warned) == 1 and f"names its materials label_1, label_2, {other} bone, label_2" in warned[0], warned
    assert json.loads(outputs["quality"].read_text())["materials"].keys() == {"label_1", "label_2"}
    assert "ELSET=bone" in outputs["export"].read_text()  # the deck takes the file's names, as it said
    # and says what follows if the file is another model's, not to give the file it was given
    assert f"unless {other} was written with this mesh's labels" in warned[0] and "give --materials" not in warned[0]


def test_set_keys_a_stage_does_not_read_are_warned_of(tmp_path, capsys, caplog):
    """image.crop given to 'dicer mesh' (the crop is made by segment and labels) and
    mesh.coordinates to 'dicer export' (fixed when the mesh is made) did nothing, silently."""
    np.save(tmp_path / "l.npy", np.ones((4, 4, 4), np.uint8))
    assert run_cli(capsys, "mesh", tmp_path / "l.npy", "-o", tmp_path / "m.vtu", "--set", "image.crop=null",
                   "--set", "image.spacing=[1, 1, 2]", "--set", "mesh.coordinates=index",
                   "--set", "smooth.coefficient=0.5")[0] == 0
    warned = [r.getMessage() for r in caplog.records if "is not read by" in r.getMessage()]
    assert warned == ["mesh: --set image.crop, smooth.coefficient is not read by dicer mesh (it reads materials, "
                      "mesh, image.spacing); give it to the stage that uses it, or to dicer run"]
    caplog.clear()
    assert run_cli(capsys, "export", tmp_path / "m.vtu", "-o", tmp_path / "m.inp", "--set", "export.order=2")[0] == 0
    assert not [r for r in caplog.records if "is not read by" in r.getMessage()]
    # a preset holds settings of every stage: each stage reads its own part of it
    assert run_cli(capsys, "mesh", tmp_path / "l.npy", "-o", tmp_path / "m.vtu", "--set", "preset=static-stress")[0] == 0
    assert not [r for r in caplog.records if "is not read by" in r.getMessage()]
    assert run_cli(capsys, "export", tmp_path / "m.vtu", "-o", tmp_path / "m.inp",
                   "--set", "mesh.coordinates=index")[0] == 0
    assert [r for r in caplog.records if "--set mesh.coordinates is not read by dicer export" in r.getMessage()]


def test_a_second_run_into_the_same_folder_is_refused_while_the_first_writes(tmp_path):
    # both shared the staging folder: the second deleted it under the first, and the folder
    # mixed the two runs' files while the first exited 0
    import time

    assert main(["phantom", "head", "-o", str(tmp_path / "head.nii.gz"), "--size", "64", "-q"]) == 0
    argv = [sys.executable, "-m", "dicer", "run", str(tmp_path / "head.nii.gz"), "-o", str(tmp_path / "out"), "-q"]
    (tmp_path / "out").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "out")
    first = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lock = tmp_path / ".out.lock"
    for _ in range(600):  # until the first run holds the folder
        if lock.exists() or first.poll() is not None:
            break
        time.sleep(0.01)
    second = subprocess.run(argv, capture_output=True, text=True)
    # by a symlink to the folder: the lock was named after the path as typed, and both exited 0
    third = subprocess.run(argv[:-2] + [str(tmp_path / "link"), "-q"], capture_output=True, text=True)
    out, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    for other in (second, third):
        assert other.returncode == 2 and other.stderr.count("\n") == 1, other.stderr
        assert "another dicer run is writing this folder" in other.stderr and str(tmp_path / "out") in other.stderr
    assert not lock.exists() and not (tmp_path / ".out.partial").exists() and not (tmp_path / "out.failed").exists()
    assert (tmp_path / "out" / "model.inp").exists()


def test_run_logs_name_the_files_where_the_finished_run_puts_them(tmp_path, caplog):
    """'wrote .out.partial/quality.json': a path gone once the run ends."""
    np.save(tmp_path / "l.npy", np.pad(np.ones((6, 6, 6), np.uint8), 1))
    caplog.set_level("INFO", logger="dicer")
    assert main(["run", "--labels", str(tmp_path / "l.npy"), "-o", str(tmp_path / "out"),
                 "--set", "image.spacing=[1,1,1]"]) == 0
    said = [r.getMessage() for r in caplog.records]
    assert not [m for m in said if ".partial" in m]
    assert any(f"wrote {tmp_path / 'out' / 'quality.json'}" in m for m in said), said
    caplog.clear()
    assert main(["mesh", str(tmp_path / "l.npy"), "-o", str(tmp_path / "m.vtu"), "--set", "image.spacing=[1,1,1]"]) == 0
    assert any(f"wrote {tmp_path / 'm.vtu'}" in r.getMessage() for r in caplog.records)  # the filter is gone


def test_run_with_a_method_without_a_criterion_says_nothing_of_a_plot_it_was_not_asked_for(tmp_path, caplog):
    # 'dicer run' with multiotsu warned "--plot draws the criterion ... so .run.partial/thresholds.png is
    # not written", naming its staging folder; 'dicer segment --plot' still says it
    assert main(["phantom", "head", "-o", str(tmp_path / "head.nii.gz"), "--size", "32", "-q"]) == 0
    caplog.set_level("WARNING", logger="dicer")
    assert main(["run", str(tmp_path / "head.nii.gz"), "-o", str(tmp_path / "out"), "-q",
                 "--set", "segment.method=multiotsu"]) == 0
    assert not [r for r in caplog.records if "--plot" in r.getMessage()]
    assert not (tmp_path / "out" / "thresholds.png").exists() and (tmp_path / "out" / "model.inp").exists()
    assert main(["segment", str(tmp_path / "head.nii.gz"), "-o", str(tmp_path / "l.nii.gz"), "-q",
                 "--set", "segment.method=multiotsu", "--plot", str(tmp_path / "t.png")]) == 0
    assert [r for r in caplog.records if "--plot draws the criterion" in r.getMessage()]


def test_the_folder_lock_is_left_out_where_the_file_system_refuses_it(tmp_path, monkeypatch):
    # NFS locks only files open for writing: flock on the folder fails with EBADF, which came
    # out of 'dicer run' as a traceback; the lock file beside the folder still holds
    import errno
    import fcntl

    import dicer.cli as cli
    from dicer.errors import DicerError

    real = fcntl.flock

    def nfs(fd, op):
        if os.path.isdir(f"/proc/self/fd/{fd}"):
            raise OSError(errno.EBADF, "Bad file descriptor")
        return real(fd, op)

    monkeypatch.setattr(fcntl, "flock", nfs)
    (tmp_path / "out").mkdir()
    with cli._output_lock(tmp_path / "out"):
        assert (tmp_path / ".out.lock").exists()
        with pytest.raises(DicerError, match="another dicer run is writing this folder"):
            with cli._output_lock(tmp_path / "out"):
                pass
    assert not (tmp_path / ".out.lock").exists()


def test_a_materials_file_takes_the_properties_of_the_materials_the_config_lists(tmp_path, capsys):
    # the workflow's label patients: materials.json gives the mapped labels' names in order;
    # the properties of a material the command's own config lists come from there, so a
    # stiffness study need not re-run the labels stage that wrote the file
    from dicer.io.meshes import write_mesh
    from dicer.mesh.voxel import voxel_mesh

    labels = np.ones((3, 3, 3), np.uint8)
    labels[0] = 2
    write_mesh(voxel_mesh(labels), tmp_path / "m.vtu")
    (tmp_path / "materials.json").write_text(json.dumps({"materials": [
        {"name": "gel", "youngs_modulus": 5.0, "poissons_ratio": 0.45, "density": 1e-9},
        {"name": "shell", "youngs_modulus": 700.0, "poissons_ratio": 0.3, "density": 2e-9}]}))

    def elastic(name):
        deck = (tmp_path / "d.inp").read_text()
        return deck[deck.index(f"*MATERIAL, NAME={name}"):].split("*ELASTIC\n", 1)[1].split("\n", 1)[0]

    argv = ["export", tmp_path / "m.vtu", "-o", tmp_path / "d.inp", "--materials", tmp_path / "materials.json", "-q"]
    assert run_cli(capsys, *argv)[0] == 0  # no config: the file's
    assert elastic("gel") == "5, 0.45" and elastic("shell") == "700, 0.3"
    (tmp_path / "c.yaml").write_text("materials:\n  - {name: shell, youngs_modulus: 900, poissons_ratio: 0.25}\n"
                                     "  - {name: other, youngs_modulus: 1}\n")
    assert run_cli(capsys, *argv, "--config", tmp_path / "c.yaml")[0] == 0
    assert elastic("gel") == "5, 0.45" and elastic("shell") == "900, 0.25"
    assert run_cli(capsys, *argv, "--set", "materials=[{name: gel, youngs_modulus: 6}]")[0] == 0
    assert elastic("gel") == "6, 0.3" and elastic("shell") == "700, 0.3"


def test_mesh_warns_of_long_voxels_with_a_factor_per_axis(tmp_path, caplog):
    from dicer.image import Volume
    from dicer.io.images import write_image

    # the factor at most half an axis's voxels (a grid 12 voxels across was told 10, which leaves one)
    for size, spacing, factor in ((24, (0.5, 0.5, 5.0), "[10, 10, 1]"), (12, (0.5, 0.5, 5.0), "[6, 6, 1]"),
                                  (24, (1.0, 1.0, 2.0), None)):
        lab = np.zeros((size, size, 4), np.uint8)
        lab[2:10, 2:10, 1:3] = 1
        write_image(Volume(lab, spacing), tmp_path / "l.nii.gz")
        caplog.clear()
        assert main(["mesh", str(tmp_path / "l.nii.gz"), "-o", str(tmp_path / "m.vtu"), "-q"]) == 0
        warned = [r.getMessage() for r in caplog.records if "times longer along one axis" in r.getMessage()]
        assert len(warned) == int(factor is not None)
        if factor:
            assert warned[0].startswith("mesh: the voxels are 0.5 x 0.5 x 5 mm, 10 times longer")
            assert f"up to {factor}" in warned[0] and "merge.passes [1, 1, 0]" in warned[0]


def test_run_outputs_hold_every_model_format_workflow_exports_names():
    from dicer.cli import RUN_OUTPUTS
    from dicer.config import schema

    formats = schema()["properties"]["workflow"]["properties"]["exports"]["items"]["enum"]
    assert {n for n in RUN_OUTPUTS if n.startswith("model.") and n != "model.png"} == {f"model.{e}" for e in formats}


def test_an_ascii_locale_reads_the_schema_and_the_stage_reports(tmp_path):
    """Under LC_ALL=C without Python's UTF-8 coercion every command stopped with a traceback:
    the schema (which holds non-ASCII characters) and the JSON files dicer writes were read in
    the locale's encoding. They are UTF-8, read as such."""
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONCOERCECLOCALE": "0", "PYTHONUTF8": "0"}
    labels = np.zeros((6, 6, 6), np.uint8)
    labels[1:5, 1:5, 1:5] = 1
    np.save(tmp_path / "l.npy", labels)

    def dicer(*args):
        return subprocess.run([sys.executable, "-m", "dicer", *map(str, args), "-q"], capture_output=True, text=True,
                              env=env, timeout=120)

    assert dicer("fix", tmp_path / "l.npy", "-o", tmp_path / "f.nii.gz", "--report", tmp_path / "fix.json").returncode == 0
    assert dicer("mesh", tmp_path / "f.nii.gz", "-o", tmp_path / "m.vtu").returncode == 0
    done = dicer("quality", tmp_path / "m.vtu", "-o", tmp_path / "q.json", "--stage-report", tmp_path / "fix.json")
    assert done.returncode == 0, done.stderr
    assert "fix" in json.loads((tmp_path / "q.json").read_text(encoding="utf-8"))["stages"]


def test_run_places_the_mid_edge_nodes_of_its_order_2_decks_once(tmp_path, monkeypatch):
    """dicer run writes model.inp and model.vtu from one quadratic mesh (its curved mid-edge
    nodes' fold check is most of an order-2 export), the same nodes dicer export places."""
    import meshio

    import dicer.mesh.quadratic as quadratic

    ball = np.zeros((14, 14, 14), np.uint8)
    g = np.indices(ball.shape) - 6.5
    ball[np.sum(g * g, axis=0) <= 5.2**2] = 1
    np.save(tmp_path / "ball.npy", ball)
    calls = []
    made = quadratic.curved_quadratic_mesh

    def counted(mesh, boundary_faces=None):
        calls.append(boundary_faces is not None)
        return made(mesh, boundary_faces)

    monkeypatch.setattr(quadratic, "curved_quadratic_mesh", counted)
    sets = ["--set", "image.spacing=[1,1,1]", "--set", "preset=explicit-dynamics", "--set", "export.order=2",
            "--set", "export.midside_nodes=curved"]  # no pillow layer: every element's first edge may lie on the surface
    assert main(["run", "--labels", str(tmp_path / "ball.npy"), "-o", str(tmp_path / "out"), "-q", *sets]) == 0
    assert calls == [True]  # two decks, one placement
    assert main(["export", str(tmp_path / "out" / "smoothed.vtu"), "-o", str(tmp_path / "alone.vtu"), "-q",
                 *sets[2:]]) == 0
    run, alone = meshio.read(tmp_path / "out" / "model.vtu"), meshio.read(tmp_path / "alone.vtu")
    cells = run.cells[0].data
    assert run.cells[0].type == "hexahedron20" and len(cells) > 100
    bent = np.linalg.norm(run.points[cells[:, 8]] - 0.5 * (run.points[cells[:, 0]] + run.points[cells[:, 1]]), axis=1)
    assert np.count_nonzero(bent > 1e-3) > 10  # curved: off their edges' midpoints
    np.testing.assert_array_equal(run.points, alone.points)
    np.testing.assert_array_equal(run.cells[0].data, alone.cells[0].data)
    inp = (tmp_path / "out" / "model.inp").read_text()
    assert "C3D20" in inp


@pytest.mark.parametrize("stage", ["merge", "smooth", "export", "quality"])
def test_a_label_image_given_as_the_mesh_is_named_an_image(tmp_path, capsys, stage):
    """meshio called a complete label volume a damaged mesh ("is the file complete?")."""
    from dicer.image import Volume
    from dicer.io.images import write_image

    write_image(Volume(np.ones((4, 4, 4), np.uint8), (1.0, 1.0, 1.0)), tmp_path / "labels.nii.gz")
    out = tmp_path / ("out.json" if stage == "quality" else "out.inp" if stage == "export" else "out.vtu")
    code, err = run_cli(capsys, stage, tmp_path / "labels.nii.gz", "-o", out)
    assert code == 2 and err.count("\n") == 1 and not out.exists()
    assert err.startswith(f"error: {tmp_path / 'labels.nii.gz'}: is an image, not a mesh; give a mesh a dicer stage")


@pytest.mark.parametrize("twice", [["--config", "a.yaml", "--config", "b.yaml"], ["--labels", "x.nii.gz"],
                                   ["-o", "elsewhere"]])
def test_an_option_given_twice_is_refused(tmp_path, capsys, monkeypatch, twice):
    """argparse kept the last of two --config files (the output as of b.yaml alone, no word)."""
    for name in ("a.yaml", "b.yaml"):
        (tmp_path / name).write_text("smooth: {coefficient: 0.5}\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as done:
        main(["run", "--labels", "x.nii.gz", "-o", "out", *twice])
    err = capsys.readouterr().err.strip().splitlines()
    assert done.value.code == 2 and len(err) == 1
    assert err[0].startswith(f"error: dicer run: {'-o/--output' if twice[0] == '-o' else twice[0]} is given twice")
    assert not (tmp_path / "out").exists()


def test_an_option_is_not_taken_by_its_beginning(capsys):
    """``--sett`` was read as the workflow's hidden --settings: 'not valid JSON'."""
    with pytest.raises(SystemExit) as done:
        main(["run", "--labels", "x.nii.gz", "-o", "out", "--sett", "smooth.coefficient=0.5"])
    assert done.value.code == 2
    assert capsys.readouterr().err == "error: dicer: unrecognized arguments: --sett; see 'dicer --help'\n"


def test_a_negative_phantom_seed_is_refused(tmp_path, capsys):
    """numpy's ValueError ended in a traceback."""
    assert main(["phantom", "head", "-o", str(tmp_path / "p.nii.gz"), "--seed", "-1"]) == 2
    assert capsys.readouterr().err == "error: phantom: --seed -1 is negative; give a whole number from 0\n"
    assert not (tmp_path / "p.nii.gz").exists()


def test_results_that_cannot_all_be_moved_in_leave_the_folder_as_it_was(tmp_path, capsys, monkeypatch):
    """A file of the folder that could not be replaced (an immutable model.inp) left it mixing
    two runs: the new fix.json and mesh.vtu beside the old model.inp."""
    lab = np.zeros((8, 8, 8), np.uint8)
    lab[1:7, 1:7, 1:7] = 1
    np.save(tmp_path / "l.npy", lab)
    out = tmp_path / "out"
    assert main(["run", "--labels", str(tmp_path / "l.npy"), "-o", str(out), "-q"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    replace = os.replace

    def refuse_one(src, dst):  # as chattr +i: neither moved away nor replaced
        if out / "model.inp" in (Path(src), Path(dst)):
            raise PermissionError(1, "Operation not permitted")
        return replace(src, dst)

    monkeypatch.setattr(os, "replace", refuse_one)
    capsys.readouterr()
    assert main(["run", "--labels", str(tmp_path / "l.npy"), "-o", str(out), "-q",
                 "--set", "smooth.coefficient=0.5"]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: {out}: cannot move the results into the folder (Operation not permitted); they are in "
                   f"{tmp_path / 'out.failed'}\n")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert (tmp_path / "out.failed" / "model.inp").read_bytes() != before["model.inp"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l.npy", "out", "out.failed"]


def test_an_error_stays_one_line_where_a_path_holds_a_line_break(tmp_path, capsys):
    """The message was split over two lines at the path's newline."""
    assert main(["run", "--labels", str(tmp_path / "no\nsuch.nii.gz"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {tmp_path}/no\\nsuch.nii.gz: no such file")


def test_a_box_filled_by_the_fixes_is_warned_of(tmp_path, caplog):
    """Noise segmented as tissue (2.8 % background) became a box of solid (0.4 %) after the
    fixes with no word of it: the segmentation's whole-box warning looks at its own 1 %."""
    rng = np.random.default_rng(2)
    labels = (rng.random((30, 30, 20)) > 0.03).astype(np.uint8)
    np.save(tmp_path / "l.npy", labels)
    assert main(["fix", str(tmp_path / "l.npy"), "-o", str(tmp_path / "f.nii.gz"), "-q"]) == 0
    said = [r.getMessage() for r in caplog.records if "of the image is background" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("fix: after the connectivity fixes 0.")
    assert "% of the image is background (2.9" in said[0] and "the model fills the image box" in said[0]
    caplog.clear()
    labels[:3] = 0  # a tenth of the image background: kept so, and no word
    np.save(tmp_path / "l.npy", labels)
    assert main(["fix", str(tmp_path / "l.npy"), "-o", str(tmp_path / "f.nii.gz"), "-q"]) == 0
    assert not [r for r in caplog.records if "of the image is background" in r.getMessage()]


def test_a_bare_smooth_is_not_warned_that_the_default_relaxation_needs_the_labels(tmp_path, capsys, caplog):
    """``dicer smooth mesh.vtu`` without --labels at the defaults (label_samples: auto) fits the
    mesh's faces: said as a note, not warned at every call; relaxed asked for by name is warned."""
    lab = np.zeros((8, 8, 8), np.uint8)
    lab[2:6, 2:6, 2:6] = 1
    np.save(tmp_path / "l.npy", lab)
    assert run_cli(capsys, "mesh", tmp_path / "l.npy", "-o", tmp_path / "m.vtu")[0] == 0
    for samples, level in ((None, "INFO"), ("relaxed", "WARNING")):
        caplog.clear()
        sets = [] if samples is None else ["--set", f"smooth.label_samples={samples}"]
        with caplog.at_level("INFO", logger="dicer"):
            assert run_cli(capsys, "smooth", tmp_path / "m.vtu", "-o", tmp_path / "s.vtu", *sets)[0] == 0
        said = [r for r in caplog.records if "relaxes the staircase of the label volume" in r.getMessage()]
        assert [r.levelname for r in said] == [level]
