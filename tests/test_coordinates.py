"""Scanner coordinates (mesh.coordinates): exported models sit where the scan sits.

The reference is SimpleITK's TransformContinuousIndexToPhysicalPoint on the file itself
(ITK/DICOM LPS mm): the node at voxel corner (i, j, k) lies at continuous index
(i, j, k) - 1/2. The NIfTI sform (RAS) is checked too: RAS = diag(-1, -1, 1) LPS.
"""

import gzip
import struct
from pathlib import Path

import meshio
import numpy as np
import pytest
import SimpleITK as sitk

from dicer.cli import main
from dicer.config import load_config
from dicer.errors import DicerError
from dicer.export import prepare_model
from dicer.io.images import read_image, read_labels
from dicer.io.meshes import read_mesh
from dicer.mesh.frame import check_direction, image_affine, to_scanner
from dicer.mesh.metrics import scaled_jacobian
from dicer.mesh.voxel import voxel_mesh

# float32-exact values with short decimals: NIfTI stores spacing and offsets as float32
SPACING = (0.5, 0.75, 1.25)
ORIGIN = (-12.5, 30.25, 7.0)  # ITK origin: centre of voxel (0, 0, 0)
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


def rotation(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


OBLIQUE = rotation([1, 2, 3], 0.5)
FLIPPED = OBLIQUE @ np.diag([1.0, 1.0, -1.0])  # left-handed: det -1
CASES = {"oblique": OBLIQUE, "flipped": FLIPPED}


def labels_array() -> np.ndarray:
    a = np.zeros((12, 10, 8), np.uint8)
    a[2:10, 2:8, 1:7] = 1
    a[3:9, 3:7, 2:6] = 2
    a[0:4, 0:3, 0] = 1  # touches the bounding planes X0, Y0, Z0
    return a


def write_itk(path: Path, array: np.ndarray, direction: np.ndarray, dtype=np.uint8) -> None:
    image = sitk.GetImageFromArray(np.ascontiguousarray(array.astype(dtype).T))
    image.SetSpacing(SPACING)
    image.SetOrigin(ORIGIN)
    image.SetDirection(tuple(direction.ravel()))
    sitk.WriteImage(image, str(path), True)


def write_sform_nifti(path: Path, array: np.ndarray, lps_direction: np.ndarray) -> np.ndarray:
    """A NIfTI-1 written byte by byte with only an sform (qform code 0), as some tools write
    them; returns the (4, 4) RAS affine stored (float32)."""
    ras = np.eye(4)
    ras[:3, :3] = LPS_TO_RAS @ lps_direction * np.asarray(SPACING)
    ras[:3, 3] = LPS_TO_RAS @ np.asarray(ORIGIN)
    ras = ras.astype(np.float32).astype(np.float64)
    write_raw_nifti(path, array, ras[:3])
    return ras


def write_raw_nifti(path: Path, array: np.ndarray, sform: np.ndarray, quatern=None, units: int = 2,
                    scode: int = 2) -> None:
    """A NIfTI-1 of int16 voxels of SPACING (pixdim), written byte by byte: the RAS ``sform``
    (3, 4) with code ``scode`` (default 2, aligned) and, when ``quatern`` (b, c, d, qx, qy, qz)
    is given, a qform with code 1 (scanner); else qform code 0. ``units``: xyzt_units (2 mm,
    3 microns)."""
    head = bytearray(348)
    struct.pack_into("<i", head, 0, 348)
    struct.pack_into("<8h", head, 40, 3, *array.shape, 1, 1, 1, 1)
    struct.pack_into("<2h", head, 70, 4, 16)  # int16
    struct.pack_into("<8f", head, 76, 1.0, *SPACING, 1, 1, 1, 1)
    struct.pack_into("<f", head, 108, 352.0)
    struct.pack_into("<f", head, 112, 1.0)
    head[123] = units  # xyzt_units
    struct.pack_into("<2h", head, 252, 0 if quatern is None else 1, scode)
    if quatern is not None:
        struct.pack_into("<6f", head, 256, *quatern)
    struct.pack_into("<12f", head, 280, *np.asarray(sform, float).ravel())
    head[344:348] = b"n+1\0"
    with gzip.open(path, "wb") as f:
        f.write(bytes(head) + b"\0" * 4 + array.astype("<i2").tobytes(order="F"))


def itk_points(image: sitk.Image, index: np.ndarray) -> np.ndarray:
    """(N, 3) physical points (LPS mm) of continuous indices (N, 3), by SimpleITK one by one."""
    return np.array([image.TransformContinuousIndexToPhysicalPoint([float(v) for v in row]) for row in index])


def config(**sets):
    return load_config(settings={"materials": [{"name": "bone"}, {"name": "marrow"}]},
                       sets=[f"{k}={v}" for k, v in sets.items()])


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd", ".mha"])
def test_nodes_at_the_itk_physical_point_of_each_voxel_corner(tmp_path, case, ext):
    path = tmp_path / f"labels{ext}"
    write_itk(path, labels_array(), CASES[case])
    volume = read_labels(path)
    mesh = voxel_mesh(volume.array, volume.spacing, volume.origin, volume.direction)
    model = prepare_model(mesh, config())
    want = itk_points(sitk.ReadImage(str(path)), mesh.lattice - 0.5)
    assert np.abs(model.points - want).max() < 1e-9
    # the documented affine gives the same points
    affine = image_affine(volume.spacing, volume.origin, volume.direction)
    assert np.abs(model.points - ((mesh.lattice - 0.5) @ affine[:3, :3].T + affine[:3, 3])).max() < 1e-9
    sj = scaled_jacobian(model.points, model.cells)
    assert np.count_nonzero(sj <= 0) == 0 and sj.min() > 0.999999
    # in the original corner order a reflection would have turned every element inside out
    inverted = np.count_nonzero(scaled_jacobian(model.points, mesh.cells) <= 0)
    assert inverted == (mesh.n_cells if case == "flipped" else 0)
    # bounding-plane sets are found on the lattice, whatever the orientation
    assert {"X0", "Y0", "Z0"} <= set(model.node_sets)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("order", [1, 2])
def test_quadratic_elements_and_face_sets_follow_the_corners(case, order):
    from dicer.mesh.topology import HEX20_FACES, HEX_FACES

    corner = np.subtract(ORIGIN, np.divide(SPACING, 2))
    mesh = voxel_mesh(labels_array(), SPACING, corner, CASES[case].ravel())
    model = prepare_model(mesh, config(**{"export.order": order}))
    plain = prepare_model(voxel_mesh(labels_array(), SPACING, corner), config(**{"export.order": order}))
    assert np.count_nonzero(scaled_jacobian(model.points, model.cells[:, :8]) <= 0) == 0
    if order == 2:  # mid-edge nodes halfway along the (mirrored) element's edges
        ends = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                         [0, 4], [1, 5], [2, 6], [3, 7]])
        half = model.points[model.cells[:, ends]].mean(axis=2)
        assert np.abs(model.points[model.cells[:, 8:]] - half).max() < 1e-12
    # an element face of a face set holds the same nodes as in the unrotated model: the
    # face numbers followed the mirrored corners
    table = HEX_FACES if order == 1 else HEX20_FACES

    def faces(m, rows):
        return sorted((int(e), tuple(sorted(m.cells[e, table[f - 1]].tolist()))) for e, f in rows)

    assert faces(model, model.exterior) == faces(plain, plain.exterior)
    assert faces(model, model.interfaces["bone_marrow"]) == faces(plain, plain.interfaces["bone_marrow"])
    assert {k: v.tolist() for k, v in model.node_sets.items()} == {k: v.tolist() for k, v in plain.node_sets.items()}
    for rows in (model.exterior, model.interfaces["bone_marrow"]):  # grouped by face number, elements ascending
        assert np.array_equal(rows, rows[np.lexsort((rows[:, 0], rows[:, 1]))])


def test_sform_only_nifti_matches_its_ras_affine(tmp_path):
    path = tmp_path / "sform.nii.gz"
    ras = write_sform_nifti(path, labels_array(), FLIPPED)
    volume = read_labels(path)
    mesh = voxel_mesh(volume.array, volume.spacing, volume.origin, volume.direction)
    model = prepare_model(mesh, config())
    corners = np.column_stack([mesh.lattice - 0.5, np.ones(mesh.n_points)])
    # the mesh is in LPS: x and y change sign against the NIfTI (RAS) affine; the sform is
    # float32, ITK's direction its normalised columns: agreement to float32 precision
    err = np.abs(model.points @ LPS_TO_RAS - corners @ ras[:3].T).max()
    assert err < 1e-5
    assert np.abs(model.points - itk_points(sitk.ReadImage(str(path)), mesh.lattice - 0.5)).max() < 1e-9


@pytest.mark.parametrize("distortion", ["scaled", "sheared"])
def test_an_sform_that_is_not_rigid_gives_way_to_the_qform(tmp_path, caplog, distortion):
    # e.g. a registration to a template stored in the sform: ITK would apply a scaled sform
    # without its scale, and a sheared one not at all; the qform is the scan's own geometry
    sform = np.zeros((3, 4))
    sform[:3, :3] = LPS_TO_RAS @ OBLIQUE * np.asarray(SPACING)
    sform[:, 3] = (-40.0, -50.0, -30.0)
    if distortion == "scaled":
        sform[:, 2] *= 1.2
    else:
        sform[0, 2] += 0.3
    path = tmp_path / "two.nii.gz"
    angle = 0.4
    write_raw_nifti(path, labels_array(), sform, (0.0, 0.0, np.sin(angle / 2), 5.0, 6.0, 7.0))
    volume = read_labels(path)
    assert "meshing in the qform's scanner geometry" in caplog.text
    rz = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    assert np.allclose(np.reshape(volume.direction, (3, 3)), LPS_TO_RAS @ rz, atol=1e-6)
    assert np.allclose(volume.spacing, SPACING)
    # Volume.origin: ITK's origin (voxel 0's centre) less half a voxel per index axis
    centre = np.asarray(volume.origin) + np.asarray(SPACING) / 2
    assert np.allclose(centre, LPS_TO_RAS @ np.array([5.0, 6.0, 7.0]), atol=1e-5)
    # in microns: the qform's offsets are converted as ITK converts pixdim (they stayed in microns)
    write_raw_nifti(path, labels_array(), sform, (0.0, 0.0, np.sin(angle / 2), 5.0, 6.0, 7.0), units=3)
    micro = read_labels(path)
    assert np.allclose(micro.spacing, np.asarray(SPACING) / 1000)
    assert np.allclose(np.asarray(micro.origin) + np.asarray(SPACING) / 2000, LPS_TO_RAS @ np.array([5e-3, 6e-3, 7e-3]),
                       atol=1e-8)
    # without a qform there is no rigid placement to use: refused with the fix
    write_raw_nifti(path, labels_array(), sform)
    with pytest.raises(DicerError, match="no qform to use instead; resample the image"):
        read_labels(path)


@pytest.mark.parametrize("units", [2, 3])
def test_an_aligned_sform_beside_a_qform_places_the_voxels(tmp_path, caplog, units):
    # ITK takes the qform when the sform's code is not 1 (here 2, aligned): the model lay
    # 10 mm from where nibabel and FSL show the scan and dicer's label files
    sform = np.zeros((3, 4))
    sform[:3, :3] = LPS_TO_RAS @ OBLIQUE * np.asarray(SPACING)
    sform[:, 3] = (-40.0, -50.0, -30.0)
    path = tmp_path / "aligned.nii.gz"
    angle = 0.4
    write_raw_nifti(path, labels_array(), sform, (0.0, 0.0, np.sin(angle / 2), 5.0, 6.0, 7.0), units=units)
    volume = read_labels(path)
    to_mm = 1e-3 if units == 3 else 1.0
    spacing = np.asarray(SPACING) * to_mm
    assert np.allclose(np.reshape(volume.direction, (3, 3)), OBLIQUE, atol=1e-6)
    assert np.allclose(volume.spacing, spacing)
    centre = np.asarray(volume.origin) + spacing / 2  # voxel 0's centre: the sform's offset
    assert np.allclose(centre, LPS_TO_RAS @ sform[:, 3] * to_mm, atol=1e-5 * to_mm)
    said = [r.getMessage() for r in caplog.records if "place the image differently" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("aligned.nii.gz: its sform (code 2) and qform (code 1)")
    assert said[0].endswith("meshing at the sform, where nibabel and FSL show it")
    # the two alike: no word
    caplog.clear()
    write_sform_nifti(path, labels_array(), OBLIQUE)
    read_labels(path)
    assert "place the image differently" not in caplog.text


def test_a_header_without_a_placement_is_warned_of(tmp_path, caplog):
    # qform and sform codes 0: ITK puts voxel 0 at the origin with identity axes, nibabel
    # mirrors x; the model was made without a word
    path = tmp_path / "nowhere.nii.gz"
    write_raw_nifti(path, labels_array(), np.zeros((3, 4)), scode=0)
    volume = read_labels(path)
    assert volume.direction is None and np.allclose(volume.origin, -np.asarray(SPACING) / 2)  # voxel 0 at 0
    said = [r.getMessage() for r in caplog.records if "places the image nowhere" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("nowhere.nii.gz: its header places the image nowhere in the scanner "
                                                 "(qform and sform codes 0)")
    caplog.clear()
    write_raw_nifti(path, labels_array(), np.zeros((3, 4)), (0.0, 0.0, 0.0, 5.0, 6.0, 7.0), scode=0)
    read_labels(path)  # a qform alone places it
    assert "places the image nowhere" not in caplog.text


def test_forms_that_differ_are_warned_of_by_how_far_the_corners_move(tmp_path, caplog):
    # an sform turned 0.4 rad about z against the qform, both at one origin, and both scanner
    # forms (code 1, which ITK takes itself): the corners, not the origins, tell them apart
    sform = np.zeros((3, 4))
    sform[:3, :3] = rotation([0, 0, 1], 0.4) * np.asarray(SPACING)
    sform[:, 3] = (5.0, 6.0, 7.0)
    path = tmp_path / "turned.nii.gz"
    write_raw_nifti(path, labels_array(), sform, (0.0, 0.0, 0.0, 5.0, 6.0, 7.0), scode=1)
    volume = read_labels(path)
    assert np.allclose(np.reshape(volume.direction, (3, 3)), LPS_TO_RAS @ rotation([0, 0, 1], 0.4), atol=1e-6)
    said = [r.getMessage() for r in caplog.records if "place the image differently" in r.getMessage()]
    far = np.array([11, 9, 7]) * np.asarray(SPACING)  # the far corner's centre from voxel 0's
    expected = np.linalg.norm(rotation([0, 0, 1], 0.4) @ far - far)
    assert len(said) == 1 and "(code 1) and qform (code 1)" in said[0]
    assert f"corners up to {expected:.3g} mm apart" in said[0]
    # forms apart by less than a tenth of a voxel (a float32 quaternion of a tilted scan: up to
    # 0.02 mm at a head's corners): header precision, no word
    caplog.clear()
    small = float(np.min(SPACING)) * 0.05 / np.linalg.norm(far)  # the far corner moves 0.05 voxel
    sform[:3, :3] = rotation([0, 0, 1], small) * np.asarray(SPACING)
    write_raw_nifti(path, labels_array(), sform, (0.0, 0.0, 0.0, 5.0, 6.0, 7.0), scode=1)
    read_labels(path)
    assert "place the image differently" not in caplog.text
    sform[:3, :3] = rotation([0, 0, 1], 4 * small) * np.asarray(SPACING)  # 0.2 voxel: said
    write_raw_nifti(path, labels_array(), sform, (0.0, 0.0, 0.0, 5.0, 6.0, 7.0), scode=1)
    read_labels(path)
    assert "place the image differently" in caplog.text


def _run(*argv) -> None:
    assert main([str(a) for a in argv] + ["-q"]) == 0


@pytest.fixture(scope="module", params=list(CASES))
def run_dir(request, tmp_path_factory):
    """``dicer run --labels`` on a small oblique (or flipped) sform-only NIfTI."""
    folder = tmp_path_factory.mktemp(request.param)
    src = folder / "labels_in.nii.gz"
    write_sform_nifti(src, labels_array(), CASES[request.param])
    _run("run", "--labels", src, "-o", folder / "out")
    return request.param, src, folder / "out"


def test_run_model_in_scanner_coordinates_never_inverted(run_dir, tmp_path):
    case, src, out = run_dir
    smoothed = read_mesh(out / "smoothed.vtu")
    assert smoothed.direction is not None and not smoothed.scanner
    exported = meshio.read(out / "model.vtu")
    # one rigid motion about the centre of voxel (0, 0, 0), as SimpleITK places the voxels
    image = sitk.ReadImage(str(src))
    d = np.asarray(image.GetDirection()).reshape(3, 3)
    c = np.asarray(image.GetOrigin())
    want = c + (smoothed.points - c) @ d.T
    assert np.abs(exported.points - want).max() < 1e-9
    deck = meshio.read(out / "model.inp", file_format="abaqus")
    assert np.abs(deck.points - exported.points).max() < 1e-6  # 9 significant digits
    for cells in (exported.cells[0].data, np.concatenate([b.data for b in deck.cells])):
        assert np.count_nonzero(scaled_jacobian(exported.points, cells) <= 0) == 0
    # model.vtu reads back into the lattice frame the stages work in
    back = read_mesh(out / "model.vtu")
    assert np.abs(back.points - smoothed.points).max() < 1e-9
    assert np.array_equal(back.cells, smoothed.cells) and not back.scanner
    import json

    assert json.loads((out / "quality.json").read_text())["inverted_elements"] == 0


def test_stage_by_stage_gives_the_run_bytes(run_dir, tmp_path):
    case, src, out = run_dir
    _run("labels", src, "-o", tmp_path / "labels.nii.gz", "--materials", tmp_path / "materials.json")
    m = ("--materials", tmp_path / "materials.json")
    _run("fix", tmp_path / "labels.nii.gz", "-o", tmp_path / "labels_fixed.nii.gz", *m)
    _run("mesh", tmp_path / "labels_fixed.nii.gz", "-o", tmp_path / "mesh.vtu", *m)
    _run("merge", tmp_path / "mesh.vtu", "-o", tmp_path / "merged.vtu")
    _run("smooth", tmp_path / "merged.vtu", "-o", tmp_path / "smoothed.vtu",
         "--labels", tmp_path / "labels_fixed.nii.gz")
    for name in ("model.inp", "model.vtu"):
        _run("export", tmp_path / "smoothed.vtu", "-o", tmp_path / name, *m)
    for name in ("labels.nii.gz", "labels_fixed.nii.gz", "mesh.vtu", "merged.vtu", "smoothed.vtu",
                 "model.inp", "model.vtu"):
        assert (tmp_path / name).read_bytes() == (out / name).read_bytes(), name


def test_voxel_mesh_through_the_cli_at_itk_corners_and_labels_centres(run_dir, tmp_path):
    """dicer mesh + dicer export of the written labels: nodes at the voxel corners of the
    input scan within 1e-9 mm, each element's centroid on its voxel's centre in the labels
    file dicer wrote."""
    case, src, out = run_dir
    fixed = out / "labels_fixed.nii.gz"
    m = ("--materials", out / "materials.json")
    _run("mesh", fixed, "-o", tmp_path / "mesh.vtu", *m)
    _run("export", tmp_path / "mesh.vtu", "-o", tmp_path / "vox.vtu", *m)
    _run("export", tmp_path / "mesh.vtu", "-o", tmp_path / "vox.inp", "--set", "export.digits=13", *m)
    model = meshio.read(tmp_path / "vox.vtu")
    lattice = np.asarray(model.point_data["lattice"])
    cells = model.cells[0].data
    # the labels dicer wrote carry the input's affine exactly: their voxels are the input's
    source, written = sitk.ReadImage(str(src)), sitk.ReadImage(str(fixed))
    want = itk_points(source, lattice - 0.5)
    assert np.array_equal(itk_points(written, lattice - 0.5), want)
    assert np.abs(model.points - want).max() < 1e-9
    deck = meshio.read(tmp_path / "vox.inp", file_format="abaqus")
    assert np.abs(deck.points - want).max() < 1e-9  # 13 significant digits
    assert np.count_nonzero(scaled_jacobian(model.points, cells) <= 0) == 0
    # centroid of each hexahedron = centre of its voxel in labels_fixed.nii.gz
    voxel = lattice[cells].min(axis=1)
    centres = itk_points(written, voxel.astype(float))
    assert np.abs(model.points[cells].mean(axis=1) - centres).max() < 1e-9
    labels = sitk.GetArrayFromImage(written).T
    assert np.array_equal(labels[tuple(voxel.T)], np.concatenate(model.cell_data["material"]))


def test_index_coordinates_keep_the_lattice_frame(run_dir, tmp_path):
    case, src, out = run_dir
    m = ("--materials", out / "materials.json")
    _run("mesh", out / "labels_fixed.nii.gz", "-o", tmp_path / "mesh.vtu", "--set", "mesh.coordinates=index", *m)
    _run("export", tmp_path / "mesh.vtu", "-o", tmp_path / "idx.vtu", *m)
    mesh = read_mesh(tmp_path / "mesh.vtu")
    assert mesh.direction is None
    exported = meshio.read(tmp_path / "idx.vtu")
    assert "direction" not in exported.field_data
    # origin: ITK's centre of voxel (0, 0, 0) minus half a voxel along each index axis
    corner = np.asarray(ORIGIN) - np.asarray(SPACING) / 2
    assert np.array_equal(exported.points, corner + np.asarray(exported.point_data["lattice"]) * SPACING)


def test_segmented_oblique_scan(tmp_path):
    """dicer run on an oblique CT: labels.nii.gz has the scan's header placement byte for
    byte, and the voxel mesh of it lies on the scan's voxel corners."""
    from dicer.phantoms import make_phantom

    image = make_phantom("sphere", size=16, seed=0)
    src = tmp_path / "ct.nii.gz"
    write_itk(src, image.array, FLIPPED, dtype=np.int16)
    assert read_image(src).direction == pytest.approx(tuple(FLIPPED.ravel()), abs=1e-6)
    _run("run", src, "-o", tmp_path / "out", "--set", "materials=[{name: bone}]",
         "--set", "segment.method=otsu")
    out = tmp_path / "out"
    with gzip.open(src) as f:
        head_in = f.read(348)
    for name in ("labels.nii.gz", "labels_ds.nii.gz", "labels_fixed.nii.gz"):
        with gzip.open(out / name) as f:
            head = f.read(348)
        if name != "labels_ds.nii.gz":  # downsampling changes the grid
            assert head[252:328] == head_in[252:328], name  # qform, sform and their codes
        written = sitk.ReadImage(str(out / name))
        assert np.abs(np.subtract(written.GetDirection(), FLIPPED.ravel())).max() < 1e-6, name
    _run("mesh", out / "labels_fixed.nii.gz", "-o", tmp_path / "mesh.vtu", "--set", "materials=[{name: bone}]")
    _run("export", tmp_path / "mesh.vtu", "-o", tmp_path / "m.vtu", "--set", "materials=[{name: bone}]")
    model = meshio.read(tmp_path / "m.vtu")
    fixed = sitk.ReadImage(str(out / "labels_fixed.nii.gz"))
    assert np.abs(model.points - itk_points(fixed, np.asarray(model.point_data["lattice"]) - 0.5)).max() < 1e-9
    assert np.count_nonzero(scaled_jacobian(model.points, model.cells[0].data) <= 0) == 0


def test_oblique_dicom_series_keeps_its_orientation(tmp_path):
    pydicom = pytest.importorskip("pydicom")
    from pydicom.data import get_testdata_file

    row, col = OBLIQUE[:, 0], OBLIQUE[:, 1]
    normal = np.cross(row, col)
    template = pydicom.dcmread(get_testdata_file("CT_small.dcm"))
    stored = np.arange(6 * 5 * 4, dtype=np.int16).reshape(6, 5, 4)
    first = np.array([-50.0, -60.0, 20.0])
    for k in range(4):
        ds = template.copy()
        uid = f"1.2.826.0.1.3680043.8.498.{k + 10}"
        ds.SOPInstanceUID = uid
        ds.file_meta.MediaStorageSOPInstanceUID = uid
        ds.SeriesInstanceUID = "1.2.826.0.1.3680043.8.498.9"
        ds.Rows, ds.Columns = 5, 6
        ds.PixelSpacing = [0.75, 0.5]  # row spacing (y), column spacing (x)
        ds.ImageOrientationPatient = [float(v) for v in np.r_[row, col]]
        ds.ImagePositionPatient = [float(v) for v in first + 1.25 * k * normal]
        ds.RescaleSlope, ds.RescaleIntercept = 1, 0
        for tag in ("SmallestImagePixelValue", "LargestImagePixelValue"):
            if tag in ds:
                delattr(ds, tag)
        ds.PixelData = np.ascontiguousarray(stored[:, :, k].T).tobytes()
        ds.save_as(tmp_path / f"s{3 - k}.dcm")  # file names against slice order
    volume = read_image(tmp_path)
    assert np.abs(np.asarray(volume.direction).reshape(3, 3) - np.column_stack([row, col, normal])).max() < 1e-6
    affine = image_affine(volume.spacing, volume.origin, volume.direction)
    centres = np.array([[0, 0, k, 1] for k in range(4)]) @ affine[:3].T
    want = first + 1.25 * np.arange(4)[:, None] * normal
    assert np.abs(centres - want).max() < 1e-4  # DS strings: a few decimals
    assert np.array_equal(volume.array, stored.astype(np.float32))


def test_direction_that_is_not_a_rotation_is_refused():
    from dicer.errors import DicerError

    sheared = np.eye(3)
    sheared[0, 1] = 0.2
    with pytest.raises(DicerError, match="not orthonormal.*mesh.coordinates: index"):
        check_direction(sheared.ravel(), 3, "x.nii")
    assert check_direction(np.eye(3).ravel(), 3) is None and check_direction(FLIPPED.ravel(), 2) is None
    p = np.array([[1.0, 2.0, 3.0]])
    assert np.allclose(to_scanner(p, (1, 1, 1), (-0.5, -0.5, -0.5), np.eye(3)), p)


@pytest.mark.parametrize("suffix", [".inp", ".vtu", ".out", ".k", ".msh", ".exo", ".feb"])
def test_every_format_of_a_flipped_image_reads_back(tmp_path, suffix):
    if suffix == ".exo":
        pytest.importorskip("netCDF4")
    from dicer.export import export_mesh

    corner = np.subtract(ORIGIN, np.divide(SPACING, 2))
    mesh = voxel_mesh(labels_array(), SPACING, corner, FLIPPED.ravel())
    for order in (1,) if suffix == ".k" else (1, 2):  # LS-DYNA: 8-node hexahedra only
        path = tmp_path / f"model{order}{suffix}"
        info = export_mesh(mesh, path, config(**{"export.order": order}))  # written, read back, checked
        assert info["verified"] and info["elements"] == mesh.n_cells


def test_sheared_header_is_one_error_on_reading(tmp_path, capsys):
    image = sitk.GetImageFromArray(np.ascontiguousarray(labels_array().T))
    sheared = np.eye(3)
    sheared[0, 1] = 0.2
    image.SetDirection(tuple(sheared.ravel()))  # ITK keeps it, columns normalised
    sitk.WriteImage(image, str(tmp_path / "shear.nrrd"))
    out = tmp_path / "mesh.vtu"
    argv = ["mesh", str(tmp_path / "shear.nrrd"), "-o", str(out), "--set", "materials=[{name: a}, {name: b}]"]
    assert main(argv) == 2 and not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(
        f"error: {tmp_path / 'shear.nrrd'}: the header's direction cosines are not orthonormal (largest error of "
        "D^T D - I: 0.196: sheared or scaled axes)")
    # meshing in the index axes would not help: the slice spacing read is the sheared column's length
    assert main(argv + ["--set", "mesh.coordinates=index", "-q"]) == 2 and not out.exists()


def test_a_flipped_2d_image_is_said_to_lie_in_its_index_frame(tmp_path, caplog):
    """A 2D image's direction cosines are not applied (no 3D placement): the log says so,
    once, instead of leaving a mirrored model unremarked."""
    image = sitk.GetImageFromArray(np.pad(np.ones((6, 8), np.uint8), 2))
    image.SetDirection((-1.0, 0.0, 0.0, 1.0))
    sitk.WriteImage(image, str(tmp_path / "x.mha"))
    caplog.set_level("INFO", logger="dicer")
    assert main(["run", "--labels", str(tmp_path / "x.mha"), "-o", str(tmp_path / "out"),
                 "--set", "fix.min_component_voxels=0"]) == 0
    assert caplog.text.count("the 2D image's direction cosines (-1 0 0 1) are not applied") == 1
    caplog.clear()
    assert main(["run", "--labels", str(tmp_path / "x.mha"), "-o", str(tmp_path / "index"),
                 "--set", "fix.min_component_voxels=0", "--set", "mesh.coordinates=index"]) == 0
    assert "direction cosines" not in caplog.text


@pytest.mark.parametrize("shape, direction, said", [
    ((1, 12, 14), None, "the model's x and y are the image's j and k index axes, not"),
    ((12, 14, 1), (-1.0, 0, 0, 0, -1.0, 0, 0, 0, 1.0), "i and j index axes (its direction cosines are dropped)"),
])
def test_a_one_slice_image_off_the_scanners_xy_plane_is_said_to_lie_in_its_index_plane(tmp_path, caplog, shape,
                                                                                          direction, said):
    """A sagittal slice, or one the scanner holds flipped (a RAS sform), was laid in the x-y
    plane without a word: the model turned or mirrored against the scan."""
    array = np.zeros(shape, np.uint8)
    array[tuple(slice(None) if n == 1 else slice(2, n - 2) for n in shape)] = 1
    image = sitk.GetImageFromArray(np.ascontiguousarray(array.T))
    if direction:
        image.SetDirection(direction)
    sitk.WriteImage(image, str(tmp_path / "slice.nii.gz"))
    caplog.set_level("INFO", logger="dicer")
    assert main(["run", "--labels", str(tmp_path / "slice.nii.gz"), "-o", str(tmp_path / "out"),
                 "--set", "fix.min_component_voxels=0"]) == 0
    assert caplog.text.count("the one-slice image is meshed in its index plane") == 1  # not again at every stage
    assert said in caplog.text


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("factor", [2, 3])
def test_the_scan_at_a_downsampled_meshs_nodes_is_read_at_their_scanner_points(case, factor):
    """Each grid's lattice frame turns about its own first voxel centre (dicer.mesh.frame), so a
    downsampled mesh's frame is shifted from its scan's where the axes are turned or flipped:
    the smoothing must read the scan at the nodes' scanner points (a CT with its y axis flipped,
    downsampled by 4, had its bone moved 1.3 mm by the faces the scan placed). The scan is linear
    in scanner coordinates, so trilinear sampling gives it exactly."""
    from dicer.image import Volume, regridded_origin
    from dicer.mesh.frame import lattice_shift, to_lattice
    from dicer.mesh.subvoxel import ImageSurface

    d = CASES[case]
    shape = (24, 18, 12)
    spacing = np.asarray(SPACING)
    index = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).reshape(-1, 3)
    slope = np.array([3.0, -2.0, 1.5])
    values = ((np.asarray(ORIGIN) + (index * spacing) @ d.T) @ slope).reshape(shape).astype(np.float32)
    scan = Volume(values, SPACING, tuple(np.asarray(ORIGIN) - spacing / 2), tuple(d.ravel()))
    coarse = tuple(spacing * factor)
    labels = np.ones(tuple(n // factor for n in shape), np.uint8)
    mesh = voxel_mesh(labels, coarse, regridded_origin(scan, coarse), scan.direction)
    surface = ImageSurface(scan, np.array([float(np.median(values))]), mesh, sigma=0.0)
    inner = np.all((mesh.lattice >= 1) & (mesh.lattice <= np.asarray(labels.shape) - 1), axis=1)
    points = mesh.points[inner]
    want = to_scanner(points, mesh.spacing, mesh.origin, d) @ slope
    assert np.abs(surface.sample(points) - want).max() < 1e-4 * np.abs(want).max()
    # the shift is the two frames' motion, and none between a grid and itself
    shift = lattice_shift(mesh.spacing, mesh.origin, scan.spacing, scan.origin, d)
    moved = to_lattice(to_scanner(points, mesh.spacing, mesh.origin, d), scan.spacing, scan.origin, d)
    assert np.abs(points + shift - moved).max() < 1e-9
    assert np.linalg.norm(shift) > 0.02  # 0.03-0.06 mm oblique, 0.9-1.8 mm flipped
    assert not lattice_shift(scan.spacing, scan.origin, scan.spacing, scan.origin, d).any()


def test_a_flipped_scan_downsampled_gives_the_model_its_unflipped_copy_gives(tmp_path):
    """One CT stored twice, its y axis as it is and flipped (direction diag(1, -1, 1)), through
    ``dicer run`` downsampled by 3 with the faces placed by the scan (the default; no plane
    merging, which pairs layers from the first): the same bone in the scanner, where the flipped copy's was 0.5 mm (factor 2) to 1.3 mm (factor 4) off
    along y before the smoothing read the scan in the mesh's own frame."""
    from dicer.phantoms import make_phantom

    array = make_phantom("sphere", size=24, seed=0).array
    origin = np.asarray(ORIGIN)
    centres = {}
    for name, stored, direction, first in (
            ("as_is", array, np.eye(3), origin),
            ("flipped", array[:, ::-1, :], np.diag([1.0, -1.0, 1.0]),
             origin + np.array([0.0, (array.shape[1] - 1) * SPACING[1], 0.0]))):
        image = sitk.GetImageFromArray(np.ascontiguousarray(stored.astype(np.int16).T))
        image.SetSpacing(SPACING)
        image.SetOrigin(tuple(first))
        image.SetDirection(tuple(direction.ravel()))
        sitk.WriteImage(image, str(tmp_path / f"{name}.nii.gz"), True)
        _run("run", tmp_path / f"{name}.nii.gz", "-o", tmp_path / name, "--set", "materials=[{name: bone}]",
             "--set", "segment.method=otsu", "--set", "downsample.factor=3",
             "--set", "merge.passes=[0, 0, 0]",  # merging pairs layers from index 0: not mirror-alike
             "--set", "preset=explicit-dynamics")
        model = meshio.read(tmp_path / name / "model.vtu")
        cells = model.cells[0].data
        centres[name] = model.points[cells].mean(axis=1).mean(axis=0)
        assert np.count_nonzero(scaled_jacobian(model.points, cells) <= 0) == 0
    assert np.abs(centres["flipped"] - centres["as_is"]).max() < 1e-3
