"""Label volumes made elsewhere (3D Slicer, ITK-SNAP, FreeSurfer/SynthSeg, TotalSegmentator)
turned into dicer's materials 1..K by the config's ``labels`` section.

``resolve_materials`` decides which material each label value becomes, ``map_labels``
applies it to a volume, and ``write_mapped_labels`` writes the result with the input
file's own header, so its grid and affine stay exactly those of the input.
"""

from __future__ import annotations

import gzip
import logging
import struct
from pathlib import Path

import numpy as np

from dicer.brief import brief_names
from dicer.config import material_defaults, takes_settings, validate
from dicer.errors import DicerError
from dicer.image import MAX_LABEL, Volume
from dicer.parallel import contiguous

log = logging.getLogger("dicer")

#: properties of a material that has no ``materials`` entry of its name (the schema's item defaults)
DEFAULT_PROPERTIES = material_defaults()


def segment_map(segments: dict[int, str], source: str = "labels") -> dict[str, str]:
    """A ``labels.map`` from a segmentation's own segment names (3D Slicer's ``.seg.nrrd``):
    each name made a material name (letters without accents, digits and ``_``, a letter first,
    32 characters at most: "Left femur" -> ``Left_femur``; segments named apart that come out
    alike take their label value, ``Muskel_1``, which is logged), or {} when the names cannot
    name materials (alike but for case, a solver's set name, ``background``), which is logged.

    Parameters
    ----------
    segments : dict
        Label value -> segment name (:func:`dicer.io.images.segment_names`).
    source : str, optional
        The file's name, for messages.

    Returns
    -------
    dict
        ``{str(value): name}``, or {}.
    """
    import re
    import unicodedata

    # letters NFKD does not take apart (Ø, ß, Æ, Ł)
    spelled = str.maketrans({"ß": "ss", "Ø": "O", "ø": "o", "Æ": "AE", "æ": "ae", "Œ": "OE", "œ": "oe",
                             "Ł": "L", "ł": "l", "Đ": "D", "đ": "d", "Þ": "Th", "þ": "th"})
    names, texts = {}, {}
    for value, text in segments.items():
        plain = "".join(c for c in unicodedata.normalize("NFKD", text.translate(spelled))
                        if not unicodedata.combining(c))  # Ä -> A
        name = re.sub(r"[^A-Za-z0-9_]+", "_", plain).strip("_")
        if not name:
            continue
        names[str(value)] = (name if name[0].isalpha() else f"s_{name}")[:32]
        texts[str(value)] = " ".join(text.split())  # "Bone " and "Bone" are one segment name
    # segments named apart that come out alike (letters dropped, names cut at 32 characters)
    # stay apart: each name takes its smallest label value; segments of one name share it
    apart: dict[str, dict[str, int]] = {}  # name -> segment name -> its smallest label value
    shared: dict[str, list[str]] = {}  # a segment name -> its label values, where several
    for value in sorted(names, key=int):
        apart.setdefault(names[value], {}).setdefault(texts[value], int(value))
        shared.setdefault(texts[value], []).append(value)
    shared = {text: values for text, values in shared.items() if len(values) > 1}
    if shared:  # one material, with no interface between them: meant, or two tissues named alike
        log.warning("labels: segments of %s share a name and become one material: %s; give labels.map to keep them "
                    "apart", source, brief_names([f"{text!r} (values {', '.join(v)})" for text, v in shared.items()]))
    renamed = []
    for value, name in names.items():
        if len(apart[name]) > 1:
            tag = str(apart[name][texts[value]])
            names[value] = f"{name[:31 - len(tag)].rstrip('_')}_{tag}"
            renamed.append(f"{texts[value]!r} -> {names[value]}")
    if renamed:
        taken = {}
        for value, name in names.items():
            taken.setdefault(name, set()).add(texts[value])
        if any(len(t) > 1 for t in taken.values()):  # a new name another segment already had
            log.warning("labels: the segment names of %s do not name the materials (two come out alike even with "
                        "their label values); give labels.map to name them", source)
            return {}
        log.warning("labels: segments of %s named apart come out alike as material names, so each takes its "
                    "label value: %s; give labels.map to name them", source, brief_names(sorted(set(renamed))))
    if not names:
        return {}
    try:
        validate({"labels": {"map": names}}, source)
    except DicerError as exc:
        log.warning("labels: the segment names of %s do not name the materials (%s); give labels.map to name "
                    "them", source, str(exc).split("key 'labels.map': ", 1)[-1])
        return {}
    return names


def _schema_materials() -> list[dict]:
    """The ``materials`` section's default, completed as a loaded config completes it."""
    from dicer.config import load_config

    return load_config()["materials"]


@takes_settings("labels")
def resolve_materials(values, *, materials: list[dict], map: dict, drop: list,  # noqa: A002 (the key's name)
                      source: str = "labels") -> tuple[dict[int, int], list[dict]]:
    """Which material each label value becomes.

    The settings are keyword-only with no defaults here (``dicer.config.stage_kwargs(config,
    "labels")`` gives them); a configuration may be given as the second argument instead,
    or settings left out (the schema's defaults fill them, :func:`dicer.config.takes_settings`).

    Parameters
    ----------
    values : iterable of int
        The distinct label values of the volume (0, background, may be among them).
    materials : list of dict
        The ``materials`` section: properties, found by name.
    map, drop
        The ``labels:`` section: label value (a string) -> material name, and the values
        made background.
    source : str
        The label file's name, for messages.

    Returns
    -------
    lut : dict
        Label value -> material number 1..K, or 0 for background and dropped values.
    materials : list of dict
        The K materials in number order (name and properties), a valid ``materials``
        config section. Materials are numbered in the order of their smallest label
        value, so with no map material k is the k-th non-zero label value.

    Raises
    ------
    DicerError
        No material left (only background and dropped values), or names that would
        clash in an export.
    """
    names = {int(k): v for k, v in map.items()}
    drop = set(drop)
    lut: dict[int, int] = {}
    number: dict[str, int] = {}
    automatic: dict[str, int] = {}  # label_<v> of the values labels.map leaves unnamed
    for value in sorted(int(v) for v in values):
        if value == 0 or value in drop:
            lut[value] = 0
            continue
        name = names.get(value, f"label_{value}")
        if value not in names:
            automatic[name] = value
        lut[value] = number.setdefault(name, len(number) + 1)
    taken = sorted((v, n) for v, n in names.items() if n in automatic and lut.get(v, 0))
    if taken:  # two values would become one material without anybody asking for it
        value, name = taken[0]
        raise DicerError(f"{source}: labels.map names value {value} {name!r}, the name value {automatic[name]} "
                         f"takes when it has no entry, so the two would become one material; map value "
                         f"{automatic[name]} too (to {name!r} to join them), or choose another name")
    if not number:
        if not any(lut):  # nothing but 0: no labels.drop could have left something
            raise DicerError(f"{source}: every voxel is 0 (background): there is nothing to mesh; give the "
                             "label volume of the part (labelled voxels 1 or more)")
        raise DicerError(f"{source}: no labelled voxels are left (values found: "
                         f"{', '.join(str(v) for v in sorted(lut))}, dropped: {sorted(drop)}); "
                         "check labels.drop in the config")
    given = {m["name"]: m for m in materials}
    # the default materials (a scan's soft tissue and bone) are no entries the user wrote
    written = materials != _schema_materials()
    materials, defaulted = [], []
    for name in number:
        if name in given:
            materials.append({**DEFAULT_PROPERTIES, **given[name]})
        else:
            materials.append({"name": name, **DEFAULT_PROPERTIES})
            defaulted.append(name)
    if not names:
        log.info("labels: no labels.map in the config: each of the %d label value(s) is its own material "
                 "(label_<value>, numbered 1..%d in increasing value order)", len(number), len(number))
    present = set(lut)
    absent = sorted(set(names) - present)
    unnamed = sorted(v for v in present if v and v not in names and v not in drop)
    if absent and unnamed:  # a typo in a label value: the meant one falls to default properties
        log.warning("labels: labels.map names value(s) %s that the volume does not hold, while value(s) %s have "
                    "no labels.map entry (materials %s, default properties); check the label values",
                    brief_names(absent), brief_names(unnamed),
                    brief_names([f"label_{v}" for v in unnamed]))
    not_dropped = sorted(set(drop) - present)
    if not_dropped and unnamed:  # a typo in a value to drop: the meant one is meshed, with default properties
        log.warning("labels: labels.drop names value(s) %s that the volume does not hold, while value(s) %s are "
                    "meshed without a labels.map entry (materials %s, default properties); check the label values",
                    brief_names(not_dropped), brief_names(unnamed), brief_names([f"label_{v}" for v in unnamed]))
    mapped = [n for n in defaulted if n in set(names.values())]
    unused = [m["name"] for m in given.values() if m["name"] not in number] if written else []
    spelled = {n.upper(): n for n in unused}
    alike = [(n, spelled[n.upper()]) for n in mapped if n.upper() in spelled]
    if alike:  # meant as one material: its properties would fall to the defaults without a word but a warning
        name, entry = alike[0]
        raise DicerError(f"{source}: labels.map names {name!r} and the materials entry {entry!r}: the names differ "
                         "only in case, and solvers read names in upper case, so the entry was meant for the "
                         "material; spell them alike")
    if not names and unused:  # the entries were meant for the label values, in order (as a stage's mesh takes them)
        kept = sorted(v for v in lut if lut[v])
        hint = ", ".join(f"{v}: {m['name']}" for v, m in zip(kept, given.values()))
        log.warning("labels: the config's materials %s are used by no label: without labels.map each label value is "
                    "its own material (label_<value>, default properties: E %g MPa); name the values with "
                    "labels.map, e.g. labels.map: {%s}", brief_names(unused), DEFAULT_PROPERTIES["youngs_modulus"],
                    hint)
    elif mapped and unused:  # a name of labels.map and a materials entry that were meant to be one
        log.warning("labels: labels.map names %s, which no materials entry has (default properties: E %g MPa), "
                    "while the materials entries %s are used by no label; check the spelling of the names",
                    brief_names(mapped), DEFAULT_PROPERTIES["youngs_modulus"], brief_names(unused))
    elif defaulted:
        # beside materials the user gave properties, one left out is likelier forgotten than meant
        level = logging.WARNING if written and len(defaulted) < len(number) else logging.INFO
        log.log(level, "labels: no materials entry for %s: default properties (E %g MPa, nu %g, density %g t/mm^3); "
                 "add materials entries of these names to set them", brief_names(defaulted),
                 DEFAULT_PROPERTIES["youngs_modulus"], DEFAULT_PROPERTIES["poissons_ratio"],
                 DEFAULT_PROPERTIES["density"])
    if len(materials) > MAX_LABEL:
        raise DicerError(f"{source}: {len(materials)} materials, more than the {MAX_LABEL} a label volume holds; "
                         "merge labels with labels.map")
    try:
        validate({"materials": materials, "labels": {"map": map, "drop": sorted(drop)}}, source)
    except DicerError as exc:
        raise DicerError(f"{exc} (materials made from the label values by labels.map)") from None
    return lut, materials


_MANY_VALUES = 100
"""Distinct values above which a label volume is checked for looking like an image of intensities."""

_SHARED_NEIGHBOURS = 0.2
"""Share of the face-neighbouring voxel pairs in the foreground (either voxel labelled) with one
value, below which such a volume is refused: a label volume's regions make many pairs alike
(atlases of 130-1000 parcels of 20 voxels and more: 0.49-0.74), an image's noise makes them
differ (an MR head given as labels: 0.001-0.004)."""


def _refuse_intensities(array: np.ndarray, distinct: int, source: str) -> None:
    """Raise DicerError when ``array`` (many distinct values) looks like grey values, not labels."""
    alike = pairs = 0
    for axis in range(array.ndim):
        if array.shape[axis] > 1:  # slabs of 64 planes: no copy of the whole volume
            for part in np.array_split(np.arange(array.shape[axis] - 1), max(1, array.shape[axis] // 64)):
                lo = np.take(array, part, axis=axis)
                hi = np.take(array, part + 1, axis=axis)
                some = (lo != 0) | (hi != 0)
                alike += np.count_nonzero((lo == hi) & some)
                pairs += np.count_nonzero(some)
    if pairs and alike < _SHARED_NEIGHBOURS * pairs:
        raise DicerError(f"{source}: {distinct} distinct values, and only {100 * alike / pairs:.1f} % of neighbouring "
                         "voxels in the foreground share one (in a label volume many do): this looks like an image "
                         "of grey values, not labels; give it as the IMAGE of dicer run (or dicer segment) to "
                         "segment it")


@takes_settings("labels")
def map_labels(volume: Volume, *, materials: list[dict], map: dict, drop: list,  # noqa: A002 (the key's name)
               source: str = "labels") -> tuple[Volume, list[dict], dict]:
    """The volume with its label values replaced by material numbers 1..K (0: background).

    Parameters
    ----------
    volume : Volume
        Integer labels.
    materials, map, drop
        The ``materials`` and ``labels:`` sections (see :func:`resolve_materials`).
    source : str, optional
        The label file's name, for messages.

    Returns
    -------
    mapped : Volume
        Same grid, origin and direction as ``volume``; uint8 or uint16 values.
    materials : list of dict
        The materials section for the mapped volume (see :func:`resolve_materials`).
    info : dict
        ``values``: label value -> material name or ``background``, and voxel counts
        per material.
    """
    array = volume.array
    values, inverse = np.unique(array, return_inverse=True)
    if values.size > _MANY_VALUES:
        _refuse_intensities(array, values.size, source)
    lut, materials = resolve_materials.__wrapped__(values.tolist(), materials=materials, map=map, drop=drop,
                                                   source=source)
    table = np.array([lut[int(v)] for v in values], dtype=np.uint8 if len(materials) < 256 else np.uint16)
    mapped = table[inverse].reshape(array.shape)
    counts = np.bincount(mapped.ravel(), minlength=len(materials) + 1)
    info = {
        "values": {str(int(v)): (materials[lut[int(v)] - 1]["name"] if lut[int(v)] else "background")
                   for v in values},
        "voxels": {m["name"]: int(counts[i + 1]) for i, m in enumerate(materials)},
    }
    return Volume(mapped, volume.spacing, volume.origin, volume.direction), materials, info


# --- writing with the input's header ---------------------------------------------------------

# NIfTI-1 datatype codes of the two label types written
_NIFTI_TYPES = {np.dtype(np.uint8): (2, 8), np.dtype(np.uint16): (512, 16)}


def _nifti1_header(path: Path) -> tuple[bytes, str] | None:
    """The 348-byte header of a single-file NIfTI-1 (.nii, .nii.gz) and its byte order, or None."""
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    try:
        with opener(path, "rb") as f:
            head = f.read(352)
    except OSError:
        return None
    if len(head) < 348:
        return None
    for endian in "<>":
        if struct.unpack(endian + "i", head[:4])[0] == 348 and head[344:347] == b"n+1":
            return head[:348], endian
    return None


_NIFTI_TEXT = ((4, 10), (14, 18), (148, 80), (228, 24), (328, 16))
"""(offset, length) of the NIfTI-1 header's free-text fields: data_type, db_name, descrip,
aux_file, intent_name."""

_NIFTI_FREE_NUMBERS = ((32, 6), (56, 12), (74, 2), (120, 3), (132, 16))
"""(offset, length) of the NIfTI-1 header's numbers that say nothing of the grid: extents and
session_error, intent_p1..3, slice_start, slice_end and slice_code, slice_duration, toffset,
glmax and glmin. Free to hold anything (a record number, a birth date), they are zeroed."""


def _write_nifti_like(header: bytes, endian: str, array: np.ndarray, path: Path) -> None:
    """Write ``array`` ([x, y, z]) as a .nii.gz with ``header``: the data type, the intensity
    scaling and the display range change, and the free-text fields and the numbers free of
    meaning for a label volume are blanked; dims, pixdim, qform, sform and codes stay the
    input's, byte for byte, along the volume's axes (beyond them a 0 or 1 stays, other numbers
    become ITK's 1 voxel of size 0)."""
    from dicer.io.atomic import atomic_path

    head = bytearray(header)
    # stored as write_labels stores them: uint8, or uint16 above 255 (the volumes read from
    # files come as int16 above 255, and label values are checked to lie in 0..MAX_LABEL)
    top = int(array.max(initial=0))
    if int(array.min(initial=0)) < 0 or top > MAX_LABEL:
        raise DicerError(f"{path}: labels range {int(array.min(initial=0))}..{top}; they must lie in 0..{MAX_LABEL}")
    array = array.astype(np.uint8 if top < 256 else np.uint16, copy=False)
    datatype, bitpix = _NIFTI_TYPES[array.dtype]
    struct.pack_into(endian + "2h", head, 70, datatype, bitpix)
    struct.pack_into(endian + "f", head, 108, 352.0)  # vox_offset: data right after the header
    struct.pack_into(endian + "2f", head, 112, 1.0, 0.0)  # scl_slope, scl_inter: the values as stored
    struct.pack_into(endian + "2f", head, 124, float(array.max(initial=0)), 0.0)  # cal_max, cal_min
    struct.pack_into(endian + "h", head, 68, 0)  # intent_code: plain values, whatever the input's was
    # free text (data_type, db_name, descrip, aux_file, intent_name) may hold a patient's name
    # or record number: none of it is passed on
    for start, length in _NIFTI_TEXT + _NIFTI_FREE_NUMBERS:
        head[start:start + length] = bytes(length)
    # the axes beyond the volume's (a time step, a fifth axis): free to hold a date, a record number;
    # the 0 or 1 that ITK and nibabel write there stays, anything else becomes ITK's
    ndim = min(max(struct.unpack_from(endian + "h", head, 40)[0], 1), 7)
    for axis in range(ndim + 1, 8):
        if struct.unpack_from(endian + "h", head, 40 + 2 * axis)[0] not in (0, 1):
            struct.pack_into(endian + "h", head, 40 + 2 * axis, 1)  # dim: one voxel along it
        if struct.unpack_from(endian + "f", head, 76 + 4 * axis)[0] not in (0.0, 1.0):
            struct.pack_into(endian + "f", head, 76 + 4 * axis, 0.0)  # pixdim
    data = contiguous(array.T, array.dtype.newbyteorder(endian))  # x fastest
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, filename="",
                                                   compresslevel=6) as f:
            # mtime 0 and no file name: the same bytes on every rerun; level 6, not gzip's 9:
            # a 256^3 label volume in 0.07 s instead of 0.5 s, 156 KB instead of 130 KB
            f.write(bytes(head) + b"\0\0\0\0")
            f.write(data)
        from dicer.io.images import read_labels

        # the source's header was judged (and any warning about it given) when it was read
        images_log = logging.getLogger("dicer.io.images")
        level = images_log.level
        images_log.setLevel(logging.ERROR)
        try:
            back = read_labels(tmp)
        finally:
            images_log.setLevel(level)
        # a single slice reads back as a 2D image
        if back.array.size != array.size or not np.array_equal(back.array, array.reshape(back.array.shape)):
            raise DicerError(f"{path}: read-back check failed: the file does not hold the labels written; "
                             "check the disk and write again")


def _same_placement(volume: Volume, source: Path, axes: tuple[int, ...] | None = None) -> bool:
    """Whether ``source``'s header places its voxels as ``volume`` does (not so when
    image.spacing replaced a broken header spacing): only then may it lend its header.
    ``axes``: the source's axes that ``volume`` keeps (a single slice read as a 2D image,
    its direction dropped); default all."""
    from dicer.io.images import image_header

    reader = image_header(source)
    if reader is None:
        return False
    n = volume.array.ndim
    kept = list(range(n)) if axes is None else list(axes)
    spacing = np.asarray(reader.GetSpacing(), float)[kept]
    centre = np.asarray(volume.origin, float) + np.asarray(volume.spacing, float) / 2
    # NIfTI keeps spacing and offsets in float32: compare at that precision
    same = (np.allclose(spacing, volume.spacing, rtol=1e-6, atol=0)
            and np.allclose(np.asarray(reader.GetOrigin(), float)[kept], centre, rtol=1e-6, atol=1e-5))
    if axes is not None:
        return bool(same)
    direction = np.eye(n).ravel() if volume.direction is None else np.asarray(volume.direction, float)
    header_direction = np.asarray(reader.GetDirection(), float).reshape(reader.GetDimension(), -1)[:n, :n]
    return bool(same and np.allclose(header_direction.ravel(), direction, atol=1e-6))


def write_mapped_labels(volume: Volume, source: str | Path, path: str | Path) -> None:
    """Write a label volume on the grid of the image or label file it came from.

    A single-file NIfTI-1 input (the usual output of Slicer, ITK-SNAP, FreeSurfer and
    TotalSegmentator) lends its own header, so the written file has exactly the input's
    grid, qform and sform (and their codes): ITK would write the affine again from its
    double-precision direction, which can move the float32 sform by a unit in the last
    place (about 1e-7 mm per mm). Any other input goes through
    :func:`dicer.io.images.write_labels`, which keeps spacing, origin and direction.
    Used for every label file on its input's grid (labels, segment, fix).

    Parameters
    ----------
    volume : Volume
        The labels to write.
    source : str or Path
        The image or label file whose grid they are on.
    path : str or Path
        The file written.
    """
    from dicer.io.images import write_labels

    source, path = Path(source), Path(path)
    found = _nifti1_header(source) if source.name.lower().endswith((".nii", ".nii.gz")) else None
    dims = struct.unpack(found[1] + "8h", found[0][40:56]) if found else None
    grid = tuple(dims[1:4]) if found and dims[0] in (3, 4) and (dims[0] == 3 or dims[4] == 1) else None
    # a single slice of a 3D file is read as a 2D image: written back on the file's 3D grid
    kept = tuple(a for a in range(3) if grid[a] != 1) if grid and volume.array.ndim == 2 else None
    if (found and path.name.lower().endswith(".nii.gz") and grid is not None
            and ((volume.array.ndim == 3 and grid == volume.array.shape and _same_placement(volume, source))
                 or (kept is not None and len(kept) == 2 and tuple(grid[a] for a in kept) == volume.array.shape
                     and _same_placement(volume, source, kept)))):
        head = bytearray(found[0])
        struct.pack_into(found[1] + "8h", head, 40, 3, *grid, 1, 1, 1, 1)
        _write_nifti_like(bytes(head), found[1], volume.array.reshape(grid), path)
        return
    write_labels(volume, path)
