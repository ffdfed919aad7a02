"""Read and write images and label volumes (SimpleITK underneath).

Conventions shared by every function here:

- Arrays are indexed ``[x, y, z]`` (SimpleITK's arrays are ``[z, y, x]``; they are
  transposed on the way in and out) and spacing is given in the same order, in mm.
- ``Volume.origin`` is ITK's origin (the *centre* of voxel (0, 0, 0)) minus half a voxel
  along each index axis: ``origin = itk_origin - spacing / 2`` on reading and the reverse
  on writing. It is the corner of that voxel while the direction is the identity.
- ``Volume.direction`` holds the file's direction cosines (NIfTI sform/qform as ITK reads
  them, DICOM Image Orientation (Patient), NRRD space directions, MetaImage
  TransformMatrix), or None for the identity, 2D images and formats without one (.npy,
  TIFF, PNG). Stages keep the voxel grid axis-aligned (the lattice frame); the exports
  place the model in scanner coordinates with it (docs/coordinates.md).
- A 3D image with one axis of a single voxel (one slice, a single PNG, a one-file
  DICOM series) becomes a 2D Volume; that axis is dropped with its spacing and origin.
"""

from __future__ import annotations

import contextlib
import gzip
import json
import logging
import os
import re
import struct
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.image import MAX_LABEL, Volume
from dicer.io import LABEL_SUFFIXES, SPACING_RANGE_MM
from dicer.io.atomic import atomic_path, captured_stderr, disk_full
from dicer.parallel import contiguous

log = logging.getLogger(__name__)


class _SimpleITKOnFirstUse:
    """SimpleITK, imported when first used: it takes 0.15 s to import, and reading .npy
    labels (or a stage that reads only meshes) never needs it."""

    def __getattr__(self, name: str):
        import SimpleITK

        globals()["sitk"] = SimpleITK
        return getattr(SimpleITK, name)


sitk = _SimpleITKOnFirstUse()

#: single-file image formats (lower-case name endings)
IMAGE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".npy", ".tif", ".tiff", ".png", ".dcm")
#: formats ``write_image`` writes
WRITE_IMAGE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha")
#: formats ``write_labels`` writes
WRITE_LABEL_SUFFIXES = (".nii", ".nii.gz")

_TIFF = (".tif", ".tiff")
_PNG = (".png",)
_SUPPORTED = (
    "supported inputs: .nii, .nii.gz, .nrrd/.nhdr, .mha/.mhd, .npy, .tif/.tiff, .png, .dcm, "
    "or a folder holding a DICOM series, TIFF slices or PNG slices"
)


# --- small helpers -------------------------------------------------------------------


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for s in sorted(IMAGE_SUFFIXES, key=len, reverse=True):
        if name.endswith(s):
            return s
    return path.suffix.lower()


def check_input_kind(path: str | os.PathLike, labels: bool = False) -> None:
    """Refuse a path that cannot be a scan (or a label volume) by its name alone, before any
    stage: the workflow's sheet is checked so, naming its line, rather than in the first job.

    Parameters
    ----------
    path : str or os.PathLike
        An existing file or folder.
    labels : bool, optional
        A label volume (one file of :data:`LABEL_SUFFIXES`), not a scan.

    Raises
    ------
    DicerError
        A folder given as a label volume, or a file of another format.
    """
    path = Path(path)
    if labels:
        if path.is_dir() or not path.name.lower().endswith(LABEL_SUFFIXES):
            raise DicerError(f"{path}: label volumes must be one of {', '.join(LABEL_SUFFIXES)}; "
                             "convert the labels to NIfTI (.nii.gz)")
        return
    if path.is_file() and _suffix(path) not in IMAGE_SUFFIXES and not _dicom_preamble(path):
        raise DicerError(f"{path}: unknown image format {_suffix(path) or '(no extension)'!r}; {_SUPPORTED}")


def _natural_key(name: str):
    # "slice2.png" before "slice10.png"
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", name)]


@contextlib.contextmanager
def quiet_itk():
    # ITK/GDCM print warnings straight to stderr; dicer reports problems itself
    previous = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(previous)


def image_header(path: str | os.PathLike, io: str | None = None):
    """The header of an image file as SimpleITK reads it (no pixels), or None when it
    cannot read one; ITK's own warnings stay quiet.

    Parameters
    ----------
    path : str or os.PathLike
    io : str, optional
        The ImageIO to use (e.g. ``"GDCMImageIO"``); default: the one the file suits.

    Returns
    -------
    SimpleITK.ImageFileReader or None
        A reader whose information (size, spacing, origin, direction, metadata) is read.
    """
    reader = sitk.ImageFileReader()
    if io:
        reader.SetImageIO(io)
    reader.SetFileName(str(path))
    try:
        with quiet_itk():
            reader.ReadImageInformation()
    except RuntimeError:
        return None
    return reader


_MODALITY_TAG = "0008|0060"  # DICOM's Modality: CT, MR, PT, ...


def _modality(header) -> str | None:
    """The Modality (0008,0060) a DICOM header gives ("CT", "MR", ...), or None without one."""
    if header is None or not header.HasMetaDataKey(_MODALITY_TAG):
        return None
    return header.GetMetaData(_MODALITY_TAG).strip().upper() or None


def _dicom_modality(path: str | os.PathLike) -> str | None:
    """The Modality of a DICOM file, or None without one."""
    return _modality(image_header(path, "GDCMImageIO"))


def _sidecar_modality(path: Path) -> str | None:
    """The ``Modality`` of the BIDS sidecar beside an image (``scan.json`` for ``scan.nii.gz``,
    as dcm2niix writes it), or None: no sidecar, not JSON, or no such field."""
    sidecar = path.with_name(path.name[: len(path.name) - len(_suffix(path))] + ".json")
    try:
        if not sidecar.is_file() or sidecar.stat().st_size > 1 << 20:
            return None
        fields = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # unreadable, not JSON, nested past the parser
        return None
    modality = fields.get("Modality") if isinstance(fields, dict) else None
    if not isinstance(modality, str):
        return None
    return modality.strip().upper() or None


def _itk_message(exc: Exception) -> str:
    # ITK exceptions span many lines with source paths; keep the last meaningful one
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[-1] if lines else type(exc).__name__
    text = re.sub(r"^.*?ITK ERROR: [^:]*: ", "", text)
    return text[:200]


def _f32_decimal(values) -> tuple[float, ...]:
    """NIfTI stores spacing and offsets as float32: give back 0.7 rather than 0.699999988.

    The short decimal is used only when it has at most 6 significant digits (what a
    writer most likely meant); otherwise the exact float32 value is kept (0.95703125).
    """
    out = []
    for v in values:
        short = str(np.float32(v))
        digits = len(short.lower().split("e")[0].replace("-", "").replace(".", "").strip("0"))
        out.append(float(short) if digits <= 6 else float(np.float32(v)))
    return tuple(out)


def _check_spacing(spacing, path, source: str) -> tuple[float, ...]:
    spacing = tuple(float(s) for s in spacing)
    if _bad_spacing(spacing):
        low, high = SPACING_RANGE_MM
        raise DicerError(
            f"{path}: voxel spacing {', '.join(f'{s:g}' for s in spacing)} mm ({source}) has a zero, "
            f"negative or non-finite value or one outside {low:g} to {high:g} mm; give every axis its voxel size in mm"
        )
    return spacing


def _check_finite(array: np.ndarray, path) -> None:
    """Raise DicerError when a float image holds NaN or infinite voxels.

    Such voxels have no value a threshold could classify; turning them into background
    (or anything else) would change the model without telling, so they are refused.
    """
    if array.dtype.kind != "f":
        return
    finite = np.count_nonzero(np.isfinite(array))
    if finite == array.size:
        return
    nan = int(np.count_nonzero(np.isnan(array)))
    raise _nonfinite_error(path, nan, array.size - finite - nan, array.size)


_said: set[str] = set()


def _warn_once(message: str, name: str, *args, level: int = logging.WARNING) -> None:
    """A warning (or a note of ``level``) about how an image is taken (``message`` % (``name``,
    *``args``)), once per process whatever the file's name: ``dicer run`` reads the label files
    it writes on the input's header again at every stage."""
    said = message % ("", *args)
    if said not in _said:
        _said.add(said)
        log.log(level, message, name, *args)


def _finish(array: np.ndarray, spacing, origin, path, dtype=np.float32, direction=None) -> Volume:
    """Drop a singleton axis (3D -> 2D), refuse NaN/Inf voxels and build the Volume."""
    spacing, origin = list(spacing), list(origin)
    singles = [ax for ax, n in enumerate(array.shape) if n == 1]
    if array.ndim == 3 and len(singles) == 1:
        ax = singles[0]
        centre = origin[ax] + spacing[ax] / 2  # the slice's position along its axis, which a 2D model drops
        _warn_once("%s: one voxel along %s (%g mm): read as a 2D image, meshed with quadrilaterals; the deck's "
                   "section thickness is export.thickness, not this%s", Path(path).name, "xyz"[ax], spacing[ax],
                   f"; the model lies at {'xyz'[ax]} = 0, not at the slice's {centre:g} mm" if centre else "",
                   level=logging.INFO)
        turned = direction is not None and not np.allclose(np.reshape(direction, (3, 3)), np.eye(3))
        if ax != 2 or turned:  # a sagittal or coronal slice, or one the scanner holds flipped or oblique
            kept = [a for a in "ijk" if a != "ijk"[ax]]
            _warn_once("%s: the one-slice image is meshed in its index plane: the model's x and y are "
                       "the image's %s and %s index axes%s, not the scanner's axes (a 2D model has no 3D "
                       "placement; docs/coordinates.md)", Path(path).name, *kept,
                       " (its direction cosines are dropped)" if turned else "")
        array = np.squeeze(array, axis=ax)
        del spacing[ax], origin[ax]
        direction = None  # a 3D orientation has no 2D counterpart in general
    if array.ndim not in (2, 3) or min(array.shape) < 2:
        raise DicerError(
            f"{path}: the image has shape {'x'.join(map(str, array.shape))} (x, y, z); dicer meshes 2D or 3D "
            "images with at least 2 voxels along each axis; give a 2D slice or a 3D volume"
        )
    _check_finite(array, path)
    if dtype is not None and np.dtype(dtype).kind == "f" and array.dtype.kind == "f" \
            and np.dtype(dtype).itemsize < array.dtype.itemsize:
        top = max(float(array.max(initial=0)), -float(array.min(initial=0)))
        if top > float(np.finfo(dtype).max):  # would become infinite in the image's float32
            raise DicerError(f"{path}: the image holds values up to {top:g}, beyond the {np.dtype(dtype).name} dicer "
                             "computes in; rescale the image to its physical units (HU for CT)")
    return Volume(contiguous(array, dtype), tuple(spacing), tuple(origin), direction)


def segment_names(path: str | os.PathLike) -> dict[int, str]:
    """The segment names a 3D Slicer segmentation (``.seg.nrrd``: ``Segment<i>_LabelValue``
    and ``Segment<i>_Name`` header fields) gives its label values; empty for any other file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    dict
        Label value -> the segment's name as the file has it (not checked as a material name).
    """
    if not str(path).lower().endswith((".nrrd", ".nhdr")) or not os.path.isfile(path):
        return {}
    reader = image_header(path)
    if reader is None:
        return {}
    fields = {k: reader.GetMetaData(k) for k in reader.GetMetaDataKeys() if k.startswith("Segment")}
    names = {}
    for key, value in fields.items():
        number = key[len("Segment"):-len("_LabelValue")] if key.endswith("_LabelValue") else None
        name = fields.get(f"Segment{number}_Name")
        if number is not None and number.isdigit() and name and value.strip().isdigit():
            names[int(value)] = name.strip()
    return dict(sorted(names.items()))


def _segmentation_layers(reader) -> int:
    """The number of segments a 3D Slicer segmentation file (``Segment<i>_Layer`` keys) holds; 0
    in any other image."""
    keys = reader.GetMetaDataKeys()
    return sum(1 for k in keys if k.startswith("Segment") and k.endswith("_Layer"))


def _from_sitk(image: sitk.Image, path, spacing_arg=None, own_spacing=True, nifti=False,
               dtype=np.float32, keep_direction=False) -> Volume:
    """Convert a SimpleITK image to a Volume ([z,y,x] -> [x,y,z], centre origin -> corner).

    keep_direction : also keep the direction cosines (so the label files written from
        the volume keep the input's orientation, and the model its place in the scanner).
    """
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise DicerError(
            f"{path}: the image has {image.GetNumberOfComponentsPerPixel()} components per voxel "
            "(colour or vector data); dicer reads single-channel (greyscale) images: convert it to greyscale"
        )
    size = list(image.GetSize())
    spacing = list(image.GetSpacing())
    origin = list(image.GetOrigin())
    if image.GetDimension() == 4 and size[3] == 1:
        # a 4D NIfTI with a single time point is just a 3D volume
        image = image[:, :, :, 0]
        size, spacing, origin = size[:3], spacing[:3], origin[:3]
    direction = None
    if keep_direction and own_spacing and image.GetDimension() in (2, 3):
        direction = tuple(image.GetDirection())
        if direction == tuple(np.eye(image.GetDimension()).ravel()):
            direction = None  # identity: the same files as a Volume without one
    if image.GetDimension() not in (2, 3):
        raise DicerError(
            f"{path}: the image is {image.GetDimension()}D ({'x'.join(map(str, size))}); dicer reads "
            "2D and 3D images only: extract one 3D volume (e.g. one time point) first"
        )
    if nifti:
        spacing, origin = list(_f32_decimal(spacing)), list(_f32_decimal(origin))
    array = sitk.GetArrayViewFromImage(image).T  # [z, y, x] -> [x, y, z], no copy yet
    if own_spacing:
        spacing = _check_spacing(spacing, path, "from the file header")
    else:
        # the format carries no reliable voxel size: origin at 0, spacing given or 1
        origin = [0.0] * len(size)
        tags = None if all(float(v) == 1.0 for v in spacing) else spacing  # a TIFF's or PNG's resolution
        spacing = _default_spacing(spacing_arg, array.shape, path, tags)
    corner = [o - s / 2 for o, s in zip(origin, spacing)] if own_spacing else origin
    return _finish(array, spacing, corner, path, dtype=dtype, direction=direction)


def _final_ndim(shape) -> int:
    singles = sum(n == 1 for n in shape)
    return len(shape) - 1 if len(shape) == 3 and singles == 1 else len(shape)


def _default_spacing(spacing_arg, shape, path, tags=None) -> list[float]:
    """Spacing for every axis of an array of ``shape`` from the user's value, else 1 mm.

    Accepts a number, one value per axis of ``shape``, or one per axis left after
    dropping a singleton axis (that axis then gets 1). A 2D image takes the first two
    of three values, so one ``image.spacing`` serves slice stacks and single slices.
    ``tags``: the voxel size a TIFF's or PNG's resolution tags give (not taken), for the
    warning.
    """
    ndim, final = len(shape), _final_ndim(shape)
    if spacing_arg is None:
        if tags is not None:  # "carries no voxel size" was untrue, and 0.1 mm tags made a model 10 times long
            log.warning("%s: the file's resolution tags give %s mm per pixel, which is not taken as the voxel size "
                        "(a TIFF's or PNG's resolution is most often a screen's or a printer's); using 1 mm per "
                        "axis: set image.spacing to the voxel size", Path(path).name,
                        " x ".join(f"{float(v):g}" for v in tags))
            return [1.0] * ndim
        log.warning("%s: the file carries no voxel size; using 1 mm per axis (set image.spacing to override)",
                    Path(path).name)
        return [1.0] * ndim
    spacing = [spacing_arg] * ndim if np.isscalar(spacing_arg) else list(spacing_arg)
    if len(spacing) == final < ndim:
        spacing.insert(list(shape).index(1), 1.0)
    elif len(spacing) == 3 and ndim == 2:
        spacing = spacing[:2]
    if len(spacing) != ndim:
        raise DicerError(
            f"{path}: the image is {final}D but the given spacing has {len(spacing)} values; "
            f"give {final} values in mm (config image.spacing)"
        )
    return list(_check_spacing(spacing, path, "given spacing"))


# --- header checks -------------------------------------------------------------------


def _nonfinite_error(path, nan: int, inf: int, size: int) -> DicerError:
    parts = [f"{nan} NaN" if nan else "", f"{inf} infinite" if inf else ""]
    return DicerError(
        f"{path}: {' and '.join(p for p in parts if p)} voxel value(s) of {size} ({(nan + inf) / size:.3%}); "
        "dicer does not guess them: replace them in the file with real values (e.g. the background value) "
        "and read it again"
    )


def _nifti_header(head: bytes):
    """``(dims, bitpix, datatype, pixdim, vox_offset, endian)`` of a NIfTI-1/2 header, or None."""
    for endian in "<>":
        (sizeof_hdr,) = struct.unpack(endian + "i", head[:4])
        if sizeof_hdr == 348:  # NIfTI-1
            dims = struct.unpack(endian + "8h", head[40:56])
            datatype, bitpix = struct.unpack(endian + "2h", head[70:74])
            pixdim = struct.unpack(endian + "8f", head[76:108])
            (vox_offset,) = struct.unpack(endian + "f", head[108:112])
            return dims, bitpix, datatype, pixdim, int(vox_offset), endian
        if sizeof_hdr == 540 and len(head) >= 540:  # NIfTI-2
            dims = struct.unpack(endian + "8q", head[16:80])
            datatype, bitpix = struct.unpack(endian + "2h", head[12:16])
            pixdim = struct.unpack(endian + "8d", head[104:168])
            (vox_offset,) = struct.unpack(endian + "q", head[168:176])
            return dims, bitpix, datatype, pixdim, int(vox_offset), endian
    return None


def _is_nifti2(path: Path) -> bool:
    """True for a file with a NIfTI-2 header (sizeof_hdr 540, either byte order)."""
    name = path.name.lower()
    if not (name.endswith(".nii") or name.endswith(".nii.gz")):
        return False
    try:
        with (gzip.open if name.endswith(".gz") else open)(path, "rb") as f:
            head = f.read(4)
    except (OSError, EOFError):
        return False
    return len(head) == 4 and 540 in (struct.unpack("<i", head)[0], struct.unpack(">i", head)[0])


def _check_nifti_complete(path: Path) -> tuple[float, ...] | None:
    """Raise DicerError when a NIfTI file is truncated or holds NaN or infinite voxels.

    ITK silently pads a truncated .nii or .nii.gz with zeros, so the header's data size
    (dims, bitpix, vox_offset) is compared with the file's (decompressed) length, and a
    gzip stream is read to its end-of-stream marker and CRC check. ITK's NIfTI reader
    also turns NaN and infinite float voxels into 0 (background) without a word, so
    they are counted here, on the stored bytes, in the same pass.

    Returns
    -------
    tuple of float or None
        The header's voxel spacing (pixdim) of the spatial axes as stored, or None for
        a header this function does not know. ITK turns a zero or NaN pixdim into 1 mm
        without a word, so the caller judges these values itself.
    """
    gz = path.name.lower().endswith(".gz")
    if gz:
        with open(path, "rb") as f:
            start = f.read(540)  # a NIfTI-2 header's length
        if start[:2] != b"\x1f\x8b" and len(start) >= 348 and _nifti_header(start) is not None:
            raise DicerError(f"{path}: the file is a NIfTI image that is not gzip-compressed, though its name ends "
                             f"in .gz; rename it to {path.name[:-3]}")
    opener = gzip.open if gz else open
    nan = inf = 0
    try:
        with opener(path, "rb") as f:
            head = f.read(540)
            total = len(head)
            header = _nifti_header(head) if len(head) >= 348 else None
            floats = None
            if header is not None and not path.name.lower().endswith((".hdr", ".img")):
                floats = {16: "f4", 64: "f8"}.get(header[2])
            if floats:
                dtype = np.dtype(header[5] + floats)
                pending = head[header[4]:]  # voxel bytes not yet counted
                skip = max(header[4] - len(head), 0)  # header extensions beyond the first 540 bytes
            while chunk := f.read(1 << 22):
                total += len(chunk)
                if floats:
                    cut = min(skip, len(chunk))
                    skip -= cut
                    pending += chunk[cut:]
                    usable = len(pending) - len(pending) % dtype.itemsize
                    values = np.frombuffer(pending, dtype, count=usable // dtype.itemsize)
                    bad = values[~np.isfinite(values)]
                    nan += int(np.count_nonzero(np.isnan(bad)))
                    inf += bad.size - int(np.count_nonzero(np.isnan(bad)))
                    pending = pending[usable:]
            if floats and pending:
                values = np.frombuffer(pending[: len(pending) - len(pending) % dtype.itemsize], dtype)
                bad = values[~np.isfinite(values)]
                nan += int(np.count_nonzero(np.isnan(bad)))
                inf += bad.size - int(np.count_nonzero(np.isnan(bad)))
    except (EOFError, OSError, gzip.BadGzipFile) as exc:
        raise DicerError(f"{path}: the file is truncated or corrupt ({exc}); copy or export it again") from None
    if len(head) < 348:
        raise DicerError(f"{path}: the file is too short for a NIfTI header; copy or export it again")
    if header is None:
        return None  # not a header we know; leave the judgement to ITK
    dims, bitpix, _, pixdim, vox_offset, endian = header
    if not 1 <= dims[0] <= 7:
        return None
    nifti1 = struct.unpack(endian + "i", head[:4])[0] == 348
    slope, inter = struct.unpack(endian + ("2f" if nifti1 else "2d"), head[112:120] if nifti1 else head[176:192])
    if (slope == 0 or not np.isfinite(slope)) and inter != 0 and np.isfinite(inter):
        # the standard: a zero or non-finite slope means the values are stored unscaled; ITK adds the intercept
        raise DicerError(f"{path}: the header's scl_slope is {slope:g} and scl_inter {inter:g}: by the NIfTI "
                         "standard the voxels are stored unscaled, but the image reader would add the intercept to "
                         "every voxel; set scl_slope to 1 and scl_inter to 0 in the header (values as stored), or to "
                         "the scaling meant")
    spatial = tuple(float(v) for v in pixdim[1 : min(int(dims[0]), 3) + 1])
    if path.name.lower().endswith((".hdr", ".img")):
        return spatial
    n = int(np.prod([max(int(d), 1) for d in dims[1 : dims[0] + 1]], dtype=np.int64))
    need = vox_offset + n * max(int(bitpix), 8) // 8
    if total < need:
        raise DicerError(
            f"{path}: the file is truncated ({total} of {need} bytes); copy or export it again"
        )
    if nan or inf:
        raise _nonfinite_error(path, nan, inf, n)
    return spatial


def _corners_apart(a: tuple, b: tuple, spacing_mm, head: bytes, n: int) -> tuple[float, float]:
    """The largest distance (mm) between the image's corner voxel centres placed by ``a`` and by
    ``b`` (each (direction, origin) as :func:`_nifti_placement` returns them), and the largest
    distance of a corner from voxel 0 (mm)."""
    found = _nifti_header(head)
    dims = np.asarray(found[0][1 : n + 1] if found else (1,) * n, float)
    corners = np.array(np.meshgrid(*[[0.0, max(d - 1, 0)] for d in dims], indexing="ij")).reshape(n, -1)
    steps = corners * np.abs(np.asarray(spacing_mm, float))[:, None]
    at = [np.asarray(d, float).reshape(n, n) @ steps + np.asarray(o, float)[:, None] for d, o in (a, b)]
    return float(np.max(np.linalg.norm(at[0] - at[1], axis=0))), float(np.max(np.linalg.norm(steps, axis=0)))


def _nifti_placement(path: Path, spatial: tuple[float, ...]):
    """The placement to use instead of ITK's for a NIfTI file, or None when ITK's own is right.

    dicer places voxels by the sform when its code is set and it is rigid (as nibabel, FSL
    and FreeSurfer do), else by the qform. ITK differs in two ways. It takes the sform only
    when its code is 1 (scanner) or there is no qform: for an aligned or template sform
    (codes 2-4) beside a qform it takes the qform, so here the sform's placement is given
    (with a warning when the two differ). And it keeps pixdim as the spacing: an sform
    whose columns are not pixdim long (a scaling, e.g. a transform to a template space)
    would be applied without its scale, and a sheared one falls back to the qform or
    fails. The qform is always a rigid placement of pixdim-sized voxels (the scanner
    geometry), so it is used whenever the sform is not one; without a qform such a file
    has no rigid placement and is refused.

    Returns
    -------
    tuple or None
        ``(direction, origin)`` for ITK's LPS frame: direction (n, n) row-major tuple,
        origin of voxel 0's centre in mm (n,), n = len(spatial).
    """
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    with opener(path, "rb") as f:
        head = f.read(540)
    found = False
    for e in "<>":
        (sizeof_hdr,) = struct.unpack(e + "i", head[:4])
        if sizeof_hdr == 348:  # NIfTI-1
            (qfac,) = struct.unpack(e + "f", head[76:80])
            qcode, scode = struct.unpack(e + "2h", head[252:256])
            quat = struct.unpack(e + "6f", head[256:280])
            srow = struct.unpack(e + "12f", head[280:328])
            units = head[123]
            found = True
        elif sizeof_hdr == 540 and len(head) >= 540:  # NIfTI-2
            (qfac,) = struct.unpack(e + "d", head[104:112])
            qcode, scode = struct.unpack(e + "2i", head[344:352])
            quat = struct.unpack(e + "6d", head[352:400])
            srow = struct.unpack(e + "12d", head[400:496])
            (units,) = struct.unpack(e + "i", head[500:504])
            found = True
    n = len(spatial)
    if found and scode <= 0 and qcode <= 0 and n >= 2:
        # ITK gives it an identity direction at the origin, nibabel the Analyze default
        # (x mirrored): no placement to keep, and tools disagree where the image lies
        _warn_once("%s: its header places the image nowhere in the scanner (qform and sform codes 0): the model "
                   "is made from its voxel size alone, at the origin with the image axes as L, P, S; other tools "
                   "may show this file mirrored; write a qform or sform if the model must overlay other images",
                   path.name)
    if not found or scode <= 0 or n < 2:
        return None
    affine = np.asarray(srow, float).reshape(3, 4)
    lengths = np.linalg.norm(affine[:, :n], axis=0)
    if not np.all(np.isfinite(affine)) or np.any(lengths == 0):
        scale_error, shear = np.inf, np.inf
    else:
        scale_error = float(np.max(np.abs(lengths - np.abs(spatial)) / np.abs(spatial)))
        unit = affine[:, :n] / lengths
        shear = float(np.max(np.abs(unit.T @ unit - np.eye(n))))
    lps = np.diag([-1.0, -1.0, 1.0])  # NIfTI is RAS, ITK LPS
    # the offsets are in the file's space unit, as ITK converts pixdim: metres, mm, microns
    to_mm = {1: 1000.0, 2: 1.0, 3: 0.001}.get(units & 7, 1.0)
    # float32 headers round at 1e-7; ITK's own tolerances are 1e-3 mm and 1e-4
    if scale_error <= 1e-4 and shear <= 1e-4:
        if qcode <= 0:
            return None  # ITK places the voxels by the sform itself
        # ITK takes the qform when both are set and the sform is not scanner-based (code 1);
        # nibabel, FSL and FreeSurfer take the sform, and so does dicer: the model then lies
        # where those tools show the scan and the label files dicer writes with its header
        sform = (tuple((lps @ unit)[:n, :n].ravel()), tuple((lps @ affine[:, 3])[:n] * to_mm))
        qform = _qform_placement(quat, qfac, n, to_mm)
        spacing_mm = np.abs(np.asarray(spatial[:n], float)) * to_mm
        apart, reach = _corners_apart(sform, qform, spacing_mm, head, n)
        # a qform's quaternion in float32 turns the image by up to about 6e-4 rad where its
        # first component is near 0 (a scan tilted about left-right): 0.2 mm at the corners of a
        # 300 mm image, header precision, not forms that disagree
        if apart > max(0.1 * float(spacing_mm.min()), 1e-3 * reach):
            _warn_once("%s: its sform (code %d) and qform (code %d) place the image differently (its corners up to "
                       "%.3g mm apart): meshing at the sform, where nibabel and FSL show it", path.name, scode, qcode,
                       apart)
        return None if scode == 1 else sform
    sizes = ", ".join(f"{v:.4g}" for v in lengths)
    stored = ", ".join(f"{v:.4g}" for v in spatial)
    problem = (f"the header's sform (code {scode}) does not place voxels of the pixdim size rigidly "
               f"(column lengths {sizes} mm against pixdim {stored} mm, largest angle error {shear:.2g})")
    if qcode <= 0:
        raise DicerError(
            f"{path}: {problem} and there is no qform to use instead; resample the image onto its sform "
            "grid, or write pixdim and an orthonormal sform that agree (e.g. with nibabel)"
        )
    _warn_once("%s: %s, so it maps to another space; meshing in the qform's scanner geometry", path.name,
               problem.replace("the header's ", "its "))
    return _qform_placement(quat, qfac, n, to_mm)


def _qform_placement(quat, qfac: float, n: int, to_mm: float) -> tuple[tuple, tuple]:
    """``(direction, origin)`` in ITK's LPS frame of a NIfTI qform (quaternion b, c, d and
    offsets, qfac), offsets converted to mm by ``to_mm``; see :func:`_nifti_placement`."""
    b, c, d, qx, qy, qz = quat
    a = np.sqrt(max(0.0, 1.0 - (b * b + c * c + d * d)))
    rotation = np.array([[a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
                         [2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b)],
                         [2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - c * c - b * b]])
    if qfac < 0:
        rotation[:, 2] = -rotation[:, 2]
    lps = np.diag([-1.0, -1.0, 1.0])  # NIfTI is RAS, ITK LPS
    direction = (lps @ rotation)[:n, :n]
    origin = (lps @ np.array([qx, qy, qz]))[:n] * to_mm
    return tuple(direction.ravel()), tuple(origin)


#: bytes per element of the MetaImage element types
_MET_SIZES = {"MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4, "MET_UINT": 4,
              "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8, "MET_FLOAT": 4,
              "MET_DOUBLE": 8}
#: bytes per element of the NRRD types (every spelling the format allows)
_NRRD_SIZES = {
    **dict.fromkeys(("signed char", "int8", "int8_t", "uchar", "unsigned char", "uint8", "uint8_t"), 1),
    **dict.fromkeys(("short", "short int", "signed short", "signed short int", "int16", "int16_t", "ushort",
                     "unsigned short", "unsigned short int", "uint16", "uint16_t"), 2),
    **dict.fromkeys(("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t",
                     "float"), 4),
    **dict.fromkeys(("longlong", "long long", "long long int", "signed long long", "signed long long int",
                     "int64", "int64_t", "ulonglong", "unsigned long long", "unsigned long long int", "uint64",
                     "uint64_t", "double"), 8),
}


def _read_header_text(path: Path, limit: int = 1 << 16) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(limit)
    except OSError as exc:
        raise DicerError(f"{path}: cannot read the file ({exc.strerror}); check the path and permissions") from None


_UNITS_TO_MM = {**dict.fromkeys(("mm", "millimeter", "millimeters", "millimetre", "millimetres"), 1.0),
                **dict.fromkeys(("um", "\u00b5m", "micron", "microns", "micrometer", "micrometers", "micrometre",
                                 "micrometres"), 1e-3),
                **dict.fromkeys(("cm", "centimeter", "centimeters", "centimetre", "centimetres"), 10.0),
                **dict.fromkeys(("m", "meter", "meters", "metre", "metres"), 1000.0)}


def _nrrd_fields(head: bytes) -> tuple[dict[str, str], re.Match | None]:
    """An NRRD header's fields (keys lower case without spaces: ``spaceunits``) and the
    blank line that ends it (None when ``head`` stops before it)."""
    match = re.search(rb"\r?\n\r?\n", head)
    fields = {}
    for line in head[:match.end() if match else len(head)].decode("utf-8", "replace").splitlines()[1:]:
        if line.startswith("#") or ":=" in line or ": " not in line:
            continue
        key, _, value = line.partition(": ")
        fields[key.strip().lower().replace(" ", "")] = value.strip()
    return fields, match


def header_data_file(header: str | os.PathLike) -> Path | None:
    """The one file a detached header names for its voxels: MetaImage ``ElementDataFile``,
    NRRD ``data file`` (absolute, or beside the header), Analyze ``.img``.

    Parameters
    ----------
    header : str or os.PathLike
        A ``.mhd``, ``.nhdr`` or ``.hdr`` file (others name none).

    Returns
    -------
    Path or None
        None where the header holds its voxels (LOCAL), names several files (LIST, a
        numbered pattern) or none, or cannot be read.
    """
    header = Path(header)
    name = header.name.lower()
    if name.endswith(".hdr"):
        img = header.with_suffix(".img")
        return img if img.exists() or not header.with_suffix(".img.gz").exists() else header.with_suffix(".img.gz")
    if not name.endswith((".mhd", ".nhdr")):
        return None
    try:
        head = _read_header_text(header)
    except DicerError:
        return None
    if name.endswith(".nhdr"):
        value = _nrrd_fields(head)[0].get("datafile")
    else:
        found = re.search(rb"^[ \t]*ElementDataFile[ \t]*=[ \t]*([^\r\n]*?)[ \t]*\r?$", head, re.M)
        value = found.group(1).decode("latin-1") if found else None
    if not value or value.split()[0].upper() in ("LOCAL", "LIST") or "%" in value:
        return None
    return header.parent / value


def _nrrd_to_mm(path: Path) -> float:
    """The factor from an NRRD header's ``space units`` to mm (1 without the field): ITK
    reads spacings and origins as mm whatever the unit (a micro-CT in microns came out
    1000 times too large)."""
    value = _nrrd_fields(_read_header_text(path))[0].get("spaceunits")
    if value is None:
        return 1.0
    factors = {_UNITS_TO_MM.get(u.strip().lower()) for u in re.findall(r'"([^"]*)"', value)}
    if None in factors or len(factors) > 1:
        raise DicerError(f"{path}: the header's space units are {value}; dicer reads mm, microns, cm or m, the same "
                         "on every axis: convert the image to mm")
    return factors.pop() if factors else 1.0


def _raw_layout(path: Path, suffix: str):
    """The raw voxel data a MetaImage or NRRD header describes, or None when not checkable.

    Returns
    -------
    tuple or None
        ``(data_file, offset, need, dims, element_size, at_end)``: the file holding the
        voxels, where they start, how many bytes the header's dimensions and element
        type need, those dimensions and element size, and whether the data sits at the
        end of the file (offset unknown). None for compressed, text, multi-file or
        unrecognised headers, which ITK judges when it reads them.
    """
    head = _read_header_text(path)
    if suffix in (".mha", ".mhd"):
        fields, end = {}, None
        for match in re.finditer(rb"^[ \t]*(\w+)[ \t]*=[ \t]*([^\r\n]*?)[ \t]*(?:\r?\n|$)", head, re.M):
            key, value = match.group(1).decode("ascii", "replace"), match.group(2).decode("latin-1")
            fields[key] = value
            if key == "ElementDataFile":
                end = match.end()
                break
        if end is None or fields.get("CompressedData", "False").lower() == "true":
            return None
        try:
            dims = [int(v) for v in fields["DimSize"].split()]
            channels = int(fields.get("ElementNumberOfChannels", "1"))
            size = _MET_SIZES[fields["ElementType"]]
            skip = int(fields.get("HeaderSize", "0"))
        except (KeyError, ValueError):
            return None
        name = fields["ElementDataFile"]
        if name.upper() == "LOCAL":
            data_file, offset = path, end
        elif name.upper().startswith("LIST") or "%" in name or " " in name.strip():
            return None
        else:
            data_file, offset = path.parent / name, max(skip, 0)
        return data_file, offset, int(np.prod(dims, dtype=np.int64)) * channels * size, dims, size, skip == -1
    # NRRD: magic line, "field: value" lines, a blank line, then the data (or a detached file)
    if not head.startswith(b"NRRD000"):
        return None
    fields, match = _nrrd_fields(head)
    end = match.end() if match else len(head)
    if fields.get("encoding", "").lower() != "raw" or fields.get("lineskip", "0") != "0":
        return None
    try:
        dims = [int(v) for v in fields["sizes"].split()]
        size = _NRRD_SIZES[fields["type"].lower()]
        skip = int(fields.get("byteskip", "0"))
    except (KeyError, ValueError):
        return None
    name = fields.get("datafile")
    if name is None:
        if match is None:
            return None  # header longer than what was read: leave it to ITK
        data_file, offset = path, end + max(skip, 0)
    elif name.upper().startswith("LIST") or " " in name:
        return None
    else:
        data_file, offset = (Path(name) if Path(name).is_absolute() else path.parent / name), max(skip, 0)
    return data_file, offset, int(np.prod(dims, dtype=np.int64)) * size, dims, size, skip == -1


def _check_raw_size(path: Path, suffix: str) -> None:
    """Raise DicerError when raw voxel data does not have the size its header promises.

    Checked before ITK reads anything: a header whose dimensions are wrong (or whose
    data file is cut short) would otherwise allocate the whole promised array first,
    then fail or pad, or read the voxels with the wrong layout.
    """
    layout = _raw_layout(path, suffix)
    if layout is None:
        return
    data_file, offset, need, dims, size, at_end = layout
    if not data_file.is_file():
        raise DicerError(f"{path}: the data file {data_file.name!r} named by the header is missing; put it "
                         "beside the header or fix the header's data file entry")
    have = data_file.stat().st_size - offset
    if have < need or (have > need and not at_end):
        where = "" if data_file == path else f" (in {data_file.name})"
        raise DicerError(
            f"{path}: the header promises {'x'.join(map(str, dims))} elements of {size} byte(s) = {need} bytes "
            f"of raw voxel data but the file holds {max(have, 0)}{where}; fix the header's dimensions or element "
            "type, or copy the complete data file again"
        )


# --- reading -----------------------------------------------------------------------


def _png_channels(path: Path) -> str | None:
    """The channels of a PNG with more than one (from its IHDR chunk's colour type), or None."""
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return None
    if len(head) < 26 or not head.startswith(b"\x89PNG\r\n\x1a\n"):
        return None
    return {2: "red, green and blue channels", 4: "grey and alpha channels",
            6: "red, green, blue and alpha channels"}.get(head[25])


def _bad_spacing(spacing) -> bool:
    return not all(np.isfinite(sp) and SPACING_RANGE_MM[0] <= sp <= SPACING_RANGE_MM[1] for sp in spacing)


def _spacing_error(path: Path, spacing, what: str) -> DicerError:
    low, high = SPACING_RANGE_MM
    return DicerError(
        f"{path}: the header's voxel spacing{what} is {', '.join(f'{sp:g}' for sp in spacing)} mm: zero, "
        f"negative, not finite or outside {low:g} to {high:g} mm; fix the spacing in the header, or set "
        "image.spacing to the voxel size in mm (x, y, z) to use instead"
    )


def _dicom_preamble(path: Path, unreadable: bool = False) -> bool:
    """Whether the file starts as a DICOM file does: 128 bytes, then ``DICM``
    (``unreadable`` for a file that cannot be opened)."""
    try:
        with open(path, "rb") as f:
            return f.read(132)[128:] == b"DICM"
    except OSError:
        return unreadable


def _read_file(path: Path, spacing_arg, dtype=np.float32, keep_direction=False) -> Volume:
    suffix = _suffix(path)
    if suffix not in IMAGE_SUFFIXES and _dicom_preamble(path):
        suffix = ".dcm"  # scanners and archives often name DICOM files without an extension (IM0001)
    if suffix == ".npy":
        return _read_npy(path, spacing_arg, dtype)
    if suffix not in IMAGE_SUFFIXES:
        raise DicerError(f"{path}: unknown image format {suffix or '(no extension)'!r}; {_SUPPORTED}")
    bad_header_spacing = False
    placement = None
    if suffix in (".nii", ".nii.gz"):
        pixdim = _check_nifti_complete(path)
        placement = _nifti_placement(path, pixdim) if pixdim is not None and not _bad_spacing(pixdim) else None
        # ITK reads a zero or NaN pixdim as 1 mm: judge the stored values instead
        if pixdim is not None and _bad_spacing(pixdim):
            if spacing_arg is None:
                raise _spacing_error(path, pixdim, " (pixdim)")
            bad_header_spacing = True
    elif suffix in (".mha", ".mhd", ".nrrd", ".nhdr"):
        _check_raw_size(path, suffix)
    elif suffix == ".dcm":
        _check_frames(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        with quiet_itk():
            reader.ReadImageInformation()
            layers = _segmentation_layers(reader)
            if reader.GetNumberOfComponents() != 1 and layers:
                raise DicerError(
                    f"{path}: a segmentation in {reader.GetNumberOfComponents()} layers of overlapping segments "
                    f"({layers} segments; 3D Slicer's .seg.nrrd): dicer reads one label per voxel; export it as one "
                    "labelmap (Slicer: Segmentations, Export to labelmap node) after resolving the overlaps")
            if reader.GetNumberOfComponents() != 1:
                raise DicerError(
                    f"{path}: the image has {reader.GetNumberOfComponents()} components per voxel (colour or "
                    "vector data); dicer reads single-channel (greyscale) images: convert it to greyscale"
                )
            # ITK turns a negative header spacing into a flipped direction: catch it here; in a
            # multi-frame DICOM file it is the frames' order (stored top to bottom), which the
            # flipped direction then places right
            spacing = reader.GetSpacing()
            descending_frames = suffix == ".dcm" and all(np.isfinite(v) and v != 0 for v in spacing)
            if _bad_spacing(spacing) and suffix not in _TIFF + _PNG and not descending_frames:
                if spacing_arg is None:
                    raise _spacing_error(path, reader.GetSpacing(), "")
                bad_header_spacing = True
            image = reader.Execute()
    except RuntimeError as exc:
        msg = _itk_message(exc)
        if "spacing" in msg.lower():
            raise DicerError(
                f"{path}: the header has a zero or negative voxel spacing ({msg}); fix the spacing in the header"
            ) from None
        if _is_nifti2(path):
            raise DicerError(f"{path}: a NIfTI-2 file, which the image reader (ITK's NIfTI-1 reader) does not "
                             "read; save it as NIfTI-1 (nibabel: nib.save(nib.Nifti1Image(img.dataobj, img.affine, "
                             "img.header), 'scan.nii.gz')) or as .nrrd or .mha") from None
        channels = _png_channels(path) if suffix in _PNG else None
        if channels:  # grey and alpha: ITK names no pixel type for it ("check that the file is complete" misled)
            raise DicerError(f"{path}: a PNG of {channels}; dicer reads single-channel (greyscale) images: convert "
                             "it to greyscale without alpha") from None
        raise DicerError(f"{path}: cannot read the image ({msg}); check that the file is complete and in a "
                         f"supported format ({_SUPPORTED})") from None
    _check_orthonormal(image, path)
    if suffix in (".nrrd", ".nhdr") and (to_mm := _nrrd_to_mm(path)) != 1.0:
        image.SetSpacing(tuple(v * to_mm for v in image.GetSpacing()))
        image.SetOrigin(tuple(v * to_mm for v in image.GetOrigin()))
    if placement is not None and image.GetDimension() >= len(placement[1]):
        n = len(placement[1])
        direction = np.eye(image.GetDimension())
        direction[:n, :n] = np.reshape(placement[0], (n, n))
        image.SetDirection(tuple(direction.ravel()))
        image.SetOrigin(tuple(placement[1]) + tuple(image.GetOrigin()[n:]))
    if bad_header_spacing:
        # the user's image.spacing replaces a header spacing that cannot be right; the
        # header's origin is dropped with it (it was placed with that spacing)
        log.warning("%s: the header's voxel spacing is zero, negative, not finite or outside %g to %g mm; using "
                    "image.spacing %s", path.name, *SPACING_RANGE_MM, spacing_arg)
    # TIFF and PNG resolution tags are unreliable (dpi, not mm): use the given spacing
    own = suffix not in _TIFF + _PNG and not bad_header_spacing
    if own and spacing_arg is not None:
        _warn_once("%s: image.spacing is set (%s), but the file carries its own voxel size (%s mm), which is used: "
                   "image.spacing applies to .npy, TIFF and PNG inputs and to header spacings that are zero, "
                   "negative or not finite; to rescale the image, write its voxel size into the header", path.name,
                   spacing_arg, " x ".join(f"{v:g}" for v in image.GetSpacing()))
    return _from_sitk(image, path, spacing_arg, own_spacing=own, nifti=suffix in (".nii", ".nii.gz"),
                      dtype=dtype, keep_direction=keep_direction)


def _check_frames(path: Path) -> None:
    """Refuse a multi-frame DICOM file whose frames are not evenly spaced along their normal.

    GDCM reads such a file without a word at 1 mm voxels (in-plane too: a model 5.6 times
    too small), so the frames' positions are judged here, from the per-frame functional
    groups (pydicom, header only): missing frames, uneven steps and two frames at one
    position are refused, as they are in a series of single-slice files.
    """
    import pydicom

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except Exception:  # noqa: BLE001 -- not for pydicom to judge: GDCM reads the file or says why
        return
    if int(ds.get("NumberOfFrames", 1) or 1) < 2 or "PerFrameFunctionalGroupsSequence" not in ds:
        return

    def first(groups, sequence, tag):
        for group in groups:
            inner = group.get(sequence)
            if inner and tag in inner[0]:
                return [float(v) for v in inner[0].get(tag)]
        return None

    shared = list(ds.get("SharedFunctionalGroupsSequence", []))
    positions, orientation = [], first(shared, "PlaneOrientationSequence", "ImageOrientationPatient")
    for frame in ds.PerFrameFunctionalGroupsSequence:
        position = first([frame], "PlanePositionSequence", "ImagePositionPatient")
        orientation = orientation or first([frame], "PlaneOrientationSequence", "ImageOrientationPatient")
        if position is None:
            raise DicerError(f"{path}: a frame of the multi-frame DICOM file carries no Image Position (Patient), "
                             "so the frames' order and spacing are unknown; export it with the frame positions")
        positions.append(position)
    if orientation is None or len(orientation) != 6:
        return  # GDCM places the frames along z as stored
    normal = np.cross(orientation[:3], orientation[3:])
    depth = np.sort(np.asarray(positions) @ normal)
    steps = np.diff(depth)
    median = float(np.median(steps))
    tol = max(0.01 * abs(median), 1e-3)
    odd = np.flatnonzero((np.abs(steps - median) > tol) | (steps <= tol))
    if odd.size:
        where = _positions_text([(depth[i], depth[i + 1]) for i in odd[:3]], odd.size - 3)
        raise DicerError(f"{path}: the frames of the multi-frame DICOM file are not evenly spaced along their normal "
                         f"(between positions {where}, where the median step is {median:g} mm): frames are missing, "
                         "doubled or uneven, and the file would be read at 1 mm voxels; export the scan again with "
                         "uniform frames, or as single-slice files (image.allow_irregular_slices can resample those)")


def _check_orthonormal(image: sitk.Image, path: Path) -> None:
    """Refuse an image whose axes are sheared or scaled in its header (NRRD space
    directions, a MetaImage TransformMatrix): a grid of voxels has perpendicular axes, and
    every file dicer writes would turn such a direction into some rotation, silently
    (a 2 mm shear over 7 mm slices placed voxels up to 37 mm off)."""
    n = image.GetDimension()
    direction = np.reshape(image.GetDirection(), (n, n))
    error = float(np.abs(direction.T @ direction - np.eye(n)).max())
    if error > 1e-4:
        raise DicerError(f"{path}: the header's direction cosines are not orthonormal (largest error of D^T D - I: "
                         f"{error:.3g}: sheared or scaled axes); a grid of voxels cannot hold the image as placed: "
                         "resample it onto an orthogonal grid (e.g. ITK's ResampleImageFilter, 3D Slicer's "
                         "Resample Scalar Volume), or fix the header's orientation")


def _check_npy_size(path: Path) -> None:
    """Compare the .npy header's shape x item size with the bytes the file holds, before
    numpy allocates what the header promises (a damaged header can ask for terabytes)."""
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = {(1, 0): np.lib.format.read_array_header_1_0,
                    (2, 0): np.lib.format.read_array_header_2_0}.get(version)
            if read is None:
                return  # a newer format: numpy's own reader judges it
            shape, _, dtype = read(f)
            start = f.tell()
    except (ValueError, OSError, EOFError, SyntaxError) as exc:
        raise DicerError(f"{path}: cannot read the .npy array ({exc}); save it again with numpy.save") from None
    if dtype.hasobject:
        return  # refused below (not a numeric array)
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
    have = path.stat().st_size - start
    if have != need:
        raise DicerError(f"{path}: the .npy header promises {'x'.join(map(str, shape))} elements of "
                         f"{dtype.itemsize} byte(s) = {need:,} bytes but the file holds {have:,}; the file is "
                         "truncated or damaged: save it again with numpy.save")


def _read_npy(path: Path, spacing_arg, dtype) -> Volume:
    _check_npy_size(path)
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DicerError(f"{path}: cannot read the .npy array ({exc}); save it again with numpy.save") from None
    if array.dtype.kind not in "biuf":
        raise DicerError(f"{path}: the array has dtype {array.dtype}; save a numeric (integer or float) array")
    if array.ndim == 4 and array.shape[3] == 1:
        array = array[..., 0]
    elif array.ndim == 4 and array.shape[0] == 1:  # a channel first, as deep-learning tools save one
        array = array[0]
    if array.ndim not in (2, 3):
        raise DicerError(
            f"{path}: the array is {array.ndim}D ({'x'.join(map(str, array.shape))}); dicer reads 2D and 3D arrays "
            "indexed [x, y(, z)], and a 4D one with one channel first or last: save one 2D or 3D array"
        )
    spacing = _default_spacing(spacing_arg, array.shape, path)
    return _finish(array, spacing, (0.0,) * array.ndim, path, dtype=dtype)


def _read_folder(folder: Path, spacing_arg, allow_irregular: bool = False) -> Volume:
    files = sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")),
                   key=lambda p: _natural_key(p.name))
    if [p.name.upper() for p in files] == ["DICOMDIR"] and any(p.is_dir() for p in folder.iterdir()):
        raise DicerError(f"{folder}: the folder holds a DICOMDIR index and subfolders (a DICOM medium); give the "
                         "subfolder that directly holds the series' slices")
    if not files:
        where = "holds only subfolders" if any(p.is_dir() for p in folder.iterdir()) else "is empty"
        raise DicerError(f"{folder}: the folder {where}; give the folder that directly holds the DICOM "
                         "series, TIFF or PNG slices")
    tiffs = [p for p in files if p.suffix.lower() in _TIFF]
    pngs = [p for p in files if p.suffix.lower() in _PNG]
    if len(tiffs) + len(pngs) < len(files):
        # other files: a DICOM series wins over stray previews (.png) beside it
        volume = _read_dicom_series(folder, required=not (tiffs or pngs), allow_irregular=allow_irregular)
        if volume is not None:
            if spacing_arg is not None:  # a series places its slices itself, as a header does
                _warn_once("%s: image.spacing is set (%s), but the DICOM series carries its own voxel size (%s mm), "
                           "which is used: image.spacing applies to .npy, TIFF and PNG inputs and to header spacings "
                           "that are zero, negative or not finite", folder.name, spacing_arg,
                           " x ".join(f"{v:g}" for v in volume.spacing))
            return volume
    if tiffs and pngs:
        raise DicerError(f"{folder}: the folder mixes TIFF and PNG slices; keep one kind of slice per folder")
    return _read_slices(folder, tiffs or pngs, spacing_arg)


def _odd_slices(files: list[Path]) -> str | None:
    """Which slice files differ from most of them (size, pages, channels) or cannot be read,
    named; None when each reads alike (a header each: about 0.7 ms a slice)."""
    kinds = []
    for path in files:
        reader = image_header(path)
        if reader is None:
            return f"{path.name} cannot be read as an image"
        size, channels = reader.GetSize(), reader.GetNumberOfComponents()
        pages = size[2] if len(size) > 2 else 1
        kinds.append("x".join(map(str, size[:2])) + (f" with {pages} pages" if pages > 1 else "")
                     + (f" with {channels} channels" if channels > 1 else ""))
    common = max(set(kinds), key=lambda k: (kinds.count(k), -kinds.index(k)))
    odd = [i for i, k in enumerate(kinds) if k != common]
    if not odd:
        return None
    named = ", ".join(f"{files[i].name} is {kinds[i]}" for i in odd[:3]) + (f" and {len(odd) - 3} more" if len(odd) > 3
                                                                              else "")
    return f"{named}, where the other {len(files) - len(odd)} are {common} pixels"


def _read_slices(folder: Path, files: list[Path], spacing_arg) -> Volume:
    """Stack 2D TIFF or PNG slices (already in natural name order) along z."""
    numbers = [re.findall(r"\d+", p.stem) for p in files]
    if len(files) > 2 and all(numbers):
        last = np.array([int(n[-1]) for n in numbers])
        steps = np.diff(last)
        if np.all(steps > 0) and np.any(steps != steps.min()):
            # numbered files with a skip: slices left out of the folder (DICOM would show it by position)
            k = int(np.flatnonzero(steps != steps.min())[0])
            log.warning("%s: the slice files' numbers skip from %d to %d (%s to %s) where they step by %d elsewhere: "
                        "slices may be missing, and the stack is made of the %d files as they are",
                        folder.name, last[k], last[k + 1], files[k].name, files[k + 1].name, steps.min(), len(files))
    # every slice's header first: ITK's stack converts a colour slice among grey ones
    # without a word, and its size errors name the first file, not the odd one
    odd = _odd_slices(files) if len(files) > 1 else None
    if odd:
        raise DicerError(f"{folder}: cannot stack the {len(files)} slices ({odd}); every slice must be a readable "
                         "single-page greyscale image of the same size")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(p) for p in files])
    try:
        with quiet_itk():
            image = reader.Execute()
    except RuntimeError as exc:
        raise DicerError(f"{folder}: cannot stack the {len(files)} slices ({_itk_message(exc)}); every slice "
                         "must be a readable single-page greyscale image of the same size") from None
    if image.GetDimension() != 3 or (len(files) > 1 and image.GetSize()[2] != len(files)):
        raise DicerError(f"{folder}: the slices are not 2D images of one size; put single-page greyscale "
                         "slices of the same size in the folder")
    return _from_sitk(image, folder, spacing_arg, own_spacing=False)


#: name endings of files that are meant to be DICOM slices (besides files without one)
_DICOM_SUFFIXES = (".dcm", ".dicom", ".ima")


def _meant_as_dicom(path: Path) -> bool:
    """Whether a file GDCM left out of every series was meant to be a DICOM slice.

    GDCM's series scan silently skips files it cannot parse, so a truncated or damaged
    slice would just be missing from the series. Files named like slices (.dcm, .ima,
    no extension) or starting with the DICOM preamble are judged; notes, previews and
    the DICOMDIR index are not.
    """
    if path.name.upper() == "DICOMDIR" or path.suffix.lower() in _TIFF + _PNG:
        return False
    if path.suffix.lower() in _DICOM_SUFFIXES or not path.suffix:
        return True
    return _dicom_preamble(path, unreadable=True)


def _non_image_object(path: Path) -> str | None:
    """What a valid DICOM file without an image is (a dose report, a presentation state, a key
    object: PACS exports put them beside the slices), by its SOP class; None for anything else."""
    import pydicom

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except Exception:  # noqa: BLE001 -- damaged or not DICOM: the slice error says so
        return None
    if "Rows" in ds or "Columns" in ds or "SOPClassUID" not in ds:
        return None  # an image GDCM could not read, or no DICOM object at all
    uid = ds.SOPClassUID
    return str(getattr(uid, "name", "") or uid)


def _slice_error(path: str, detail: str) -> DicerError:
    return DicerError(f"{path}: this slice of the DICOM series cannot be read ({detail}); the file is truncated "
                      "or damaged: copy it again from the scanner or archive")


def _check_pixel_data(name: str) -> None:
    """Refuse a slice whose uncompressed pixel data is shorter than its header's rows, columns,
    samples and bits promise: GDCM reads it padded with zeros (a slice cut to 1000 of its 3200
    bytes became air, -1024 HU, over two thirds of it: exit 0, no word)."""
    import pydicom

    try:  # the pixel data's length from its element header, its bytes left unread
        ds = pydicom.dcmread(name, defer_size=1024, force=True)
        element = ds.get_item(0x7FE00010)
        rows, columns = int(ds.Rows), int(ds.Columns)
        bits, samples = int(ds.BitsAllocated), int(ds.get("SamplesPerPixel", 1))
        frames = int(ds.get("NumberOfFrames", 1) or 1)
    except Exception:  # noqa: BLE001 -- no such tags, or pydicom reads the file otherwise: GDCM's checks decide
        return
    length = getattr(element, "length", None)
    if length is None or length == 0xFFFFFFFF:  # encapsulated (compressed): its own decoder checks it
        return
    promised = rows * columns * samples * frames * bits // 8
    if length < promised:
        raise _slice_error(name, f"its pixel data holds {length} bytes where its header promises {promised}, "
                                 f"{columns} x {rows} x {bits} bits")


def _read_dicom_slices(names: list[str]):
    """Read every slice file: headers first (geometry, checked), then the pixels into one array.

    Returns
    -------
    array : ndarray, float32, shape (nx, ny, n)
        Slices in the order of ``names``, rescale slope and intercept applied.
    positions : ndarray, shape (n, 3)
        Image position (patient) of each slice, mm.
    direction : ndarray, shape (3, 3)
        Direction cosines of the first slice; column 2 is the slice normal.
    pixel_spacing : tuple of float
        In-plane voxel size (x, y), mm.
    paddings : list
        Each slice's padding range (``_padding_range``), for ``_clear_padding``.
    modality : str or None
        The first Modality (0008,0060) a slice gives.
    """
    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    positions, directions, sizes, spacings, paddings = [], [], [], [], []
    sessions = set()
    modality = None
    for name in names:
        reader.SetFileName(name)
        try:
            reader.ReadImageInformation()
        except RuntimeError as exc:
            raise _slice_error(name, _itk_message(exc)) from None
        _check_orientation_tag(reader, name)
        _check_pixel_data(name)
        # a slice of another patient or study filed under the series' UID: compared, never shown
        sessions.add(tuple(reader.GetMetaData(tag).strip() if reader.HasMetaDataKey(tag) else ""
                           for tag, _, _ in _SESSION_TAGS))
        if len(sessions) > 1:
            differs = next(label for i, (_, _, label) in enumerate(_SESSION_TAGS) if len({v[i] for v in sessions}) > 1)
            raise DicerError(f"{Path(name).parent}: the slices of the DICOM series belong to more than one patient or "
                             f"study ({differs} differs, first at {Path(name).name}), so the stack mixes scans: "
                             "export the series again from its own scan")
        for tag, what, unknown in (("0028|0030", "Pixel Spacing (0028,0030)", "in-plane voxel size is unknown "
                                    "(GDCM would take 1 mm)"),
                                   ("0020|0032", "Image Position (Patient) (0020,0032)", "order and spacing are "
                                    "unknown")):
            if len(names) > 1 and not reader.HasMetaDataKey(tag):
                raise DicerError(f"{Path(name).parent}: the DICOM slices carry no {what}, so their {unknown}; export "
                                 "the series with it, or convert it to NIfTI with the geometry set there")
        paddings.append(_padding_range(reader, name))
        modality = modality or _modality(reader)  # the first slice that says
        positions.append(reader.GetOrigin()[:3])
        directions.append(reader.GetDirection())
        sizes.append(reader.GetSize()[:2])
        spacings.append(reader.GetSpacing()[:2])
    positions = np.asarray(positions, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    first = Path(names[0]).parent
    if positions.shape[1] != 3 or directions.shape[1] != 9:
        raise DicerError(f"{first}: the DICOM slices carry no 3D position and orientation; export the series "
                         "with Image Position and Image Orientation (Patient)")
    if np.abs(directions - directions[0]).max() > 1e-4:
        raise DicerError(f"{first}: the slices of the DICOM series have different orientations; a series must "
                         "be one stack of parallel slices: export each orientation as its own series")
    if len(set(sizes)) > 1 or np.ptp(np.asarray(spacings), axis=0).max() > 1e-6:
        raise DicerError(f"{first}: the slices of the DICOM series differ in size or pixel spacing; "
                         "a series must be one stack of equal slices: export it again")
    nx, ny = sizes[0]
    array = np.empty((nx, ny, len(names)), dtype=np.float32)
    reader.SetOutputPixelType(sitk.sitkFloat32)  # keeps rescale slope/intercept (HU) exact
    for k, name in enumerate(names):
        reader.SetFileName(name)
        try:
            image = reader.Execute()
        except RuntimeError as exc:
            raise _slice_error(name, _itk_message(exc)) from None
        pixels = sitk.GetArrayViewFromImage(image)
        if pixels.size != nx * ny or image.GetNumberOfComponentsPerPixel() != 1:
            raise _slice_error(name, f"{pixels.size} values where the header promises {nx}x{ny}")
        array[:, :, k] = pixels.reshape(ny, nx).T  # [y, x] -> [x, y]
    return array, positions, directions[0].reshape(3, 3), tuple(float(v) for v in spacings[0]), paddings, modality


def _check_orientation_tag(reader, name: str) -> None:
    """Refuse a slice whose Image Orientation (Patient) (0020,0037) GDCM did not take (not two
    perpendicular unit vectors): it puts the identity in its place, and the slice was read as
    axial whatever it said ([0.9, 0.1, 0, 0, 1, 0]: exit 0, no word)."""
    if not reader.HasMetaDataKey("0020|0037"):
        return
    try:
        values = [float(v) for v in reader.GetMetaData("0020|0037").strip().split("\\")]
    except ValueError:
        values = []
    if len(values) != 6:
        raise _slice_error(name, "its Image Orientation (Patient) (0020,0037) is not six numbers")
    row, col = np.asarray(values[:3]), np.asarray(values[3:])
    taken = np.asarray(reader.GetDirection(), float).reshape(3, 3)  # columns: the index axes
    with np.errstate(all="ignore"):
        given = np.column_stack([row / np.linalg.norm(row), col / np.linalg.norm(col)])
    if not np.all(np.abs(given - taken[:, :2]) <= 1e-3):  # GDCM put the identity in its place
        raise _slice_error(name, "its Image Orientation (Patient) (0020,0037) is not two perpendicular unit vectors "
                           f"({', '.join(f'{v:g}' for v in values)})")


def _padding_range(reader, name: str) -> tuple[float, float] | None:
    """The rescaled values a slice's Pixel Padding Value (0028,0120) and Range Limit
    (0028,0121) mark as outside the image, widened by half a stored step; None without.
    DicerError for an unsigned padding value beyond the slice's Bits Stored (0028,0101): GDCM
    keeps those bits only (63536 in 12 bits reads 2096, a bone's value), so the padding could
    not be told from the scan."""
    def number(tag: str, default=None):
        try:
            return float(reader.GetMetaData(tag).strip()) if reader.HasMetaDataKey(tag) else default
        except ValueError:
            return default

    pad = number("0028|0120")
    if pad is None:
        return None
    limit = number("0028|0121", pad)
    bits, signed = number("0028|0101"), number("0028|0103", 0.0)
    if bits is not None and not signed and 0 < bits < 32 and max(pad, limit) >= 2.0**bits:
        raise DicerError(f"{name}: the slice's Pixel Padding Value (0028,0120) {max(pad, limit):g} does not fit "
                         f"the {bits:g} bits it stores (Bits Stored (0028,0101)); the pixels keep only those bits, "
                         f"so padding reads as {int(max(pad, limit)) % 2**int(bits)}, a value the scan may hold too: "
                         "export the series with its Bits Stored covering the padding (16), or without padding")
    slope, intercept = number("0028|1053", 1.0) or 1.0, number("0028|1052", 0.0)
    lo, hi = sorted((min(pad, limit) * slope + intercept, max(pad, limit) * slope + intercept))
    return lo - abs(slope) / 2, hi + abs(slope) / 2


def _clear_padding(array: np.ndarray, paddings: list, folder: Path) -> None:
    """Voxels a slice marks as padding (outside the scanned field of view) take the lowest
    value of the others: unsigned CTs pad with values that rescale to 62,000 HU, which
    segmentation took for bone."""
    if all(band is None for band in paddings):
        return
    padded = np.zeros(array.shape, bool)
    for k, band in enumerate(paddings):
        if band is not None:
            padded[:, :, k] = (array[:, :, k] >= band[0]) & (array[:, :, k] <= band[1])
    count = int(np.count_nonzero(padded))
    if count and count < array.size:
        floor = array[~padded].min()
        array[padded] = floor
        log.info("%s: %d voxels hold the series' Pixel Padding Value (outside the field of view): set to the "
                 "lowest other value, %g", folder.name, count, floor)


def _positions_text(pairs, n_more: int) -> str:
    text = "; ".join(f"{a:g} and {b:g} mm (step {b - a:g} mm)" for a, b in pairs)
    return text + (f" and {n_more} more" if n_more > 0 else "")


def _uniform_slices(array, depth, names, folder, allow_irregular: bool):
    """Check that sorted slice positions are evenly spaced; resample them if allowed.

    Parameters
    ----------
    array : ndarray, shape (nx, ny, n)
        Slices sorted by ``depth``.
    depth : ndarray, shape (n,)
        Increasing slice positions along the slice normal, mm.
    names : list of str
        Slice files in the same order (to name duplicates).
    folder : Path
        The series folder, for messages.
    allow_irregular : bool
        Resample a series with missing slices or irregular steps (not duplicates) to
        the median step by linear interpolation along the slice normal.

    Returns
    -------
    array : ndarray, shape (nx, ny, m)
    dz : float
        The slice spacing in mm, from the positions (never from a header field).
    """
    steps = np.diff(depth)
    positive = steps[steps > 1e-3]
    median = float(np.median(positive)) if positive.size else 0.0
    # 1 % of a step: positions are written with a few decimals, real gaps are whole steps
    tol = max(0.01 * median, 1e-3)
    dup = np.flatnonzero(steps <= tol)
    if dup.size:
        k = int(dup[0])
        raise DicerError(
            f"{folder}: {dup.size} pair(s) of slices of the DICOM series lie at the same position along the "
            f"slice normal ({', '.join(f'{depth[i]:g} mm' for i in dup[:5])}; first: {Path(names[k]).name} "
            f"and {Path(names[k + 1]).name}); a series holds one slice per position: remove the duplicate "
            "files, or put each acquisition (echo, phase) in its own folder"
        )
    odd = np.flatnonzero(np.abs(steps - median) > tol)
    if odd.size == 0:
        return array, median
    whole = np.rint(steps[odd] / median)
    gaps = bool(np.all((whole >= 2) & (np.abs(steps[odd] - whole * median) <= tol * whole)))
    where = _positions_text([(depth[i], depth[i + 1]) for i in odd[:3]], odd.size - 3)
    problem = (f"misses slices between positions {where}" if gaps
               else f"has uneven slice steps between positions {where}")
    if not allow_irregular:
        raise DicerError(
            f"{folder}: the DICOM series {problem} along the slice normal, where the median step is "
            f"{median:g} mm (tolerance {tol:g} mm); {'add the missing slice files' if gaps else 'export the series with uniform spacing'}, "
            f"or set image.allow_irregular_slices: true to resample it to uniform {median:g} mm slices by "
            "linear interpolation"
        )
    count = int(np.floor((depth[-1] - depth[0]) / median + 0.01)) + 1
    target = depth[0] + median * np.arange(count)
    # each target slice between its two neighbours in the series, weighted by distance
    lower = np.clip(np.searchsorted(depth, target, side="right") - 1, 0, depth.size - 2)
    weight = ((target - depth[lower]) / (depth[lower + 1] - depth[lower])).astype(np.float32)
    weight = np.clip(weight, 0.0, 1.0)
    resampled = array[:, :, lower] * (1 - weight) + array[:, :, lower + 1] * weight
    log.warning("%s: the DICOM series %s; resampled its %d slices to %d uniform slices of %g mm by linear "
                "interpolation (image.allow_irregular_slices)", folder.name, problem, depth.size, count, median)
    return resampled.astype(np.float32, copy=False), median


def _refuse_tilt(positions: np.ndarray, depth: np.ndarray, normal: np.ndarray, pixel_spacing, folder: Path) -> None:
    """Raise DicerError when the slices of a series shift within their plane from one to the next.

    A series acquired with gantry tilt has its slice positions along the table, not along
    the slice normal: a grid of boxes built on the first slice and the normal would shear
    the anatomy (by the tilt's tangent times the depth). ``positions`` (n, 3) and ``depth``
    (n,) are sorted by depth, mm; ``normal`` (3,) is the unit slice normal.
    """
    drift = (positions - positions[0]) - np.outer(depth - depth[0], normal)
    shift = np.linalg.norm(drift, axis=1)
    # a tenth of a pixel: positions are written to a few decimals, a tilt moves slices by millimetres
    if shift.size < 2 or float(shift.max()) <= 0.1 * float(min(pixel_spacing)):
        return
    k = int(np.argmax(shift))
    angle = float(np.degrees(np.arctan2(shift[k], depth[k] - depth[0])))
    raise DicerError(
        f"{folder}: the slices of the DICOM series shift within their plane along the series (gantry tilt of "
        f"about {angle:.1f} degrees: {shift[k]:.2f} mm over {depth[k] - depth[0]:.1f} mm); a grid of voxels would "
        "shear the anatomy. Correct the tilt first (e.g. dcm2niix writes a tilt-corrected NIfTI) and give that file"
    )


def _frames(name: str) -> int:
    """Number of Frames (0028,0008) of a DICOM file; 1 when not said."""
    reader = image_header(name, "GDCMImageIO")
    try:
        return int(reader.GetMetaData("0028|0008").strip() or 1) if reader.HasMetaDataKey("0028|0008") else 1
    except (AttributeError, ValueError):  # no header (None), or a Number of Frames that is no number
        return 1


_SESSION_TAGS = (("0010|0020", "patients", "Patient ID"), ("0020|000d", "studies", "Study Instance UID"))


def _refuse_other_sessions(folder: Path, members: dict) -> None:
    """Refuse a folder whose series belong to different patients or studies (scan sessions):
    the series of the most slices could be another patient's scan. Their values are
    compared, never shown."""
    headers = [h for h in (image_header(names[0], "GDCMImageIO") for names in members.values()) if h is not None]
    for tag, what, name in _SESSION_TAGS:
        values = {h.GetMetaData(tag).strip() if h.HasMetaDataKey(tag) else "" for h in headers}
        if len(values) > 1:
            raise DicerError(f"{folder}: the folder holds DICOM series of {len(values)} different {what} ({name} "
                             "differs), and dicer would read one of them: put each one's series in a folder of "
                             "its own and give that folder")


def _read_dicom_series(folder: Path, required: bool = True, allow_irregular: bool = False) -> Volume | None:
    """Read the DICOM series with the most slices; None if there is none and not ``required``.

    Slices are sorted by their position along the slice normal, which also gives the
    slice spacing; missing, duplicate or unevenly spaced slices are refused unless
    ``allow_irregular`` (then resampled, duplicates still refused). A file in the folder
    that looks like a slice but cannot be parsed is refused by name.
    """
    # GDCM decodes JPEG slices already to list the series, and its decoder prints a line per
    # damaged block ('Corrupt JPEG data: ...') straight to standard error: dicer says in one
    # line what is wrong itself
    with quiet_itk(), captured_stderr():
        found = _dicom_series_slices(folder, required)
    if found is None:
        return None
    names, array, positions, direction, pixel_spacing, paddings, modality, counts = found
    if array is not None:
        _clear_padding(array, paddings, folder)  # it says what it cleared: out of the captured block
    if len(counts) > 1:
        # slice counts only: series and patient identifiers stay out of the log
        log.info("%s: %d DICOM series found (slices: %s); reading the one with the most slices (%d)",
                 folder.name, len(counts), ", ".join(map(str, counts)), len(names))
    if array is None:  # one multi-frame file
        volume = _read_file(Path(names[0]), None, keep_direction=True)
    else:
        volume = _stack_dicom_slices(folder, names, array, positions, direction, pixel_spacing, allow_irregular)
    volume.modality = modality
    return volume


def _dicom_series_slices(folder: Path, required: bool):
    """The chosen series' slice files, read (``_read_dicom_series``); array None for one
    multi-frame file, and the slice count of every series found."""
    try:
        series = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    except RuntimeError:
        series = ()
    if not series and not required:
        return None
    if not series:
        dicom = [p for p in sorted(folder.iterdir(), key=lambda p: _natural_key(p.name))
                 if p.is_file() and _dicom_preamble(p)]
        if dicom:  # GDCM's scan drops them all for one malformed value (a DS of Image Position)
            raise DicerError(f"{folder}: GDCM finds no DICOM series in the folder's {len(dicom)} DICOM file(s) (the "
                             f"first: {dicom[0].name}): a header value it cannot parse (Image Position, Pixel "
                             "Spacing, Image Orientation) drops them; check the slices' headers, or export the "
                             "series again")
        raise DicerError(
            f"{folder}: the folder holds no DICOM series, TIFF or PNG slices; {_SUPPORTED}"
        )
    # the series with the most slices; a tie is refused
    members = {sid: sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), sid) for sid in sorted(series)}
    if len(members) > 1:
        _refuse_other_sessions(folder, members)
    candidates = [(len(names), sid) for sid, names in members.items()]
    count, chosen = max(candidates, key=lambda c: c[0])
    tied = sum(c == count for c, _ in candidates)
    if tied > 1:  # no way to tell which is the scan (CT and its reformat, two echoes)
        raise DicerError(f"{folder}: the folder holds {len(series)} DICOM series, {tied} of them of {count} slices "
                         "(the most); dicer cannot tell which one is the scan: put each series in a folder of "
                         "its own and give that folder")
    known = {Path(name).name for names in members.values() for name in names}
    for path in sorted(folder.iterdir(), key=lambda p: _natural_key(p.name)):
        if (path.is_file() and not path.name.startswith(".") and path.name not in known
                and _meant_as_dicom(path)):
            kind = _non_image_object(path)
            if kind is None:
                raise _slice_error(str(path), "not a DICOM file GDCM can parse")
            log.info("%s: a DICOM %s object, no image: left out of the series", path.name, kind)
    names = list(members[chosen])
    counts = [c for c, _ in candidates]
    if len(names) == 1 and _frames(names[0]) > 1:  # one multi-frame file: read as the file it is
        return names, None, None, None, None, None, _dicom_modality(names[0]), counts
    return (names, *_read_dicom_slices(names), counts)


def _stack_dicom_slices(folder: Path, names: list, array, positions, direction, pixel_spacing,
                        allow_irregular: bool) -> Volume:
    """The slices of ``_read_dicom_slices`` sorted along the slice normal, checked and stacked."""
    normal = direction[:, 2]
    depth = positions @ normal
    order = np.argsort(depth, kind="stable")
    array, depth, positions = array[:, :, order], depth[order], positions[order]
    names = [names[i] for i in order]
    _refuse_tilt(positions, depth, normal, pixel_spacing, folder)
    dz = 1.0  # a single slice becomes a 2D image; its spacing along z is dropped
    if len(names) > 1:
        array, dz = _uniform_slices(array, depth, names, folder, allow_irregular)
    spacing = (*pixel_spacing, dz)
    corner = [o - sp / 2 for o, sp in zip(positions[0], spacing)]  # ITK: centre of the first voxel
    # columns: row and column directions of Image Orientation (Patient), then the slice
    # normal, along which the slices were sorted: the index axes' directions in LPS
    cosines = None if np.array_equal(direction, np.eye(3)) else tuple(direction.ravel())
    return _finish(array, spacing, corner, folder, direction=cosines)


def read_image(path: str | os.PathLike, spacing=None, allow_irregular_slices: bool = False) -> Volume:
    """Read an intensity image (CT in HU, MR, ...) from a file or a folder.

    Parameters
    ----------
    path : str or path-like
        A file (.nii, .nii.gz, .nrrd, .mha/.mhd, .npy, .tif/.tiff, .png, .dcm, or a
        DICOM file of any name, told by its preamble) or a folder holding one DICOM
        series (the series with the most slices if several; a tie is refused), TIFF
        slices or PNG slices (stacked along z in natural file-name order).
    spacing : None, float or sequence of float, optional
        Voxel size in mm (x, y[, z]) for inputs that carry none: .npy, TIFF and PNG.
        For the other formats it replaces only a header spacing that is zero,
        negative or not finite (else an error). Without it .npy, TIFF and PNG
        inputs get 1 mm per axis and a logged warning.
    allow_irregular_slices : bool, optional
        A DICOM series with missing slices or unevenly spaced slice positions is
        resampled to its median slice step by linear interpolation along the slice
        normal (with a logged warning) instead of refused. Duplicate positions are
        refused either way.

    Returns
    -------
    Volume
        ``array`` float32 of shape (nx, ny[, nz]); DICOM values have the rescale slope
        and intercept applied (CT in HU). A multi-page TIFF is a 3D stack; a single
        page or a single slice gives a 2D Volume. ``.npy`` arrays are taken as
        indexed [x, y(, z)] with origin 0. ``direction``: the header's direction
        cosines of a 3D NIfTI, NRRD, MetaImage or DICOM series (None: identity).
        ``modality``: a DICOM input's Modality, or that of a BIDS sidecar beside the file
        (``scan.json``, as dcm2niix writes it); None when neither says.

    Raises
    ------
    DicerError
        Missing path, unknown format, empty folder, unreadable or truncated file,
        colour/vector or 4D image, zero, negative or non-finite spacing, NaN or
        infinite voxels, raw data of another size than the header's, a DICOM series
        with missing, duplicate or unevenly spaced slices, or a damaged slice file.
    """
    path = Path(path)
    if not path.exists():
        raise DicerError(f"{path}: no such file or folder; check the path (and the image column of the patient sheet)")
    if path.is_dir():
        return _read_folder(path, spacing, allow_irregular_slices)
    volume = _read_file(path, spacing, keep_direction=True)
    dicom = _suffix(path) == ".dcm" or _dicom_preamble(path)
    if volume.array.ndim == 2 and dicom:
        _say_series_of_slice(path)
    volume.modality = _dicom_modality(path) if dicom else _sidecar_modality(path)
    return volume


def _say_series_of_slice(path: Path) -> None:
    """Warn when a DICOM file read as a 2D image is one slice of a series in its folder: a
    slice given for the series made a 2D model with a note only."""
    try:
        folder = str(path.parent)
        for sid in sitk.ImageSeriesReader.GetGDCMSeriesIDs(folder):
            names = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(folder, sid)
            if len(names) > 1 and any(Path(n).name == path.name for n in names):
                _warn_once("%s: one slice of a series of %d in its folder, read as a 2D image; give the folder "
                           "(%s) to read the series as a volume", path.name, len(names), path.parent.name or ".")
                return
    except RuntimeError:  # GDCM could not scan the folder: nothing to say
        return


def read_labels(path: str | os.PathLike, spacing=None) -> Volume:
    """Read a label volume (0 = background, 1..K = material classes).

    Parameters
    ----------
    path : str or path-like
        .nii, .nii.gz, .nrrd, .mha/.mhd or .npy (indexed [x, y(, z)], origin 0).
    spacing : None, float or sequence of float, optional
        Voxel size in mm (``image.spacing``): a .npy's (default 1 mm, with a warning), or in place of
        a header spacing that is zero, negative or not finite (without it such a header
        is an error); a header's own spacing is kept, with a warning.

    Returns
    -------
    Volume
        ``array`` of shape (nx, ny[, nz]): uint8 when the largest label is below 256,
        else int16 (int32 beyond 32767).

    Raises
    ------
    DicerError
        Missing or unreadable file, unsupported format, non-integer or negative values.
    """
    path = Path(path)
    if not path.exists():
        raise DicerError(f"{path}: no such file; check the path to the label volume")
    check_input_kind(path, labels=True)
    volume = _read_file(path, spacing, dtype=None, keep_direction=True)
    array = volume.array
    if array.dtype.kind == "f":
        if not np.all(np.isfinite(array)):
            raise DicerError(f"{path}: the labels hold NaN or infinite values; save integer class labels "
                             "(0 = background, 1..K = materials)")
        off = array != np.round(array)
        if off.any():
            example = array[off].flat[0].item()
            raise DicerError(f"{path}: {np.count_nonzero(off)} of {array.size} labels are not whole numbers (e.g. "
                             f"{example:.9g}): a label volume resampled or smoothed by linear interpolation mixes its "
                             "classes; resample it by nearest neighbour, or round it, and save integer class labels "
                             "(0 = background, 1..K = materials)")
    elif array.dtype.kind == "b":
        array = array.astype(np.uint8)
    # as Python numbers: a float32 2**31 equals int32's largest value in float32 arithmetic
    lo, hi = (array.min().item(), array.max().item()) if array.size else (0, 0)
    if lo < 0:
        raise DicerError(f"{path}: the labels contain negative values (min {lo:g}); use 0 for background "
                         "and 1..K for materials (rewrite the file so: labels.map and labels.drop name values "
                         "from 1)" + ("; a scan's values (a CT's air is near -1000) are segmented "
                                                     "from the IMAGE of dicer run (or dicer segment), not given "
                                                     "as labels" if lo <= -100 else ""))
    dtype = np.uint8 if hi < 256 else np.int16 if hi <= np.iinfo(np.int16).max else np.int32
    if hi > np.iinfo(np.int32).max:
        raise DicerError(f"{path}: label value {int(hi)} is too large (at most {np.iinfo(np.int32).max}); number the "
                         "classes 1..K")
    return Volume(array.astype(dtype, copy=False), volume.spacing, volume.origin, volume.direction)


# --- writing -----------------------------------------------------------------------


def _to_sitk(volume: Volume, array: np.ndarray) -> sitk.Image:
    image = sitk.GetImageFromArray(contiguous(array.T))  # [x,y,z] -> [z,y,x]
    spacing = [float(s) for s in volume.spacing]
    corner = [float(o) for o in volume.origin]
    image.SetSpacing(spacing)
    image.SetOrigin([c + s / 2 for c, s in zip(corner, spacing)])  # ITK: centre of voxel (0, 0, 0)
    if volume.direction is not None and len(volume.direction) == array.ndim ** 2:
        image.SetDirection(volume.direction)
    return image


def _check_volume(volume: Volume, path: Path, what: str) -> None:
    if volume.array.ndim not in (2, 3):
        raise DicerError(f"{path}: cannot write a {volume.array.ndim}D {what}; dicer writes 2D and 3D volumes")
    if len(volume.spacing) != volume.array.ndim or len(volume.origin) != volume.array.ndim:
        raise DicerError(f"{path}: the {what} has {volume.array.ndim} axes but spacing/origin of "
                         f"{len(volume.spacing)}/{len(volume.origin)} values; give one per axis")
    _check_spacing(volume.spacing, path, f"of the {what}")


def _same_values(back: np.ndarray, written: np.ndarray) -> bool:
    """The read-back array equals the written one wherever that is finite (ITK's NIfTI
    reader turns NaN and infinite values into 0)."""
    if back.shape != written.shape:
        return False
    if written.dtype.kind != "f":
        return np.array_equal(back, written)
    finite = np.isfinite(written)
    return bool(np.array_equal(back[finite], written[finite]))


def _write(image: sitk.Image, path: Path, compress: bool) -> None:
    writer = sitk.ImageFileWriter()
    with atomic_path(path) as tmp:
        writer.SetFileName(str(tmp))
        writer.SetUseCompression(compress)
        try:
            # the NIfTI and MetaImage writers print a short write straight to stderr
            with quiet_itk(), captured_stderr() as printed:
                writer.Execute(image)
                # ITK only warns when a write comes up short (a full disk): read the file
                # back and compare it with what was to be written
                back = sitk.ReadImage(str(tmp))
        except RuntimeError as exc:
            if disk_full(tmp.parent) or "wrote only" in "".join(printed) or "No space" in str(exc):
                raise DicerError(f"{path}: the disk is full (the image could not be written completely); free "
                                 "space or write elsewhere, nothing was written") from None
            raise DicerError(f"{path}: cannot write the image ({_itk_message(exc).replace(str(tmp), str(path))}); "
                             "check the disk space and the output folder") from None
        # NIfTI keeps spacing and origin in single precision
        same = (back.GetSize() == image.GetSize()
                and np.allclose(back.GetSpacing(), image.GetSpacing(), rtol=1e-6, atol=0)
                and np.allclose(back.GetOrigin(), image.GetOrigin(), rtol=1e-6, atol=1e-6)
                and _same_values(sitk.GetArrayViewFromImage(back), sitk.GetArrayViewFromImage(image)))
        if not same:
            if disk_full(tmp.parent) or "wrote only" in "".join(printed):
                raise DicerError(f"{path}: the disk is full (the image could not be written completely); free "
                                 "space or write elsewhere, nothing was written")
            raise DicerError(f"{path}: the written file does not hold the image (a full disk?); check the disk "
                             "space and write again, nothing was written")


def write_labels(volume: Volume, path: str | os.PathLike) -> None:
    """Write a label volume as NIfTI (.nii or .nii.gz), atomically.

    Stored as uint8 when the largest label is below 256, else uint16; spacing, the
    voxel-corner origin (as ITK's voxel-centre origin) and the direction cosines, when the
    volume has them, go into the header; nothing else (no metadata from the input image). Two writes of the same volume give identical bytes.

    Parameters
    ----------
    volume : Volume
        Integer labels (or integral floats) >= 0, shape (nx, ny[, nz]).
    path : str or path-like
        Output file ending in .nii or .nii.gz.
    """
    path = Path(path)
    if not path.name.lower().endswith(WRITE_LABEL_SUFFIXES):
        raise DicerError(f"{path}: label volumes are written as NIfTI; name the output .nii.gz or .nii")
    _check_volume(volume, path, "label volume")
    array = np.asarray(volume.array)
    if array.dtype.kind == "f" and not (np.all(np.isfinite(array)) and np.array_equal(array, np.round(array))):
        raise DicerError(f"{path}: the labels are not whole numbers; labels must be integers 0..K")
    if array.dtype.kind not in "biuf":
        raise DicerError(f"{path}: labels of dtype {array.dtype} cannot be written; use integers 0..K")
    hi = array.max() if array.size else 0
    lo = array.min() if array.size else 0
    if lo < 0 or hi > MAX_LABEL:
        raise DicerError(f"{path}: labels range {lo:g}..{hi:g}; they must lie in 0..{MAX_LABEL}")
    out = array.astype(np.uint8 if hi < 256 else np.uint16, copy=False)
    _write(_to_sitk(volume, out), path, compress=True)


def write_image(volume: Volume, path: str | os.PathLike) -> None:
    """Write an intensity image (.nii, .nii.gz, .nrrd, .mha), atomically.

    Stored as int16 when every value is a whole number in -32768..32767 (CT in HU),
    else float32. .nrrd and .mha are zlib-compressed. Deterministic bytes.

    Parameters
    ----------
    volume : Volume
        Intensities, shape (nx, ny[, nz]).
    path : str or path-like
        Output file; the format follows the extension.
    """
    path = Path(path)
    if not path.name.lower().endswith(WRITE_IMAGE_SUFFIXES):
        raise DicerError(f"{path}: images are written as {', '.join(WRITE_IMAGE_SUFFIXES)}; rename the output")
    _check_volume(volume, path, "image")
    array = np.asarray(volume.array)
    if array.dtype.kind == "b":
        array = array.astype(np.uint8)
    if array.dtype.kind not in "iuf":
        raise DicerError(f"{path}: images of dtype {array.dtype} cannot be written; use numbers")
    integral = array.dtype.kind in "iu" or (bool(np.all(np.isfinite(array))) and np.array_equal(array, np.round(array)))
    in_range = array.size == 0 or (array.min() >= -32768 and array.max() <= 32767)
    out = array.astype(np.int16 if integral and in_range else np.float32, copy=False)
    _write(_to_sitk(volume, out), path, compress=True)
