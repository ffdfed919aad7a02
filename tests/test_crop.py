"""image.crop: cut the scan or label volume to a region of interest, keeping it in place."""

import meshio
import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st

from dicer.cli import main
from dicer.crop import crop_volume
from dicer.errors import DicerError
from dicer.image import Volume
from dicer.mesh.frame import image_affine
from test_coordinates import FLIPPED, OBLIQUE, ORIGIN, SPACING, itk_points, labels_array, write_itk

SHAPE = (12, 10, 8)


def volume(direction=OBLIQUE):
    array = np.arange(np.prod(SHAPE)).reshape(SHAPE)
    return Volume(array, SPACING, tuple(np.subtract(ORIGIN, np.divide(SPACING, 2))), tuple(direction.ravel()))


def centres(vol, index):
    """Scanner (LPS) centres of voxels ``index`` (N, 3) of ``vol``."""
    a = image_affine(vol.spacing, vol.origin, vol.direction)
    return index @ a[:3, :3].T + a[:3, 3]


@settings(max_examples=40, deadline=None)
@given(st.tuples(*[st.integers(0, n - 1) for n in SHAPE]), st.tuples(*[st.integers(1, n) for n in SHAPE]),
       st.sampled_from([OBLIQUE, FLIPPED, np.eye(3)]))
def test_voxel_crop_keeps_every_voxel_in_place(start, size, direction):
    start = np.array(start)
    stop = np.minimum(start + np.array(size), SHAPE)
    vol = volume(direction)
    if np.count_nonzero(stop - start < 2) > 1:  # a line or a point: nothing any stage meshes
        with pytest.raises(DicerError, match="every stage needs 2 voxels or more along each axis"):
            crop_volume(vol, {"unit": "voxels", "min": start.tolist(), "max": stop.tolist()}, "x.nii")
        return
    out, info = crop_volume(vol, {"unit": "voxels", "min": start.tolist(), "max": stop.tolist()}, "x.nii")
    assert out.array.shape == tuple(stop - start) == tuple(info["shape"])
    assert np.array_equal(out.array, vol.array[start[0]:stop[0], start[1]:stop[1], start[2]:stop[2]])
    idx = np.indices(out.array.shape).reshape(3, -1).T
    # voxel idx of the crop is voxel start + idx of the input, at the same place (1e-9 mm)
    assert np.abs(centres(out, idx) - centres(vol, idx + start)).max() < 1e-9
    assert out.spacing == vol.spacing and out.direction == vol.direction


@pytest.mark.parametrize("direction", [np.eye(3), np.diag([-1.0, 1.0, -1.0])])
def test_mm_crop_keeps_the_voxels_whose_centres_lie_in_the_box(direction):
    vol = volume(direction)
    allc = centres(vol, np.indices(SHAPE).reshape(3, -1).T)
    lo, hi = allc.min(axis=0) + [1.1, 0.9, 2.6], allc.min(axis=0) + [3.2, 4.5, 6.25]
    out, info = crop_volume(vol, {"unit": "mm", "min": hi.tolist(), "max": lo.tolist()}, "x.nii")  # any corner order
    inside = np.all((allc >= lo - 1e-9) & (allc <= hi + 1e-9), axis=1).reshape(SHAPE)
    assert out.array.size == np.count_nonzero(inside) > 0
    assert np.array_equal(np.sort(out.array.ravel()), np.sort(vol.array[inside]))
    # a box edge exactly through a row of centres keeps that row (6.25 = 5 voxels of 1.25 mm)
    assert out.array.shape[2] == 3


def test_bad_crops_are_one_clear_error():
    vol = volume()
    for crop, what in [({"unit": "voxels", "min": [0, 0, 0], "max": [13, 10, 8]}, "inside the image's 12x10x8"),
                       ({"unit": "voxels", "min": [4, 0, 0], "max": [4, 10, 8]}, "0 <= min < max"),
                       ({"unit": "voxels", "min": [0.5, 0, 0], "max": [4, 10, 8]}, "whole voxel"),
                       ({"unit": "voxels", "min": [0, 0], "max": [4, 10]}, "3D image"),
                       ({"unit": "mm", "min": [500, 500, 500], "max": [600, 600, 600]}, "holds no voxel"),
                       ({"unit": "voxels", "min": [4, 3, 2], "max": [5, 4, 8]},
                        "image.crop keeps 1 voxel along x, 1 voxel along y; every stage needs 2 voxels")]:
        with pytest.raises(DicerError, match=what):
            crop_volume(vol, crop, "x.nii")


@pytest.fixture
def oblique_labels(tmp_path):
    src = tmp_path / "in.nii.gz"
    write_itk(src, labels_array(), OBLIQUE)
    return src


def test_labels_cli_crop_overlays_the_input(tmp_path, oblique_labels):
    out = tmp_path / "cropped.nii.gz"
    crop = "image.crop={unit: voxels, min: [1, 2, 0], max: [11, 9, 7]}"
    assert main(["labels", str(oblique_labels), "-o", str(out), "--set", crop, "-q"]) == 0
    before, after = sitk.ReadImage(str(oblique_labels)), sitk.ReadImage(str(out))
    assert after.GetSize() == (10, 7, 7)
    assert np.array_equal(sitk.GetArrayFromImage(after).T, labels_array()[1:11, 2:9, 0:7])
    idx = np.indices(after.GetSize()).reshape(3, -1).T.astype(float)
    assert np.abs(itk_points(after, idx) - itk_points(before, idx + [1, 2, 0])).max() < 1e-5  # float32 header


def test_run_labels_with_crop_model_sits_on_the_input_corners(tmp_path, oblique_labels):
    out = tmp_path / "run"
    crop = "image.crop={unit: voxels, min: [1, 1, 0], max: [11, 9, 8]}"
    assert main(["run", "--labels", str(oblique_labels), "-o", str(out), "--set", crop, "-q"]) == 0
    # the voxel mesh of the run, exported: its nodes are the voxel corners in scanner coordinates
    assert main(["export", str(out / "mesh.vtu"), "-o", str(tmp_path / "voxels.vtu"), "--materials",
                 str(out / "materials.json"), "-q"]) == 0
    model = meshio.read(tmp_path / "voxels.vtu")
    lattice = np.asarray(model.point_data["lattice"], float)
    want = itk_points(sitk.ReadImage(str(oblique_labels)), lattice + [1, 1, 0] - 0.5)
    assert np.abs(model.points - want).max() < 1e-5


def test_cli_bad_crop_leaves_nothing(tmp_path, oblique_labels, capsys):
    out = tmp_path / "run"
    code = main(["run", "--labels", str(oblique_labels), "-o", str(out), "-q",
                 "--set", "image.crop={unit: voxels, min: [0, 0, 0], max: [20, 9, 8]}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and str(oblique_labels) in err and "image.crop" in err
    assert not out.exists()
    code = main(["labels", str(oblique_labels), "-o", str(tmp_path / "l.nii.gz"), "-q",
                 "--set", "image.crop={unit: inches, min: [0, 0, 0], max: [2, 2, 2]}"])
    err = capsys.readouterr().err
    assert code == 2 and "image.crop" in err and not (tmp_path / "l.nii.gz").exists()


def test_segment_crops_the_scan_before_segmenting(tmp_path):
    scan = tmp_path / "head.nii.gz"
    assert main(["phantom", "head", "-o", str(scan), "--size", "32", "-q"]) == 0
    out, info = tmp_path / "labels.nii.gz", tmp_path / "seg.json"
    crop = "image.crop={unit: mm, min: [-1000, -1000, -1000], max: [1000, 1000, 6]}"
    assert main(["segment", str(scan), "-o", str(out), "--info", str(info), "--set", crop, "-q"]) == 0
    whole, cut = sitk.ReadImage(str(scan)), sitk.ReadImage(str(out))
    import json

    got = json.loads(info.read_text())["crop"]
    assert got["start"] == [0, 0, 0] and got["stop"][:2] == list(whole.GetSize()[:2])
    assert cut.GetSize() == tuple(got["shape"]) and cut.GetSize()[2] < whole.GetSize()[2]
    assert cut.GetOrigin() == pytest.approx(whole.GetOrigin(), abs=1e-6)
    # every kept slice's centre at z <= 6 mm, the next one above it
    z = whole.TransformIndexToPhysicalPoint((0, 0, cut.GetSize()[2]))[2]
    assert cut.TransformIndexToPhysicalPoint((0, 0, cut.GetSize()[2] - 1))[2] <= 6.0 < z


def test_run_with_crop_pulls_onto_the_scan_where_the_uncropped_run_does(tmp_path):
    # the pull samples the scan in the mesh's lattice frame: a cropped mesh starts at the crop's
    # first voxel, so the scan must be cut the same way (with flipped axes the frames differ)
    size, centre, radius = 20, np.array([9.6, 10.3, 9.2]), 6.2
    g = (np.arange(size * 4) + 0.5) / 4
    x, y, z = np.meshgrid(g, g, g, indexing="ij", sparse=True)
    inside = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2 < radius**2
    hu = 2000.0 * inside.reshape(size, 4, size, 4, size, 4).mean(axis=(1, 3, 5)) - 1000.0
    scan = tmp_path / "ball.nii.gz"
    write_itk(scan, hu, np.diag([-1.0, -1.0, 1.0]) @ OBLIQUE, np.int16)
    config = tmp_path / "config.yaml"
    config.write_text("segment: {method: manual, thresholds: [0], opening_radius: 0, closing_radius: 0, keep: all}\n"
                      "materials: [{name: solid, youngs_modulus: 1000, poissons_ratio: 0.3}]\n"
                      "smooth: {surface_from_image: true}\nmerge: {passes: [0, 0, 0]}\n"
                      "preset: explicit-dynamics\n")  # no pillow layer: one node per lattice point
    start = [2, 1, 1]
    crop = f"image.crop={{unit: voxels, min: {start}, max: [19, 20, 18]}}"
    models = []
    for name, extra in (("whole", []), ("cut", ["--set", crop])):
        out = tmp_path / name
        assert main(["run", str(scan), "-o", str(out), "--config", str(config), "-q", *extra]) == 0
        models.append(meshio.read(out / "model.vtu"))
    whole, cut = models
    at = {tuple(v): i for i, v in enumerate(np.asarray(whole.point_data["lattice"]).tolist())}
    pairs = np.array([(at[tuple(v)], j) for j, v in enumerate((np.asarray(cut.point_data["lattice"]) + start).tolist())])
    assert pairs.shape[0] == cut.points.shape[0] == whole.points.shape[0]  # the crop cuts nothing of the ball
    assert np.abs(whole.points[pairs[:, 0]] - cut.points[pairs[:, 1]]).max() < 0.01  # mm (5.7 mm when not cut)


def test_a_mm_box_on_an_oblique_scan_keeps_the_smallest_index_box_of_its_centres():
    """The index box of the mm box's corners was taken, which on a scan turned 20 degrees holds
    rows whose centres all lie outside the box (a row 0.23 mm out was kept)."""
    from dicer.crop import crop_box

    angle = np.radians(20.0)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    spacing = np.array([0.8, 0.9, 2.0])
    volume = Volume(np.zeros((40, 36, 12), np.int16), tuple(spacing), (-12.0, 3.0, 5.0), tuple(turn.ravel()))
    lo, hi = np.array([-5.0, 8.0, 9.0]), np.array([14.0, 27.0, 20.0])
    start, stop = crop_box(volume, {"unit": "mm", "min": lo.tolist(), "max": hi.tolist()}, "oblique")
    # every voxel's centre, by brute force
    index = np.stack(np.meshgrid(*[np.arange(n) for n in volume.array.shape], indexing="ij")).reshape(3, -1)
    centre0 = np.asarray(volume.origin) + spacing / 2
    centres = centre0[:, None] + turn @ (index * spacing[:, None])
    inside = np.all((centres >= lo[:, None]) & (centres <= hi[:, None]), axis=0)
    assert inside.sum() > 100
    assert start.tolist() == index[:, inside].min(axis=1).tolist()
    assert stop.tolist() == (index[:, inside].max(axis=1) + 1).tolist()
    # 2D, turned the other way
    turn2 = turn[:2, :2].T
    flat = Volume(np.zeros((50, 30), np.int16), (0.7, 1.1), (4.0, -9.0), tuple(turn2.ravel()))
    start, stop = crop_box(flat, {"unit": "mm", "min": [6.0, -20.0], "max": [30.0, 5.0]}, "oblique 2D")
    index = np.stack(np.meshgrid(np.arange(50), np.arange(30), indexing="ij")).reshape(2, -1)
    centres = (np.asarray(flat.origin) + np.array([0.35, 0.55]))[:, None] + turn2 @ (index * np.array([[0.7], [1.1]]))
    inside = np.all((centres >= np.array([[6.0], [-20.0]])) & (centres <= np.array([[30.0], [5.0]])), axis=0)
    assert inside.sum() > 50
    assert start.tolist() == index[:, inside].min(axis=1).tolist()
    assert stop.tolist() == (index[:, inside].max(axis=1) + 1).tolist()
