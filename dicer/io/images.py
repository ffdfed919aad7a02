"""Read and write images and label volumes (SimpleITK underneath).

Conventions shared by every function here:

- Arrays are indexed ``[x, y, z]`` (SimpleITK's arrays are ``[z, y, x]``; they are
  transposed on the way in and out) and spacing is given in the same order, in mm.
- ``Volume.origin`` is the position of the *corner* of voxel (0, 0, 0). ITK stores the
  *centre* of that voxel, so ``corner = itk_origin - spacing / 2`` on reading and the
  reverse on writing. Direction cosines are ignored: the voxel grid is taken as
  axis-aligned, which is what the hexahedral lattice needs; a scan acquired with a
  tilted or flipped orientation is meshed in its own voxel frame.
- A 3D image with one axis of a single voxel (one slice, a single PNG, a one-file
  DICOM series) becomes a 2D Volume; that axis is dropped with its spacing and origin.
"""

from __future__ import annotations

import contextlib
import gzip
import logging
import os
import re
import struct
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dicer.errors import DicerError
from dicer.image import MAX_LABEL, Volume
from dicer.io.atomic import atomic_path

log = logging.getLogger(__name__)

#: single-file image formats (lower-case name endings)
IMAGE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha", ".mhd", ".npy", ".tif", ".tiff", ".png", ".dcm")
#: label volume formats
LABEL_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha", ".mhd", ".npy")
#: formats ``write_image`` writes
WRITE_IMAGE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha")
#: formats ``write_labels`` writes
WRITE_LABEL_SUFFIXES = (".nii", ".nii.gz")

_TIFF = (".tif", ".tiff")
_PNG = (".png",)
_SUPPORTED = (
    "supported inputs: .nii, .nii.gz, .nrrd, .mha/.mhd, .npy, .tif/.tiff, .png, .dcm, "
    "or a folder holding a DICOM series, TIFF slices or PNG slices"
)


# --- small helpers -------------------------------------------------------------------


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for s in sorted(IMAGE_SUFFIXES, key=len, reverse=True):
        if name.endswith(s):
            return s
    return path.suffix.lower()


def _natural_key(name: str):
    # "slice2.png" before "slice10.png"
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", name)]


@contextlib.contextmanager
def _quiet_itk():
    # ITK/GDCM print warnings straight to stderr; dicer reports problems itself
    previous = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(previous)


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
    if not all(np.isfinite(s) and s > 0 for s in spacing):
        raise DicerError(
            f"{path}: voxel spacing {', '.join(f'{s:g}' for s in spacing)} mm ({source}) has a zero, "
            "negative or non-finite value; give every axis a positive voxel size in mm"
        )
    return spacing


def _finish(array: np.ndarray, spacing, origin, path, dtype=np.float32) -> Volume:
    """Drop a singleton axis (3D -> 2D) and build the Volume."""
    spacing, origin = list(spacing), list(origin)
    singles = [ax for ax, n in enumerate(array.shape) if n == 1]
    if array.ndim == 3 and len(singles) == 1:
        ax = singles[0]
        array = np.squeeze(array, axis=ax)
        del spacing[ax], origin[ax]
    if array.ndim not in (2, 3) or min(array.shape) < 2:
        raise DicerError(
            f"{path}: the image has shape {'x'.join(map(str, array.shape))} (x, y, z); dicer meshes 2D or 3D "
            "images with at least 2 voxels along each axis; give a 2D slice or a 3D volume"
        )
    return Volume(np.ascontiguousarray(array, dtype=dtype), tuple(spacing), tuple(origin))


def _from_sitk(image: sitk.Image, path, spacing_arg=None, own_spacing=True, nifti=False,
               dtype=np.float32) -> Volume:
    """Convert a SimpleITK image to a Volume ([z,y,x] -> [x,y,z], centre origin -> corner)."""
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
        spacing = _default_spacing(spacing_arg, array.shape, path)
    corner = [o - s / 2 for o, s in zip(origin, spacing)] if own_spacing else origin
    return _finish(array, spacing, corner, path, dtype=dtype)


def _final_ndim(shape) -> int:
    singles = sum(n == 1 for n in shape)
    return len(shape) - 1 if len(shape) == 3 and singles == 1 else len(shape)


def _default_spacing(spacing_arg, shape, path) -> list[float]:
    """Spacing for every axis of an array of ``shape`` from the user's value, else 1 mm.

    Accepts a number, one value per axis of ``shape``, or one per axis left after
    dropping a singleton axis (that axis then gets 1). A 2D image takes the first two
    of three values, so one ``image.spacing`` serves slice stacks and single slices.
    """
    ndim, final = len(shape), _final_ndim(shape)
    if spacing_arg is None:
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


# --- NIfTI completeness ------------------------------------------------------------------


def _check_nifti_complete(path: Path) -> None:
    """Raise DicerError when a NIfTI file holds fewer bytes than its header promises.

    ITK silently pads a truncated .nii or .nii.gz with zeros, so the header's data size
    (dims, bitpix, vox_offset) is compared with the file's (decompressed) length, and a
    gzip stream is read to its end-of-stream marker and CRC check.
    """
    gz = path.name.lower().endswith(".gz")
    opener = gzip.open if gz else open
    try:
        with opener(path, "rb") as f:
            head = f.read(540)
            total = len(head)
            while chunk := f.read(1 << 22):
                total += len(chunk)
    except (EOFError, OSError, gzip.BadGzipFile) as exc:
        raise DicerError(f"{path}: the file is truncated or corrupt ({exc}); copy or export it again") from None
    if len(head) < 348:
        raise DicerError(f"{path}: the file is too short for a NIfTI header; copy or export it again")
    for endian in "<>":
        (sizeof_hdr,) = struct.unpack(endian + "i", head[:4])
        if sizeof_hdr == 348:  # NIfTI-1
            dims = struct.unpack(endian + "8h", head[40:56])
            (bitpix,) = struct.unpack(endian + "h", head[72:74])
            (vox_offset,) = struct.unpack(endian + "f", head[108:112])
            break
        if sizeof_hdr == 540:  # NIfTI-2
            dims = struct.unpack(endian + "8q", head[16:80])
            (bitpix,) = struct.unpack(endian + "h", head[14:16])
            (vox_offset,) = struct.unpack(endian + "q", head[168:176])
            break
    else:
        return  # not a header we know; leave the judgement to ITK
    if not 1 <= dims[0] <= 7 or path.name.lower().endswith((".hdr", ".img")):
        return
    n = int(np.prod([max(int(d), 1) for d in dims[1 : dims[0] + 1]], dtype=np.int64))
    need = int(vox_offset) + n * max(int(bitpix), 8) // 8
    if total < need:
        raise DicerError(
            f"{path}: the file is truncated ({total} of {need} bytes); copy or export it again"
        )


# --- reading -----------------------------------------------------------------------


def _read_file(path: Path, spacing_arg, dtype=np.float32) -> Volume:
    suffix = _suffix(path)
    if suffix == ".npy":
        return _read_npy(path, spacing_arg, dtype)
    if suffix not in IMAGE_SUFFIXES:
        raise DicerError(f"{path}: unknown image format {suffix or '(no extension)'!r}; {_SUPPORTED}")
    if suffix in (".nii", ".nii.gz"):
        _check_nifti_complete(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        with _quiet_itk():
            reader.ReadImageInformation()
            if reader.GetNumberOfComponents() != 1:
                raise DicerError(
                    f"{path}: the image has {reader.GetNumberOfComponents()} components per voxel (colour or "
                    "vector data); dicer reads single-channel (greyscale) images: convert it to greyscale"
                )
            # ITK turns a negative header spacing into a flipped direction: catch it here
            if not all(sp > 0 for sp in reader.GetSpacing()) and suffix not in _TIFF + _PNG:
                raise DicerError(
                    f"{path}: the header has a zero or negative voxel spacing "
                    f"({', '.join(f'{sp:g}' for sp in reader.GetSpacing())}); fix the spacing in the header"
                )
            image = reader.Execute()
    except RuntimeError as exc:
        msg = _itk_message(exc)
        if "spacing" in msg.lower():
            raise DicerError(
                f"{path}: the header has a zero or negative voxel spacing ({msg}); fix the spacing in the header"
            ) from None
        raise DicerError(f"{path}: cannot read the image ({msg}); check that the file is complete and in a "
                         f"supported format ({_SUPPORTED})") from None
    # TIFF and PNG resolution tags are unreliable (dpi, not mm): use the given spacing
    own = suffix not in _TIFF + _PNG
    return _from_sitk(image, path, spacing_arg, own_spacing=own, nifti=suffix in (".nii", ".nii.gz"),
                      dtype=dtype)


def _read_npy(path: Path, spacing_arg, dtype) -> Volume:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise DicerError(f"{path}: cannot read the .npy array ({exc}); save it again with numpy.save") from None
    if array.dtype.kind not in "biuf":
        raise DicerError(f"{path}: the array has dtype {array.dtype}; save a numeric (integer or float) array")
    if array.ndim == 4 and array.shape[3] == 1:
        array = array[..., 0]
    if array.ndim not in (2, 3):
        raise DicerError(
            f"{path}: the array is {array.ndim}D; dicer reads 2D and 3D arrays indexed [x, y(, z)]: "
            "save one 2D or 3D array"
        )
    spacing = _default_spacing(spacing_arg, array.shape, path)
    return _finish(array, spacing, (0.0,) * array.ndim, path, dtype=dtype)


def _read_folder(folder: Path, spacing_arg) -> Volume:
    files = sorted((p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")),
                   key=lambda p: _natural_key(p.name))
    if not files:
        where = "holds only subfolders" if any(p.is_dir() for p in folder.iterdir()) else "is empty"
        raise DicerError(f"{folder}: the folder {where}; give the folder that directly holds the DICOM "
                         "series, TIFF or PNG slices")
    tiffs = [p for p in files if p.suffix.lower() in _TIFF]
    pngs = [p for p in files if p.suffix.lower() in _PNG]
    if len(tiffs) + len(pngs) < len(files):
        # other files: a DICOM series wins over stray previews (.png) beside it
        volume = _read_dicom_series(folder, required=not (tiffs or pngs))
        if volume is not None:
            return volume
    if tiffs and pngs:
        raise DicerError(f"{folder}: the folder mixes TIFF and PNG slices; keep one kind of slice per folder")
    return _read_slices(folder, tiffs or pngs, spacing_arg)


def _read_slices(folder: Path, files: list[Path], spacing_arg) -> Volume:
    """Stack 2D TIFF or PNG slices (already in natural name order) along z."""
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames([str(p) for p in files])
    try:
        with _quiet_itk():
            image = reader.Execute()
    except RuntimeError as exc:
        raise DicerError(f"{folder}: cannot stack the {len(files)} slices ({_itk_message(exc)}); every slice "
                         "must be a readable single-page greyscale image of the same size") from None
    if image.GetDimension() != 3 or (len(files) > 1 and image.GetSize()[2] != len(files)):
        raise DicerError(f"{folder}: the slices are not 2D images of one size; put single-page greyscale "
                         "slices of the same size in the folder")
    return _from_sitk(image, folder, spacing_arg, own_spacing=False)


def _read_dicom_series(folder: Path, required: bool = True) -> Volume | None:
    """Read the DICOM series with the most slices; None if there is none and not ``required``."""
    with _quiet_itk():
        try:
            series = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
        except RuntimeError:
            series = ()
        if not series and not required:
            return None
        if not series:
            raise DicerError(
                f"{folder}: the folder holds no DICOM series, TIFF or PNG slices; {_SUPPORTED}"
            )
        # the series with the most slices; ties go to the first series ID in sorted order
        candidates = [(len(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), sid)), sid)
                      for sid in sorted(series)]
        count, chosen = max(candidates, key=lambda c: c[0])  # max keeps the first of equal counts
        if len(series) > 1:
            # slice counts only: series and patient identifiers stay out of the log
            log.info("%s: %d DICOM series found (slices: %s); reading the one with the most slices (%d)",
                     folder.name, len(series), ", ".join(str(c) for c, _ in candidates), count)
        names = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), chosen)  # ordered by position
        reader = sitk.ImageSeriesReader()
        reader.SetFileNames(names)
        reader.SetOutputPixelType(sitk.sitkFloat32)  # keeps rescale slope/intercept (HU) exact
        try:
            image = reader.Execute()
        except RuntimeError as exc:
            raise DicerError(f"{folder}: cannot read the DICOM series ({_itk_message(exc)}); check that "
                             "every slice file is complete") from None
    return _from_sitk(image, folder)


def read_image(path: str | os.PathLike, spacing=None) -> Volume:
    """Read an intensity image (CT in HU, MR, ...) from a file or a folder.

    Parameters
    ----------
    path : str or path-like
        A file (.nii, .nii.gz, .nrrd, .mha/.mhd, .npy, .tif/.tiff, .png, .dcm) or a folder
        holding one DICOM series (the series with the most slices if several), TIFF
        slices or PNG slices (stacked along z in natural file-name order).
    spacing : None, float or sequence of float, optional
        Voxel size in mm (x, y[, z]) for inputs that carry none: .npy, TIFF and PNG.
        Ignored for the other formats, which keep their header spacing. Without it
        such inputs get 1 mm per axis and a logged warning.

    Returns
    -------
    Volume
        ``array`` float32 of shape (nx, ny[, nz]); DICOM values have the rescale slope
        and intercept applied (CT in HU). A multi-page TIFF is a 3D stack; a single
        page or a single slice gives a 2D Volume. ``.npy`` arrays are taken as
        indexed [x, y(, z)] with origin 0.

    Raises
    ------
    DicerError
        Missing path, unknown format, empty folder, unreadable or truncated file,
        colour/vector or 4D image, zero or negative spacing.
    """
    path = Path(path)
    if not path.exists():
        raise DicerError(f"{path}: no such file or folder; check the path (and the image column of the patient sheet)")
    if path.is_dir():
        return _read_folder(path, spacing)
    return _read_file(path, spacing)


def read_labels(path: str | os.PathLike) -> Volume:
    """Read a label volume (0 = background, 1..K = material classes).

    Parameters
    ----------
    path : str or path-like
        .nii, .nii.gz, .nrrd, .mha/.mhd or .npy (indexed [x, y(, z)], spacing 1 mm,
        origin 0).

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
    if path.is_dir() or not path.name.lower().endswith(LABEL_SUFFIXES):
        raise DicerError(f"{path}: label volumes must be one of {', '.join(LABEL_SUFFIXES)}; "
                         "convert the labels to NIfTI (.nii.gz)")
    volume = _read_file(path, 1.0 if path.suffix.lower() == ".npy" else None, dtype=None)
    array = volume.array
    if array.dtype.kind == "f":
        if not np.all(np.isfinite(array)) or not np.array_equal(array, np.round(array)):
            raise DicerError(f"{path}: the labels are not whole numbers; save integer class labels "
                             "(0 = background, 1..K = materials)")
    elif array.dtype.kind == "b":
        array = array.astype(np.uint8)
    lo, hi = (array.min(), array.max()) if array.size else (0, 0)
    if lo < 0:
        raise DicerError(f"{path}: the labels contain negative values (min {lo:g}); use 0 for background "
                         "and 1..K for materials")
    dtype = np.uint8 if hi < 256 else np.int16 if hi <= np.iinfo(np.int16).max else np.int32
    if hi > np.iinfo(np.int32).max:
        raise DicerError(f"{path}: label value {hi:g} is too large; number the classes 1..K")
    return Volume(array.astype(dtype, copy=False), volume.spacing, volume.origin)


# --- writing -----------------------------------------------------------------------


def _to_sitk(volume: Volume, array: np.ndarray) -> sitk.Image:
    image = sitk.GetImageFromArray(np.ascontiguousarray(array.T))  # [x,y,z] -> [z,y,x]
    spacing = [float(s) for s in volume.spacing]
    corner = [float(o) for o in volume.origin]
    image.SetSpacing(spacing)
    image.SetOrigin([c + s / 2 for c, s in zip(corner, spacing)])  # ITK: centre of voxel (0, 0, 0)
    return image


def _check_volume(volume: Volume, path: Path, what: str) -> None:
    if volume.array.ndim not in (2, 3):
        raise DicerError(f"{path}: cannot write a {volume.array.ndim}D {what}; dicer writes 2D and 3D volumes")
    if len(volume.spacing) != volume.array.ndim or len(volume.origin) != volume.array.ndim:
        raise DicerError(f"{path}: the {what} has {volume.array.ndim} axes but spacing/origin of "
                         f"{len(volume.spacing)}/{len(volume.origin)} values; give one per axis")
    _check_spacing(volume.spacing, path, f"of the {what}")


def _write(image: sitk.Image, path: Path, compress: bool) -> None:
    writer = sitk.ImageFileWriter()
    with atomic_path(path) as tmp:
        writer.SetFileName(str(tmp))
        writer.SetUseCompression(compress)
        try:
            with _quiet_itk():
                writer.Execute(image)
        except RuntimeError as exc:
            raise DicerError(f"{path}: cannot write the image ({_itk_message(exc)}); check the disk space "
                             "and the output folder") from None


def write_labels(volume: Volume, path: str | os.PathLike) -> None:
    """Write a label volume as NIfTI (.nii or .nii.gz), atomically.

    Stored as uint8 when the largest label is below 256, else uint16; spacing and the
    voxel-corner origin go into the header (as ITK's voxel-centre origin); nothing else
    (no metadata from the input image). Two writes of the same volume give identical bytes.

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
