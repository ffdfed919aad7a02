"""Image and label I/O: round trips for every format, DICOM series, and the error cases."""

import gzip
import logging
import re

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.images import read_image, read_labels, write_image, write_labels

tifffile = pytest.importorskip("tifffile")
pydicom = pytest.importorskip("pydicom")

RNG = np.random.default_rng(7)
HU = RNG.integers(-1024, 2000, size=(7, 6, 5)).astype(np.float32)
SPACING = (0.7, 0.8, 1.5)
CORNER = (-10.0, 4.25, 30.0)


def _stored_type(path):
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    return sitk.GetPixelIDValueAsString(reader.GetPixelID())


# --- round trips through the header formats ----------------------------------------------


@pytest.mark.parametrize("ext", [".nii", ".nii.gz", ".nrrd", ".mha"])
def test_image_round_trip_int16(tmp_path, ext):
    path = tmp_path / f"ct{ext}"
    write_image(Volume(HU, SPACING, CORNER), path)
    assert _stored_type(path) == "16-bit signed integer"
    v = read_image(path)
    assert v.array.dtype == np.float32 and v.array.shape == (7, 6, 5)
    np.testing.assert_array_equal(v.array, HU)
    np.testing.assert_allclose(v.spacing, SPACING, rtol=1e-6)
    np.testing.assert_allclose(v.origin, CORNER, atol=1e-5)


@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd", ".mha"])
def test_image_round_trip_float32_when_not_integral(tmp_path, ext):
    values = HU * 0.25 + 0.125
    path = tmp_path / f"mr{ext}"
    write_image(Volume(values, SPACING, CORNER), path)
    assert _stored_type(path) == "32-bit float"
    np.testing.assert_array_equal(read_image(path).array, values)


def test_image_out_of_int16_range_is_float32(tmp_path):
    path = tmp_path / "big.nii.gz"
    write_image(Volume(np.array([[0, 40000], [1, 2]], np.float32), (1, 1)), path)
    assert _stored_type(path) == "32-bit float"
    np.testing.assert_array_equal(read_image(path).array, [[0, 40000], [1, 2]])


def test_mhd_with_raw_file(tmp_path):
    image = sitk.GetImageFromArray(np.ascontiguousarray(HU.T.astype(np.int16)))
    image.SetSpacing(SPACING)
    image.SetOrigin((1.0, 2.0, 3.0))  # ITK: centre of the first voxel
    sitk.WriteImage(image, str(tmp_path / "ct.mhd"))
    v = read_image(tmp_path / "ct.mhd")
    np.testing.assert_array_equal(v.array, HU)
    np.testing.assert_allclose(v.origin, (1.0 - 0.35, 2.0 - 0.4, 3.0 - 0.75))


def test_nifti_spacing_reads_back_as_short_decimal(tmp_path):
    write_image(Volume(HU, (0.7, 0.957, 1.5)), tmp_path / "a.nii.gz")
    assert read_image(tmp_path / "a.nii.gz").spacing == (0.7, 0.957, 1.5)


@settings(max_examples=15, deadline=None)
@given(
    shape=st.lists(st.integers(2, 6), min_size=2, max_size=3),
    spacing=st.floats(0.1, 5.0),
    seed=st.integers(0, 2**16),
)
def test_image_round_trip_property(tmp_path_factory, shape, spacing, seed):
    rng = np.random.default_rng(seed)
    values = rng.normal(0, 300, size=shape).astype(np.float32)
    sp = tuple(spacing * (1 + i) for i in range(len(shape)))
    path = tmp_path_factory.mktemp("rt") / "x.nrrd"
    write_image(Volume(values, sp, tuple(-s for s in sp)), path)
    v = read_image(path)
    np.testing.assert_array_equal(v.array, values)
    np.testing.assert_allclose(v.spacing, sp, rtol=1e-12)
    np.testing.assert_allclose(v.origin, [-s for s in sp], atol=1e-9)


def test_2d_nifti_and_singleton_axis(tmp_path, caplog):
    img2d = HU[:, :, 0]
    write_image(Volume(img2d, (0.5, 0.25), (1.0, 2.0)), tmp_path / "slice.nii")
    v = read_image(tmp_path / "slice.nii")
    assert v.ndim == 2 and v.spacing == (0.5, 0.25)
    np.testing.assert_array_equal(v.array, img2d)
    np.testing.assert_allclose(v.origin, (1.0, 2.0))
    # a 3D file with a single slice becomes 2D; the remaining axes keep their spacing
    write_image(Volume(HU[:, :, :1], SPACING, CORNER), tmp_path / "one.nrrd")
    with caplog.at_level(logging.INFO, logger="dicer"):
        v = read_image(tmp_path / "one.nrrd")
    assert f"one.nrrd: one voxel along z ({SPACING[2]:g} mm): read as a 2D image" in caplog.text
    # said once a process: dicer run reads its label files again at every stage (6 times a run)
    with caplog.at_level(logging.INFO, logger="dicer"):
        read_image(tmp_path / "one.nrrd")
    assert caplog.text.count("one voxel along z") == 1
    assert v.array.shape == (7, 6) and v.spacing == SPACING[:2]
    np.testing.assert_allclose(v.origin, CORNER[:2])


# --- formats without a voxel size -------------------------------------------------------


def test_npy_spacing_argument_and_default_warning(tmp_path, caplog):
    np.save(tmp_path / "a.npy", HU.astype(np.int16))
    v = read_image(tmp_path / "a.npy", spacing=[0.5, 0.5, 2.0])
    assert v.spacing == (0.5, 0.5, 2.0) and v.origin == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(v.array, HU)
    assert v.array.dtype == np.float32
    with caplog.at_level(logging.WARNING, logger="dicer"):
        v = read_image(tmp_path / "a.npy")
    assert v.spacing == (1.0, 1.0, 1.0)
    assert "no voxel size" in caplog.text
    with pytest.raises(DicerError, match="3D but the given spacing has 2"):
        read_image(tmp_path / "a.npy", spacing=[1, 1])


def test_npy_with_one_channel_first_or_last_is_its_3d_volume(tmp_path):
    """A segmentation saved with its channel axis, (1, x, y, z) as deep-learning tools write it
    or (x, y, z, 1): the volume. A 4D array of more channels, or one elsewhere, is refused."""
    np.save(tmp_path / "first.npy", HU[None].astype(np.int16))
    np.save(tmp_path / "last.npy", HU[..., None].astype(np.int16))
    for name in ("first", "last"):
        v = read_image(tmp_path / f"{name}.npy", spacing=[0.5, 0.5, 2.0])
        np.testing.assert_array_equal(v.array, HU)
    np.save(tmp_path / "middle.npy", HU[:, None].astype(np.int16))
    with pytest.raises(DicerError, match=r"middle.npy: the array is 4D \(7x1x6x5\).*one channel first or last"):
        read_image(tmp_path / "middle.npy")


def test_multipage_tiff_is_3d_single_page_is_2d(tmp_path):
    stack = HU.astype(np.int16)
    tifffile.imwrite(tmp_path / "stack.tif", np.ascontiguousarray(stack.T))  # pages = z, rows = y
    v = read_image(tmp_path / "stack.tif", spacing=(0.3, 0.3, 1.0))
    assert v.array.shape == (7, 6, 5) and v.spacing == (0.3, 0.3, 1.0)
    np.testing.assert_array_equal(v.array, stack)
    tifffile.imwrite(tmp_path / "page.tiff", np.ascontiguousarray(stack[:, :, 2].T))
    v = read_image(tmp_path / "page.tiff", spacing=0.3)
    assert v.ndim == 2 and v.spacing == (0.3, 0.3)
    np.testing.assert_array_equal(v.array, stack[:, :, 2])


@pytest.mark.parametrize("kind", ["png", "tif"])
def test_slice_folder_natural_order(tmp_path, kind):
    nz = 12  # names slice1 .. slice12 so that plain sorting would put slice10 first
    vol = RNG.integers(0, 60000, size=(5, 4, nz)).astype(np.uint16)
    for k in range(nz):
        sitk.WriteImage(sitk.GetImageFromArray(np.ascontiguousarray(vol[:, :, k].T)),
                        str(tmp_path / f"slice{k + 1}.{kind}"))
    (tmp_path / ".hidden").write_text("ignored")
    v = read_image(tmp_path, spacing=(0.4, 0.4, 1.2))
    assert v.array.shape == (5, 4, nz) and v.spacing == (0.4, 0.4, 1.2) and v.origin == (0.0, 0.0, 0.0)
    np.testing.assert_array_equal(v.array, vol)


def test_png_single_image_2d(tmp_path):
    img = RNG.integers(0, 255, size=(9, 4)).astype(np.uint8)
    sitk.WriteImage(sitk.GetImageFromArray(np.ascontiguousarray(img.T)), str(tmp_path / "a.png"))
    v = read_image(tmp_path / "a.png", spacing=[0.2, 0.3])
    assert v.array.shape == (9, 4) and v.spacing == (0.2, 0.3)
    np.testing.assert_array_equal(v.array, img)


# --- DICOM ------------------------------------------------------------------------------

SECRET_NAME = "Testperson^Zelda"
SECRET_ID = "PID-88231577"


def _write_dicom_series(folder, nslices, series_uid, stored, z0=-20.0, dz=2.5, prefix="im", order=None,
                        positions=None, shift_y=0.0, pixel_spacing=True, patient_id=None, study_uid=None,
                        padding=None, modality=None, bits_stored=None):
    """Write a CT series built on pydicom's CT_small.dcm: stored values, slope 2, intercept -1024.

    Slice k lies at z = ``positions[k]`` (default ``z0 + dz * k``); its SliceThickness is
    a misleading 5 mm so that the spacing can only come from the positions.
    """
    from pydicom.data import get_testdata_file
    from pydicom.uid import generate_uid

    template = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
    order = list(range(nslices)) if order is None else order
    for k in range(nslices):
        ds = template.copy()
        ds.PatientName = SECRET_NAME
        ds.PatientID = SECRET_ID if patient_id is None else patient_id
        if study_uid is not None:
            ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        uid = generate_uid(entropy_srcs=[series_uid, str(k)])
        ds.SOPInstanceUID = uid
        ds.file_meta.MediaStorageSOPInstanceUID = uid
        ny, nx = stored.shape[1], stored.shape[0]
        ds.Rows, ds.Columns = ny, nx
        ds.PixelSpacing = [0.6, 0.8]  # row spacing (y), column spacing (x)
        if not pixel_spacing:
            del ds.PixelSpacing
        z = z0 + dz * k if positions is None else positions[k]
        ds.SliceThickness = 5.0
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [-50.0, -60.0 + shift_y * k, z]  # shift_y: a gantry tilt
        ds.SliceLocation = z
        ds.InstanceNumber = nslices - k  # misleading on purpose: position must decide
        ds.RescaleSlope = 2
        ds.RescaleIntercept = -1024
        if bits_stored is not None:  # unsigned, as a 12-bit CT stores its values
            ds.BitsStored, ds.HighBit, ds.PixelRepresentation = bits_stored, bits_stored - 1, 0
        if padding is not None:
            ds.add_new(0x00280120, "SS" if ds.PixelRepresentation else "US", padding)  # Pixel Padding Value
        if modality is not None:
            ds.Modality = modality
        for tag in ("SmallestImagePixelValue", "LargestImagePixelValue"):
            if tag in ds:
                delattr(ds, tag)
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T.astype(np.int16)).tobytes()  # rows = y
        ds.save_as(folder / f"{prefix}{order[k]:03d}.dcm")


@pytest.fixture
def dicom_folder(tmp_path):
    folder = tmp_path / "dicom"
    folder.mkdir()
    stored = np.zeros((10, 8, 6), np.int16)
    stored += (np.arange(6, dtype=np.int16) * 100)[None, None, :]  # slice k holds 100 k + ...
    stored += (np.arange(10, dtype=np.int16)[:, None] + 10 * np.arange(8, dtype=np.int16)[None, :])[:, :, None]
    order = [3, 0, 5, 1, 4, 2]  # file names shuffled against slice position
    _write_dicom_series(folder, 6, "1.2.826.0.1.3680043.8.498.1", stored, order=order)
    return folder, stored


def test_dicom_series_in_hu_ordered_by_position(dicom_folder, tmp_path, caplog):
    folder, stored = dicom_folder
    with caplog.at_level(logging.DEBUG, logger="dicer"):
        v = read_image(folder)
    assert v.array.shape == (10, 8, 6) and v.array.dtype == np.float32
    np.testing.assert_array_equal(v.array, stored.astype(np.float32) * 2 - 1024)
    np.testing.assert_allclose(v.spacing, (0.8, 0.6, 2.5), rtol=1e-6)
    np.testing.assert_allclose(v.origin, (-50.0 - 0.4, -60.0 - 0.3, -20.0 - 1.25), atol=1e-4)
    # the label file derived from it carries no patient information
    out = tmp_path / "labels.nii.gz"
    write_labels(Volume((v.array > -500).astype(np.uint8), v.spacing, v.origin), out)
    raw = out.read_bytes()
    for secret in (SECRET_NAME, SECRET_ID, "Testperson", "Zelda"):
        assert secret.encode() not in raw
        assert secret.encode() not in gzip.decompress(raw)
        assert secret not in caplog.text


def _head_like(shape=(24, 22, 8)):
    """Stored values of a disc of 'tissue' with a brighter core, on a dark background."""
    x, y = np.meshgrid(np.arange(shape[0]) - shape[0] / 2, np.arange(shape[1]) - shape[1] / 2, indexing="ij")
    r = np.hypot(x, y)[:, :, None] + np.zeros(shape)
    return np.where(r < 5, 1400, np.where(r < 9, 900, 20)).astype(np.int16)


@pytest.mark.parametrize("modality, refused", [("MR", True), ("PT", True), ("CT", False), (None, False)])
def test_segmentation_refuses_ct_defaults_for_a_series_that_is_not_ct(tmp_path, capsys, modality, refused):
    from dicer.cli import main

    folder = tmp_path / "series"
    folder.mkdir()
    _write_dicom_series(folder, 8, "1.2.826.0.1.3680043.8.498.7", _head_like(), modality=modality)
    assert read_image(folder).modality == (modality or "CT")  # the template is a CT
    out = tmp_path / "labels.nii.gz"
    code = main(["segment", str(folder), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    if not refused:
        assert code == 0 and out.exists()
        return
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and not out.exists()
    assert lines[0].startswith(f"error: {folder}: the scan is ") and f"(DICOM Modality {modality})" in lines[0]
    assert "segment.method: multiotsu" in lines[0] and "segment.ranges" in lines[0]
    # the histogram's thresholds, or ranges set for the image's values, take the same series
    assert main(["segment", str(folder), "-o", str(out), "-q", "--set", "segment.method=multiotsu"]) == 0
    labels = read_labels(out).array
    assert np.count_nonzero(labels == 2) == np.count_nonzero(_head_like() * 2 - 1024 >= 1400 * 2 - 1024)
    out.unlink()
    assert main(["segment", str(folder), "-o", str(out), "-q", "--set", "segment.method=manual",
                 "--set", "segment.thresholds=[0, 1000]"]) == 0


def test_modality_from_a_bids_sidecar(tmp_path):
    from dicer.segment import segment

    image = tmp_path / "sub-01_T1w.nii.gz"
    write_image(Volume(_head_like().astype(np.float32), (1.0, 1.0, 1.0)), image)
    assert read_image(image).modality is None
    sidecar = tmp_path / "sub-01_T1w.json"
    sidecar.write_text('{"Modality": "MR", "MagneticFieldStrength": 3}')
    volume = read_image(image)
    assert volume.modality == "MR"
    with pytest.raises(DicerError, match=r"the scan is an MR \(DICOM Modality MR\), not a CT"):
        segment(volume, source=str(image))
    _, info = segment(volume, {"segment": {"method": "multiotsu"}}, str(image))
    assert info["thresholds"][0] > 20  # the dark background is background
    for text in ("not json {", '["Modality", "MR"]', '{"Modality": 3}', '{"Modality": " "}', "[" * 100_000):
        sidecar.write_text(text)  # the last nests past the JSON parser's recursion
        assert read_image(image).modality is None


def test_modality_from_the_first_slice_that_gives_it(tmp_path):
    import pydicom

    _write_dicom_series(tmp_path, 6, "1.2.826.0.1.3680043.8.498.8", _head_like(shape=(24, 22, 6)), modality="MR")
    for name in ("im000.dcm", "im001.dcm", "im002.dcm", "im003.dcm", "im004.dcm"):  # im005 alone says it
        ds = pydicom.dcmread(tmp_path / name)
        del ds.Modality
        ds.save_as(tmp_path / name)
    assert read_image(tmp_path).modality == "MR"


def test_dicom_picks_the_largest_series(dicom_folder, caplog):
    folder, stored = dicom_folder
    small = np.full((10, 8, 3), 7, np.int16)
    _write_dicom_series(folder, 3, "1.2.826.0.1.3680043.8.498.2", small, prefix="other")
    with caplog.at_level(logging.INFO, logger="dicer"):
        v = read_image(folder)
    assert v.array.shape == (10, 8, 6)
    np.testing.assert_array_equal(v.array, stored * 2.0 - 1024)
    assert "2 DICOM series" in caplog.text and "(6)" in caplog.text
    for secret in (SECRET_NAME, SECRET_ID, "1.2.826.0.1.3680043.8.498"):
        assert secret not in caplog.text


def test_ct_small_single_file():
    from pydicom.data import get_testdata_file

    path = get_testdata_file("CT_small.dcm")
    ds = pydicom.dcmread(path)
    hu = ds.pixel_array.astype(np.float32) * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    v = read_image(path)
    assert v.ndim == 2 and v.array.shape == (128, 128)
    np.testing.assert_array_equal(v.array, hu.T)
    np.testing.assert_allclose(v.spacing, [float(s) for s in ds.PixelSpacing[::-1]])


def _series_at(tmp_path, positions, name="series"):
    folder = tmp_path / name
    folder.mkdir()
    n = len(positions)
    stored = np.broadcast_to((np.arange(n, dtype=np.int16) * 100)[None, None, :], (10, 8, n))
    _write_dicom_series(folder, n, "1.2.826.0.1.3680043.8.498.9", stored, positions=positions)
    return folder


def test_dicom_spacing_from_positions_not_header(tmp_path):
    v = read_image(_series_at(tmp_path, [10.0, 12.0, 14.0, 16.0, 18.0, 20.0]))
    assert v.array.shape == (10, 8, 6)
    assert v.spacing[2] == pytest.approx(2.0)  # SliceThickness says 5
    np.testing.assert_array_equal(v.array[0, 0], np.arange(6) * 200.0 - 1024)


@pytest.mark.parametrize("case,positions,message", [
    ("gap", [0.0, 2.0, 4.0, 8.0, 10.0, 12.0], r"misses slices between positions 4 and 8 mm \(step 4 mm\)"),
    ("irregular", [0.0, 2.0, 4.0, 7.0, 8.0, 10.0], r"uneven slice steps between positions 4 and 7 mm"),
    ("duplicate", [0.0, 2.0, 4.0, 4.0, 6.0, 8.0], r"same position along the slice normal \(4 mm"),
])
def test_dicom_uneven_series_refused(tmp_path, case, positions, message):
    folder = _series_at(tmp_path, positions)
    with pytest.raises(DicerError, match=message) as err:
        read_image(folder)
    text = str(err.value)
    assert text.startswith(f"{folder}: ")
    assert ("allow_irregular_slices" in text) == (case != "duplicate")
    for secret in (SECRET_NAME, SECRET_ID, "Testperson", "1.2.826.0.1.3680043.8.498"):
        assert secret not in text


def test_dicom_uneven_series_resampled_when_allowed(tmp_path, caplog):
    irregular = _series_at(tmp_path, [0.0, 2.0, 4.0, 7.0, 8.0, 10.0], "irregular")
    with caplog.at_level(logging.WARNING, logger="dicer"):
        v = read_image(irregular, allow_irregular_slices=True)
    assert "resampled its 6 slices to 6 uniform slices of 2 mm" in caplog.text
    assert v.array.shape == (10, 8, 6) and v.spacing[2] == pytest.approx(2.0)
    # slices hold 200 k - 1024; z = 6 lies 2/3 of the way from z = 4 (k 2) to z = 7 (k 3)
    expected = np.array([0, 1, 2, 2 + 2 / 3, 4, 5]) * 200.0 - 1024
    np.testing.assert_allclose(v.array[3, 4], expected, rtol=1e-6)
    gap = _series_at(tmp_path, [0.0, 2.0, 4.0, 8.0, 10.0], "gap")
    v = read_image(gap, allow_irregular_slices=True)
    assert v.array.shape == (10, 8, 6)
    np.testing.assert_allclose(v.array[0, 0], np.array([0, 1, 2, 2.5, 3, 4]) * 200.0 - 1024)
    duplicate = _series_at(tmp_path, [0.0, 2.0, 2.0, 4.0], "duplicate")
    with pytest.raises(DicerError, match="same position"):
        read_image(duplicate, allow_irregular_slices=True)


def test_dicom_tolerance_and_decreasing_positions(tmp_path):
    # positions written with rounding noise well inside 1 % of the step, in reverse file order
    v = read_image(_series_at(tmp_path, [10.0, 8.004, 6.0, 3.998, 2.0, 0.0]))
    assert v.spacing[2] == pytest.approx(2.0, abs=0.01)
    np.testing.assert_array_equal(v.array[0, 0], np.arange(5, -1, -1) * 200.0 - 1024)


@pytest.mark.parametrize("damage", ["truncated", "header only", "random bytes", "short pixel data"])
def test_dicom_damaged_slice_named(tmp_path, damage):
    """Also a slice whose pixel data element is shorter than its rows and columns promise, the
    file otherwise whole: GDCM read it padded with zeros, air over the rest of the slice."""
    import pydicom

    folder = _series_at(tmp_path, [0.0, 2.0, 4.0, 6.0, 8.0, 10.0])
    slice_file = sorted(folder.iterdir())[3]
    data = slice_file.read_bytes()
    if damage == "short pixel data":
        ds = pydicom.dcmread(slice_file)
        ds.PixelData = ds.PixelData[:50]
        ds.save_as(slice_file)
    else:
        slice_file.write_bytes({"truncated": data[:-40], "header only": data[:300],
                                "random bytes": RNG.integers(0, 256, 4000).astype(np.uint8).tobytes()}[damage])
    with pytest.raises(DicerError) as err:
        read_image(folder)
    assert str(err.value).startswith(f"{slice_file}: this slice of the DICOM series cannot be read")
    if damage == "short pixel data":
        assert "its pixel data holds 50 bytes where its header promises 160, 10 x 8 x 16 bits" in str(err.value)


def test_dicom_notes_and_dicomdir_beside_the_series(tmp_path):
    folder = _series_at(tmp_path, [0.0, 2.0, 4.0])
    (folder / "notes.txt").write_text("scanned on a Tuesday")
    (folder / "DICOMDIR").write_bytes(bytes(200))
    assert read_image(folder).array.shape == (10, 8, 3)


# --- input sanity: non-finite voxels, spacing, raw data size --------------------------------


@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd", ".mha", ".npy"])
def test_nan_and_inf_voxels_refused(tmp_path, ext):
    values = HU.copy()
    values[1, 2, 3] = np.nan
    values[0, 0, 0] = np.inf
    values[0, 1, 0] = -np.inf
    path = tmp_path / f"mr{ext}"
    if ext == ".npy":
        np.save(path, values)
    else:
        write_image(Volume(values, SPACING), path)
    with pytest.raises(DicerError, match=f"mr{ext.replace('.', '[.]')}: 1 NaN and 2 infinite voxel value"):
        read_image(path)


def _nifti_with_pixdim(path, value, axis=2):
    write_image(Volume(HU, SPACING), path)
    data = bytearray(path.read_bytes())
    import struct

    data[76 + 4 * axis : 80 + 4 * axis] = struct.pack("<f", value)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("value", [0.0, float("nan"), float("inf"), -1.5])
def test_nifti_bad_pixdim_refused_or_replaced(tmp_path, value):
    path = tmp_path / "ct.nii"
    _nifti_with_pixdim(path, value)
    with pytest.raises(DicerError, match=r"ct[.]nii: the header's voxel spacing \(pixdim\) .*image[.]spacing"):
        read_image(path)
    v = read_image(path, spacing=[0.5, 0.6, 0.7])
    assert v.spacing == (0.5, 0.6, 0.7)
    np.testing.assert_array_equal(v.array, HU)


@pytest.mark.parametrize("slope, inter, refused", [(0.0, 5.0, True), (0.0, 0.0, False), (1.0, 5.0, False),
                                                   (float("nan"), -1024.0, True)])
def test_nifti_zero_slope_with_an_intercept_is_refused(tmp_path, slope, inter, refused):
    """A zero scl_slope means unscaled values (the NIfTI standard); ITK would add the
    intercept to every voxel: a label volume's background would become label 5."""
    import struct

    path = tmp_path / "ct.nii"
    write_image(Volume(HU, SPACING), path)
    data = bytearray(path.read_bytes())
    struct.pack_into("<2f", data, 112, slope, inter)
    path.write_bytes(bytes(data))
    if refused:
        with pytest.raises(DicerError, match=rf"ct[.]nii: the header's scl_slope is {slope:g} and scl_inter {inter:g}: "
                                             r".* set scl_slope to 1 and scl_inter to 0"):
            read_image(path)
    else:
        np.testing.assert_array_equal(read_image(path).array, HU + (inter if slope else 0))


def test_metaimage_infinite_spacing_refused(tmp_path):
    path = tmp_path / "z.mha"
    header = "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementSpacing = 1 inf 1\nElementType = MET_UCHAR\n"
    path.write_bytes((header + "ElementDataFile = LOCAL\n").encode() + bytes(8))
    with pytest.raises(DicerError, match="z.mha: .*not finite.*image.spacing"):
        read_image(path)


def _raw_headers(tmp_path, dims, nbytes):
    """A .mhd and a .nhdr header for ``dims`` int16 voxels, each beside ``nbytes`` of raw data."""
    (tmp_path / "ct.raw").write_bytes(bytes(nbytes))
    size = " ".join(map(str, dims))
    (tmp_path / "ct.mhd").write_text(f"ObjectType = Image\nNDims = 3\nDimSize = {size}\nElementSpacing = 1 1 1\n"
                                     "ElementType = MET_SHORT\nElementDataFile = ct.raw\n")
    (tmp_path / "ct.nhdr").write_text(f"NRRD0004\ntype: short\ndimension: 3\nsizes: {size}\n"
                                      "spacings: 1 1 1\nencoding: raw\nendian: little\ndata file: ct.raw\n")
    return tmp_path / "ct.mhd", tmp_path / "ct.nhdr"


@pytest.mark.parametrize("header", [0, 1])
def test_header_only_raw_size_checked(tmp_path, header):
    path = _raw_headers(tmp_path, (4, 5, 6), 4 * 5 * 6 * 2)[header]
    assert read_image(path).array.shape == (4, 5, 6)
    for nbytes in (4 * 5 * 6 * 2 - 10, 4 * 5 * 6 * 2 + 100):
        path = _raw_headers(tmp_path, (4, 5, 6), nbytes)[header]
        with pytest.raises(DicerError, match=f"{path.name}: the header promises 4x5x6 elements of 2 byte.* "
                                             f"= 240 bytes .* holds {nbytes - 0} [(]in ct.raw[)]"):
            read_image(path)
    # dimensions that would need terabytes: refused before anything is allocated
    path = _raw_headers(tmp_path, (100000, 100000, 1000), 240)[header]
    with pytest.raises(DicerError, match="20000000000000 bytes"):
        read_image(path)
    (tmp_path / "ct.raw").unlink()
    with pytest.raises(DicerError, match="data file 'ct.raw' named by the header is missing"):
        read_image(path)


def test_attached_raw_nrrd_and_mha_size_checked(tmp_path):
    nrrd = tmp_path / "a.nrrd"
    head = b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: raw\n\n"
    nrrd.write_bytes(head + bytes(24))
    assert read_image(nrrd).array.shape == (2, 3, 4)
    nrrd.write_bytes(head + bytes(20))
    with pytest.raises(DicerError, match="a.nrrd: the header promises 2x3x4 elements of 1 byte.* holds 20;"):
        read_image(nrrd)
    mha = tmp_path / "a.mha"
    head = b"ObjectType = Image\nNDims = 3\nDimSize = 2 3 4\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n"
    mha.write_bytes(head + bytes(96))
    assert read_image(mha).array.shape == (2, 3, 4)
    mha.write_bytes(head + bytes(90))
    with pytest.raises(DicerError, match="a.mha: the header promises 2x3x4 elements of 4 byte.* holds 90;"):
        read_image(mha)


# --- labels ------------------------------------------------------------------------------


def test_write_labels_dtype_header_and_determinism(tmp_path):
    labels = RNG.integers(0, 3, size=(9, 7, 5)).astype(np.int64)
    vol = Volume(labels, SPACING, CORNER)
    a, b = tmp_path / "a.nii.gz", tmp_path / "sub" / "b.nii.gz"
    write_labels(vol, a)
    write_labels(vol, b)
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes()[4:8] == b"\0\0\0\0"  # gzip MTIME: no timestamp
    assert _stored_type(a) == "8-bit unsigned integer"
    back = read_labels(a)
    assert back.array.dtype == np.uint8
    np.testing.assert_array_equal(back.array, labels)
    np.testing.assert_allclose(back.spacing, SPACING)
    np.testing.assert_allclose(back.origin, CORNER, atol=1e-5)
    big = labels.copy()
    big[0, 0, 0] = 300
    write_labels(Volume(big, SPACING), tmp_path / "big.nii")
    assert _stored_type(tmp_path / "big.nii") == "16-bit unsigned integer"
    back = read_labels(tmp_path / "big.nii")
    assert back.array.dtype == np.int16 and back.array.max() == 300
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.nii.gz", "big.nii", "sub"]  # no temp files


@pytest.mark.parametrize("ext", [".nrrd", ".mha", ".npy"])
def test_read_labels_other_formats(tmp_path, ext):
    labels = RNG.integers(0, 4, size=(6, 5, 4)).astype(np.uint8)
    path = tmp_path / f"l{ext}"
    if ext == ".npy":
        np.save(path, labels.astype(np.int32))
    else:
        img = sitk.GetImageFromArray(np.ascontiguousarray(labels.T))
        img.SetSpacing((0.5, 0.5, 0.5))
        sitk.WriteImage(img, str(path))
    v = read_labels(path)
    assert v.array.dtype == np.uint8
    np.testing.assert_array_equal(v.array, labels)
    assert v.spacing == ((1.0,) * 3 if ext == ".npy" else (0.5,) * 3)


def test_read_labels_rejects_fractions_and_negatives(tmp_path):
    np.save(tmp_path / "f.npy", np.full((3, 3, 3), 0.5))
    with pytest.raises(DicerError, match="not whole numbers"):
        read_labels(tmp_path / "f.npy")
    np.save(tmp_path / "n.npy", np.full((3, 3, 3), -1, np.int16))
    with pytest.raises(DicerError, match="negative"):
        read_labels(tmp_path / "n.npy")
    np.save(tmp_path / "ok.npy", np.full((3, 3, 3), 2.0))
    assert read_labels(tmp_path / "ok.npy").array.dtype == np.uint8
    # float32 rounds 2**31 - 1 up to 2**31, which equals int32's largest in float32 arithmetic:
    # it was cast to -2**31 (with a RuntimeWarning) and named 'label_-2147483648'
    big = np.full((3, 3, 3), 1234567, np.float32)
    big[1, 1, 1] = 2147483647
    np.save(tmp_path / "big.npy", big)
    with pytest.raises(DicerError, match=r"label value 2147483648 is too large \(at most 2147483647\)"):
        read_labels(tmp_path / "big.npy")
    (tmp_path / "x.png").touch()
    with pytest.raises(DicerError, match="NIfTI"):
        read_labels(tmp_path / "x.png")


def test_write_labels_rejects_bad_values_and_leaves_nothing(tmp_path):
    for bad in (np.full((3, 3), -1), np.full((3, 3), 0.5), np.full((3, 3), 70000)):
        with pytest.raises(DicerError):
            write_labels(Volume(bad, (1, 1)), tmp_path / "l.nii.gz")
    with pytest.raises(DicerError, match="NIfTI"):
        write_labels(Volume(np.zeros((3, 3), np.uint8), (1, 1)), tmp_path / "l.vtu")
    assert list(tmp_path.iterdir()) == []


# --- errors ------------------------------------------------------------------------------


def test_missing_unknown_and_empty(tmp_path):
    with pytest.raises(DicerError, match="no such file") as err:
        read_image(tmp_path / "nope.nii.gz")
    assert "nope.nii.gz" in str(err.value)
    (tmp_path / "a.xyz").write_text("x")
    with pytest.raises(DicerError, match="unknown image format"):
        read_image(tmp_path / "a.xyz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DicerError, match="empty"):
        read_image(tmp_path / "empty")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("not an image")
    with pytest.raises(DicerError, match="no DICOM series"):
        read_image(tmp_path / "junk")
    with pytest.raises(DicerError, match="no such file"):
        read_labels(tmp_path / "nope.nii.gz")


@pytest.mark.parametrize("ext,cut", [(".nii.gz", 0.5), (".nii", 0.9), (".nrrd", 0.9), (".mha", 0.9)])
def test_truncated_file(tmp_path, ext, cut):
    path = tmp_path / f"ct{ext}"
    write_image(Volume(HU, SPACING), path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut)])
    with pytest.raises(DicerError, match=f"ct{ext.replace('.', '[.]')}: .*(truncated|cannot read)"):
        read_image(path)


def test_4d_and_colour_are_refused(tmp_path):
    four_d = sitk.GetImageFromArray(np.zeros((2, 3, 4, 5), np.float32), isVector=False)
    sitk.WriteImage(four_d, str(tmp_path / "t.nii.gz"))
    with pytest.raises(DicerError, match="4D.*2D and 3D"):
        read_image(tmp_path / "t.nii.gz")
    # a single time point is a 3D volume
    one_t = sitk.GetImageFromArray(np.ones((1, 3, 4, 5), np.float32), isVector=False)
    sitk.WriteImage(one_t, str(tmp_path / "t1.nii.gz"))
    assert read_image(tmp_path / "t1.nii.gz").array.shape == (5, 4, 3)
    rgb = np.zeros((5, 6, 3), np.uint8)
    sitk.WriteImage(sitk.GetImageFromArray(rgb, isVector=True), str(tmp_path / "c.png"))
    with pytest.raises(DicerError, match="3 components.*greyscale"):
        read_image(tmp_path / "c.png")


def test_zero_or_negative_spacing(tmp_path):
    np.save(tmp_path / "a.npy", HU)
    with pytest.raises(DicerError, match="zero, negative"):
        read_image(tmp_path / "a.npy", spacing=(1.0, 0.0, 1.0))
    with pytest.raises(DicerError, match="zero, negative"):
        read_image(tmp_path / "a.npy", spacing=(1.0, -2.0, 1.0))
    header = "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementSpacing = {}\nElementType = MET_UCHAR\n"
    for sp in ("0 1 1", "1 -1 1"):
        path = tmp_path / "z.mha"
        path.write_bytes((header.format(sp) + "ElementDataFile = LOCAL\n").encode() + bytes(8))
        with pytest.raises(DicerError, match="z.mha: .*(zero|negative)"):
            read_image(path)
    with pytest.raises(DicerError, match="zero, negative"):
        write_image(Volume(HU, (1.0, 0.0, 1.0)), tmp_path / "w.nii.gz")


@pytest.mark.parametrize("size", [1e-20, 1e-8, 2e6, 1e18])
def test_voxel_sizes_no_scan_has_are_refused_or_replaced(tmp_path, size, caplog):
    """Voxels smaller than an atom or larger than a kilometre: a header in other units or
    damaged. 1e18 mm voxels overflowed the smoothing's squared edges (an error naming
    non-finite coordinates), 1e-20 mm ones were smoothed 0.4 to 0.75 voxel from the same
    model at 1 mm, without a word."""
    path = tmp_path / "s.nii.gz"
    img = sitk.GetImageFromArray(np.ones((4, 4, 4), np.uint8))
    img.SetSpacing((1.0, size, 1.0))
    sitk.WriteImage(img, str(path))
    with pytest.raises(DicerError, match=r"s\.nii\.gz: the header's voxel spacing \(pixdim\) is 1, .* mm: zero, "
                                         r"negative, not finite or outside 1e-07 to 1e\+06 mm; fix the spacing"):
        read_image(path)
    assert read_image(path, spacing=(1.0, 0.5, 1.0)).spacing[1] == 0.5
    assert "outside 1e-07 to 1e+06 mm; using image.spacing" in caplog.text
    np.save(tmp_path / "a.npy", HU)
    with pytest.raises(DicerError, match="outside 1e-07 to 1e\\+06 mm; give every axis its voxel size in mm"):
        read_image(tmp_path / "a.npy", spacing=(1.0, size, 1.0))
    read_image(tmp_path / "a.npy", spacing=(1.0, 1e-7, 1e6))  # the range's ends are scans' voxels


def test_one_dimensional_image_refused(tmp_path):
    np.save(tmp_path / "line.npy", np.zeros((5, 1, 1)))
    with pytest.raises(DicerError, match="2D or 3D"):
        read_image(tmp_path / "line.npy")


def test_write_image_unknown_extension(tmp_path):
    with pytest.raises(DicerError, match="rename"):
        write_image(Volume(HU, SPACING), tmp_path / "a.png")


def test_tiff_resolution_tags_are_named_where_they_are_not_taken(tmp_path, caplog):
    """A TIFF whose tags give 0.1 mm was said to carry no voxel size (and was meshed 10 times
    as long)."""
    img = sitk.GetImageFromArray((np.arange(64 * 64).reshape(64, 64) % 200).astype(np.uint8))
    img.SetSpacing((0.1, 0.1))
    sitk.WriteImage(img, str(tmp_path / "s.tif"))
    with caplog.at_level(logging.WARNING, logger="dicer"):
        assert read_image(tmp_path / "s.tif").spacing == (1.0, 1.0)
    assert "s.tif: the file's resolution tags give 0.1 x 0.1 mm per pixel, which is not taken as the voxel size" \
           in caplog.text and "no voxel size" not in caplog.text
    assert read_image(tmp_path / "s.tif", spacing=(0.1, 0.1)).spacing == (0.1, 0.1)


def test_a_png_of_grey_and_alpha_is_named_so(tmp_path):
    """ITK names no pixel type for it: 'check that the file is complete' misled."""
    path = tmp_path / "la.png"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((16, 16, 2), np.uint8), isVector=True), str(path))
    with pytest.raises(DicerError, match=r"la\.png: a PNG of grey and alpha channels; dicer reads single-channel "
                                         r"\(greyscale\) images: convert it to greyscale without alpha$"):
        read_image(path)


@pytest.mark.parametrize("name", ["bad.nii.gz", "bad.nii", "bad.nrrd", "bad.mha", "bad.npy", "bad.png"])
def test_garbage_file_is_unreadable(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(DicerError, match=name.replace(".", "[.]")):
        read_image(path)


def test_dicom_folder_with_a_stray_preview_png(dicom_folder):
    folder, stored = dicom_folder
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 4), np.uint8)), str(folder / "preview.png"))
    assert read_image(folder).array.shape == stored.shape


def test_folder_of_subfolders(tmp_path):
    (tmp_path / "series1").mkdir()
    with pytest.raises(DicerError, match="only subfolders"):
        read_image(tmp_path)


def test_spacing_argument_shapes(tmp_path):
    img = RNG.integers(0, 255, size=(6, 5)).astype(np.uint8)
    sitk.WriteImage(sitk.GetImageFromArray(np.ascontiguousarray(img.T)), str(tmp_path / "a.png"))
    # one image.spacing for stacks and single slices: a 2D image takes x and y
    assert read_image(tmp_path / "a.png", spacing=[0.2, 0.3, 2.0]).spacing == (0.2, 0.3)
    np.save(tmp_path / "sag.npy", np.zeros((1, 4, 5)))
    assert read_image(tmp_path / "sag.npy", spacing=[9.0, 0.5, 0.6]).spacing == (0.5, 0.6)
    assert read_image(tmp_path / "sag.npy", spacing=[0.5, 0.6]).spacing == (0.5, 0.6)
    with pytest.raises(DicerError, match="2D but the given spacing has 4"):
        read_image(tmp_path / "a.png", spacing=[1, 1, 1, 1])


def test_slice_folder_errors(tmp_path):
    (tmp_path / "mixed").mkdir()
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 5), np.uint8)), str(tmp_path / "mixed" / "a1.png"))
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((6, 5), np.uint8)), str(tmp_path / "mixed" / "a2.png"))
    with pytest.raises(DicerError, match="mixed: cannot stack the 2 slices"):
        read_image(tmp_path / "mixed")
    (tmp_path / "rgb").mkdir()
    for k in range(2):
        rgb = sitk.GetImageFromArray(np.zeros((4, 5, 3), np.uint8), isVector=True)
        sitk.WriteImage(rgb, str(tmp_path / "rgb" / f"a{k}.png"))
    with pytest.raises(DicerError, match="3 components"):
        read_image(tmp_path / "rgb")
    (tmp_path / "both").mkdir()
    tifffile.imwrite(tmp_path / "both" / "a.tif", np.zeros((4, 5), np.uint8))
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 5), np.uint8)), str(tmp_path / "both" / "b.png"))
    with pytest.raises(DicerError, match="mixes TIFF and PNG"):
        read_image(tmp_path / "both")


@pytest.mark.parametrize("odd, kind, said", [
    (3, np.zeros((6, 4), np.uint16), "s3.tif is 4x6, where the other 5 are 5x4 pixels"),
    (0, np.zeros((6, 4), np.uint16), "s0.tif is 4x6, where the other 5 are 5x4 pixels"),
    (5, np.zeros((2, 4, 5), np.uint16), "s5.tif is 5x4 with 2 pages, where the other 5 are 5x4 pixels"),
    (2, np.zeros((4, 5, 3), np.uint8), "s2.tif is 5x4 with 3 channels, where the other 5 are 5x4 pixels"),
    (4, None, "s4.tif cannot be read as an image"),
])
def test_an_odd_slice_in_a_stack_is_named(tmp_path, odd, kind, said):
    """ITK named the first file of a stack, whichever slice was odd, and took a colour slice
    among grey ones without a word."""
    for k in range(6):
        if k == odd and kind is None:
            (tmp_path / f"s{k}.tif").write_bytes(b"not a TIFF")
        else:
            tifffile.imwrite(tmp_path / f"s{k}.tif", kind if k == odd else np.zeros((4, 5), np.uint16),
                             photometric="rgb" if k == odd and kind.ndim == 3 and kind.shape[2] == 3 else None)
    with pytest.raises(DicerError, match=rf"cannot stack the 6 slices \({said}\)"):
        read_image(tmp_path, spacing=1.0)


@pytest.mark.parametrize("numbers, warned", [([0, 1, 2, 6, 7], "skip from 2 to 6"), ([0, 5, 10, 15], None),
                                             ([1, 2, 3, 4], None)])
def test_a_skip_in_the_slice_file_numbers_is_warned_of(tmp_path, caplog, numbers, warned):
    folder = tmp_path / "slices"
    folder.mkdir()
    for n in numbers:
        tifffile.imwrite(folder / f"s{n:03d}.tif", np.full((4, 5), n, np.uint8))
    with caplog.at_level(logging.WARNING, logger="dicer"):
        volume = read_image(folder, spacing=1.0)
    assert volume.array.shape == (5, 4, len(numbers))
    if warned:
        assert f"slices: the slice files' numbers {warned} (s002.tif to s006.tif)" in caplog.text
    else:
        assert "numbers skip" not in caplog.text


@pytest.mark.parametrize("shift,refused", [(0.0, False), (0.01, False), (0.91, True)])
def test_dicom_series_with_gantry_tilt_refused(tmp_path, shift, refused):
    """Slices that shift within their plane along the series (gantry tilt) would make a
    sheared grid: refused, naming the tilt; rounding of written positions is not a tilt."""
    folder = tmp_path / "tilted"
    folder.mkdir()
    stored = np.zeros((10, 8, 6), np.int16)
    _write_dicom_series(folder, 6, "1.2.826.0.1.3680043.8.498.12", stored, shift_y=shift)
    if not refused:
        assert read_image(folder).array.shape == (10, 8, 6)
        return
    with pytest.raises(DicerError, match=r"gantry tilt of about 20\.0 degrees: 4\.55 mm over 12\.5 mm") as err:
        read_image(folder)
    assert str(err.value).startswith(f"{folder}: ") and "dcm2niix" in str(err.value)


@settings(max_examples=60, deadline=None)
@given(arrays(np.uint16, st.tuples(st.integers(1, 140), st.integers(1, 140), st.integers(1, 140)),
              elements=st.integers(0, 300)), st.integers(0, 400), st.sampled_from(["C", "T"]))
def test_contiguous_copy_and_label_counts_match_numpy(a, minlength, layout):
    """The tiled copy (cut for volumes of a million voxels or more) and the sliced count
    agree with numpy's own on any shape and layout."""
    from dicer.image import count_labels
    from dicer.parallel import contiguous

    view = a.T if layout == "T" else a
    copy = contiguous(view, np.float32)
    assert copy.flags.c_contiguous and copy.dtype == np.float32 and np.array_equal(copy, view)
    assert np.array_equal(count_labels(view, minlength), np.bincount(view.ravel(), minlength=minlength))


@pytest.mark.parametrize("shape", [(130, 90, 100), (17, 300, 260), (260, 65, 70)])
def test_contiguous_copy_of_a_large_transposed_volume(shape):
    from dicer.image import count_labels
    from dicer.parallel import contiguous

    a = np.random.default_rng(1).integers(0, 700, shape).astype(np.int16)
    for view in (a.T, a.transpose(1, 0, 2), a[::2, :, ::-1]):
        assert view.size >= (1 << 20) // 2
        for dtype in (None, np.float32):
            copy = contiguous(view, dtype)
            assert copy.flags.c_contiguous and np.array_equal(copy, view)
            assert copy.dtype == (dtype or view.dtype)
    assert np.array_equal(count_labels(a, 3), np.bincount(a.ravel()))


def test_sheared_or_scaled_header_axes_are_refused(tmp_path):
    """NRRD space directions with a shear, a MetaImage TransformMatrix with a scale: every
    file dicer writes would turn them into some rotation, so they are refused on reading."""
    data = np.arange(4 * 5 * 6, dtype=np.int16).tobytes()
    nrrd = tmp_path / "shear.nrrd"
    nrrd.write_bytes(b"NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: 4 5 6\n"
                     b"space directions: (1,0,0) (0,1,0) (0,0.3,1)\nkinds: domain domain domain\n"
                     b"endian: little\nencoding: raw\nspace origin: (0,0,0)\n\n" + data)
    mha = tmp_path / "scaled.mha"
    mha.write_bytes(b"ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
                    b"TransformMatrix = 2 0 0 0 2 0 0 0 2\nOffset = 0 0 0\nElementSpacing = 1 1 1\n"
                    b"DimSize = 4 5 6\nElementType = MET_SHORT\nElementDataFile = LOCAL\n" + data)
    for path, error in ((nrrd, "0.287"), (mha, "3")):
        with pytest.raises(DicerError, match=rf"{path.name}: the header's direction cosines are not orthonormal "
                                             rf"\(largest error of D\^T D - I: {error}: .*resample it onto an "
                                             "orthogonal grid"):
            read_image(path)


def _write_enhanced_ct(path, frames, z):
    """An enhanced CT in one file: ``frames`` (n, nx, ny) HU, frame k at z = ``z[k]`` mm
    (x 10, y 20), pixels 0.75 (x) by 0.5 mm (y)."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import EnhancedCTImageStorage, ExplicitVRLittleEndian, generate_uid

    def item(**tags):
        ds = Dataset()
        for key, value in tags.items():
            setattr(ds, key, value)
        return ds

    n, nx, ny = frames.shape
    ds = item(SOPClassUID=EnhancedCTImageStorage, SOPInstanceUID=generate_uid(), Modality="CT",
              StudyInstanceUID=generate_uid(), SeriesInstanceUID=generate_uid(), FrameOfReferenceUID=generate_uid(),
              SamplesPerPixel=1, PhotometricInterpretation="MONOCHROME2", BitsAllocated=16, BitsStored=16,
              HighBit=15, PixelRepresentation=1, Rows=ny, Columns=nx, NumberOfFrames=n)
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = EnhancedCTImageStorage
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.SharedFunctionalGroupsSequence = Sequence([item(
        PixelMeasuresSequence=Sequence([item(PixelSpacing=["0.5", "0.75"], SliceThickness="2.5")]),
        PlaneOrientationSequence=Sequence([item(ImageOrientationPatient=["1", "0", "0", "0", "1", "0"])]),
        PixelValueTransformationSequence=Sequence([item(RescaleIntercept="0", RescaleSlope="1", RescaleType="HU")]))])
    ds.PerFrameFunctionalGroupsSequence = Sequence([
        item(PlanePositionSequence=Sequence([item(ImagePositionPatient=["10", "20", f"{zk:g}"])])) for zk in z])
    ds.PixelData = np.ascontiguousarray(frames.astype(np.int16).transpose(0, 2, 1)).tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path


@pytest.mark.parametrize("descending", [False, True])
def test_multiframe_dicom_in_either_frame_order(tmp_path, descending):
    """An enhanced CT in one file, its frames stored bottom to top or (as many scanners
    write them) top to bottom: each frame lands at its own Image Position."""
    nx, ny, nz, dz = 6, 5, 4, 2.5
    hu = np.full((nx, ny, nz), -1000.0)
    hu[:, :, nz - 1] = 1000.0  # the top frame (largest z) is bone
    z = [-20.0 + dz * (nz - 1 - k if descending else k) for k in range(nz)]  # frame k's position
    frames = np.stack([hu[:, :, int(round((zk + 20.0) / dz))] for zk in z])
    volume = read_image(_write_enhanced_ct(tmp_path / "mf.dcm", frames, z))
    assert volume.spacing == pytest.approx((0.75, 0.5, dz))  # x: column spacing, y: row spacing
    # the bone frame sits at z = -20 + 3 dz whatever the order it was stored in
    from dicer.mesh.frame import image_affine

    affine = image_affine(volume.spacing, volume.origin, volume.direction)
    bone = np.argwhere(volume.array[0, 0, :] > 0).ravel()
    assert bone.size == 1
    centre = affine[:3, :3] @ np.array([0.0, 0.0, float(bone[0])]) + affine[:3, 3]
    assert centre[2] == pytest.approx(-20.0 + dz * (nz - 1))


@pytest.mark.parametrize("z, where", [([0.0, 2.5, 7.5, 10.0], "2.5 and 7.5 mm"), ([0.0, 2.5, 2.5, 5.0], "2.5 and 2.5 mm"),
                                      ([0.0, 2.5, 4.0, 6.5], "2.5 and 4 mm")])
def test_multiframe_dicom_with_missing_doubled_or_uneven_frames_is_refused(tmp_path, z, where):
    """GDCM read such a file at 1 mm voxels, in-plane too, without a word."""
    frames = np.zeros((4, 6, 5))
    with pytest.raises(DicerError, match=rf"mf.dcm: the frames of the multi-frame DICOM file are not evenly spaced "
                                         rf"along their normal \(between positions {where}"):
        read_image(_write_enhanced_ct(tmp_path / "mf.dcm", frames, z))


def test_dicom_series_of_equal_length_or_without_pixel_spacing_are_refused(tmp_path):
    """Two series of as many slices in one folder: no way to tell the scan (it took the one
    whose identifier sorts first); slices without Pixel Spacing: GDCM took 1 mm in-plane."""
    stored = np.zeros((6, 5, 4), np.int16)
    both = tmp_path / "both"
    both.mkdir()
    _write_dicom_series(both, 4, "1.2.826.0.1.3680043.8.498.11", stored, prefix="a")
    _write_dicom_series(both, 4, "1.2.826.0.1.3680043.8.498.12", stored + 250, prefix="b")
    with pytest.raises(DicerError, match=r"both: the folder holds 2 DICOM series, 2 of them of 4 slices \(the most\); "
                                         "dicer cannot tell which one is the scan: put each series in a folder"):
        read_image(both)
    _write_dicom_series(both, 5, "1.2.826.0.1.3680043.8.498.13", stored[:, :, [0, 1, 2, 3, 3]], prefix="c")
    assert read_image(both).array.shape == (6, 5, 5)  # a longer series is the scan
    bare = tmp_path / "bare"
    bare.mkdir()
    _write_dicom_series(bare, 4, "1.2.826.0.1.3680043.8.498.14", stored, pixel_spacing=False)
    with pytest.raises(DicerError, match=r"bare: the DICOM slices carry no Pixel Spacing \(0028,0030\)"):
        read_image(bare)


@pytest.mark.parametrize("other", [{"patient_id": "MRN_OTHER_PATIENT"}, {"study_uid": "1.2.826.0.1.3680043.8.498.99"}])
def test_series_of_other_patients_or_studies_in_one_folder_are_refused(tmp_path, capsys, other):
    """The series of the most slices was read, whoever's it was: another patient's scan
    exported into the same folder gave that patient's model."""
    stored = np.zeros((6, 5, 5), np.int16)
    _write_dicom_series(tmp_path, 5, "1.2.826.0.1.3680043.8.498.21", stored, prefix="a", **other)
    _write_dicom_series(tmp_path, 4, "1.2.826.0.1.3680043.8.498.22", stored[:, :, :4], prefix="b")
    what = "patients (Patient ID" if "patient_id" in other else "studies (Study Instance UID"
    with pytest.raises(DicerError, match=rf"the folder holds DICOM series of 2 different {re.escape(what)} differs\), "
                                         "and dicer would read one of them: put each one's series in a folder") as err:
        read_image(tmp_path)
    assert "MRN_OTHER" not in str(err.value) and SECRET_ID not in str(err.value)


def test_pixel_padding_value_marks_voxels_outside_the_image(tmp_path, caplog):
    """Voxels holding the Pixel Padding Value (0028,0120) lie outside the field of view: read
    as stored they rescaled to 59,000 HU here (62,512 for an unsigned CT), and became bone."""
    stored = np.full((6, 5, 4), 12, np.int16)  # -1000 HU
    stored[2:4, 1:4] = 532  # 40 HU
    stored[0] = 30000  # outside the field of view
    _write_dicom_series(tmp_path, 4, "1.2.826.0.1.3680043.8.498.31", stored, padding=30000)
    caplog.set_level("INFO", logger="dicer")
    volume = read_image(tmp_path)
    assert volume.array.max() == 40.0 and np.all(volume.array[0] == -1000.0)
    assert "20 voxels hold the series' Pixel Padding Value (outside the field of view): set to the lowest other " \
           "value, -1000" in caplog.text
    without = tmp_path / "plain"
    without.mkdir()
    _write_dicom_series(without, 4, "1.2.826.0.1.3680043.8.498.32", stored)
    assert read_image(without).array.max() == 30000 * 2 - 1024  # no padding value said: the values as stored


def test_a_padding_value_beyond_the_bits_stored_is_refused(tmp_path):
    """A 12-bit unsigned series whose Pixel Padding Value is 63536: the pixels keep 12 bits, so
    the padding read as 2096 (1072 HU, bone) and the padding check never matched (exit 0, the
    field of view's ring of bone). It is refused, naming the slice and the bits."""
    stored = np.full((6, 5, 4), 12, np.int16)
    stored[2:4, 1:4] = 532
    _write_dicom_series(tmp_path, 4, "1.2.826.0.1.3680043.8.498.33", stored, padding=63536, bits_stored=12)
    with pytest.raises(DicerError, match=r"im\d{3}\.dcm: the slice's Pixel Padding Value \(0028,0120\) 63536 does "
                                         r"not fit the 12 bits it stores .* padding reads as 2096"):
        read_image(tmp_path)
    # a padding value within the bits: read as before
    fits = tmp_path / "fits"
    fits.mkdir()
    stored[0] = 4000
    _write_dicom_series(fits, 4, "1.2.826.0.1.3680043.8.498.34", stored, padding=4000, bits_stored=12)
    volume = read_image(fits)
    assert np.all(volume.array[0] == -1000.0) and volume.array.max() == 40.0


def test_a_folder_of_one_multiframe_file_or_a_dicom_medium(tmp_path):
    folder = tmp_path / "mf"
    folder.mkdir()
    frames = np.arange(4 * 6 * 5, dtype=float).reshape(4, 6, 5)
    _write_enhanced_ct(folder / "mf.dcm", frames, [0.0, 2.5, 5.0, 7.5])
    whole, alone = read_image(folder), read_image(folder / "mf.dcm")
    assert np.array_equal(whole.array, alone.array) and whole.spacing == alone.spacing
    # named as scanners and archives often name them, without an extension: read by content
    named = tmp_path / "named"
    named.mkdir()
    (folder / "mf.dcm").rename(named / "IM0001")
    for volume in (read_image(named), read_image(named / "IM0001")):
        assert np.array_equal(volume.array, alone.array) and volume.spacing == alone.spacing
        assert volume.origin == alone.origin
    (named / "notes").write_text("not an image")
    with pytest.raises(DicerError, match=r"notes: unknown image format '\(no extension\)'"):
        read_image(named / "notes")
    medium = tmp_path / "medium"
    (medium / "PT000000").mkdir(parents=True)
    (medium / "DICOMDIR").write_bytes(b"\0" * 132)
    with pytest.raises(DicerError, match="medium: the folder holds a DICOMDIR index and subfolders"):
        read_image(medium)


@pytest.mark.parametrize("units, factor", [('"microns" "microns" "microns"', 1e-3), ('"mm" "mm" "mm"', 1.0),
                                           ('"m" "m" "m"', 1e3), (None, 1.0), ('"inch" "inch" "inch"', None)])
def test_nrrd_space_units_are_converted_to_mm(tmp_path, units, factor):
    """ITK read an NRRD in microns as mm: the micro-CT's model came out 1000 times too large."""
    data = np.arange(4 * 3 * 2, dtype="<i2")
    header = ("NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: 4 3 2\n"
              "space directions: (8,0,0) (0,8,0) (0,0,20)\n" + (f"space units: {units}\n" if units else "")
              + "kinds: domain domain domain\nendian: little\nencoding: raw\nspace origin: (100,0,0)\n\n")
    path = tmp_path / "scan.nrrd"
    path.write_bytes(header.encode() + data.tobytes())
    if factor is None:
        with pytest.raises(DicerError, match=r'scan.nrrd: the header.s space units are "inch" "inch" "inch"; dicer reads'):
            read_image(path)
        return
    volume = read_image(path)
    assert volume.spacing == pytest.approx((8 * factor, 8 * factor, 20 * factor))
    assert volume.origin == pytest.approx((96 * factor, -4 * factor, -10 * factor))


def test_float64_values_beyond_float32_are_refused(tmp_path):
    """1e39 became infinite in the float32 image, and bone, with numpy's overflow warning on
    standard error."""
    array = np.zeros((6, 5, 4))
    array[2:4, 2:4, 1:3] = 1e39
    np.save(tmp_path / "big.npy", array)
    with pytest.raises(DicerError, match=r"big.npy: the image holds values up to 1e\+39, beyond the float32 dicer "
                                         r"computes in; rescale"):
        read_image(tmp_path / "big.npy", spacing=1.0)
    array[2:4, 2:4, 1:3] = 3e38  # within float32
    np.save(tmp_path / "big.npy", array)
    assert read_image(tmp_path / "big.npy", spacing=1.0).array.max() == np.float32(3e38)


@pytest.mark.parametrize("gz", [False, True])
def test_a_nifti2_file_is_refused_saying_so(tmp_path, gz):
    import struct

    # a 4x4x4 int16 NIfTI-2 image: 540-byte header, 4 bytes of extension flag, the voxels
    head = bytearray(540)
    struct.pack_into("<i", head, 0, 540)
    head[4:12] = b"n+2\0\r\n\x1a\n"
    struct.pack_into("<2h", head, 12, 4, 16)  # datatype int16, bitpix
    struct.pack_into("<8q", head, 16, 3, 4, 4, 4, 1, 1, 1, 1)
    struct.pack_into("<8d", head, 104, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<q", head, 168, 544)
    data = bytes(head) + bytes(4) + np.arange(64, dtype="<i2").tobytes()
    path = tmp_path / ("scan.nii.gz" if gz else "scan.nii")
    path.write_bytes(gzip.compress(data, mtime=0) if gz else data)
    with pytest.raises(DicerError, match="a NIfTI-2 file.*save it as NIfTI-1"):
        read_image(path)


def test_dicom_series_with_a_slice_of_another_patient_is_refused_without_naming_either(dicom_folder):
    # one slice of another patient filed under the series' UID was stacked into the scan
    folder, _ = dicom_folder
    slice_path = sorted(folder.glob("*.dcm"))[2]
    ds = pydicom.dcmread(slice_path)
    ds.PatientID = "PID-INTRUDER-42"
    ds.save_as(slice_path)
    with pytest.raises(DicerError) as err:
        read_image(folder)
    message = str(err.value)
    assert "more than one patient or study (Patient ID differs" in message and slice_path.name in message
    assert SECRET_ID not in message and "INTRUDER" not in message


def test_dicom_slice_with_an_orientation_gdcm_does_not_take_is_refused(dicom_folder):
    # not unit vectors: GDCM read the slice as axial (the identity) without a word
    folder, _ = dicom_folder
    slice_path = sorted(folder.glob("*.dcm"))[1]
    ds = pydicom.dcmread(slice_path)
    ds.ImageOrientationPatient = [0.9, 0.1, 0, 0, 1, 0]
    ds.save_as(slice_path)
    with pytest.raises(DicerError, match=re.escape(slice_path.name) + r".*Image Orientation \(Patient\).*not two "
                       r"perpendicular unit vectors \(0.9, 0.1, 0, 0, 1, 0\)"):
        read_image(folder)


def test_dicom_folder_gdcm_drops_for_a_malformed_value_says_so(dicom_folder):
    # one slice's Image Position as text: GDCM's scan dropped every file, and the error said
    # the folder holds no DICOM series
    from pydicom.dataelem import DataElement

    folder, _ = dicom_folder
    slice_path = sorted(folder.glob("*.dcm"))[2]
    ds = pydicom.dcmread(slice_path)
    ds[0x00200032] = DataElement(0x00200032, "LO", "abc\\1\\2")
    ds.save_as(slice_path)
    with pytest.raises(DicerError, match=r"GDCM finds no DICOM series in the folder's 6 DICOM file\(s\).*Image "
                                         r"Position"):
        read_image(folder)


def test_enclosed_voids_are_counted_with_their_walls():
    """The voids a model encloses, with their walls (the decks' CAVITIES): fix names them."""
    from dicer.image import enclosed_voids

    block = np.ones((7, 7, 7), np.uint8)
    assert enclosed_voids(block) == (0, 0)
    block[3, 3, 3] = 0
    assert enclosed_voids(block) == (1, 6)
    block[1:3, 1, 1] = 0  # a second void of two voxels: 10 faces
    assert enclosed_voids(block) == (2, 16)
    block[0, 1, 1] = 0  # opened to the image's outside: no longer enclosed
    assert enclosed_voids(block) == (1, 6)
    flat = np.ones((5, 5), np.uint8)
    flat[2, 2] = 0
    assert enclosed_voids(flat) == (1, 4)
