"""Hostile-input re-run: about 260 bad (and a few good) uses of the ``dicer`` command, each
run as a whole process in a fresh folder, each outcome classified.

A bad case passes when the process exits with status 2 (143 for SIGTERM, 130 for
SIGINT), standard error holds exactly one line starting ``error: `` (log lines of dicer
aside) and no ``Traceback``, the line holds the expected text (the file it names, the
problem), and no file under the case folder is new, changed, removed, 0 bytes or a
``*.tmp*`` file (inputs and outputs included; the case may name paths it allows, such as
``out.failed``). A good case passes when it exits 0, its outputs exist, are not empty and
can be read back, and nothing else changed.

Run ``python -m tests.hostile`` (from the repository root) for a table per class;
``python -m tests.hostile -k dicom -v`` runs the cases whose name holds ``dicom`` and
prints each outcome. ``tests/test_hostile.py`` (marked slow) asserts that none fails.
Full-disk and read-only cases mount a small tmpfs (root only); elsewhere they are skipped
with the reason.
"""

from __future__ import annotations

import argparse
import collections
import re
import gzip
import hashlib
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PYTHON = sys.executable

#: class key -> title (the summary table's rows, in this order)
CLASSES = {
    "1-full-disk": "full disk (ENOSPC) on every writer",
    "2-dicom": "DICOM series defects",
    "3-traceback": "former tracebacks: output folders, config bytes, bad VTU, odd values",
    "4-rerun": "reruns, SIGTERM/SIGINT, stale temporaries, failed runs",
    "5-inputs": "inputs destroyed or silently changed",
    "6-cohort": "cohort sheet (workflow dry run)",
    "7-blame": "errors that must blame the right thing",
    "8-memory": "memory: headers promising huge volumes",
    "9-kinds": "wrong file kinds, empty files, odd shapes and labels",
    "10-paths": "output folders and paths: unwritable, missing, spaces, unicode, symlinks",
    "11-good": "good inputs: exit 0 and checked outputs",
}


@dataclass
class Case:
    cls: str
    name: str
    build: object  # (Ctx) -> argv after "dicer" (items may be Paths); "snakemake" cases: argv of snakemake
    expect: tuple = ()  # texts the error line must contain
    good: bool = False
    outputs: tuple = ()  # good: paths (relative to the case folder) that must be written, checked by kind
    allowed: tuple = ()  # glob patterns (relative) of paths that may appear, change or go
    needs: str | None = None  # "mount" (tmpfs), "snakemake"
    exit: int = 2
    signal_at: tuple | None = None  # (glob that appears in the case folder, signal number)
    mode: str = "dicer"


class Skip(Exception):
    """The case cannot be built on this machine (the reason is the message)."""


class Ctx:
    """A case's folder ``t``, the shared inputs ``b`` and the mounts to undo."""

    def __init__(self, t: Path, b: Path):
        self.t, self.b, self.mounts = t, b, []

    def copy(self, name: str, as_name: str | None = None) -> Path:
        dst = self.t / (as_name or name)
        src = self.b / name
        if src.is_dir():
            shutil.copytree(src, dst)
        else:
            shutil.copy(src, dst)
        return dst

    def mount(self, name: str = "disk", size: str = "256k", free: int | None = None, ro: bool = False,
              keep: dict | None = None) -> Path:
        """A small tmpfs at ``t/name``; ``keep``: files to write first; ``free``: bytes left free
        (a filler file takes the rest); ``ro``: remounted read-only."""
        path = self.t / name
        path.mkdir()
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            raise Skip("cannot mount a small tmpfs here (needs root): " + proc.stderr.strip()[:80])
        self.mounts.append(path)
        for rel, data in (keep or {}).items():
            (path / rel).write_bytes(data)
        if free is not None:
            st = os.statvfs(path)
            have = st.f_bavail * st.f_frsize
            with open(path / "filler", "wb") as f:
                chunk = b"\x01" * 4096
                left = max(have - free, 0)
                try:
                    while left > 0:
                        f.write(chunk[:min(left, 4096)])
                        left -= 4096
                    f.flush()
                    os.fsync(f.fileno())
                except OSError:
                    pass
        if ro:
            subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True, capture_output=True)
        return path

    def close(self):
        for path in reversed(self.mounts):
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


# --- inputs ------------------------------------------------------------------------------


def hu_volume(shape=(12, 12, 12)) -> np.ndarray:
    """A float32 HU cube: air around soft tissue around a bone core."""
    v = np.full(shape, -1000.0, np.float32)
    s = [slice(max(n // 6, 0), n - max(n // 6, 0)) for n in shape]
    v[tuple(s)] = 40.0
    s = [slice(n // 3, n - n // 3) for n in shape]
    v[tuple(s)] = 900.0
    return v


def write_sitk(path: Path, array: np.ndarray, spacing=(1.0, 1.0, 1.0)) -> Path:
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(np.ascontiguousarray(np.asarray(array).transpose()))
    if image.GetDimension() == len(spacing):
        image.SetSpacing(spacing)
    sitk.WriteImage(image, str(path))
    return path


def nifti(path: Path, array: np.ndarray, pixdim=None) -> Path:
    """A NIfTI file; ``pixdim``: {axis 1..3: value} written over the stored header."""
    write_sitk(path, array)
    if pixdim:
        gz = path.name.endswith(".gz")
        data = bytearray(gzip.decompress(path.read_bytes()) if gz else path.read_bytes())
        for axis, value in pixdim.items():
            data[76 + 4 * axis:80 + 4 * axis] = struct.pack("<f", value)
        path.write_bytes(gzip.compress(bytes(data)) if gz else bytes(data))
    return path


def _scaled_sform_only(path: Path) -> Path:
    """``path`` (a .nii.gz) with its qform code 0 and its sform's third column 1.5 times
    pixdim: a transform to another space and no scanner placement."""
    data = bytearray(gzip.decompress(path.read_bytes()))
    struct.pack_into("<h", data, 252, 0)
    column = [struct.unpack_from("<f", data, 280 + 16 * row + 8)[0] for row in range(3)]
    for row, value in enumerate(column):
        struct.pack_into("<f", data, 280 + 16 * row + 8, 1.5 * value)
    struct.pack_into("<h", data, 254, 1)
    path.write_bytes(gzip.compress(bytes(data)))
    return path


def npy(path: Path, array) -> Path:
    np.save(path, array, allow_pickle=True)
    return path


def text(path: Path, content: str | bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return path


def write_dicom_series(folder: Path, positions, shape=(12, 10), orient=None, sizes=None, modality="CT",
                       padding=None) -> Path:
    """A series from scratch (a CT unless ``modality`` says otherwise): one int16 slice per z
    position (slope 1, intercept -1024); ``padding``: a Pixel Padding Value for 12-bit unsigned
    slices, set in the corner pixel."""
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    series_uid = generate_uid(entropy_srcs=["hostile series"])
    for k, z in enumerate(positions):
        cols, rows = (sizes or {}).get(k, shape)
        uid = generate_uid(entropy_srcs=["hostile slice", str(k)])
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = uid
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(folder / f"im{k:03d}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, uid
        ds.StudyInstanceUID = generate_uid(entropy_srcs=["hostile study"])
        ds.SeriesInstanceUID = series_uid
        ds.Modality = modality
        ds.PatientName, ds.PatientID = "Anonymous^Hostile", "HX-0001"
        ds.Rows, ds.Columns = rows, cols
        ds.PixelSpacing = [0.7, 0.7]
        ds.SliceThickness = 1.0
        ds.ImageOrientationPatient = (orient or {}).get(k, [1, 0, 0, 0, 1, 0])
        ds.ImagePositionPatient = [0.0, 0.0, float(z)]
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        pixels = np.full((rows, cols), 0, np.int16)
        pixels[2:-2, 2:-2] = 1100
        pixels[4:-4, 4:-4] = 2000
        if padding is not None:  # 12 bits stored, unsigned: a padding value beyond them
            ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 12, 11, 0
            ds.add_new(0x00280120, "US", padding)
            pixels[0, 0] = padding & 0xFFF  # what the 12 bits keep of it
        ds.PixelData = pixels.tobytes()
        ds.save_as(folder / f"im{k:03d}.dcm", enforce_file_format=True)
    return folder


def _jpeg_slice(t: Path) -> Path:
    """A series whose slice 3 declares JPEG baseline and holds a broken JPEG stream: GDCM's
    decoder printed 'Corrupt JPEG data ...' lines before dicer's one."""
    import pydicom
    from pydicom.encaps import encapsulate

    folder = write_dicom_series(t / "series", np.arange(6) * 2.0)
    ds = pydicom.dcmread(folder / "im003.dcm")
    ds.PixelData = encapsulate([b"\xff\xd8garbage\xff\xd9"])
    ds["PixelData"].is_undefined_length = True
    ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.4.50"
    ds.save_as(folder / "im003.dcm", enforce_file_format=False)
    return folder


def damaged_series(t: Path, how: str) -> Path:
    folder = write_dicom_series(t / "series", np.arange(6) * 2.0)
    victim = folder / "im003.dcm"
    data = victim.read_bytes()
    victim.write_bytes({"truncated": data[: len(data) - 60], "random": os.urandom(len(data)),
                        "empty": b"", "header": data[:300]}[how])
    return folder


def vtu_edit(src: Path, dst: Path, edit) -> Path:
    """A copy of a dicer VTU with one appended array changed: ``edit(name, array) -> array``
    (same dtype and size), applied to every DataArray."""
    import re

    data = src.read_bytes()
    head_end = data.index(b"<AppendedData")
    start = data.index(b"_", head_end) + 1
    header = data[:head_end].decode()
    out = bytearray(data)
    for m in re.finditer(r'<DataArray ([^>]*)>', header):
        attrs = dict(re.findall(r'(\w+)="([^"]*)"', m.group(1)))
        if "offset" not in attrs:
            continue
        off = start + int(attrs["offset"])
        (nbytes,) = struct.unpack("<Q", bytes(out[off:off + 8]))
        dtype = np.dtype({"Float64": "<f8", "Float32": "<f4", "Int64": "<i8", "Int32": "<i4", "UInt8": "u1",
                          "Int8": "i1", "UInt16": "<u2", "UInt32": "<u4", "UInt64": "<u8",
                          "Int16": "<i2"}[attrs["type"]])
        arr = np.frombuffer(bytes(out[off + 8:off + 8 + nbytes]), dtype).copy()
        new = edit(attrs.get("Name", ""), arr)
        if new is not None:
            out[off + 8:off + 8 + nbytes] = np.asarray(new, dtype).tobytes()
    dst.write_bytes(bytes(out))
    return dst


def _set_first(value):
    def edit(name, arr):
        if name == "connectivity":
            arr[0] = value
            return arr
        return None
    return edit


def _nan_point(name, arr):
    if name == "Points":
        arr[4] = np.nan
        return arr
    return None


def _negative_lattice(name, arr):
    if name in ("lattice", "voxel_index", "ijk", "lattice_index"):
        arr[:3] = -5
        return arr
    return None


def dead_pid() -> int:
    proc = subprocess.Popen([PYTHON, "-c", "pass"])
    proc.wait()
    return proc.pid


def make_base(b: Path) -> Path:
    """The shared inputs (made once in-process): a head phantom, its labels and meshes, a run."""
    from dicer.cli import main

    b.mkdir(parents=True, exist_ok=True)
    steps = [
        ["phantom", "head", "-o", b / "head.nii.gz", "--size", "32"],
        ["segment", b / "head.nii.gz", "-o", b / "labels.nii.gz"],
        ["mesh", b / "labels.nii.gz", "-o", b / "mesh.vtu"],
        ["smooth", b / "mesh.vtu", "-o", b / "smoothed.vtu"],
        ["quality", b / "smoothed.vtu", "-o", b / "p1" / "quality.json"],
        ["run", b / "head.nii.gz", "-o", b / "run_out", "--set", "downsample.factor=2"],
        ["phantom", "head", "-o", b / "head48.nii.gz", "--size", "48"],
    ]
    for argv in steps:
        if main([str(a) for a in argv] + ["-q"]) != 0:
            raise RuntimeError(f"cannot build the shared input {argv}")
    from dicer.io.images import read_labels

    labels = read_labels(b / "labels.nii.gz").array
    np.save(b / "labels.npy", labels.astype(np.uint8))
    np.save(b / "big_ones.npy", np.ones((110, 110, 110), np.uint8))
    return b


# --- the cases ---------------------------------------------------------------------------

CASES: list[Case] = []


def case(cls, name, build, *expect, **kw):
    CASES.append(Case(cls, name, build, tuple(expect), **kw))


# every command's good use: (command, input in base, output name, extra args)
COMMANDS = {
    "segment": ("head.nii.gz", "l.nii.gz", []),
    "labels": ("labels.nii.gz", "l.nii.gz", []),
    "downsample": ("labels.nii.gz", "d.nii.gz", ["--set", "downsample.factor=2"]),
    "fix": ("labels.nii.gz", "f.nii.gz", []),
    "mesh": ("labels.nii.gz", "m.vtu", []),
    "merge": ("mesh.vtu", "g.vtu", []),
    "smooth": ("mesh.vtu", "s.vtu", []),
    "export": ("mesh.vtu", "model.inp", []),
    "quality": ("smoothed.vtu", "q.json", []),
    "surface": ("smoothed.vtu", "surf", []),
    "cohort": ("p1", "c.html", []),
    "phantom": (None, "p.nii.gz", ["--size", "12"]),
    "run": ("head.nii.gz", "out", ["--set", "downsample.factor=2"]),
}
IMAGE_INPUT = ("segment", "labels", "downsample", "fix", "mesh", "run")
MESH_INPUT = ("merge", "smooth", "export", "quality", "surface")


def argv_for(c: Ctx, command: str, inp=None, out=None, extra=()) -> list:
    """The command's good argv in ``c``, with the input (a Path) or output (a Path) replaced."""
    base_in, out_name, args = COMMANDS[command]
    if command == "phantom":
        return ["phantom", "sphere", "-o", out or c.t / out_name, *args, *extra]
    if inp is None:
        inp = c.copy(base_in)
        if command == "cohort":
            inp = inp / "quality.json"
    return [command, inp, "-o", out or c.t / out_name, *args, *extra]


def _bind(f, *a, **k):
    return lambda c: f(c, *a, **k)


# 1. full disk ------------------------------------------------------------------------------

WRITERS = [  # (label, command, output name, extra args) -- each a separate writer of the project
    ("segment .nii.gz", "segment", "l.nii.gz", []),
    ("segment .nii", "segment", "l.nii", []),
    ("segment --info", "segment", None, ["--info", "{disk}/info.json"]),
    ("segment --overlay", "segment", None, ["--overlay", "{disk}/o.png"]),
    ("labels", "labels", "l.nii.gz", []),
    ("labels --materials", "labels", None, ["--materials", "{disk}/mat.json"]),
    ("downsample", "downsample", "d.nii.gz", []),
    ("fix", "fix", "f.nii.gz", []),
    ("fix --report", "fix", None, ["--report", "{disk}/fix.json"]),
    ("mesh", "mesh", "m.vtu", []),
    ("merge", "merge", "g.vtu", []),
    ("smooth", "smooth", "s.vtu", []),
    ("export .inp", "export", "model.inp", []),
    ("export .vtu", "export", "model.vtu", []),
    ("export .k", "export", "model.k", []),
    ("export .feb", "export", "model.feb", []),
    ("export .exo", "export", "model.exo", []),
    ("export .msh", "export", "model.msh", []),
    ("export .out", "export", "model.out", []),
    ("quality", "quality", "q.json", []),
    ("quality --html", "quality", None, ["--html", "{disk}/q.html"]),
    ("quality --csv", "quality", None, ["--csv", "{disk}/q.csv"]),
    ("quality --histogram", "quality", None, ["--histogram", "{disk}/j.png"]),
    ("surface", "surface", "surf", []),
    ("cohort", "cohort", "c.html", []),
    ("cohort --tsv", "cohort", None, ["--tsv", "{disk}/c.tsv"]),
    ("phantom .nii.gz", "phantom", "p.nii.gz", []),
    ("phantom .nrrd", "phantom", "p.nrrd", []),
    ("phantom .mha", "phantom", "p.mha", []),
    ("run", "run", "out", []),
]


def _full_disk(c: Ctx, command, out_name, extra, free=0, good_file=False):
    keep = {}
    if good_file and out_name and command != "surface" and command != "run":
        keep = {out_name: b"a good earlier result\n"}
    disk = c.mount(free=free, keep=keep)
    extra = [a.replace("{disk}", str(disk)) for a in extra]
    out = disk / out_name if out_name else None
    if command == "downsample":
        extra = ["--set", "downsample.factor=1"] + extra  # the factor-1 path (keeps the header)
    return argv_for(c, command, out=out, extra=extra)


for label, command, out_name, extra in WRITERS:
    case("1-full-disk", f"{label}: disk full (0 bytes free)",
         _bind(_full_disk, command, out_name, extra), "disk", needs="mount")
for label, command, out_name, extra in WRITERS:
    if out_name and command not in ("surface", "run", "cohort"):
        case("1-full-disk", f"{label}: disk full, a good earlier file to keep",
             _bind(_full_disk, command, out_name, extra, good_file=True), "disk", needs="mount")
for label, command, out_name, extra in WRITERS:
    if command in ("mesh", "merge", "smooth", "export", "surface") or label == "quality --csv":
        case("1-full-disk", f"{label}: disk nearly full (8 KiB free)",
             _bind(_full_disk, command, out_name, extra, free=8192, good_file=True), "disk", needs="mount")
case("1-full-disk", "run: disk nearly full (64 KiB free)", _bind(_full_disk, "run", "out", [], free=65536),
     "disk", needs="mount", allowed=("disk/out.failed", "disk/out.failed/*"))

# 2. DICOM series ---------------------------------------------------------------------------

DICOM_CASES = {
    "missing slice": (lambda c: write_dicom_series(c.t / "series", [0, 2, 4, 8, 10, 12]), "misses slices"),
    "two missing slices in a row": (lambda c: write_dicom_series(c.t / "series", [0, 2, 4, 10, 12, 14]),
                                    "misses slices"),
    "uneven steps": (lambda c: write_dicom_series(c.t / "series", [0, 2, 4, 7, 8, 10]), "uneven slice steps"),
    "duplicate position": (lambda c: write_dicom_series(c.t / "series", [0, 2, 4, 4, 6, 8]), "same position"),
    "all slices at one position": (lambda c: write_dicom_series(c.t / "series", [3, 3, 3, 3]), "same position"),
    "truncated slice": (lambda c: damaged_series(c.t, "truncated"), "im003.dcm"),
    "random-bytes slice": (lambda c: damaged_series(c.t, "random"), "im003.dcm"),
    "0-byte slice": (lambda c: damaged_series(c.t, "empty"), "im003.dcm"),
    "slice cut in its header": (lambda c: damaged_series(c.t, "header"), "im003.dcm"),
    "slice with a broken JPEG stream": (lambda c: _jpeg_slice(c.t), "im003.dcm"),
    "slices of two orientations": (lambda c: write_dicom_series(c.t / "series", [0, 2, 4, 6],
                                                                orient={2: [0, 1, 0, 0, 0, 1]}), "orientation"),
    "slices of two sizes": (lambda c: write_dicom_series(c.t / "series", [0, 2, 4, 6], sizes={1: (14, 10)}),
                            "differ in size"),
    "folder of notes only": (lambda c: (text(c.t / "series" / "notes.txt", "scan notes\n"), c.t / "series")[1],
                             "series"),
    "empty folder": (lambda c: (c.t / "series").mkdir() or c.t / "series", "series"),
    "MR series under the CT defaults": (lambda c: write_dicom_series(c.t / "series", np.arange(6) * 2.0,
                                                                     modality="MR"), "Modality MR"),
    "12-bit slices with a padding value beyond their bits": (
        lambda c: write_dicom_series(c.t / "series", np.arange(6) * 2.0, padding=63536), "Bits Stored"),
}
for label, (build, expect) in DICOM_CASES.items():
    case("2-dicom", f"segment: DICOM {label}",
         (lambda build: lambda c: ["segment", build(c), "-o", c.t / "l.nii.gz"])(build), expect)
for label in ("missing slice", "duplicate position", "truncated slice", "random-bytes slice", "slices of two sizes",
              "MR series under the CT defaults"):
    build, expect = DICOM_CASES[label]
    case("2-dicom", f"run: DICOM {label}",
         (lambda build: lambda c: ["run", build(c), "-o", c.t / "out"])(build), expect)
for label in ("duplicate position", "truncated slice", "random-bytes slice"):
    build, expect = DICOM_CASES[label]
    case("2-dicom", f"segment: DICOM {label} with allow_irregular_slices",
         (lambda build: lambda c: ["segment", build(c), "-o", c.t / "l.nii.gz",
                                   "--set", "image.allow_irregular_slices=true"])(build), expect)
case("2-dicom", "smooth --image: a DICOM series with a missing slice",
     lambda c: ["smooth", c.copy("mesh.vtu"), "-o", c.t / "s.vtu", "--image",
                write_dicom_series(c.t / "series", [0, 2, 4, 8]), "--set", "smooth.surface_from_image=true",
                "--set", "segment.method=manual"], "misses slices")

# 3. former tracebacks ----------------------------------------------------------------------

for command in COMMANDS:
    if command == "surface":
        case("3-traceback", "surface: output is an existing file",
             lambda c: ["surface", c.copy("smoothed.vtu"), "-o", text(c.t / "surf", "x")], "not a folder")
        continue
    if command == "run":
        case("3-traceback", "run: output is an existing file",
             lambda c: ["run", c.copy("head.nii.gz"), "-o", text(c.t / "out", "x")], "not a folder")
        continue
    case("3-traceback", f"{command}: output is an existing folder",
         (lambda command: lambda c: (c.t.joinpath(COMMANDS[command][1]).mkdir(), argv_for(c, command))[1])(command),
         "existing folder")
NON_UTF8 = b"segment:\n  method: otsu  # caf\xe9\n"
for command in ("segment", "mesh", "export", "run"):
    case("3-traceback", f"{command}: config file not UTF-8",
         (lambda command: lambda c: argv_for(c, command, extra=["--config", text(c.t / "c.yaml", NON_UTF8)]))(command),
         "c.yaml", "UTF-8")
for value in (".inf", "-.inf", ".nan", "1e400", "0", "-1"):
    case("3-traceback", f"downsample: voxel_size={value}",
         (lambda value: lambda c: argv_for(c, "downsample", extra=["--set", f"downsample.voxel_size={value}"]))(value),
         "voxel_size")
for value in ("nan", "inf", "1e999"):
    case("3-traceback", f"segment: manual thresholds with {value}",
         (lambda value: lambda c: argv_for(c, "segment", extra=["--set", "segment.method=manual", "--set",
                                                                f"segment.thresholds=[-100,{value}]"]))(value),
         "thresholds")
BAD_VTU = {
    "connectivity past the last node": (_set_first(10 ** 6), "mesh.vtu"),
    "negative connectivity": (_set_first(-3), "mesh.vtu"),
    "NaN node coordinate": (_nan_point, "mesh.vtu"),
    "negative lattice index": (_negative_lattice, "mesh.vtu"),
}
for label, (edit, expect) in BAD_VTU.items():
    for command in MESH_INPUT:
        case("3-traceback", f"{command}: VTU with {label}",
             (lambda command, edit: lambda c: argv_for(
                 c, command, inp=vtu_edit(c.b / "mesh.vtu", c.t / "mesh.vtu", edit)))(command, edit), expect)
for command in MESH_INPUT:
    case("3-traceback", f"{command}: VTU cut in half",
         (lambda command: lambda c: argv_for(c, command, inp=text(
             c.t / "mesh.vtu", (c.b / "mesh.vtu").read_bytes()[: (c.b / "mesh.vtu").stat().st_size // 2])))(command),
         "mesh.vtu")
case("3-traceback", "export --order 3", lambda c: argv_for(c, "export", extra=["--order", "3"]), exit=2)
case("3-traceback", "--settings not JSON", lambda c: argv_for(c, "mesh", extra=["--settings", "{"]), "--settings")
case("3-traceback", "--set without '='", lambda c: argv_for(c, "mesh", extra=["--set", "mesh.coordinates"]),
     "mesh.coordinates")
case("3-traceback", "--set of an unknown key", lambda c: argv_for(c, "mesh", extra=["--set", "mesh.colour=1"]),
     "mesh.colour")
case("3-traceback", "--set YAML that does not parse", lambda c: argv_for(c, "mesh", extra=["--set", "fix.type_c=[1,"]),
     "fix.type_c")
case("3-traceback", "run: keep_bounding_planes false without free planes (refused before any stage)",
     lambda c: argv_for(c, "run", extra=["--set", "smooth.keep_bounding_planes=false"]),
     "smooth.keep_bounding_planes")
case("3-traceback", "run: workflow.exports with LS-DYNA at export.order 2 (refused before any stage)",
     lambda c: argv_for(c, "run", extra=["--set", "workflow.exports=[inp,k]", "--set", "export.order=2"]),
     "workflow.exports")
case("3-traceback", "merge: merge.templates.levels 2.5",
     lambda c: argv_for(c, "merge", extra=["--set", "merge.method=templates", "--set", "merge.templates.levels=2.5"]),
     "merge.templates.levels")
case("3-traceback", "config file that is YAML nonsense",
     lambda c: argv_for(c, "mesh", extra=["--config", text(c.t / "c.yaml", "segment: [1, 2\n  - :\n")]), "c.yaml")
case("3-traceback", "config file that is a list",
     lambda c: argv_for(c, "mesh", extra=["--config", text(c.t / "c.yaml", "- 1\n- 2\n")]), "c.yaml")
case("3-traceback", "config file that is empty",
     lambda c: argv_for(c, "mesh", extra=["--config", text(c.t / "c.yaml", ""), "--set", "mesh.colour=1"]),
     "mesh.colour")
case("3-traceback", "config file is a folder",
     lambda c: argv_for(c, "mesh", extra=["--config", (c.t / "c.yaml").mkdir() or c.t / "c.yaml"]), "c.yaml")
case("3-traceback", "config file missing", lambda c: argv_for(c, "mesh", extra=["--config", c.t / "no.yaml"]),
     "no.yaml")
case("3-traceback", "materials file not JSON",
     lambda c: argv_for(c, "mesh", extra=["--materials", text(c.t / "mat.json", "{")]), "mat.json")
case("3-traceback", "materials file with a number as material",
     lambda c: argv_for(c, "mesh", extra=["--materials", text(c.t / "mat.json", '{"materials": [1, 2]}')]),
     "mat.json")
case("3-traceback", "smooth --thresholds not a list",
     lambda c: ["smooth", c.copy("mesh.vtu"), "-o", c.t / "s.vtu", "--image", c.copy("head.nii.gz"),
                "--thresholds", text(c.t / "seg.json", '{"thresholds": "high"}'),
                "--set", "smooth.surface_from_image=true"], "seg.json")
case("3-traceback", "quality --stage-report not UTF-8",
     lambda c: argv_for(c, "quality", extra=["--stage-report", text(c.t / "fix.json", b"\xff\xfe{")]), "fix.json")
case("3-traceback", "cohort: a benchmark file not UTF-8",
     lambda c: argv_for(c, "cohort", extra=["--benchmarks", (text(c.t / "bench" / "p1" / "mesh.tsv", b"s\t\xff\n1\n"),
                                                              c.t / "bench")[1]]), "mesh.tsv")
case("3-traceback", "cohort: a quality report that is a JSON list",
     lambda c: ["cohort", text(c.t / "p1" / "quality.json", "[1, 2]"), "-o", c.t / "c.html"], "quality.json")
case("3-traceback", "phantom: unknown name", lambda c: ["phantom", "cube", "-o", c.t / "p.nii.gz"], "cube")
case("3-traceback", "phantom: --size 0", lambda c: ["phantom", "sphere", "-o", c.t / "p.nii.gz", "--size", "0"],
     "size")
case("3-traceback", "phantom: --size -5", lambda c: ["phantom", "sphere", "-o", c.t / "p.nii.gz", "--size", "-5"],
     "size")
case("3-traceback", "phantom: --noise nan", lambda c: ["phantom", "sphere", "-o", c.t / "p.nii.gz", "--noise", "nan"],
     "noise")
case("3-traceback", "phantom: --noise -1", lambda c: ["phantom", "sphere", "-o", c.t / "p.nii.gz", "--noise", "-1"],
     "noise")

# 4. reruns, signals, stale temporaries -------------------------------------------------------

RUN_FAIL = ["--set", "smooth.min_scaled_jacobian=0.99", "--set", "smooth.max_backoff_rounds=0"]
case("4-rerun", "run fails at smooth into an existing result folder",
     lambda c: ["run", c.copy("head.nii.gz"), "-o", c.copy("run_out", "out"), "--set", "downsample.factor=2",
                *RUN_FAIL], "stopped at the smooth stage", "out.failed", allowed=("out.failed", "out.failed/*"))
case("4-rerun", "run fails at smooth into a new folder",
     lambda c: ["run", c.copy("head.nii.gz"), "-o", c.t / "out", "--set", "downsample.factor=2", *RUN_FAIL],
     "stopped at the smooth stage", allowed=("out.failed", "out.failed/*"))
case("4-rerun", "run fails at smooth, an older out.failed is replaced",
     lambda c: (text(c.t / "out.failed" / "old.txt", "x"),
                ["run", c.copy("head.nii.gz"), "-o", c.t / "out", "--set", "downsample.factor=2", *RUN_FAIL])[1],
     "stopped at the smooth stage", allowed=("out.failed", "out.failed/*"))
case("4-rerun", "run fails at segment into an existing result folder",
     lambda c: (c.copy("run_out", "out"),
                ["run", npy(c.t / "flat.npy", np.zeros((8, 8, 8), np.float32)), "-o", c.t / "out"])[1], "flat.npy")
case("4-rerun", "run fails at fix (too few materials) into an existing result folder",
     lambda c: (c.copy("run_out", "out"),
                ["run", "--labels", npy(c.t / "l.npy", np.full((8, 8, 8), 0, np.uint8)), "-o", c.t / "out"])[1],
     "l.npy")
for stage_file in ("labels.nii.gz", "labels_ds.nii.gz", "labels_fixed.nii.gz", "mesh.vtu", "merged.vtu",
                   "smoothed.vtu", "model.inp"):
    case("4-rerun", f"run: SIGTERM after {stage_file} is written",
         lambda c: ["run", c.copy("head48.nii.gz"), "-o", c.t / "out"], "terminated",
         exit=143, signal_at=(f".out.partial/{stage_file}", signal.SIGTERM), allowed=("out.failed", "out.failed/*"))
case("4-rerun", "run into an existing folder: SIGTERM after mesh.vtu is written",
     lambda c: ["run", c.copy("head48.nii.gz"), "-o", c.copy("run_out", "out")], "terminated",
     "out is unchanged; the finished stage files are in", exit=143, signal_at=(".out.partial/mesh.vtu", signal.SIGTERM), allowed=("out.failed", "out.failed/*"))
case("4-rerun", "run into a folder given by an empty -o (an unset shell variable)",
     lambda c: ["run", c.copy("head48.nii.gz"), "-o", ""], "-o names no folder")
case("4-rerun", "run: SIGINT after mesh.vtu is written",
     lambda c: ["run", c.copy("head48.nii.gz"), "-o", c.t / "out"], "interrupted",
     "the finished stage files are in", exit=130, signal_at=(".out.partial/mesh.vtu", signal.SIGINT), allowed=("out.failed", "out.failed/*"))
for command, out_name, pattern in (("mesh", "m.vtu", ".m.vtu.*.tmp*"),):
    case("4-rerun", f"{command}: SIGTERM while the output is written",
         lambda c: ["mesh", c.copy("big_ones.npy"), "-o", c.t / "m.vtu"], "terminated", exit=143,
         signal_at=(pattern, signal.SIGTERM))
    case("4-rerun", f"{command}: SIGTERM while the output is written, a good file to keep",
         lambda c: (text(c.t / "m.vtu", "an earlier mesh"),
                    ["mesh", c.copy("big_ones.npy"), "-o", c.t / "m.vtu"])[1], "terminated", exit=143,
         signal_at=(pattern, signal.SIGTERM))
case("4-rerun", "export: SIGTERM while the deck is written",
     lambda c: ["export", c.copy("big_mesh.vtu"), "-o", c.t / "model.inp"], "terminated", exit=143,
     signal_at=(".model.inp.*.tmp*", signal.SIGTERM))
for command in ("mesh", "export", "segment", "quality"):
    out_name = COMMANDS[command][1]
    case("4-rerun", f"{command}: a stale temporary file of a killed run is removed",
         (lambda command, out_name: lambda c: (
             text(c.t / f".{out_name}.{dead_pid()}.abcdef.tmp{Path(out_name).suffix}", "partial"),
             argv_for(c, command))[1])(command, out_name),
         good=True, outputs=(out_name,), allowed=(f".{out_name}.*.tmp*",))
case("4-rerun", "run: a stale staging folder of a killed run is replaced",
     lambda c: (text(c.t / ".out.partial" / "mesh.vtu", "partial"), argv_for(c, "run"))[1],
     good=True, outputs=("out/model.inp", "out/quality.json"), allowed=(".out.partial", ".out.partial/*"))
case("4-rerun", "run: rerun into an existing result folder (good)",
     lambda c: (c.copy("run_out", "out"), argv_for(c, "run"))[1], good=True,
     outputs=("out/model.inp", "out/mesh.vtu"), allowed=("out/*",))
case("4-rerun", "run: a temporary file of a live process is left alone",
     lambda c: (text(c.t / f".m.vtu.{os.getpid()}.ghijkl.tmp.vtu", "live"), argv_for(c, "mesh"))[1],
     good=True, outputs=("m.vtu",), allowed=(".m.vtu.*.ghijkl.tmp.vtu",))

# 5. inputs destroyed or silently changed -----------------------------------------------------

for command in ("segment", "labels", "downsample", "fix", "merge", "smooth", "export"):
    case("5-inputs", f"{command}: -o the input itself",
         (lambda command: lambda c: argv_for(c, command, out=c.copy(COMMANDS[command][0]),
                                             inp=c.t / COMMANDS[command][0]))(command), "input file itself")
for command in ("segment", "fix", "smooth"):
    case("5-inputs", f"{command}: -o a hard link to the input",
         (lambda command: lambda c: (os.link(c.copy(COMMANDS[command][0]), c.t / ("link" + COMMANDS[command][1])),
                                     argv_for(c, command, inp=c.t / COMMANDS[command][0],
                                              out=c.t / ("link" + COMMANDS[command][1])))[1])(command),
         "input file itself")
    case("5-inputs", f"{command}: -o a symlink to the input",
         (lambda command: lambda c: ((c.t / ("link" + COMMANDS[command][1])).symlink_to(c.copy(COMMANDS[command][0])),
                                     argv_for(c, command, inp=c.t / COMMANDS[command][0],
                                              out=c.t / ("link" + COMMANDS[command][1])))[1])(command),
         "input file itself")
case("5-inputs", "quality: --html is the mesh", lambda c: argv_for(c, "quality", extra=["--html", c.t / "smoothed.vtu"]),
     "input file itself")
case("5-inputs", "quality: --csv is --labels",
     lambda c: argv_for(c, "quality", extra=["--labels", c.copy("labels.nii.gz"), "--csv", c.t / "labels.nii.gz"]),
     "labels.nii.gz")
case("5-inputs", "run: -o a folder holding the input as labels.nii.gz",
     lambda c: (c.t.joinpath("out").mkdir(), ["run", c.copy("head.nii.gz", "out/labels.nii.gz"), "-o", c.t / "out"])[1],
     "labels.nii.gz")
for axis, value in ((1, 0.0), (2, float("nan")), (3, float("inf")), (3, -1.0), (1, float("-inf"))):
    for suffix in (".nii", ".nii.gz") if axis == 3 else (".nii.gz",):
        case("5-inputs", f"segment: NIfTI pixdim[{axis}] = {value} ({suffix})",
             (lambda axis, value, suffix: lambda c: argv_for(
                 c, "segment", inp=nifti(c.t / f"bad{suffix}", hu_volume(), {axis: value})))(axis, value, suffix),
             f"bad{suffix}", "spacing")
for label, value in (("NaN", np.nan), ("+Inf", np.inf), ("-Inf", -np.inf)):
    case("5-inputs", f"segment: a {label} voxel in .npy",
         (lambda value: lambda c: argv_for(c, "segment", inp=npy(c.t / "v.npy", _with(hu_volume(), (5, 5, 5), value))))(value),
         "v.npy")
    for suffix in (".nii.gz", ".nrrd", ".mha"):
        case("5-inputs", f"segment: a {label} voxel in {suffix}",
             (lambda value, suffix: lambda c: argv_for(c, "segment", inp=write_sitk(
                 c.t / f"v{suffix}", _with(hu_volume(), (5, 5, 5), value))))(value, suffix), f"v{suffix}")
case("5-inputs", "mesh: labels .npy of float with NaN",
     lambda c: argv_for(c, "mesh", inp=npy(c.t / "l.npy", _with(np.ones((8, 8, 8), np.float32), (1, 1, 1), np.nan))),
     "l.npy")
case("5-inputs", "labels: label volume .nii.gz of float with NaN",
     lambda c: argv_for(c, "labels", inp=write_sitk(c.t / "l.nii.gz",
                                                     _with(np.ones((8, 8, 8), np.float32), (1, 1, 1), np.nan))),
     "l.nii.gz")
for command in ("quality", "export", "surface", "smooth", "merge"):
    case("5-inputs", f"{command}: a mesh with a NaN node coordinate",
         (lambda command: lambda c: argv_for(c, command, inp=vtu_edit(c.b / "smoothed.vtu", c.t / "n.vtu",
                                                                      _nan_point)))(command), "n.vtu")
case("5-inputs", "smooth --labels: labels of another grid",
     lambda c: argv_for(c, "smooth", extra=["--labels", c.copy("big_ones.npy")]), "big_ones.npy", "110x110x110")
def _moved_labels(c: Ctx, voxels: int, name: str) -> Path:
    """The base labels moved by ``voxels`` along x: the mesh's grid, another anatomy (6) or the
    same a slip away (1: a few per cent of the elements miss their material)."""
    from dicer.image import Volume
    from dicer.io.images import read_labels, write_labels

    labels = read_labels(c.b / "labels.nii.gz")
    write_labels(Volume(np.roll(labels.array, voxels, axis=0), labels.spacing, labels.origin, labels.direction),
                 c.t / name)
    return c.t / name


for label, voxels, name in (("labels of another scan", 6, "moved.nii.gz"),
                            ("the labels shifted by a voxel (exit 0 until 6 December 2026)", 1, "shifted.nii.gz")):
    case("5-inputs", f"smooth --labels: {label}",
         (lambda voxels, name: lambda c: argv_for(c, "smooth", extra=["--labels", _moved_labels(c, voxels, name)]))(
             voxels, name), name, "hold no voxel of their material")
case("5-inputs", "smooth --labels: the scan instead of its labels",
     lambda c: argv_for(c, "smooth", extra=["--labels", c.copy("head.nii.gz")]), "head.nii.gz")
case("5-inputs", "smooth --labels: a float label volume with NaN",
     lambda c: argv_for(c, "smooth", extra=["--labels", npy(c.t / "l.npy", _with(np.ones((32, 32, 32), np.float32),
                                                                                 (1, 1, 1), np.nan))]), "l.npy")
for label, content in (("a key twice", "smooth:\n  interior: true\nsmooth:\n  interior: false\n"),
                       ("a nested key twice", "smooth:\n  interior: true\n  interior: false\n"),
                       ("an anchor merge key twice", "a: &x {b: 1}\nfix:\n  <<: *x\n  type_c: true\n  type_c: false\n")):
    case("5-inputs", f"config with {label}",
         (lambda content: lambda c: argv_for(c, "mesh", extra=["--config", text(c.t / "c.yaml", content)]))(content),
         "c.yaml")
case("5-inputs", "config with a tab indent",
     lambda c: argv_for(c, "mesh", extra=["--config", text(c.t / "c.yaml", "smooth:\n\tinterior: true\n")]), "c.yaml")

# 6. cohort sheet (Snakemake dry run) -----------------------------------------------------------


def _sheet(c: Ctx, rows: str | bytes, config: dict | None = None):
    import yaml

    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    cfg["workflow"]["phantom_size"] = 32
    for key, value in (config or {}).items():
        cfg.setdefault(key, {}).update(value)
    text(c.t / "config" / "config.yaml", yaml.safe_dump(cfg, sort_keys=False))
    text(c.t / "config" / "patients.tsv", rows)
    return ["-s", ROOT / "Snakefile", "-d", c.t, "--cores", "1", "-n"]


HEAD = "patient\timage\toverrides\n"
PHANTOM_ROW = "head\tresources/phantoms/head.nii.gz\t\n"
SHEETS = {
    "a row whose image is missing": (HEAD + PHANTOM_ROW + "absent\tno/such/scan.nii.gz\t\n",
                                     {"workflow": {"skip_missing": False}}, "line 3: patient 'absent'"),
    "an unknown column": ("patient\tscan\n" + "head\tresources/phantoms/head.nii.gz\n", None, "unknown column 'scan'"),
    "a sheet not UTF-8": ((HEAD + PHANTOM_ROW).encode() + b"caf\xe9\tresources/phantoms/head.nii.gz\t\n", None,
                          "not UTF-8"),
    "a patient twice": (HEAD + PHANTOM_ROW + PHANTOM_ROW, None, "appears twice"),
    "a row with image and labels": ("patient\timage\tlabels\nhead\tresources/phantoms/head.nii.gz\tl.nii.gz\n",
                                    None, "not both"),
    "a row without a patient code": (HEAD + "\tresources/phantoms/head.nii.gz\t\n", None, "line 2"),
    "an override with an unknown key": (HEAD + "head\tresources/phantoms/head.nii.gz\tfix.colour=1\n", None,
                                        "fix.colour"),
    "an override that is not KEY=VALUE": (HEAD + "head\tresources/phantoms/head.nii.gz\tfix\n", None, "head"),
    "a bad override below blank rows": (HEAD + "\n\n" + "head\tresources/phantoms/head.nii.gz\tfix.colour=1\n", None,
                                         "line 4: patient head"),
    "an unclosed quote": (HEAD + 'head\t"resources/phantoms/head.nii.gz\t\n' + PHANTOM_ROW.replace("head", "b", 1),
                          {"workflow": {"skip_missing": True}}, "line 2: a quote"),
    "an override in a fourth cell": (HEAD + "head\tresources/phantoms/head.nii.gz\t\tdownsample.factor=2\n", None,
                                     "line 2: 4 cells where the header names 3"),
    "a per-patient workflow setting": (HEAD + "head\tresources/phantoms/head.nii.gz\tworkflow.exports=[feb]\n",
                                       None, "the workflow settings are the whole cohort's"),
    "a patient named as the workflow's files": (HEAD + "cohort.log\tresources/phantoms/head.nii.gz\t\n", None,
                                                "is a name the workflow gives its own files"),
    "an unknown phantom": (HEAD + "head\tresources/phantoms/Head.nii.gz\t\n", None,
                           "the workflow makes resources/phantoms/<name>.nii.gz"),
    "no patient": (HEAD, None, "the sheet lists no patient"),
}
for label, (rows, cfg, expect) in SHEETS.items():
    case("6-cohort", f"sheet with {label}", (lambda rows, cfg: lambda c: _sheet(c, rows, cfg))(rows, cfg), expect,
         mode="snakemake", needs="snakemake", exit=1, allowed=(".snakemake", ".snakemake/*", ".snakemake/*/*",
                                                                ".snakemake/*/*/*"))
case("6-cohort", "sheet with a UTF-8 byte-order mark (good)",
     lambda c: _sheet(c, b"\xef\xbb\xbf" + (HEAD + PHANTOM_ROW).encode()), mode="snakemake", needs="snakemake",
     good=True, exit=0, allowed=(".snakemake", ".snakemake/*", ".snakemake/*/*", ".snakemake/*/*/*"))
case("6-cohort", "sheet with a missing image, skip_missing: true (good)",
     lambda c: _sheet(c, HEAD + PHANTOM_ROW + "absent\tno/such.nii.gz\t\n"), mode="snakemake", needs="snakemake",
     good=True, exit=0, allowed=(".snakemake", ".snakemake/*", ".snakemake/*/*", ".snakemake/*/*/*"))

# 7. errors that must blame the right thing ----------------------------------------------------

case("7-blame", "merge: two passes for a 3D mesh (read as z unmerged until 6 December 2026)",
     lambda c: argv_for(c, "merge", extra=["--set", "merge.passes=[1,1]"]), "merge.passes=[1, 1]", "give three")
case("7-blame", "downsample: factor larger than the image",
     lambda c: argv_for(c, "downsample", extra=["--set", "downsample.factor=50"]), "labels.nii.gz", "factor")
case("7-blame", "downsample: voxel_size larger than the image",
     lambda c: argv_for(c, "downsample", extra=["--set", "downsample.voxel_size=500"]), "labels.nii.gz", "voxel_size")
case("7-blame", "downsample: factor 0", lambda c: argv_for(c, "downsample", extra=["--set", "downsample.factor=0"]),
     "downsample.factor")
case("7-blame", "downsample: factor per axis with 2 values",
     lambda c: argv_for(c, "downsample", extra=["--set", "downsample.factor=[2,2]"]), "downsample.factor")
def _shifted_padded(c) -> Path:
    """The head phantom stored as HU + 1024 with padding (-2000) outside its field-of-view circle:
    the padding, taken for air, put the default search ranges inside its values (exit 0, air as
    soft tissue, soft tissue as bone)."""
    import SimpleITK as sitk

    image = sitk.ReadImage(str(c.copy("head.nii.gz")))
    a = np.maximum(sitk.GetArrayFromImage(image).astype(np.int32) + 1024, 0)  # stored unsigned, air near 0
    _, y, x = np.indices(a.shape)
    a[np.hypot(y - a.shape[1] / 2, x - a.shape[2] / 2) > 0.5 * a.shape[2]] = -2000
    out = sitk.GetImageFromArray(a.astype(np.int16))
    out.CopyInformation(image)
    sitk.WriteImage(out, str(c.t / "shifted.nii.gz"))
    return c.t / "shifted.nii.gz"


def _mr_with_sidecar(c) -> Path:
    """An image beside the BIDS sidecar dcm2niix writes, which says it is an MR."""
    image = c.copy("head.nii.gz", "sub-01_T1w.nii.gz")
    text(c.t / "sub-01_T1w.json", '{"Modality": "MR", "MagneticFieldStrength": 3, "SeriesDescription": "T1"}\n')
    return image


case("7-blame", "run: an MR NIfTI with its dcm2niix sidecar under the CT defaults",
     lambda c: ["run", _mr_with_sidecar(c), "-o", c.t / "out"], "sub-01_T1w.nii.gz", "Modality MR")
case("7-blame", "segment: a CT stored as HU + 1024 with padding outside its field of view",
     lambda c: ["segment", _shifted_padded(c), "-o", c.t / "l.nii.gz"], "shifted.nii.gz", "HU + 1024")
case("7-blame", "segment: opening_radius=1000",
     lambda c: argv_for(c, "segment", extra=["--set", "segment.opening_radius=1000"]), "opening_radius")
case("7-blame", "segment: closing_radius=1000",
     lambda c: argv_for(c, "segment", extra=["--set", "segment.closing_radius=1000"]), "closing_radius")
case("7-blame", "segment: manual thresholds in the wrong order",
     lambda c: argv_for(c, "segment", extra=["--set", "segment.method=manual", "--set",
                                             "segment.thresholds=[500,-100]"]), "thresholds")
case("7-blame", "segment: manual thresholds above every voxel",
     lambda c: argv_for(c, "segment", extra=["--set", "segment.method=manual", "--set",
                                             "segment.thresholds=[5000,6000]"]), "head.nii.gz")
case("7-blame", "segment: one threshold for two materials",
     lambda c: argv_for(c, "segment", extra=["--set", "segment.method=manual", "--set", "segment.thresholds=[100]"]),
     "thresholds")
for key, value, expect in (("smooth.interior_band", "-2", ">= 0"), ("smooth.coefficient", "1.5", "< 1"),
                           ("merge.min_scaled_jacobian", "2", "merge.min_scaled_jacobian"),
                           ("fix.max_iterations", "-1", "fix.max_iterations"),
                           ("export.digits", "3", "export.digits"), ("quality.poor_scaled_jacobian", "7", "quality"),
                           ("downsample.min_fraction", "1.5", "min_fraction"),
                           ("segment.bins", "1", "segment.bins"), ("mesh.coordinates", "world", "mesh.coordinates")):
    case("7-blame", f"schema: {key}={value}",
         (lambda key, value: lambda c: argv_for(c, "mesh", extra=["--set", f"{key}={value}"]))(key, value), expect)
case("7-blame", "materials: poissons_ratio 0.5 in a config file",
     lambda c: argv_for(c, "mesh", extra=["--config", text(
         c.t / "c.yaml", "materials:\n  - {name: a, youngs_modulus: 1, poissons_ratio: 0.5, density: 1e-9}\n"
                         "  - {name: b, youngs_modulus: 1, poissons_ratio: 0.3, density: 1e-9}\n")]),
     "poissons_ratio")
case("7-blame", "materials: poissons_ratio a deck prints as 0.5",
     lambda c: argv_for(c, "mesh", extra=["--set", "materials=[{name: a, poissons_ratio: 0.4999999999}, {name: b}]"]),
     "poissons_ratio", "0.4999999")
case("7-blame", "labels.map: a label value with a leading zero",
     lambda c: argv_for(c, "labels", extra=["--config", text(c.t / "c.yaml", "labels:\n  map: {'08': bone}\n")]),
     "leading zeros")
case("7-blame", "labels.map: one label value written two ways",
     lambda c: argv_for(c, "labels", extra=["--config", text(c.t / "c.yaml", "labels:\n  map: {8: a, '8': b}\n")]),
     "given twice")
case("7-blame", "NIfTI: a scaled sform and no qform",
     lambda c: argv_for(c, "segment", inp=_scaled_sform_only(nifti(c.t / "s.nii.gz", hu_volume()))),
     "s.nii.gz", "no qform")
case("7-blame", "materials: a negative Young's modulus",
     lambda c: argv_for(c, "mesh", extra=["--config", text(
         c.t / "c.yaml", "materials:\n  - {name: a, youngs_modulus: -1, poissons_ratio: 0.3, density: 1e-9}\n"
                         "  - {name: b, youngs_modulus: 1, poissons_ratio: 0.3, density: 1e-9}\n")]),
     "youngs_modulus")
case("7-blame", "materials: two materials of one name",
     lambda c: argv_for(c, "mesh", extra=["--config", text(
         c.t / "c.yaml", "materials:\n  - {name: a, youngs_modulus: 1, poissons_ratio: 0.3, density: 1e-9}\n"
                         "  - {name: a, youngs_modulus: 1, poissons_ratio: 0.3, density: 1e-9}\n")]), "c.yaml")
case("7-blame", "mesh: a label above the materials",
     lambda c: argv_for(c, "mesh", inp=npy(c.t / "l.npy", _with(np.ones((8, 8, 8), np.uint8), (2, 2, 2), 7))),
     "label 7")
case("7-blame", "fix: min_component_voxels removes every part",
     lambda c: argv_for(c, "fix", extra=["--set", "fix.min_component_voxels=1000000"]), "min_component_voxels")
case("7-blame", "fix: fix.priority names no material",
     lambda c: argv_for(c, "fix", extra=["--set", "fix.priority=[skull]"]), "fix.priority names 'skull'")
case("7-blame", "run: fix.priority names no material (found at the fix stage, after segment and downsample wrote "
     "OUT.failed)", lambda c: ["run", c.copy("head48.nii.gz"), "-o", c.t / "out", "--set", "fix.priority=[skull]"],
     "head48.nii.gz: fix.priority names 'skull'")
case("7-blame", "run: image.crop with two values in min and three in max (a traceback from the memory check)",
     lambda c: ["run", c.copy("head48.nii.gz"), "-o", c.t / "out", "--set",
                "image.crop={unit: mm, min: [0,0], max: [10,10,10]}"], "image.crop gives 2 and 3 values")
case("7-blame", "image.crop past the image",
     lambda c: argv_for(c, "segment", extra=["--set", "image.crop={unit: voxels, min: [0,0,0], max: [99,9,9]}"]),
     "image.crop")
case("7-blame", "image.crop box in mm beside the scan",
     lambda c: argv_for(c, "segment", extra=["--set", "image.crop={unit: mm, min: [900,900,900], max: [999,999,999]}"]),
     "image.crop")
case("7-blame", "image.spacing 0 for a .npy",
     lambda c: argv_for(c, "segment", inp=npy(c.t / "v.npy", hu_volume()), extra=["--set", "image.spacing=[1,0,1]"]),
     "spacing")
case("7-blame", "quality --labels of another grid",
     lambda c: argv_for(c, "quality", extra=["--labels", npy(c.t / "l.npy", np.ones((5, 5, 5), np.uint8))]), "l.npy")
case("7-blame", "surface --material unknown", lambda c: argv_for(c, "surface", extra=["--material", "skull"]), "skull")
case("7-blame", "smooth --image of another grid",
     lambda c: argv_for(c, "smooth", extra=["--image", npy(c.t / "v.npy", hu_volume((5, 5, 5))), "--set",
                                            "smooth.surface_from_image=true", "--set", "segment.method=manual"]),
     "v.npy")
case("7-blame", "quality --node-classes of an unsmoothed mesh",
     lambda c: argv_for(c, "quality", inp=c.copy("mesh.vtu"), extra=["--node-classes", c.t / "n.png"]), "n.png")
case("7-blame", "run: both an image and --labels",
     lambda c: ["run", c.copy("head.nii.gz"), "--labels", c.copy("labels.nii.gz"), "-o", c.t / "out"], "not both")
case("7-blame", "run: neither an image nor --labels", lambda c: ["run", "-o", c.t / "out"], "not both")

# 8. memory ------------------------------------------------------------------------------------

HUGE = "100000 100000 100000"
for header_name, content in (
        ("huge.mha", f"ObjectType = Image\nNDims = 3\nDimSize = {HUGE}\nElementSpacing = 1 1 1\n"
                     "ElementType = MET_SHORT\nElementDataFile = LOCAL\n"),
        ("huge.mhd", f"ObjectType = Image\nNDims = 3\nDimSize = {HUGE}\nElementSpacing = 1 1 1\n"
                     "ElementType = MET_SHORT\nElementDataFile = huge.raw\n"),
        ("huge.nrrd", f"NRRD0004\ntype: short\ndimension: 3\nsizes: {HUGE}\nspacings: 1 1 1\nencoding: raw\n"
                      "endian: little\n\n"),
        ("huge.nhdr", f"NRRD0004\ntype: short\ndimension: 3\nsizes: {HUGE}\nspacings: 1 1 1\nencoding: raw\n"
                      "endian: little\ndata file: huge.raw\n"),
        ("gzip.nrrd", f"NRRD0004\ntype: short\ndimension: 3\nsizes: {HUGE}\nspacings: 1 1 1\nencoding: gzip\n"
                      "endian: little\n\n"),
        ("gzip.mha", f"ObjectType = Image\nNDims = 3\nDimSize = {HUGE}\nElementSpacing = 1 1 1\n"
                     "ElementType = MET_SHORT\nCompressedData = True\nElementDataFile = LOCAL\n"),
        ("text.nrrd", f"NRRD0004\ntype: short\ndimension: 3\nsizes: {HUGE}\nspacings: 1 1 1\nencoding: ascii\n\n1 2 3\n"),
):
    name = header_name.split(".")[0]
    for command in ("segment", "run"):
        case("8-memory", f"{command}: {header_name} header promising 10^15 voxels",
             (lambda header_name, content, command: lambda c: (
                 text(c.t / "huge.raw", bytes(1024)) if "huge.raw" in content else None,
                 argv_for(c, command, inp=text(c.t / header_name, content.encode() + (
                     gzip.compress(bytes(64)) if "gzip" in content else b""))))[1])(header_name, content, command),
             header_name)
case("8-memory", "run: a NIfTI header promising 2^31 voxels",
     lambda c: argv_for(c, "run", inp=_huge_nifti(c.t / "huge.nii")), "huge.nii")
case("8-memory", "segment: a NIfTI header promising 2^31 voxels",
     lambda c: argv_for(c, "segment", inp=_huge_nifti(c.t / "huge.nii")), "huge.nii")
case("8-memory", "mesh: .npy header promising 10^12 voxels",
     lambda c: argv_for(c, "mesh", inp=_huge_npy(c.t / "huge.npy")), "huge.npy")
case("8-memory", "run: .npy header promising 10^12 voxels",
     lambda c: argv_for(c, "run", inp=_huge_npy(c.t / "huge.npy")), "huge.npy")
case("8-memory", "phantom: --size 100000", lambda c: ["phantom", "sphere", "-o", c.t / "p.nii.gz", "--size", "100000"],
     "size")


def _huge_nifti(path: Path) -> Path:
    write_sitk(path, np.zeros((4, 4, 4), np.int16))
    data = bytearray(path.read_bytes())
    data[42:48] = struct.pack("<hhh", 2048, 1024, 1024)
    path.write_bytes(bytes(data[:352 + 4096]))
    return path


def _huge_npy(path: Path) -> Path:
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (10000, 10000, 10000), }"
    header = header + " " * (117 - len(header)) + "\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + bytes(4096))
    return path


def _with(values, index, value):
    values = np.array(values, copy=True)
    values[index] = value
    return values


# 9. wrong kinds, empty files, shapes, labels --------------------------------------------------

WRONG_KIND = {
    "0-byte file": lambda c, suffix: text(c.t / f"empty{suffix}", b""),
    "random bytes": lambda c, suffix: text(c.t / f"random{suffix}", os.urandom(3000)),
    "a text file": lambda c, suffix: text(c.t / f"notes{suffix}", "just some notes\n"),
    "a PNG picture": lambda c, suffix: _png(c.t / f"pic{suffix}"),
    "missing": lambda c, suffix: c.t / f"absent{suffix}",
    "a folder": lambda c, suffix: (c.t / f"dir{suffix}").mkdir() or c.t / f"dir{suffix}",
}
KIND_SUFFIX = {"segment": ".nii.gz", "fix": ".nii", "mesh": ".npy", "merge": ".vtu", "export": ".vtu",
               "quality": ".vtu", "run": ".nrrd", "cohort": ".json"}


def _png(path: Path) -> Path:
    from PIL import Image

    Image.fromarray(np.zeros((8, 8), np.uint8)).save(path, format="PNG")
    return path


for kind, make in WRONG_KIND.items():
    for command, suffix in KIND_SUFFIX.items():
        if kind in ("a text file", "a PNG picture") and command not in ("segment", "mesh", "export"):
            continue
        if kind == "a folder" and command in ("segment", "run"):
            continue  # a folder is a slice series there (class 2)
        case("9-kinds", f"{command}: input is {kind} ({suffix})",
             (lambda make, command, suffix: lambda c: argv_for(c, command, inp=make(c, suffix)))(make, command, suffix),
             suffix)
case("9-kinds", "segment: a plain NIfTI named .nii.gz (said to be truncated or corrupt)",
     lambda c: argv_for(c, "segment", inp=text(c.t / "plain.nii.gz", gzip.decompress(c.copy("head.nii.gz").read_bytes()))),
     "not gzip-compressed", "rename it to plain.nii")
case("9-kinds", "mesh: a mesh given as labels", lambda c: argv_for(c, "mesh", inp=c.copy("mesh.vtu")), "mesh.vtu")
case("9-kinds", "merge: an image given as mesh", lambda c: argv_for(c, "merge", inp=c.copy("labels.nii.gz")),
     "labels.nii.gz")
case("9-kinds", "export: a gzip of random bytes as .nii.gz input to segment",
     lambda c: argv_for(c, "segment", inp=text(c.t / "r.nii.gz", gzip.compress(os.urandom(2000)))), "r.nii.gz")
case("9-kinds", "segment: a .vtu given as image", lambda c: argv_for(c, "segment", inp=c.copy("mesh.vtu")), "mesh.vtu")
SHAPES = {
    "1 voxel": np.ones((1, 1, 1)),
    "a line 8x1x1": np.ones((8, 1, 1)), "4D": np.ones((4, 4, 4, 2)), "1D": np.ones(8), "0-d": np.array(1),
    "empty 0x8x8": np.ones((0, 8, 8)),
}
for label, array in SHAPES.items():
    case("9-kinds", f"segment: .npy {label}",
         (lambda array: lambda c: argv_for(c, "segment", inp=npy(c.t / "v.npy", array.astype(np.float32) * 900)))(array),
         "v.npy")
    case("9-kinds", f"mesh: labels .npy {label}",
         (lambda array: lambda c: argv_for(c, "mesh", inp=npy(c.t / "l.npy", array.astype(np.uint8))))(array), "l.npy")
LABELS = {
    "all background (0 materials)": np.zeros((8, 8, 8), np.uint8),
    "label 65535": _with(np.ones((8, 8, 8), np.uint16), (1, 1, 1), 65535),
    "label 70000 (int32)": _with(np.ones((8, 8, 8), np.int32), (1, 1, 1), 70000),
    "negative labels": _with(np.ones((8, 8, 8), np.int16), (1, 1, 1), -2),
    "fractional labels 1.5": _with(np.ones((8, 8, 8), np.float32), (1, 1, 1), 1.5),
    "complex values": np.ones((8, 8, 8), np.complex64),
    "object array": np.array([[["a"] * 4] * 4] * 4, dtype=object),
    "bool": np.ones((8, 8, 8), bool),
}
for label, array in LABELS.items():
    for command in ("mesh", "fix", "labels"):
        if label == "bool" and command != "mesh":
            continue
        if command == "labels" and label.startswith("label "):  # any value names a material there
            case("9-kinds", f"labels: labels {label} (good: a material label_<value>)",
                 (lambda array: lambda c: argv_for(c, "labels", inp=npy(c.t / "l.npy", array)))(array),
                 good=True, outputs=("l.nii.gz",))
            continue
        case("9-kinds", f"{command}: labels {label}",
             (lambda array, command: lambda c: argv_for(c, command, inp=npy(c.t / "l.npy", array)))(array, command),
             "l.npy", good=(label == "bool"), outputs=(COMMANDS[command][1],) if label == "bool" else ())
case("9-kinds", "mesh: labels 8x8x1 (a 2D slice, good)",
     lambda c: argv_for(c, "mesh", inp=npy(c.t / "l.npy", np.ones((8, 8, 1), np.uint8))), good=True,
     outputs=("m.vtu",))
case("9-kinds", "labels: 300 distinct label values in blocks of 2 voxels a side (good)",
     lambda c: argv_for(c, "labels", inp=npy(c.t / "l.npy", ((np.indices((16, 16, 16)) // 2 * [[[[64]]], [[[8]]], [[[1]]]])
                                                            .sum(0) % 300 + 1).astype(np.uint16))),
     good=True, outputs=("l.nii.gz",))
case("9-kinds", "labels: 300 distinct label values, every voxel's neighbours other values (an image's grey values)",
     lambda c: argv_for(c, "labels", inp=npy(c.t / "l.npy", (np.arange(16 ** 3) % 300 + 1).reshape(16, 16, 16)
                                             .astype(np.uint16))), "l.npy", "grey values")
case("9-kinds", "segment: a constant image", lambda c: argv_for(c, "segment", inp=npy(c.t / "v.npy",
                                                                                     np.full((8, 8, 8), 40.0))), "v.npy")
case("9-kinds", "segment: a 2-voxel-thick image",
     lambda c: argv_for(c, "segment", inp=npy(c.t / "v.npy", hu_volume((12, 12, 2)))), good=True,
     outputs=("l.nii.gz",))
case("9-kinds", "cohort: quality.json not UTF-8", lambda c: ["cohort", text(c.t / "p1" / "quality.json", b"{\xff}"),
                                                             "-o", c.t / "c.html"], "quality.json")
case("9-kinds", "quality: --picture is not a file",
     lambda c: argv_for(c, "quality", extra=["--html", c.t / "q.html", "--picture", c.t / "absent.png"]), "absent.png")
case("9-kinds", "segment: output with a wrong extension", lambda c: argv_for(c, "segment", out=c.t / "l.png"), "l.png")
case("9-kinds", "export: output with an unknown extension", lambda c: argv_for(c, "export", out=c.t / "m.stp"), "m.stp")

# 10. output folders and paths ----------------------------------------------------------------

for command in COMMANDS:
    out_name = COMMANDS[command][1]
    case("10-paths", f"{command}: output folder read-only",
         (lambda command, out_name: lambda c: argv_for(c, command, out=c.mount("ro", ro=True) / out_name))(command, out_name),
         "ro", needs="mount")
    case("10-paths", f"{command}: output under a file (parent is a file)",
         (lambda command, out_name: lambda c: argv_for(c, command, out=text(c.t / "afile", "x") / out_name))(command, out_name),
         "afile")
for command in ("mesh", "export", "run"):
    out_name = COMMANDS[command][1]
    case("10-paths", f"{command}: output a dangling symlink into a missing folder",
         (lambda command, out_name: lambda c: ((c.t / out_name).symlink_to(c.t / "gone" / "x"),
                                               argv_for(c, command, out=c.t / out_name))[1])(command, out_name),
         out_name) if command == "run" else None
    case("10-paths", f"{command}: output path of 300 characters",
         (lambda command, out_name: lambda c: argv_for(c, command, out=c.t / ("x" * 300 + out_name)))(command, out_name),
         "x" * 20)
for label, name, out in (("spaces", "my scan folder/head scan.nii.gz", "my scan folder/labels scan.nii.gz"),
                         ("unicode", "Ärzte/schädel é ü 頭.nii.gz", "Ärzte/labels é ü 頭.nii.gz"),
                         ("a leading dash", "-head.nii.gz", "-labels.nii.gz")):
    case("11-good", f"segment + paths with {label}",
         (lambda name, out: lambda c: (c.t.joinpath(name).parent.mkdir(parents=True, exist_ok=True),
                                       ["segment", c.copy("head.nii.gz", name), "-o", c.t / out])[1])(name, out),
         good=True, outputs=(out,))
case("11-good", "run with paths with spaces and unicode",
     lambda c: ["run", c.copy("head.nii.gz", "kopf scan é.nii.gz"), "-o", c.t / "out put ü", "--set",
                "downsample.factor=2"], good=True, outputs=("out put ü/model.inp", "out put ü/quality.json"))
case("11-good", "mesh of a symlinked input",
     lambda c: ((c.t / "link.nii.gz").symlink_to(c.copy("labels.nii.gz")), argv_for(c, "mesh", inp=c.t / "link.nii.gz"))[1],
     good=True, outputs=("m.vtu",))
case("11-good", "export through a symlinked output folder",
     lambda c: ((c.t / "real").mkdir(), (c.t / "lnk").symlink_to(c.t / "real"),
                argv_for(c, "export", out=c.t / "lnk" / "model.inp"))[2], good=True, outputs=("real/model.inp",))
case("11-good", "mesh into a folder that does not exist yet",
     lambda c: argv_for(c, "mesh", out=c.t / "new" / "deeper" / "m.vtu"), good=True, outputs=("new/deeper/m.vtu",))
for command in COMMANDS:
    outs = {"surface": ("surf/soft_tissue.stl",), "run": ("out/model.inp", "out/quality.json")}.get(
        command, (COMMANDS[command][1],))
    case("11-good", f"{command}: the good use", (lambda command: lambda c: argv_for(c, command))(command), good=True,
         outputs=outs)
case("11-good", "config with density: 1e-9 (YAML 1.1 exponent without a dot)",
     lambda c: argv_for(c, "export", extra=["--config", text(
         c.t / "c.yaml", "materials:\n  - {name: a, youngs_modulus: 1, poissons_ratio: 0.3, density: 1e-9}\n"
                         "  - {name: b, youngs_modulus: 2, poissons_ratio: 0.3, density: 2e-9}\n")]),
     good=True, outputs=("model.inp",))
case("11-good", "config with a UTF-8 byte-order mark",
     lambda c: argv_for(c, "mesh", extra=["--config", text(c.t / "c.yaml", b"\xef\xbb\xbfmesh:\n  coordinates: index\n")]),
     good=True, outputs=("m.vtu",))
case("11-good", "segment of a single DICOM slice (a 2D image)",
     lambda c: argv_for(c, "segment", inp=write_dicom_series(c.t / "series", [0], shape=(16, 14)),
                        extra=["--set", "segment.method=manual"]), good=True, outputs=("l.nii.gz",))
case("11-good", "segment of a DICOM series beside a folder named like a slice",
     lambda c: argv_for(c, "segment", inp=((write_dicom_series(c.t / "series", [0, 2, 4, 6], shape=(16, 14))
                                            / "im009.dcm").mkdir(), c.t / "series")[1],
                        extra=["--set", "segment.method=manual"]), good=True, outputs=("l.nii.gz",))
case("11-good", "segment of a DICOM series", lambda c: argv_for(c, "segment", inp=write_dicom_series(
    c.t / "series", [0, 2, 4, 6, 8, 10], shape=(16, 14)), extra=["--set", "segment.method=manual"]),
     good=True, outputs=("l.nii.gz",))
case("11-good", "segment of a DICOM series with a missing slice, allow_irregular_slices",
     lambda c: argv_for(c, "segment", inp=write_dicom_series(c.t / "series", [0, 2, 4, 8, 10, 12], shape=(16, 14)),
                        extra=["--set", "segment.method=manual", "--set", "image.allow_irregular_slices=true"]),
     good=True, outputs=("l.nii.gz",))


def _nifti2(path: Path) -> Path:
    """A 4x4x4 int16 NIfTI-2 file (which ITK's NIfTI-1 reader does not read)."""
    head = bytearray(540)
    struct.pack_into("<i", head, 0, 540)
    head[4:12] = b"n+2\0\r\n\x1a\n"
    struct.pack_into("<2h", head, 12, 4, 16)
    struct.pack_into("<8q", head, 16, 3, 4, 4, 4, 1, 1, 1, 1)
    struct.pack_into("<8d", head, 104, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<q", head, 168, 544)
    path.write_bytes(gzip.compress(bytes(head) + bytes(4) + np.arange(64, dtype="<i2").tobytes(), mtime=0))
    return path


def _thick_head(path: Path) -> Path:
    """An ellipsoid head with a skull shell on 0.4 x 0.4 x 5 mm voxels (labels)."""
    shape, spacing, radii = (128, 128, 16), np.array([0.4, 0.4, 5.0]), np.array([22.0, 24.0, 35.0])
    idx = np.indices(shape).astype(float)
    r = np.sqrt(sum(((idx[i] - (shape[i] - 1) / 2) * spacing[i] / radii[i]) ** 2 for i in range(3)))
    labels = np.zeros(shape, np.uint8)
    labels[r < 1] = 1
    labels[(r < 0.88) & (r >= 0.76)] = 2
    return write_sitk(path, labels, tuple(spacing))


case("9-kinds", "segment: a NIfTI-2 file", lambda c: argv_for(c, "segment", inp=_nifti2(c.t / "n2.nii.gz")),
     "n2.nii.gz", "NIfTI-2")
case("9-kinds", "labels: float32 labels holding 2**31 (rounded from 2**31 - 1)",
     lambda c: argv_for(c, "labels", inp=npy(c.t / "l.npy", _with(np.full((8, 8, 8), 1234567, np.float32),
                                                                 (3, 3, 3), 2147483647))), "l.npy", "too large")
case("11-good", "run --labels on 0.4 x 0.4 x 5 mm voxels at default settings",
     lambda c: ["run", "--labels", _thick_head(c.t / "thick.nii.gz"), "-o", c.t / "out", "-q"], good=True,
     outputs=("out/model.inp", "out/quality.json"))

CASES[:] = [c for c in CASES if c is not None]


# --- running and judging ---------------------------------------------------------------------


def snapshot(root: Path) -> dict:
    """Relative path -> (sha256 of the bytes, size) for files, None for folders, 'link:...' for symlinks."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            rel = str(path.relative_to(root))
            if path.is_symlink():
                out[rel] = "link:" + os.readlink(path)
            elif path.is_dir():
                out[rel] = None
            else:
                try:
                    data = path.read_bytes()
                except OSError as exc:
                    out[rel] = f"unreadable:{exc.errno}"
                    continue
                out[rel] = (hashlib.sha256(data).hexdigest(), len(data))
    return out


def _check_output(path: Path) -> str | None:
    """Why the good case's output ``path`` is not a readable result (None: it is)."""
    if not path.exists():
        return "missing"
    if path.stat().st_size == 0:
        return "0 bytes"
    name = path.name.lower()
    try:
        if name.endswith((".nii", ".nii.gz", ".nrrd", ".mha")):
            from dicer.io.images import read_labels, read_image

            (read_image(path) if "p." in name else read_labels(path))
        elif name.endswith(".vtu"):
            from dicer.io.meshes import read_mesh

            if read_mesh(path).n_cells == 0:
                return "no elements"
        elif name.endswith(".json"):
            json.loads(path.read_text())
        elif name.endswith(".inp"):
            if "*NODE" not in path.read_text().upper():
                return "no *NODE"
        elif name.endswith(".stl"):
            if path.stat().st_size < 84:
                return "short STL"
        elif name.endswith((".html", ".htm")):
            if "<html" not in path.read_text().lower():
                return "not HTML"
    except Exception as exc:  # noqa: BLE001 -- any failure to read back is the finding
        return f"cannot read back ({type(exc).__name__}: {str(exc)[:80]})"
    return None


@dataclass
class Outcome:
    case: Case
    status: str  # pass | fail | skip
    reasons: list = field(default_factory=list)
    code: int | None = None
    stderr: str = ""
    seconds: float = 0.0
    rss_mb: float = 0.0


def _allowed(rel: str, patterns) -> bool:
    return any(fnmatch(rel, p) for p in patterns)


def _wait(proc, timeout):
    """(status, rusage) of ``proc`` (killed after ``timeout`` seconds)."""
    timer = threading.Timer(timeout, lambda: proc.kill())
    timer.start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        timer.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage


def run_case(case: Case, base: Path, workdir: Path, timeout: float = 300.0) -> Outcome:
    t = Path(tempfile.mkdtemp(prefix="case.", dir=workdir))
    ctx = Ctx(t, base)
    try:
        if case.needs == "snakemake":
            try:
                import snakemake  # noqa: F401
            except ImportError:
                return Outcome(case, "skip", ["snakemake is not installed"])
        try:
            argv = [str(a) for a in case.build(ctx)]
        except Skip as exc:
            return Outcome(case, "skip", [str(exc)])
        before = snapshot(t)
        if case.mode == "snakemake":
            cmd = [PYTHON, "-m", "snakemake", *argv]
        else:
            cmd = [PYTHON, "-m", "dicer", *argv, "-q"]
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        env["PATH"] = os.path.dirname(PYTHON) + os.pathsep + env.get("PATH", "")
        t0 = time.monotonic()
        with open(t.parent / f"{t.name}.err", "w+") as err, open(t.parent / f"{t.name}.out", "w+") as out:
            proc = subprocess.Popen(cmd, cwd=t, env=env, stdout=out, stderr=err)
            sent = False
            if case.signal_at:
                pattern, signum = case.signal_at
                deadline = time.monotonic() + timeout
                while proc.poll() is None and time.monotonic() < deadline and not list(t.glob(pattern)):
                    time.sleep(0.002)
                if proc.returncode is None:
                    proc.send_signal(signum)
                    sent = True
            usage = _wait(proc, timeout) if proc.returncode is None else None
            err.seek(0)
            stderr = err.read()
            out.seek(0)
            stdout = out.read()
        seconds = time.monotonic() - t0
        after = snapshot(t)
        result = Outcome(case, "pass", [], proc.returncode, stderr, seconds,
                         (usage.ru_maxrss / 1024) if usage else 0.0)
        judge(case, result, before, after, stdout, t)
        if case.signal_at and not sent:
            result.reasons.insert(0, "not exercised: the process ended before the signal")
            result.status = "fail"
        return result
    finally:
        ctx.close()
        shutil.rmtree(t, ignore_errors=True)
        for suffix in (".err", ".out"):
            (t.parent / f"{t.name}{suffix}").unlink(missing_ok=True)


LOG_LINE = re.compile(r"^dicer(\.\w+)* ")  # a log record (format "%(name)s %(message)s")


def judge(case: Case, result: Outcome, before: dict, after: dict, stdout: str, t: Path) -> None:
    reasons = result.reasons
    stderr = result.stderr
    if result.code is not None and result.code < 0:
        reasons.append(f"killed by signal {-result.code} (timeout?)")
    if "Traceback" in stderr or "Traceback" in stdout:
        reasons.append("traceback")
    new = [r for r in after if r not in before]
    gone = [r for r in before if r not in after]
    changed = [r for r in after if r in before and after[r] != before[r]]
    temporaries = [r for r in after if ".tmp" in Path(r).name and not _allowed(r, case.allowed)]
    empty = [r for r in new + changed if isinstance(after[r], tuple) and after[r][1] == 0]
    if temporaries:
        reasons.append("temporary file left: " + ", ".join(temporaries[:3]))
    if empty:
        reasons.append("0-byte file: " + ", ".join(empty[:3]))
    if case.mode == "snakemake":
        if case.good:
            if result.code != 0:
                reasons.append(f"exit {result.code} on good input")
        else:
            if result.code == 0:
                reasons.append("exit 0 on bad input")
            text_all = stderr + stdout
            for e in case.expect:
                if e not in text_all:
                    reasons.append(f"message lacks {e!r}")
        unexpected = [r for r in new + gone + changed if not _allowed(r, case.allowed)]
        if unexpected:
            reasons.append("files new/changed/removed: " + ", ".join(unexpected[:4]))
    elif case.good:
        if result.code != 0:
            reasons.append(f"exit {result.code} on good input: {stderr.strip().splitlines()[-1:] }")
        outputs = {str(Path(o)) for o in case.outputs}
        for o in case.outputs:
            why = _check_output(t / o)
            if why:
                reasons.append(f"output {o}: {why}")
        made_dirs = {str(p) for o in outputs for p in Path(o).parents if str(p) != "."}
        unexpected = [r for r in new if r not in outputs and r not in made_dirs and not _allowed(r, case.allowed)
                      and not any(r.startswith(o.split("/")[0] + "/") for o in outputs if "/" in o)
                      and not r.startswith(COMMANDS.get("surface")[1] + "/")]
        unexpected += [r for r in gone + changed if not _allowed(r, case.allowed) and r not in outputs]
        if unexpected:
            reasons.append("unexpected files new/changed/removed: " + ", ".join(unexpected[:4]))
    else:
        if result.code == 0:
            reasons.append("exit 0 on bad input")
        elif result.code != case.exit:
            reasons.append(f"exit {result.code}, expected {case.exit}")
        lines = [line for line in stderr.splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith("error: ")]
        other = [line for line in lines if not line.startswith("error: ") and not LOG_LINE.match(line)]
        if len(errors) != 1:
            reasons.append(f"{len(errors)} error lines")
        if other:
            reasons.append("other stderr lines: " + other[0][:120])
        if errors:
            for e in case.expect:
                if e not in errors[0]:
                    reasons.append(f"message lacks {e!r}")
        unexpected = [r for r in new + gone + changed if not _allowed(r, case.allowed)]
        if unexpected:
            reasons.append("files new/changed/removed: " + ", ".join(unexpected[:4]))
        if result.rss_mb > 1024:
            reasons.append(f"peak memory {result.rss_mb:.0f} MB")
    if reasons:
        result.status = "fail"


def select(pattern: str | None = None, classes=None) -> list[Case]:
    return [c for c in CASES if (not pattern or pattern.lower() in c.name.lower() or pattern == c.cls)
            and (not classes or c.cls in classes)]


def run_all(cases: list[Case], jobs: int = 2, verbose: bool = False, workdir: Path | None = None) -> list[Outcome]:
    from concurrent.futures import ThreadPoolExecutor

    own = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="dicer-hostile.")) if own else workdir
    try:
        base = make_base(workdir / "base")
        # a mesh big enough that writing its deck takes a while (for the SIGTERM case)
        from dicer.cli import main

        if not (base / "big_mesh.vtu").exists():
            main(["mesh", str(base / "big_ones.npy"), "-o", str(base / "big_mesh.vtu"), "-q"])
        results = []
        with ThreadPoolExecutor(jobs) as pool:
            def one(c):
                outcome = run_case(c, base, workdir)
                for _ in range(2):  # a signal case whose process outran the signal runs again
                    if not (outcome.reasons and outcome.reasons[0].startswith("not exercised")):
                        break
                    outcome = run_case(c, base, workdir)
                return outcome

            for outcome in pool.map(one, cases):
                results.append(outcome)
                if verbose or outcome.status == "fail":
                    last = outcome.stderr.strip().splitlines()[-1:] or [""]
                    print(f"{outcome.status.upper():4} [{outcome.case.cls}] {outcome.case.name} "
                          f"(exit {outcome.code}, {outcome.seconds:.1f} s) {'; '.join(outcome.reasons)}"
                          f"{'  | ' + last[0][:300] if outcome.status != 'pass' or verbose else ''}", flush=True)
        return results
    finally:
        if own:
            shutil.rmtree(workdir, ignore_errors=True)


def summary(results: list[Outcome]) -> str:
    table = collections.OrderedDict((k, collections.Counter()) for k in CLASSES)
    for r in results:
        table[r.case.cls][r.status] += 1
    rows = ["| Class | Cases | Pass | Fail | Skipped |", "|---|---:|---:|---:|---:|"]
    total = collections.Counter()
    for cls, count in table.items():
        n = sum(count.values())
        if not n:
            continue
        total.update(count)
        rows.append(f"| {cls} {CLASSES[cls]} | {n} | {count['pass']} | {count['fail']} | {count['skip']} |")
    rows.append(f"| total | {sum(total.values())} | {total['pass']} | {total['fail']} | {total['skip']} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.hostile", description=__doc__.split("\n\n")[0])
    parser.add_argument("-k", metavar="TEXT", help="only cases whose name holds TEXT (or of class TEXT)")
    parser.add_argument("-j", "--jobs", type=int, default=2, help="cases run at once (default 2)")
    parser.add_argument("-v", "--verbose", action="store_true", help="print every outcome")
    parser.add_argument("--list", action="store_true", help="list the cases and stop")
    args = parser.parse_args(argv)
    cases = select(args.k)
    if args.list:
        for c in cases:
            print(f"[{c.cls}] {c.name}")
        print(len(cases), "cases")
        return 0
    t0 = time.monotonic()
    results = run_all(cases, args.jobs, args.verbose)
    print(summary(results))
    print(f"{len(results)} cases in {time.monotonic() - t0:.0f} s")
    return 1 if any(r.status == "fail" for r in results) else 0


if __name__ == "__main__":
    raise SystemExit(main())
