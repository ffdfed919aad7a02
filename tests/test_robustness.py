"""Bad input and faults, one row per case: exit status 2, one ``error:`` line, no traceback,
and no new or changed file anywhere under the test folder (inputs included).

Each row builds its inputs in a fresh folder, runs the ``dicer`` command in-process, and
compares a snapshot (every path and the bytes of every file) from before and after.
docs/robustness.md lists the same cases with their messages.
"""

import hashlib
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dicer.cli import main

import hostile  # the damaged-file edits of the hostile re-run (tests/hostile.py)
from meshcheck import meshio_vtu_with_grid

pydicom = pytest.importorskip("pydicom")


# --- inputs ------------------------------------------------------------------------------


def write_dicom_series(folder, positions, shape=(12, 10)):
    """A CT series built from scratch: one int16 slice per z position, slope 1, intercept -1024."""
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    series_uid = generate_uid(entropy_srcs=["robustness series"])
    for k, z in enumerate(positions):
        uid = generate_uid(entropy_srcs=["robustness slice", str(k)])
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(folder / f"im{k:03d}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, uid
        ds.StudyInstanceUID = generate_uid(entropy_srcs=["robustness study"])
        ds.SeriesInstanceUID = series_uid
        ds.Modality = "CT"
        ds.PatientName, ds.PatientID = "Anonymous^Robust", "RB-0001"
        ds.Rows, ds.Columns = shape[1], shape[0]
        ds.PixelSpacing = [0.7, 0.7]
        ds.SliceThickness = 1.0  # deliberately not the step between positions
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [0.0, 0.0, float(z)]
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.PixelData = np.full((shape[1], shape[0]), 1000 + 10 * k, np.int16).tobytes()
        ds.save_as(folder / f"im{k:03d}.dcm", enforce_file_format=True)
    return folder


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A small head phantom, its labels and a mesh, made once and copied into each row."""
    root = tmp_path_factory.mktemp("base")
    head, labels, mesh = root / "head.nii.gz", root / "labels.nii.gz", root / "mesh.vtu"
    assert main(["phantom", "head", "-o", str(head), "--size", "32", "-q"]) == 0
    assert main(["segment", str(head), "-o", str(labels), "-q"]) == 0
    assert main(["mesh", str(labels), "-o", str(mesh), "-q"]) == 0
    return root


def _copy(base, tmp_path, name):
    shutil.copy(base / name, tmp_path / name)
    return tmp_path / name


def _nifti(tmp_path, name, values, pixdim=None):
    from dicer.image import Volume
    from dicer.io.images import write_image

    path = tmp_path / name
    write_image(Volume(values, (1.0, 1.0, 1.0)), path)
    if pixdim is not None:  # overwrite pixdim[3] (z) in the stored header
        data = bytearray(path.read_bytes())
        data[88:92] = struct.pack("<f", pixdim)
        path.write_bytes(bytes(data))
    return path


def _raw_pair(tmp_path, header_name, nbytes):
    (tmp_path / "ct.raw").write_bytes(bytes(nbytes))
    path = tmp_path / header_name
    if header_name.endswith(".mhd"):
        path.write_text("ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementSpacing = 1 1 1\n"
                        "ElementType = MET_SHORT\nElementDataFile = ct.raw\n")
    else:
        path.write_text("NRRD0004\ntype: short\ndimension: 3\nsizes: 8 8 8\nspacings: 1 1 1\n"
                        "encoding: raw\nendian: little\ndata file: ct.raw\n")
    return path


def _damaged_series(tmp_path, how):
    folder = write_dicom_series(tmp_path / "series", np.arange(6) * 2.0)
    victim = folder / "im003.dcm"
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) - 60] if how == "truncated" else os.urandom(len(data)))
    return folder


def _hu(tmp_path):
    values = np.full((8, 8, 8), -1000.0, np.float32)
    values[2:6, 2:6, 2:6] = 400.0
    return values


def _with(values, index, value):
    values = values.copy()
    values[index] = value
    return values


OUT = "labels.nii.gz"


def _vtu_edit(src, dst, edit):
    return hostile.vtu_edit(src, dst, edit)


def _huge_npy(path):
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (10000, 10000, 10000), }"
    header = header + " " * (117 - len(header)) + "\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + bytes(4096))
    return path

# name -> (build(tmp_path, base) -> argv, text the error line must contain)
CASES = {
    # 1. DICOM series
    "dicom: missing slice": (
        lambda t, b: ["segment", write_dicom_series(t / "series", [0, 2, 4, 8, 10, 12]), "-o", t / OUT],
        "misses slices between positions 4 and 8 mm"),
    "dicom: duplicate position": (
        lambda t, b: ["segment", write_dicom_series(t / "series", [0, 2, 4, 4, 6, 8]), "-o", t / OUT],
        "same position along the slice normal (4 mm"),
    "dicom: uneven steps": (
        lambda t, b: ["segment", write_dicom_series(t / "series", [0, 2, 4, 7, 8, 10]), "-o", t / OUT],
        "uneven slice steps between positions 4 and 7 mm"),
    "dicom: duplicate even with allow_irregular_slices": (
        lambda t, b: ["segment", write_dicom_series(t / "series", [0, 2, 2, 4]), "-o", t / OUT,
                      "--set", "image.allow_irregular_slices=true"],
        "same position"),
    "dicom: truncated slice file": (
        lambda t, b: ["segment", _damaged_series(t, "truncated"), "-o", t / OUT], "series/im003.dcm: "),
    "dicom: random-bytes slice file": (
        lambda t, b: ["segment", _damaged_series(t, "random"), "-o", t / OUT], "series/im003.dcm: "),
    # 2. input sanity
    "NaN voxels": (
        lambda t, b: ["segment", _nifti(t, "nan.nii.gz", _with(_hu(t), (3, 3, 3), np.nan)), "-o", t / OUT],
        "nan.nii.gz: 1 NaN voxel value(s)"),
    "infinite voxels (.npy)": (
        lambda t, b: ["segment", (np.save(t / "inf.npy", _with(_hu(t), (slice(0, 2), 0, 0), -np.inf)),
                                  t / "inf.npy")[1], "-o", t / OUT],
        "inf.npy: 2 infinite voxel value(s)"),
    "NIfTI pixdim 0": (
        lambda t, b: ["segment", _nifti(t, "flat.nii", _hu(t), pixdim=0.0), "-o", t / OUT],
        "flat.nii: the header's voxel spacing (pixdim) is 1, 1, 0 mm"),
    "NIfTI pixdim NaN": (
        lambda t, b: ["segment", _nifti(t, "nanpix.nii", _hu(t), pixdim=np.nan), "-o", t / OUT],
        "image.spacing"),
    "MetaImage negative spacing": (
        lambda t, b: ["segment", (t / "neg.mha").write_bytes(
            b"ObjectType = Image\nNDims = 3\nDimSize = 8 8 8\nElementSpacing = 1 -1 1\n"
            b"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n" + bytes(512)) and t / "neg.mha", "-o", t / OUT],
        "neg.mha: the header's voxel spacing is 1, -1, 1 mm"),
    "MetaImage header with short raw data": (
        lambda t, b: ["segment", _raw_pair(t, "ct.mhd", 1000), "-o", t / OUT],
        "ct.mhd: the header promises 8x8x8 elements of 2 byte(s) = 1024 bytes"),
    "NRRD header with long raw data": (
        lambda t, b: ["segment", _raw_pair(t, "ct.nhdr", 2048), "-o", t / OUT],
        "ct.nhdr: the header promises 8x8x8 elements of 2 byte(s) = 1024 bytes"),
    # 3. outputs: an existing folder
    **{f"{command}: output is a folder": (
        (lambda command, name, out: lambda t, b: (
            (t / out).mkdir(), [command, _copy(b, t, name), "-o", t / out])[1])(command, name, out),
        "is an existing folder")
       for command, name, out in [("segment", "head.nii.gz", "l.nii.gz"), ("downsample", "labels.nii.gz", "d.nii.gz"),
                                  ("fix", "labels.nii.gz", "f.nii.gz"), ("mesh", "labels.nii.gz", "m.vtu"),
                                  ("merge", "mesh.vtu", "g.vtu"), ("smooth", "mesh.vtu", "s.vtu"),
                                  ("export", "mesh.vtu", "model.inp"), ("quality", "mesh.vtu", "q.json")]},
    "phantom: output is a folder": (
        lambda t, b: ((t / "p.nii.gz").mkdir(), ["phantom", "sphere", "-o", t / "p.nii.gz"])[1],
        "p.nii.gz: the output (-o) is an existing folder"),
    "fix: report is a folder": (
        lambda t, b: ((t / "fix.json").mkdir(),
                      ["fix", _copy(b, t, "labels.nii.gz"), "-o", t / "f.nii.gz", "--report", t / "fix.json"])[1],
        "fix.json: the output (--report) is an existing folder"),
    "run: a result name is a folder": (
        lambda t, b: ((t / "out" / "mesh.vtu").mkdir(parents=True), ["run", _copy(b, t, "head.nii.gz"), "-o", t / "out"])[1],
        "mesh.vtu: is a folder where dicer run writes"),
    # 3. outputs: the input itself
    **{f"{command}: output is the input": (
        (lambda command, name: lambda t, b: [command, _copy(b, t, name), "-o", t / name])(command, name),
        "is the input file itself")
       for command, name in [("segment", "head.nii.gz"), ("downsample", "labels.nii.gz"), ("fix", "labels.nii.gz"),
                             ("merge", "mesh.vtu"), ("smooth", "mesh.vtu"), ("export", "mesh.vtu")]},
    "segment: output is the input by another spelling": (
        lambda t, b: ["segment", _copy(b, t, "head.nii.gz"), "-o", t / "sub" / ".." / "head.nii.gz"],
        "is the input file itself"),
    "quality: output is a stage report given as input": (
        lambda t, b: ((t / "q.json").write_text("{}\n"),
                      ["quality", _copy(b, t, "mesh.vtu"), "-o", t / "q.json", "--stage-report", t / "q.json"])[1],
        "q.json: the output (-o) is the input file itself"),
    "run: output folder is the input folder": (
        lambda t, b: ["run", write_dicom_series(t / "series", [0, 2, 4]), "-o", t / "series"],
        "series: the output (-o) is the input itself"),
    # 4. found by the hostile re-run (tests/hostile.py)
    **{f"{command}: VTU with {label}": (
        (lambda command, out, edit: lambda t, b: [command, _vtu_edit(b / "mesh.vtu", t / "bad.vtu", edit), "-o",
                                                  t / out])(command, out, edit), expected)
       for command, out in (("merge", "g.vtu"), ("export", "model.inp"), ("quality", "q.json"))
       for label, edit, expected in (
           ("connectivity past the nodes", hostile._set_first(10 ** 6), "bad.vtu: 1 element corner(s) refer to nodes"),
           ("negative connectivity", hostile._set_first(-3), "bad.vtu: 1 element corner(s) refer to nodes"),
           ("a NaN coordinate", hostile._nan_point, "bad.vtu: 1 node(s) have NaN or infinite coordinates"),
           ("a negative lattice index", hostile._negative_lattice, "bad.vtu: 1 node(s) have a negative lattice index"))},
    # 5. found by probing meshes made or edited elsewhere
    **{f"{command}: a mesh with an inverted element": (
        (lambda command, out: lambda t, b: [command, _inverted_vtu(t / "inv.vtu"), "-o", t / out])(command, out),
        "inv.vtu: 1 degenerate or inverted element(s), e.g. element 1")
       for command, out in (("export", "model.inp"), ("surface", "surf"))},
    **{f"{command}: a mesh saved again by meshio (no grid data)": (
        (lambda command, out: lambda t, b: [command, _resaved_vtu(b / "mesh.vtu", t / "re.vtu"), "-o", t / out])(
            command, out), "re.vtu: the mesh file has no grid data")
       for command, out in (("export", "model.inp"), ("smooth", "s.vtu"))},
    **{f"{command}: an order-2 export (20-node hexahedra) as its mesh": (
        (lambda command, out: lambda t, b: [command, _quadratic_vtu(b / "mesh.vtu", t / "model.vtu"), "-o",
                                            t / out])(command, out),
        "model.vtu: holds quadratic elements (hexahedron20), as an export with export.order 2 writes them, and "
        "dicer reads meshes of linear hexahedra or quads; give the stage mesh it was exported from (smoothed.vtu), "
        "or a model.vtu exported with export.order 1")
       for command, out in (("surface", "surf"), ("quality", "q.json"))},
    "export: material 0 in a mesh": (
        lambda t, b: ["export", _material_vtu(t / "m0.vtu", 0), "-o", t / "model.inp"],
        "m0.vtu: 1 element(s) have material 0; material numbers are labels 1..K"),
    "quality: a fractional material number": (
        lambda t, b: ["quality", _material_vtu(t / "mf.vtu", 1.5), "-o", t / "q.json"],
        "mf.vtu: the 'material' cell data hold values that are not whole numbers"),
    "downsample: voxel_size=.inf": (
        lambda t, b: ["downsample", _copy(b, t, "labels.nii.gz"), "-o", t / "d.nii.gz",
                      "--set", "downsample.voxel_size=.inf"],
        "key 'downsample.voxel_size': inf is not a finite number"),
    "segment: a manual threshold 1e999": (
        lambda t, b: ["segment", _copy(b, t, "head.nii.gz"), "-o", t / OUT, "--set", "segment.method=manual",
                      "--set", "segment.thresholds=[-100,1e999]"],
        "key 'segment.thresholds[1]': inf is not a finite number"),
    "downsample: factor larger than the image": (
        lambda t, b: ["downsample", _copy(b, t, "labels.nii.gz"), "-o", t / "d.nii.gz",
                      "--set", "downsample.factor=50"],
        "leaves 1x1x1 voxels of the "),
    "segment: opening_radius=1000": (
        lambda t, b: ["segment", _copy(b, t, "head.nii.gz"), "-o", t / OUT, "--set", "segment.opening_radius=1000"],
        "segment.opening_radius=1000 voxels is wider than the image"),
    "quality: a stage report that is not UTF-8": (
        lambda t, b: ["quality", _copy(b, t, "mesh.vtu"), "-o", t / "q.json", "--stage-report",
                      (t / "fix.json").write_bytes(b"\xff{") and t / "fix.json"],
        "fix.json: cannot read the stage report"),
    "quality: --labels of another grid": (
        lambda t, b: ["quality", _copy(b, t, "mesh.vtu"), "-o", t / "q.json", "--labels",
                      (np.save(t / "l.npy", np.ones((5, 5, 5), np.uint8)), t / "l.npy")[1]],
        "l.npy: the labels have 5x5x5 voxels but the mesh was made from "),
    "schema: quality.poor_scaled_jacobian=7": (
        lambda t, b: ["mesh", _copy(b, t, "labels.nii.gz"), "-o", t / "m.vtu", "--set",
                      "quality.poor_scaled_jacobian=7"],
        "key 'quality.poor_scaled_jacobian'"),
    "mesh: a .npy header promising 10^12 voxels": (
        lambda t, b: ["mesh", _huge_npy(t / "huge.npy"), "-o", t / "m.vtu"],
        "huge.npy: the .npy header promises 10000x10000x10000 elements of 4 byte(s)"),
    "phantom: --size 100000": (
        lambda t, b: ["phantom", "sphere", "-o", t / "p.nii.gz", "--size", "100000"],
        "size 100000 is too large"),
    "run: the output folder is a dangling symlink": (
        lambda t, b: ((t / "out").symlink_to(t / "gone"), ["run", _copy(b, t, "head.nii.gz"), "-o", t / "out"])[1],
        "out: exists and is not a folder"),
    "mesh: an output name too long for the file system": (
        lambda t, b: ["mesh", _copy(b, t, "labels.nii.gz"), "-o", t / ("x" * 300 + ".vtu")],
        "cannot use this path (File name too long)"),
    "segment --info that cannot be written keeps no labels": (
        lambda t, b: ["segment", _copy(b, t, "head.nii.gz"), "-o", t / OUT, "--info",
                      (t / "afile").write_text("x") and t / "afile" / "info.json"],
        "info.json: cannot write to folder"),
    "quality: one file for two outputs": (
        lambda t, b: ["quality", _copy(b, t, "mesh.vtu"), "-o", t / "q.json", "--html", t / "q.json"],
        "q.json: given as the output of both -o and --html"),
}


def _inverted_vtu(path: Path) -> Path:
    """A dicer mesh file (all its data) whose first element is turned inside out."""
    from dicer.io.meshes import write_mesh
    from dicer.mesh.topology import HEX_MIRROR
    from dicer.mesh.voxel import voxel_mesh

    mesh = voxel_mesh(np.pad(np.ones((3, 3, 3), np.uint8), ((0, 0), (0, 0), (0, 1))) + 0)
    mesh.cells[0] = mesh.cells[0, HEX_MIRROR]
    write_mesh(mesh, path, allow_inverted=True)
    return path


def _quadratic_vtu(src: Path, path: Path) -> Path:
    """``src`` exported as a VTU of 20-node hexahedra (export.order 2)."""
    assert main(["export", str(src), "-o", str(path), "--set", "export.order=2", "-q"]) == 0
    return path


def _resaved_vtu(src: Path, path: Path) -> Path:
    import meshio

    meshio.write(path, meshio.read(src))
    return path


def _material_vtu(path: Path, value) -> Path:
    """A meshio VTU of a dicer mesh's data with its grid, element 1's material ``value``."""
    from dicer.io.meshes import to_meshio
    from dicer.mesh.voxel import voxel_mesh

    mesh = voxel_mesh(np.ones((2, 2, 2), np.uint8))
    m = to_meshio(mesh)
    material = m.cell_data["material"][0].astype(np.float64)
    material[0] = value
    m.cell_data["material"] = [material]
    meshio_vtu_with_grid(mesh, path, m).unlink()
    return path


def _snapshot(root):
    """Every path under ``root`` with the hash of its bytes (None for folders)."""
    out = {}
    for path in sorted(root.rglob("*")):
        rel = str(path.relative_to(root))
        out[rel] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    return out


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_one_error_line_no_change(tmp_path, capsys, base, case):
    build, expected = CASES[case]
    argv = [str(a) for a in build(tmp_path, base)] + ["-q"]
    before = _snapshot(tmp_path)
    capsys.readouterr()
    code = main(argv)
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2, err
    assert len(errors) == 1, err
    assert "Traceback" not in err
    assert expected in errors[0], errors[0]
    assert _snapshot(tmp_path) == before  # nothing new, nothing changed, no temporary file left
    for secret in ("Anonymous", "Robust", "RB-0001"):
        assert secret not in err


@pytest.mark.parametrize("case", ["dicom: missing slice", "mesh: output is a folder", "segment: output is the input"])
def test_bad_input_from_the_shell(tmp_path, base, case):
    """The same promise through a real process: stderr is the one line, nothing else."""
    build, expected = CASES[case]
    argv = [str(a) for a in build(tmp_path, base)]
    before = _snapshot(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))  # this checkout's dicer
    proc = subprocess.run([sys.executable, "-m", "dicer", *argv, "-q"], capture_output=True, text=True, env=env)
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], proc.stderr
    assert _snapshot(tmp_path) == before


def test_allow_irregular_slices_through_the_command(tmp_path, caplog):
    folder = write_dicom_series(tmp_path / "series", [0, 2, 4, 8, 10, 12], shape=(40, 36))
    out = tmp_path / "labels.nii.gz"
    argv = ["segment", str(folder), "-o", str(out), "--set", "image.allow_irregular_slices=true",
            "--set", "segment.method=manual", "--set", "segment.thresholds=[-500,500]"]
    assert main(argv) == 0
    from dicer.io.images import read_labels

    labels = read_labels(out)
    assert labels.array.shape == (40, 36, 7) and labels.spacing[2] == pytest.approx(2.0)
    assert "resampled its 6 slices to 7 uniform slices of 2 mm" in caplog.text


def test_dicom_objects_without_an_image_are_left_out_and_image_spacing_is_said_unused(tmp_path, caplog):
    """A dose report (SR) or a presentation state beside the slices, as PACS exports put them,
    was refused as a damaged slice ("copy it again from the scanner")."""
    from pydicom.data import get_testdata_file

    from dicer.io.images import read_image

    folder = write_dicom_series(tmp_path / "series", np.arange(6) * 2.0, shape=(16, 14))
    alone = read_image(folder)
    shutil.copy(get_testdata_file("test-SR.dcm"), folder / "SR0001.dcm")
    caplog.set_level("INFO", logger="dicer")
    with_report = read_image(folder)
    assert np.array_equal(with_report.array, alone.array) and with_report.spacing == alone.spacing
    assert "SR0001.dcm: a DICOM Comprehensive SR Storage object, no image: left out of the series" in caplog.text
    # image.spacing does not rescale a series (its slices place themselves): said, as for a file
    assert read_image(folder, spacing=[0.5, 0.5, 0.5]).spacing == alone.spacing
    assert ("series: image.spacing is set ([0.5, 0.5, 0.5]), but the DICOM series carries its own voxel size "
            "(0.7 x 0.7 x 2 mm), which is used") in caplog.text
    # one slice of the series given: a 2D image, and the series said
    assert read_image(folder / "im002.dcm").array.ndim == 2
    assert "im002.dcm: one slice of a series of 6 in its folder, read as a 2D image; give the folder (series)" \
        in caplog.text
    # a damaged slice is still one
    data = (folder / "im003.dcm").read_bytes()
    (folder / "im003.dcm").write_bytes(data[: len(data) - 60])
    with pytest.raises(Exception, match="im003.dcm: this slice of the DICOM series cannot be read"):
        read_image(folder)


def test_a_usage_error_is_one_error_line(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.run([sys.executable, "-m", "dicer", "export", "m.vtu", "-o", "m.inp", "--order", "3"],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == ["error: dicer export: argument --order: invalid choice: 3 (choose from 1, 2); "
                                        "see 'dicer export --help'"]
    assert list(tmp_path.iterdir()) == []
