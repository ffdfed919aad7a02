"""The cohort sheet (``config/patients.tsv``): one row per patient, read and checked.

Tab-separated UTF-8 text (a byte-order mark is allowed), a header line naming the columns,
then a row per patient; blank rows are skipped. Every problem is a :class:`DicerError`
naming the sheet, the line and the fix, found before any job runs: a cell that a quote
opens and no quote closes (it would swallow the rows after it), more cells than columns
(a tab inside a cell: the rest would be dropped), a patient twice (also when the two
differ only in case: their result folders are one on a case-insensitive disk), a patient
code the workflow uses for its own files, an override of the workflow's own settings or
of one key twice.
"""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path

from dicer.errors import DicerError

RESERVED_PATIENTS = ("phantoms", "logs", "benchmarks", "cohort.html", "cohort.tsv", "cohort.log")
"""Names the workflow gives its own files and folders beside the patients' folders."""


def read_sheet(path: str | os.PathLike, schema: dict) -> list[tuple[int, dict[str, str]]]:
    """The rows of a cohort sheet with the line each starts on, every row checked.

    Parameters
    ----------
    path : str or os.PathLike
        The sheet.
    schema : dict
        The JSON Schema of one row (``workflow/schemas/patients.schema.yaml``).

    Returns
    -------
    list of (int, dict of str to str)
        The line number (1 = the header) and the row, its cells stripped of spaces and
        missing cells empty.

    Raises
    ------
    DicerError
        The first problem found, naming the line.
    """
    path = Path(path)
    if not path.exists():
        raise DicerError(f"{path}: cohort sheet not found; set workflow.patients in the config")
    if path.is_dir():
        raise DicerError(f"{path}: is a folder; set workflow.patients to the cohort sheet, a tab-separated file")
    try:
        text = path.read_bytes().decode("utf-8-sig")  # a byte-order mark (spreadsheet exports) is not text
    except UnicodeDecodeError as exc:
        raise DicerError(f"{path}: not UTF-8 text (byte {exc.start + 1}); save the cohort sheet as UTF-8") from None
    rows = _records(path, text)
    if not rows:
        raise DicerError(f"{path}: the sheet is empty; write a header line (patient, image or labels, overrides, "
                         "separated by tabs) and a row per patient")
    (_, header), rows = rows[0], rows[1:]
    names = [name.strip() for name in header]
    twice = sorted({n for n in names if n and names.count(n) > 1})
    if twice:
        raise DicerError(f"{path}, line 1: column {twice[0]!r} appears twice in the header; keep one")
    known = set(schema["properties"])
    unknown = [n for n in names if n and n not in known]
    if unknown:  # the header's fault, not each row's
        comma = " (the sheet's columns are separated by tabs, not commas)" if any("," in n for n in unknown) else ""
        raise DicerError(f"{path}, line 1: unknown column {', '.join(map(repr, unknown))}{comma}; the columns are "
                         f"{', '.join(schema['properties'])}")
    if not rows:
        raise DicerError(f"{path}: the sheet lists no patient; add a row per patient below the header")
    checked, seen = [], {}
    for number, cells in rows:
        if len(cells) > len(names) and any(c.strip() for c in cells[len(names):]):
            raise DicerError(f"{path}, line {number}: {len(cells)} cells where the header names {len(names)} columns "
                             "(a tab inside a cell?); separate the overrides with ';' and give each column once")
        row = {n: c.strip() for n, c in zip(names, cells) if n}
        row.update({n: "" for n in names if n and n not in row})
        where = f"{path}, line {number}"
        _check_row(row, schema, where)
        key = row["patient"].casefold()
        if key in seen:
            same = "appears twice" if seen[key][1] == row["patient"] else (
                f"and {seen[key][1]!r} (line {seen[key][0]}) differ only in case, and their result folders are one "
                "on a case-insensitive disk")
            raise DicerError(f"{where}: patient {row['patient']!r} {same}; give each patient one row and one code")
        seen[key] = (number, row["patient"])
        checked.append((number, row))
    return checked


def _records(path: Path, text: str) -> list[tuple[int, list[str]]]:
    """The sheet's non-blank records with the line each starts on."""
    reader = csv.reader(io.StringIO(text, newline=""), delimiter="\t")
    records, start = [], 1
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            return records
        except csv.Error:  # a field over csv's size limit: an unclosed quote took in the rest of the file
            cells = ['"\n']
        if any("\n" in c or "\r" in c for c in cells):
            raise DicerError(f"{path}, line {start}: a quote (\") opens a cell that no quote on that line closes, so "
                             "the rows after it would be read as part of it; remove the quote or close it")
        if any(c.strip() for c in cells):
            records.append((start, cells))
        start = reader.line_num + 1


_SEGMENTATION_ONLY = ("segment.method", "segment.thresholds", "segment.ranges", "segment.bins")
"""Settings of the threshold search, which a label volume made elsewhere skips (the segment
section's morphology and priority still serve its downsampling)."""


_SCAN_ONLY = ("smooth.surface_from_image", "smooth.image_sigma", "smooth.fit_to_scan")
"""Smoothing settings that act only on a scan, which a label volume's smoothing has not."""


def _unread_override(key: str, label_volume: bool) -> str | None:
    """Why no stage of the row's patient reads override ``key``, or None when one does."""
    if not label_volume and (key == "labels" or key.startswith("labels.")):
        return "is read only for a label volume (the labels column), and this row's image is segmented"
    if label_volume and any(key == k or key.startswith(k + ".") for k in _SEGMENTATION_ONLY):
        return "sets the threshold search, which this row's label volume (the labels column) skips"
    if label_volume and any(key == k or key.startswith(k + ".") for k in _SCAN_ONLY):
        return "acts on the scan a segmented row's smoothing is given, and this row's label volume has none"
    return None


_LABEL_MORPHOLOGY = ("segment.opening_radius", "segment.closing_radius", "segment.keep", "segment.min_component_size")
"""The segment section's morphology, which a label volume's downsampling applies again only
with downsample.morphology: true."""


def _inert(key: str, config: dict) -> str | None:
    """Why ``key`` acts on nothing under ``config``'s other settings (another method's, a
    switch that is off), or None (a patient's downsample.factor under the cohort's
    voxel_size, or merge.passes under templates, changed nothing without a word)."""
    def under(prefix: str) -> bool:
        return key == prefix or key.startswith(prefix + ".")

    smooth, merge, segment, export = config["smooth"], config["merge"], config["segment"], config["export"]
    if key == "downsample.factor" and config["downsample"]["voxel_size"] is not None:
        return "is replaced by downsample.voxel_size, which is set"
    if under("smooth.coefficients") and smooth["coefficient"] is not None:
        return "is replaced by smooth.coefficient, which is set (one coefficient for every node class)"
    if key == "smooth.pillow_thickness" and not smooth["pillow"]:
        return "sets the pillow layer, and smooth.pillow is off"
    if under("merge.templates") and merge["method"] != "templates":
        return f"acts with merge.method: templates, and merge.method is {merge['method']}"
    planes_only = ("passes", "min_thickness", "granularity", "min_scaled_jacobian", "rim_moves")
    if merge["method"] == "templates" and any(under(f"merge.{k}") for k in planes_only):
        return "acts with merge.method: planes, and merge.method is templates"
    if under("segment.thresholds") and segment["method"] != "manual":
        return f"acts with segment.method: manual, and segment.method is {segment['method']}"
    if under("segment.ranges") and segment["method"] != "shape_connectivity":
        return f"acts with segment.method: shape_connectivity, and segment.method is {segment['method']}"
    if key == "export.midside_nodes" and export["order"] == 1:
        return "places the mid-edge nodes of export.order 2, and export.order is 1"
    if key == "export.febio_material" and "feb" not in config["workflow"]["exports"]:
        return "acts on .feb models, and workflow.exports names no feb"
    return None


def unknown_priorities(config: dict) -> str | None:
    """What ``fix.priority`` or ``segment.priority`` of a segmented scan's ``config`` names
    that its materials do not hold (found only when the fix or segment stage ran, a patient's
    earlier stages done), or None."""
    from dicer.config import unknown_materials

    names = [m["name"] for m in config["materials"]]
    return (unknown_materials(names, config["segment"]["priority"], "segment.priority")
            or unknown_materials(names, config["fix"]["priority"], "fix.priority"))


def unread_settings(items, config: dict, label_volume: bool) -> list[tuple[str, str]]:
    """The settings of ``items`` (``KEY=VALUE`` overrides or ``--set`` items) that no stage reads
    under ``config``, each with why: the downsampling's own settings act only with a
    downsample.factor other than 1 or a voxel_size; a label volume's morphology and vote
    (segment.priority orders it, and breaks a plurality's ties) only when it is downsampled, its
    morphology only with downsample.morphology: true (a floating part "dropped" by
    segment.keep=largest stayed without a word).

    Parameters
    ----------
    items : iterable of str
    config : dict
        Loaded (a label volume's by :func:`dicer.config.for_label_volume`).
    label_volume : bool
        A label volume made elsewhere, not a segmented scan.

    Returns
    -------
    list of (key, reason)
        In the items' order, a leaf each.
    """
    from dicer.config import downsample_applies, parse_set

    downsampled, morphology = downsample_applies(config), config["downsample"]["morphology"]
    found = []
    for item in items:
        for key in sorted(_leaves(parse_set(item.strip()))):
            why = _unread_override(key, label_volume) or _inert(key, config)
            if why:
                found.append((key, why))
                continue
            in_downsample = key.startswith("downsample.") and key not in ("downsample.factor", "downsample.voxel_size")
            serves_it = label_volume and (key in _LABEL_MORPHOLOGY or key == "segment.priority")
            if not downsampled and (in_downsample or serves_it):
                found.append((key, "acts when the labels are downsampled, and these are not (downsample.factor 1, "
                                   "no downsample.voxel_size)"))
            elif downsampled and label_volume and key in _LABEL_MORPHOLOGY and not morphology:
                found.append((key, "sets the morphology a label volume's downsampling applies only with "
                                   "downsample.morphology: true"))
    return found


def _check_row(row: dict, schema: dict, where: str) -> None:
    """One row against the schema and the rules a schema cannot say, naming the column."""
    import jsonschema

    errors = sorted(jsonschema.Draft202012Validator(schema).iter_errors(row), key=lambda e: list(e.path))
    if errors:
        err = errors[0]
        if err.validator == "additionalProperties":
            extra = sorted(set(row) - set(schema["properties"]))
            raise DicerError(f"{where}: unknown column {', '.join(map(repr, extra))}; the columns are "
                             f"{', '.join(schema['properties'])}")
        if err.validator == "required":
            raise DicerError(f"{where}: {err.message}; every row needs a patient code")
        column = ".".join(map(str, err.path)) or "row"
        if column == "patient" and err.validator == "pattern":  # the regular expression tells a user little
            raise DicerError(f"{where}: column 'patient': {err.instance!r} is not a patient code: use letters, "
                             "digits, '_', '.' and '-', starting with a letter or digit (no spaces, slashes or "
                             "invisible characters)")
        raise DicerError(f"{where}: column {column!r}: {err.message}")
    if row["patient"].casefold() in RESERVED_PATIENTS:
        raise DicerError(f"{where}: patient code {row['patient']!r} is a name the workflow gives its own files "
                         f"({', '.join(RESERVED_PATIENTS)}); choose another code")
    if bool(row.get("image")) == bool(row.get("labels")):
        raise DicerError(f"{where}: patient {row['patient']!r}: give either an image or a labels file (a label "
                         "volume to mesh), not both and not neither")
    glued = next((m for m in re.finditer(r",\s*([A-Za-z_]\w*(?:\.\w+)*)\s*=", row.get("overrides", ""))
                  if "." in m.group(1) or m.group(1) in _config_sections()), None)
    if glued:  # "downsample.factor=2,segment.keep=largest": the second became part of the first's value
        raise DicerError(f"{where}: patient {row['patient']!r}: overrides are separated by ';', not ',' (before "
                         f"{glued.group(1)!r}); write KEY=VALUE;KEY=VALUE")
    keys = [item.split("=", 1)[0].strip() for item in row.get("overrides", "").split(";") if item.strip()]
    leaves_of = _override_leaves(row.get("overrides", ""))
    clash = _sets_one_key_twice(leaves_of)
    if clash:  # a section and one of its keys: the later value would be dropped unsaid
        raise DicerError(f"{where}: patient {row['patient']!r}: override {clash[0]!r} and {clash[1]!r} both set "
                         f"{clash[2]}; keep one")
    for key in keys:
        if key == "workflow" or key.startswith("workflow."):
            raise DicerError(f"{where}: patient {row['patient']!r}: override {key!r}: the workflow settings are the "
                             "whole cohort's; set them in the config, not per patient")
        if keys.count(key) > 1:
            raise DicerError(f"{where}: patient {row['patient']!r}: override {key!r} is given twice; keep one")
    for key, leaves in leaves_of.items():
        # each value it sets: a section given whole (smooth={fit_to_scan: false}) by its keys
        for leaf in sorted(leaves or {key}):
            unread = _unread_override(leaf, bool(row.get("labels")))
            if unread:
                what = f"override {key!r}" if leaf == key else f"override {key!r} sets {leaf!r}, which"
                raise DicerError(f"{where}: patient {row['patient']!r}: {what} {unread}, so it would change "
                                 "nothing: remove it, or move the file to the other column")


def _leaves(tree, prefix: str = "") -> set[str]:
    """The dotted names of the values a nested dict sets."""
    if not isinstance(tree, dict) or not tree:
        return {prefix}
    return set().union(*(_leaves(v, f"{prefix}.{k}" if prefix else str(k)) for k, v in tree.items()))


def _override_leaves(overrides: str) -> dict[str, set[str] | None]:
    """Each override's key -> the dotted keys of the values it sets (a section given whole
    sets several), None for one that does not parse (its own fault is said where the row's
    config is read)."""
    from dicer.config import parse_set

    items = {}
    for item in overrides.split(";"):
        if item.strip():
            key = item.split("=", 1)[0].strip()
            try:
                items.setdefault(key, _leaves(parse_set(item.strip())))
            except DicerError:
                items.setdefault(key, None)
    return items


def _sets_one_key_twice(items: dict[str, set[str] | None]) -> tuple[str, str, str] | None:
    """(a section's override, an override of a key in it, the key both set) when a row's
    overrides (:func:`_override_leaves`) set one key two ways (``downsample={factor: 2}`` and
    ``downsample.factor=3``); else None."""
    if None in items.values():
        return None
    for key, leaves in items.items():
        for other in (k for k in items if k.startswith(key + ".")):
            both = sorted(leaf for leaf in leaves if leaf == other or leaf.startswith(other + ".")
                          or other.startswith(leaf + "."))
            if both:
                return key, other, both[0]
    return None


def beside_sheet(path: str | os.PathLike, sheet: str | os.PathLike) -> Path | None:
    """The file a relative input path of the sheet names from the sheet's folder, when
    that is another file than the one it names from the working folder (the workflow's
    paths are taken from the working folder): for a hint or a warning; else None.

    Parameters
    ----------
    path : str or os.PathLike
        The image or labels path as the sheet gives it.
    sheet : str or os.PathLike
        The sheet.

    Returns
    -------
    pathlib.Path or None
    """
    here, beside = Path(path), Path(sheet).parent / path
    if here.is_absolute() or not beside.exists():
        return None
    if here.exists() and os.path.samefile(here, beside):
        return None
    return beside


def scan_files(path: str | os.PathLike) -> list[Path]:
    """The files that hold a scan or label volume: a folder's files (a DICOM series, a TIFF
    stack), or the file and the data file its detached header names (MetaImage
    ``ElementDataFile``, NRRD ``data file``, Analyze ``.img``) — not other files that share its
    name's stem (``ct.v2.nii.gz`` beside ``ct.v1.nii.gz``).

    Parameters
    ----------
    path : str or os.PathLike
        The image or labels path of a sheet's row.

    Returns
    -------
    list of Path
        Sorted; those that exist.
    """
    from dicer.io.images import header_data_file

    path = Path(path)
    if path.is_dir():
        return sorted(f for f in path.rglob("*") if f.is_file())
    return sorted(f for f in {path, header_data_file(path)} if f is not None and f.is_file())


def _config_sections() -> set[str]:
    """The configuration's top-level sections (an override glued to another by a comma names one)."""
    from dicer.config import schema

    return set(schema()["properties"])
