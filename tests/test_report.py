"""The report: floating parts, volume against the original segmentation, the pictures, the cohort table."""

import json
import subprocess
import sys

import numpy as np
import pytest
from matplotlib.image import imread

from dicer.cohort import cohort_rows, cohort_tsv, render_cohort_html
from dicer.config import load_config
from dicer.image import Volume
from dicer.io.pictures import (material_colour, save_jacobian_histogram, save_model_picture,
                               save_node_class_chart, visible_faces)
from dicer.mesh.voxel import voxel_mesh
from dicer.quality import element_neighbours, floating_parts, quality_report, render_html


def _islands():
    """A 4x4x4 soft-tissue block holding a 2x2x1 bone plate, a 1-voxel bone island beside it
    (touching only along an edge), and a free 2x1x1 soft-tissue island far off."""
    labels = np.zeros((10, 6, 6), np.uint8)
    labels[:4, :4, :4] = 1
    labels[1:3, 1:3, 3] = 2           # bone plate on the block's top, inside it
    labels[4, 4, 2] = 2               # shares only an edge with the block: floats
    labels[8:10, 0, 0] = 1            # a free pair of elements
    return labels


def test_floating_parts_count_face_connected_parts():
    mesh = voxel_mesh(_islands())
    parts = floating_parts(mesh)
    assert parts["model"] == {"parts": 3, "largest": 64, "smallest": 1, "floating_elements": 3}
    assert parts["materials"][1] == {"parts": 2, "largest": 60, "smallest": 2}
    assert parts["materials"][2] == {"parts": 2, "largest": 4, "smallest": 1}
    report = quality_report(mesh, load_config())
    assert report["parts"]["model"]["parts"] == 3
    assert report["parts"]["materials"]["bone"]["parts"] == 2
    page = render_html(report)
    assert "<h2>Floating parts</h2>" in page and "3 parts: 3 element(s) float" in page


def test_quality_command_warns_of_a_model_in_parts(tmp_path, caplog):
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    write_mesh(voxel_mesh(_islands()), tmp_path / "m.vtu")
    with caplog.at_level("INFO", logger="dicer"):
        assert main(["quality", str(tmp_path / "m.vtu"), "-o", str(tmp_path / "q.json")]) == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["quality: the model is 3 parts joined by no face: 3 element(s) float free of the largest "
                      "part (the smallest part 1); hold each part in the solver, or drop the parts below a size "
                      "with fix.min_component_voxels"]


def test_one_part_is_reported_as_nothing_floating():
    labels = np.ones((3, 3, 3), np.uint8)
    labels[1, 1, 1] = 2  # enclosed: one part of the model, one of each material
    parts = floating_parts(voxel_mesh(labels))
    assert parts["model"] == {"parts": 1, "largest": 27, "smallest": 27, "floating_elements": 0}
    assert parts["materials"] == {1: {"parts": 1, "largest": 26, "smallest": 26},
                                  2: {"parts": 1, "largest": 1, "smallest": 1}}


def test_volume_against_the_original_segmentation():
    # the original at 1 mm; the meshed labels at 2 mm with a grown bone (as downsampling grows thin bone)
    original = np.zeros((8, 8, 8), np.uint8)
    original[:, :, :4] = 1
    original[:, :, 4] = 2               # one voxel-layer of bone: 64 mm^3
    coarse = np.zeros((4, 4, 4), np.uint8)
    coarse[:, :, :2] = 1
    coarse[:, :, 2] = 2                 # a 2 mm layer: 128 mm^3
    mesh = voxel_mesh(coarse, spacing=(2.0, 2.0, 2.0))
    report = quality_report(mesh, load_config(), labels=Volume(coarse, (2.0, 2.0, 2.0)),
                            original=Volume(original, (1.0, 1.0, 1.0)))
    bone, soft = report["materials"]["bone"], report["materials"]["soft_tissue"]
    assert bone["volume_change_percent"] == pytest.approx(0.0)
    assert bone["original_volume_mm^3"] == pytest.approx(64.0)
    assert bone["original_volume_change_percent"] == pytest.approx(100.0)
    assert soft["original_volume_change_percent"] == pytest.approx(0.0)
    page = render_html(report)
    assert "<td>+100.00</td>" in page and "original segmentation" in page


def test_visible_faces_of_a_cube_and_its_cut():
    mesh = voxel_mesh(np.ones((2, 2, 2), np.uint8))
    nb = element_neighbours(mesh)
    towards = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
    keep = np.ones(8, bool)
    e_idx, quads, lambert = visible_faces(mesh.points, mesh.cells, nb, keep, towards)
    assert quads.shape == (12, 4)  # three sides of 4 faces each face the eye from (1, 1, 1)
    assert np.all(lambert > 0)
    centre = mesh.points[quads].mean(axis=1)
    assert np.all(np.diff(centre @ towards) >= -1e-12)  # far to near
    # cut away x > 1: the x = 2 side is gone, the cut face x = 1 (4 faces) shows, and 2 + 2 on y and z
    keep = mesh.points[mesh.cells].mean(axis=1)[:, 0] < 1.0
    _, quads, _ = visible_faces(mesh.points, mesh.cells, nb, keep, towards)
    assert quads.shape == (8, 4)
    assert np.count_nonzero(np.all(np.isclose(mesh.points[quads][:, :, 0], 1.0), axis=1)) == 4


def test_pictures_are_reproducible_and_show_the_materials(tmp_path):
    labels = _islands()
    mesh = voxel_mesh(labels)
    mesh.points += np.random.default_rng(1).normal(0, 0.05, mesh.points.shape)
    names = {1: "soft_tissue", 2: "bone"}
    from dicer.mesh.metrics import scaled_jacobian

    sj = scaled_jacobian(mesh.points, mesh.cells)
    for run in ("a", "b"):
        save_model_picture(mesh, names, tmp_path / f"model_{run}.png")
        save_jacobian_histogram(sj, mesh.material, names, tmp_path / f"sj_{run}.png", poor=0.2)
        save_node_class_chart({"interior": 5, "A": 3, "B": 2, "C": 0, "D": 7, "E": 1, "F": 1}, tmp_path / f"nc_{run}.png")
    for stem in ("model", "sj", "nc"):
        assert (tmp_path / f"{stem}_a.png").read_bytes() == (tmp_path / f"{stem}_b.png").read_bytes(), stem
        assert b"tEXt" not in (tmp_path / f"{stem}_a.png").read_bytes()  # no date or software tag
    picture = imread(tmp_path / "model_a.png")[:, :, :3]
    assert picture.shape == (500, 1000, 3)  # 10 x 5 inches at 100 dpi
    from matplotlib.colors import to_rgb

    # both materials' colours appear (shaded: the hue's ratio holds); background white dominates
    for label in (1, 2):
        rgb = np.array(to_rgb(material_colour(label)))
        ratio = picture / np.maximum(picture.max(axis=2, keepdims=True), 1e-6)
        near = np.all(np.abs(ratio - rgb / rgb.max()) < 0.06, axis=2) & (picture.max(axis=2) > 0.2)
        assert np.count_nonzero(near) > 200, label


def _material_pixels(picture: np.ndarray, labels=(1, 2)) -> np.ndarray:
    """(H, W) label of the material colour each pixel shows (shaded: the hue's ratio), 0 for none."""
    from matplotlib.colors import to_rgb

    ratio = picture / np.maximum(picture.max(axis=2, keepdims=True), 1e-6)
    out = np.zeros(picture.shape[:2], np.int64)
    for label in labels:
        rgb = np.array(to_rgb(material_colour(label)))
        out[np.all(np.abs(ratio - rgb / rgb.max()) < 0.06, axis=2) & (picture.max(axis=2) > 0.2)] = label
    return out


def test_model_picture_of_a_two_material_box(tmp_path):
    # a 4 mm cube, material 1 at x < 2, material 2 at x > 2; the eye at azimuth -60, elevation 20
    # sees the faces +x (all material 2), -y and +z (half each), in proportion to |n . eye|:
    # 0.470 * 16, 0.814 * 16 and 0.342 * 16 mm^2
    labels = np.ones((4, 4, 4), np.uint8)
    labels[2:] = 2
    path = save_model_picture(voxel_mesh(labels), {1: "a", 2: "b"}, tmp_path / "box.png", max_edges=0)
    shown = _material_pixels(imread(path)[:440, :, :3])  # above the legend
    exterior, cut = shown[:, :500], shown[:, 500:]
    eye = np.array([0.470, 0.814, 0.342])
    expected = (eye[1] + eye[2]) / 2 / eye.sum()  # material 1's share of the exterior
    counts = np.bincount(exterior.ravel(), minlength=3)
    assert counts[1] / (counts[1] + counts[2]) == pytest.approx(expected, abs=0.02)
    assert 0.4 < (counts[1] + counts[2]) / exterior.size < 0.75  # the cube fills the panel
    # x runs to the right on the screen: material 1 left of material 2
    columns = np.nonzero(exterior)[1]
    assert columns[exterior[np.nonzero(exterior)] == 1].mean() < columns[exterior[np.nonzero(exterior)] == 2].mean() - 50
    # the cut keeps the elements with their centre at x <= 2: material 1 only, its cut face showing
    counts = np.bincount(cut.ravel(), minlength=3)
    assert counts[2] == 0 and counts[1] > 0.2 * cut.size


def test_zbuffer_keeps_the_nearest_quad_and_leaves_no_gap():
    from dicer.io.pictures import zbuffer

    # two 4 x 4 pixel squares side by side (sharing the edge x = 3.5), a third over their middle, nearer
    xy = np.array([[[-0.5, -0.5], [3.5, -0.5], [3.5, 3.5], [-0.5, 3.5]],
                   [[3.5, -0.5], [7.5, -0.5], [7.5, 3.5], [3.5, 3.5]],
                   [[1.5, -0.5], [5.5, -0.5], [5.5, 3.5], [1.5, 3.5]]])
    depth = np.array([[2.0] * 4, [2.0] * 4, [1.0] * 4])
    face = zbuffer(xy, depth, (4, 10))
    assert face[:, :2].tolist() == [[0, 0]] * 4 and face[:, 2:6].tolist() == [[2] * 4] * 4
    assert face[:, 6:8].tolist() == [[1, 1]] * 4 and np.all(face[:, 8:] == -1)
    # behind, the third quad is hidden where the others are
    face = zbuffer(xy, depth[::-1].copy() + [[0], [2], [0]], (4, 10))
    assert face[:, :4].tolist() == [[0] * 4] * 4 and face[:, 4:6].tolist() == [[2] * 2] * 4
    # many tiny quads (a fine grid, 0.25 px each) cover every pixel centre of their region
    i, j = np.meshgrid(np.arange(40), np.arange(20), indexing="ij")
    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])
    tiny = (np.stack([i, j], -1).reshape(-1, 1, 2) + corners) * 0.25 - 0.5
    face = zbuffer(tiny, np.zeros(tiny.shape[:2]), (5, 10), chunk=64)
    assert np.all(face >= 0) and np.unique(face).size == 50


def test_model_picture_of_a_2d_mesh(tmp_path):
    labels = np.zeros((6, 5), np.uint8)
    labels[1:5, 1:4] = 1
    labels[2:4, 2] = 2
    path = save_model_picture(voxel_mesh(labels), {1: "a", 2: "b"}, tmp_path / "m.png")
    assert imread(path).shape[:2] == (500, 500)


def test_model_picture_of_a_model_one_element_thick_along_x(tmp_path):
    """Every element centre past the mid-plane of x (a plate merged to one element, then
    smoothed): the cut panel had no face and the picture a numpy traceback; it cuts at the
    centres' median then."""
    labels = np.zeros((3, 6, 6), np.uint8)
    labels[1, 1:5, 1:5] = 1
    mesh = voxel_mesh(labels)
    low = np.flatnonzero(np.isclose(mesh.points[:, 0], 1.0))
    mesh.points[low[1:], 0] += 0.02  # one node keeps the lowest x, the others move in
    centre = mesh.points[mesh.cells][:, :, 0].mean(axis=1)
    assert (centre > 0.5 * (mesh.points[:, 0].min() + mesh.points[:, 0].max())).all()
    path = save_model_picture(mesh, {1: "plate"}, tmp_path / "m.png")
    picture = imread(path)[:, :, :3]
    assert picture.shape[:2] == (500, 1000)
    right = picture[:420, 500:]  # the cut panel holds faces: coloured pixels, not all white
    assert np.count_nonzero(right.min(axis=2) < 0.9) > 1000


def _report(elements, inverted=0, parts=1, bone=(1.5, 23.0)):
    return {"elements": elements, "nodes": elements + 7, "scaled_jacobian": {"min": 0.31, "p1": 0.52},
            "inverted_elements": inverted, "poor_elements": 2, "poor_threshold": 0.2, "stretched_elements": 3,
            "parts": {"model": {"parts": parts, "floating_elements": 4 * (parts - 1)}},
            "materials": {"soft_tissue": {"volume_change_percent": -0.5, "original_volume_change_percent": 2.0},
                          "bone": {"volume_change_percent": bone[0], "original_volume_change_percent": bone[1]}}}


def test_cohort_table_rows_and_columns():
    reports = {"p1": _report(100), "p2": _report(200, inverted=1, parts=2)}
    bench = {"p1": {"quality": {"s": "1.25", "max_rss": "300.5"}, "mesh": {"s": "0.5", "max_rss": "NA"}},
             "p2": {"mesh": {"s": "0.7", "max_rss": "120"}}}
    columns, rows = cohort_rows(reports, bench)
    at = {c: i for i, c in enumerate(columns)}
    assert columns[:10] == ["patient", "elements", "nodes", "min_scaled_jacobian", "p1_scaled_jacobian", "inverted",
                            "poor", "stretched", "parts", "floating_elements"]
    assert [row[at["stretched"]] for row in rows] == [3, 3]
    # stages in pipeline order, materials in report order
    assert [c for c in columns if c.startswith("seconds:")] == ["seconds:mesh", "seconds:quality"]
    assert rows[0][at["original_volume_change_percent:bone"]] == 23.0
    assert rows[0][at["peak_mb:quality"]] == 300.5 and rows[0][at["peak_mb:mesh"]] is None
    assert rows[1][at["seconds:quality"]] is None and rows[1][at["floating_elements"]] == 4
    tsv = cohort_tsv(columns, rows).splitlines()
    assert len(tsv) == 3 and tsv[1].split("\t")[:3] == ["p1", "100", "107"]
    page = render_cohort_html(columns, rows, 0.2)
    assert page.count("<tr class=warn>") == 1  # p2: inverted and floating
    assert "<th rowspan='2'>stretched</th>" in page and "<td>2</td><td>3</td><td>1</td>" in page
    assert "<td>+1.5 / +23.0</td>" in page and "<td>1.2 / 300</td>" in page and "<td>0.5 / –</td>" in page


def test_cohort_rows_counted_below_other_thresholds_show_their_own():
    """One patient's config set quality.poor_threshold 0.9: its 32 poor elements sat under the
    heading 'poor (< 0.2)' beside the others' counts, with nothing to tell them apart."""
    other = dict(_report(100), poor_elements=32, poor_threshold=0.9, stretched_threshold=10.0)
    columns, rows = cohort_rows({"p1": dict(_report(100), stretched_threshold=20.0), "p2": other})
    at = {c: i for i, c in enumerate(columns)}
    assert [row[at["poor_threshold"]] for row in rows] == [0.2, 0.9]
    assert [row[at["stretched_threshold"]] for row in rows] == [20.0, 10.0]
    page = render_cohort_html(columns, rows, 0.2)
    assert "poor (&lt; 0.2)</th>" in page and "stretched (edge ratio &gt; 20)</th>" in page
    assert "<td>2</td><td>3</td>" in page  # p1: the heading's thresholds, bare counts
    assert "<td>32 (&lt; 0.9)</td><td>3 (&gt; 10)</td>" in page
    assert cohort_tsv(columns, rows).splitlines()[0].split("\t")[12:14] == ["poor_threshold", "stretched_threshold"]


def test_a_material_without_elements_is_named_in_the_report_the_page_and_the_cohort(tmp_path, caplog):
    # a class the segmentation left empty: the workflow logged the stage's warning only, and the
    # report, the page and the cohort table showed nothing (the cohort's "–" meant "not recorded")
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    labels = np.ones((4, 4, 4), np.uint8)  # soft tissue only: the default config names bone too
    report = quality_report(voxel_mesh(labels), load_config())
    assert report["materials_without_elements"] == ["bone"] and list(report["materials"]) == ["soft_tissue"]
    assert "<tr class='warn'><td>materials without elements</td><td>bone</td></tr>" in render_html(report)
    labels[0] = 2
    full = quality_report(voxel_mesh(labels), load_config())
    assert full["materials_without_elements"] == [] and "materials without elements" not in render_html(full)
    columns, rows = cohort_rows({"p1": report, "p2": full, "old": _report(100)})
    at = columns.index("materials_without_elements")
    assert [row[at] for row in rows] == ["bone", "", None]
    page = render_cohort_html(columns, rows)
    assert page.count("<tr class=warn>") == 1 and "<td>bone</td>" in page
    changed = dict(full, topology_changed=["soft_tissue"])
    columns, rows = cohort_rows({"p2": changed})
    assert rows[0][columns.index("topology_changed")] == "soft_tissue"
    assert render_cohort_html(columns, rows).count("<tr class=warn>") == 1
    write_mesh(voxel_mesh(np.ones((4, 4, 4), np.uint8)), tmp_path / "m.vtu")
    assert main(["quality", str(tmp_path / "m.vtu"), "-o", str(tmp_path / "q.json"), "-q"]) == 0
    warned = [r.getMessage() for r in caplog.records if "no elements in the model" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("quality: 1 material(s) have no elements in the model: bone")


def _dicer(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "dicer", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_cohort_command_and_its_errors(tmp_path):
    for patient, n in (("a", 10), ("b", 20)):
        (tmp_path / "results" / patient).mkdir(parents=True)
        (tmp_path / "results" / patient / "quality.json").write_text(json.dumps(_report(n)))
    (tmp_path / "benchmarks" / "a").mkdir(parents=True)
    (tmp_path / "benchmarks" / "a" / "fix.tsv").write_text("s\th:m:s\tmax_rss\n2.5\t0:00:02\t150.1\n")
    proc = _dicer("cohort", tmp_path / "results/a/quality.json", tmp_path / "results/b/quality.json",
                  "-o", tmp_path / "cohort.html", "--tsv", tmp_path / "cohort.tsv", "--benchmarks", tmp_path / "benchmarks")
    assert proc.returncode == 0, proc.stderr
    lines = (tmp_path / "cohort.tsv").read_text().splitlines()
    assert lines[0].endswith("seconds:fix\tpeak_mb:fix")
    assert lines[1].split("\t")[0] == "a" and lines[1].endswith("2.5\t150.1")
    assert lines[2].split("\t")[0] == "b" and lines[2].endswith("\t\t")
    (tmp_path / "results" / "b" / "quality.json").write_text("{not json")
    proc = _dicer("cohort", tmp_path / "results/b/quality.json", "-o", tmp_path / "c2.html")
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and len(proc.stderr.splitlines()) == 1
    assert "cannot read the quality report" in proc.stderr and not (tmp_path / "c2.html").exists()
    (tmp_path / "benchmarks" / "a" / "fix.tsv").write_text("garbage\n")
    proc = _dicer("cohort", tmp_path / "results/a/quality.json", "-o", tmp_path / "c3.html",
                  "--benchmarks", tmp_path / "benchmarks")
    assert proc.returncode == 2 and "not a Snakemake benchmark file" in proc.stderr


def test_cohort_warns_of_models_made_by_different_versions(tmp_path):
    """A cohort partly run again a year later, with newer libraries: its models may differ in
    their last bits for that alone, and the cohort says which versions differ, for how many."""
    from dicer import library_versions

    here = library_versions()
    for patient, numpy in (("a", here["numpy"]), ("b", here["numpy"]), ("c", "9.9.9")):
        (tmp_path / patient).mkdir()
        report = {**_report(10), "dicer_version": "0.1.0", "library_versions": {**here, "numpy": numpy}}
        (tmp_path / patient / "quality.json").write_text(json.dumps(report))
    old = {**_report(10), "dicer_version": "0.1.0"}  # made before the versions were recorded: left out
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "quality.json").write_text(json.dumps(old))
    proc = _dicer("cohort", *(tmp_path / p / "quality.json" for p in "abd"), "-o", tmp_path / "same.html")
    assert proc.returncode == 0 and "different versions" not in proc.stderr
    proc = _dicer("cohort", *(tmp_path / p / "quality.json" for p in "abcd"), "-o", tmp_path / "mixed.html")
    assert proc.returncode == 0 and (tmp_path / "mixed.html").exists()
    warned = [line for line in proc.stderr.splitlines() if "different versions" in line]
    assert len(warned) == 1 and f"numpy {here['numpy']} (2 patient(s)), 9.9.9 (1 patient(s))" in warned[0]
    assert "scipy" not in warned[0] and "constraints.txt" in warned[0]
    # a malformed version is refused, not a traceback
    (tmp_path / "c" / "quality.json").write_text(json.dumps({**_report(10), "library_versions": {"numpy": 2}}))
    proc = _dicer("cohort", tmp_path / "c" / "quality.json", "-o", tmp_path / "bad.html")
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1
    assert "'library_versions.numpy' is 2, not a version" in proc.stderr and not (tmp_path / "bad.html").exists()


@pytest.mark.parametrize("report, said", [
    ({"elements": 5, "materials": ["bone"]}, "'materials' is a list, not an object"),
    ({"elements": 5, "scaled_jacobian": 0.5}, "'scaled_jacobian' is a float, not an object"),
    ({"elements": 5, "parts": {"model": {"parts": "2"}}}, "'parts.model.parts' is '2', not a number"),
    ({"elements": 5, "materials": {"bone": {"volume_change_percent": True}}},
     "'materials.bone.volume_change_percent' is True, not a number"),
    ([1, 2], "the file holds a list, not an object"),
    ({"elements": 5, "nodes": 9, "node_classes": {"A": 1}}, "no scaled Jacobian: a stage's report?"),  # smooth.json
])
def test_cohort_refuses_a_report_of_other_types(tmp_path, report, said):
    """Valid JSON of other types gave a traceback."""
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "quality.json").write_text(json.dumps(report))
    proc = _dicer("cohort", tmp_path / "p" / "quality.json", "-o", tmp_path / "c.html")
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert f"quality.json: not a dicer quality report ({said})" in proc.stderr
    assert not (tmp_path / "c.html").exists()


def test_cohort_takes_the_benchmark_files_given_and_arguments_from_a_file(tmp_path):
    """The workflow names the benchmark files of the stages a model now goes through: an
    earlier run's file of a stage since dropped (downsample) stays out of the table. A
    folder that does not exist is an error (it was ignored)."""
    for patient, n in (("a", 10), ("b", 20)):
        (tmp_path / "results" / patient).mkdir(parents=True)
        (tmp_path / "results" / patient / "quality.json").write_text(json.dumps(_report(n)))
        (tmp_path / "benchmarks" / patient).mkdir(parents=True)
        for stage, seconds in (("fix", 2.5), ("downsample", 9.0)):
            (tmp_path / "benchmarks" / patient / f"{stage}.tsv").write_text(f"s\tmax_rss\n{seconds}\t150\n")
    reports = [tmp_path / "results" / p / "quality.json" for p in "ab"]
    files = [tmp_path / "benchmarks" / "a" / "fix.tsv", tmp_path / "benchmarks" / "a" / "downsample.tsv",
             tmp_path / "benchmarks" / "b" / "fix.tsv"]
    (tmp_path / "args").write_text("".join(f"{x}\n" for x in [*reports, "--benchmarks", *files]))
    assert _dicer("cohort", f"@{tmp_path / 'args'}", "-o", tmp_path / "c.html", "--tsv", tmp_path / "c.tsv").returncode == 0
    head, a, b = [line.split("\t") for line in (tmp_path / "c.tsv").read_text().splitlines()]
    assert head[-4:] == ["seconds:downsample", "peak_mb:downsample", "seconds:fix", "peak_mb:fix"]
    assert a[-4:] == ["9.0", "150.0", "2.5", "150.0"] and b[-4:] == ["", "", "2.5", "150.0"]
    proc = _dicer("cohort", *reports, "-o", tmp_path / "d.html", "--benchmarks", tmp_path / "nowhere")
    assert proc.returncode == 2 and "nowhere: no such benchmark file or folder" in proc.stderr
    assert not (tmp_path / "d.html").exists()


def _atlas(parcels=30, n=24, seed=3):
    """A ball cut into ``parcels`` Voronoi parcels (labels 1..parcels), as an atlas."""
    rng = np.random.default_rng(seed)
    g = np.indices((n, n, n)).reshape(3, -1).T + 0.5
    seeds = rng.uniform(0, n, (parcels, 3))
    nearest = np.argmin(((g[:, None, :] - seeds[None]) ** 2).sum(-1), axis=1) + 1
    inside = ((g - n / 2) ** 2).sum(1) < (0.45 * n) ** 2
    return np.where(inside, nearest, 0).reshape(n, n, n).astype(np.uint16)


def test_an_atlas_legend_names_its_largest_materials_and_counts_the_rest(tmp_path):
    import warnings

    from dicer.io.pictures import legend_materials, worst_materials
    from dicer.mesh.metrics import scaled_jacobian

    mesh = voxel_mesh(_atlas())
    labels, sizes = np.unique(mesh.material, return_counts=True)
    assert labels.size > 20
    shown, more = legend_materials(mesh.material)
    assert shown.size == 8 and more == labels.size - 8
    assert np.all(np.diff(shown) > 0)
    assert sizes[np.isin(labels, shown)].min() >= np.sort(sizes)[-8]  # the eight largest
    few, none = legend_materials(mesh.material[mesh.material <= 3])
    assert few.tolist() == [1, 2, 3] and none == 0
    mesh.points += np.random.default_rng(2).normal(0, 0.08, mesh.points.shape)
    sj = scaled_jacobian(mesh.points, mesh.cells)
    worst = worst_materials(sj, mesh.material, 6)
    lowest = np.array([sj[mesh.material == k].min() for k in worst])
    assert worst.size == 6 and np.all(np.diff(lowest) >= 0)
    assert lowest[-1] <= min(sj[mesh.material == k].min() for k in labels if k not in worst)
    names = {int(k): f"parcel_{k}" for k in labels}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a legend too large for the figure warns
        model = save_model_picture(mesh, names, tmp_path / "model.png")
        save_jacobian_histogram(sj, mesh.material, names, tmp_path / "sj.png", poor=0.2)
    assert imread(model).shape[:2] == (500, 1000)


def test_the_palette_tells_an_atlas_s_neighbours_apart():
    colours = [material_colour(k) for k in range(1, 21)]
    assert len(set(colours)) == 20
    assert material_colour(1) == "#e6550d" and material_colour(21) == material_colour(1)


def test_cohort_gives_each_patient_s_smallest_element_length():
    """An explicit solver's time step follows the smallest element length: the cohort lists it
    (– for a report made before quality.json gave it) and refuses a report where it is no
    number."""
    from dicer.cohort import report_problem

    measured = dict(_report(100), characteristic_length_mm={"min": 0.1541, "mean": 0.9})
    columns, rows = cohort_rows({"p1": measured, "p2": _report(200)})
    at = columns.index("min_characteristic_length_mm")
    assert [row[at] for row in rows] == [0.1541, None]
    assert cohort_tsv(columns, rows).splitlines()[1].split("\t")[at] == "0.1541"
    page = render_cohort_html(columns, rows, 0.2)
    assert "smallest element length, mm</th>" in page and "<td>0.154</td>" in page
    assert report_problem(dict(measured, characteristic_length_mm={"min": "small"})) == (
        "'characteristic_length_mm.min' is 'small', not a number")


def test_cohort_gives_each_patient_s_explicit_time_step(tmp_path):
    """`dicer quality` gives the step from the config's materials (the decks' properties); the
    cohort lists it (– for a report made before) and refuses one where it is no number."""
    from dicer.cli import main
    from dicer.cohort import report_problem
    from dicer.quality import wave_speeds

    np.save(tmp_path / "bar.npy", np.ones((3, 2, 2), np.uint8))
    assert main(["mesh", str(tmp_path / "bar.npy"), "-o", str(tmp_path / "bar.vtu")]) == 0
    assert main(["quality", str(tmp_path / "bar.vtu"), "-o", str(tmp_path / "q.json"),
                 "--set", "materials=[{name: soft_tissue, youngs_modulus: 2000, poissons_ratio: 0.25, "
                 "density: 1.5e-9}]"]) == 0
    report = json.loads((tmp_path / "q.json").read_text())
    speed = wave_speeds([{"youngs_modulus": 2000.0, "poissons_ratio": 0.25, "density": 1.5e-9}])[1]
    assert report["explicit_time_step"]["smallest_s"] == pytest.approx(1.0 / speed, rel=1e-5)
    columns, rows = cohort_rows({"p1": report, "p2": _report(200)})
    at = columns.index("explicit_time_step_s")
    assert rows[0][at] == pytest.approx(1.0 / speed, rel=1e-5) and rows[1][at] is None
    assert "explicit time step, s</th>" in render_cohort_html(columns, rows, 0.2)
    assert report_problem(dict(report, explicit_time_step={"smallest_s": "short"})) == (
        "'explicit_time_step.smallest_s' is 'short', not a number")
