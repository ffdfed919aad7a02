"""Segmentation: image intensities -> material labels 0..K (section 2.1 of the paper).

Global thresholds split the image into the K configured material classes (ordered
by increasing intensity; label 0 is background), then opening by reconstruction,
closing and optional component filters clean each class (see
:mod:`dicer.segment.morphology` for the exact rule on nested classes).
"""

from __future__ import annotations

import json
import time

import numpy as np

from dicer.config import section_defaults, takes_settings
from dicer.errors import DicerError
from dicer.image import Volume, count_labels
from dicer.segment.morphology import axis_radii, clean_labels
from dicer.segment.thresholds import (
    check_ranges,
    check_thresholds,
    classify,
    histogram_values,
    multiotsu_thresholds,
    otsu_thresholds,
    shape_connectivity_thresholds,
    thresholds_in_a_mode,
    value_range,
)

__all__ = ["segment", "class_priority", "morphology_options", "label_counts"]

NO_AIR_HU = -500.0
"""A CT in HU holds air (about -1000) around the body; an image whose lowest value lies above
this is an MR, a rescaled image or one cropped inside the body."""

WHOLE_BOX = 0.01
"""A model whose image holds less background than this share fills its box (warned)."""

OPENED_AWAY = 0.1
"""Share of a class's thresholded voxels whose removal by the opening is warned of (0.2 % of
the head CT's bone, 7 % of the head phantom's soft tissue; a 10 mm plate on 5 mm slices 64 %;
a head's one-slice skull caps on 5 mm slices 14 %, which 25 % let pass)."""

LARGE_DROPPED_PART = 0.1
"""A part that segment.keep drops is warned of when it holds at least this fraction of the
voxels of the part kept (a CT table or headrest holds far less than a body: 1.4 % on the
head CT; a specimen inside an open sample tube a fifth of the tube)."""


AMBIGUOUS_CRITERION = 0.005
"""Two thresholds of one class whose criterion J differs by less than this, at peaks apart by
a dip deeper than it, are reported: a small change of the scan outside the body can then
swap them (the head phantom's bone at 3.5 mm voxels: 180 or 956 HU 1.6e-4 apart, bone -31 %
with the other; the head CT's second peak lies 0.026 below its first)."""


def class_priority(names: list[str], priority, source: str = "") -> list[int]:
    """Class labels in priority order, highest first, from ``segment.priority``.

    Parameters
    ----------
    names : list of str
        The material names; label i is ``names[i - 1]``.
    priority : list of str or None
        ``segment.priority``: class names, highest priority first.
    source : str
        File named in error messages.

    Returns
    -------
    priority : list of int
        Every label 1..K once. Named classes come first in the given order; classes
        not named follow, densest first. ``None``: ``K, K-1, ..., 1``.

    Raises
    ------
    DicerError
        An unknown or repeated class name.
    """
    out = []
    for name in priority or []:
        if name not in names:
            raise DicerError(f"{source}: segment.priority names unknown class '{name}'; "
                             f"known classes: {', '.join(names)}")
        label = names.index(name) + 1
        if label in out:
            raise DicerError(f"{source}: segment.priority lists class '{name}' twice; list each class once")
        out.append(label)
    out += [c for c in range(len(names), 0, -1) if c not in out]
    return out


def check_radii(options: dict, shape, source: str = "") -> None:
    """Refuse an opening or closing radius wider than the image: its ball alone would need
    (2r + 1)^3 voxels of memory (radius 1000: 8 GB) for a result the image cannot show."""
    top = max(max(shape) // 2, 1)
    for key in ("opening_radius", "closing_radius"):
        r = options[key]
        if r > top:
            raise DicerError(f"{source}: segment.{key}={r} voxels is wider than the image "
                             f"({'x'.join(map(str, shape))} voxels); give a radius of 0..{top} voxels")


def morphology_options(names: list[str], *, opening_radius: int, closing_radius: int, keep, min_component_size,
                       priority, source: str = "") -> dict:
    """Keyword arguments of :func:`clean_labels` from the ``segment`` settings.

    Parameters
    ----------
    names : list of str
        The material names; label i is ``names[i - 1]``.
    opening_radius, closing_radius, keep, min_component_size, priority
        Those keys of the ``segment:`` config section (see the schema).
    source : str, optional
        File named in error messages.

    Returns
    -------
    options : dict
        ``n_classes``, ``opening_radius``, ``closing_radius``, ``keep``, ``min_size``,
        ``priority``.

    Raises
    ------
    DicerError
        A per-material list of another length than the materials.
    """
    k = len(names)
    if keep == "body":  # the largest part of the outermost class, with everything inside it
        keep = ["largest"] + ["all"] * (k - 1)
    for key, value in (("keep", keep), ("min_component_size", min_component_size)):
        if isinstance(value, list) and len(value) != k:
            raise DicerError(f"{source}: segment.{key} has {len(value)} entries for {k} materials "
                             f"({', '.join(names)}); give one per material or a single value")
    return {
        "n_classes": k,
        "opening_radius": int(opening_radius),
        "closing_radius": int(closing_radius),
        "keep": keep,
        "min_size": min_component_size,
        "priority": class_priority(names, priority, source),
    }


def label_counts(labels: np.ndarray, names: list[str]) -> dict:
    """Voxels and fraction of the volume per class name (background under 'background').

    Parameters
    ----------
    labels : ndarray of int
        0 background, 1..K classes.
    names : list of str
        Class names by label (names[0] is label 1's).

    Returns
    -------
    counts : dict
        ``{name: {"label": c, "voxels": n, "fraction": f}}`` for background and each class.
    """
    k = len(names)
    counts = count_labels(labels, k + 1)
    total = max(int(labels.size), 1)
    out = {}
    for c, name in enumerate(["background"] + list(names)):
        n = int(counts[c]) if c < counts.size else 0
        out[name] = {"label": c, "voxels": n, "fraction": round(n / total, 6)}
    return out


def _check_image(image: Volume, source: str) -> tuple[float, float]:
    if image.array.ndim not in (2, 3):
        raise DicerError(f"{source}: a {image.array.ndim}D image; dicer segments 2D or 3D images, "
                         "extract one volume first")
    if image.array.size == 0:
        raise DicerError(f"{source}: the image has no voxels; check the file")
    if np.iscomplexobj(image.array) or image.array.dtype == bool:
        raise DicerError(f"{source}: image of type {image.array.dtype}; give a grey-level (integer or float) image")
    lo, hi = value_range(image.array)
    if not np.isfinite(lo):
        raise DicerError(f"{source}: the image holds no finite value (all NaN or infinite); check the file")
    if lo == hi:
        raise DicerError(f"{source}: the image has a single grey level ({lo:g}); nothing to segment, "
                         "check that the file holds the scan")
    return lo, hi


PADDING_BELOW = -1024.0
"""A CT's padding value lies below the lowest HU a scanner reconstructs (air is -1000; HU
stored unsigned with intercept -1024 bottom out at -1024): -2000, -2048, -3024, -32768."""

PADDING_SHARE = 0.005
"""Share of the voxels the padding value must hold (the corners outside the scan circle
hold 20-30 % of a slice), with next to none between it and -1024."""


def padding_value(array: np.ndarray, lo: float | None = None) -> float | None:
    """The value a CT holds outside its field of view (padding), when it has one.

    The image's smallest value, when it lies below :data:`PADDING_BELOW`, holds at least
    :data:`PADDING_SHARE` of the voxels, and fewer than a tenth as many lie between it and
    ``PADDING_BELOW``: a separate block of values, not the low tail of air.

    Parameters
    ----------
    array : ndarray
        Image intensities (HU for CT).
    lo : float, optional
        The image's smallest finite value, when known.

    Returns
    -------
    float or None
    """
    if lo is None:
        lo = float(np.nanmin(array)) if array.size else 0.0
    if not lo < PADDING_BELOW:
        return None
    at = int(np.count_nonzero(array == lo))
    between = int(np.count_nonzero((array > lo) & (array < PADDING_BELOW)))
    return lo if at >= PADDING_SHARE * array.size and between * 10 < at else None


def _without_padding(array: np.ndarray, lo: float) -> tuple[np.ndarray, float | None, int, float]:
    """The image for the threshold search, its padding at -1024 HU, as a scanner that pads
    with the lowest HU it stores (within the air's noise, not at its far tail): Otsu's and
    multi-Otsu's splits and the search ranges then see the scan and its air only. Also the
    padding value, its voxel count and the lowest value of the scan within its field of view
    (``lo`` without padding)."""
    pad = padding_value(array, lo)
    if pad is None:
        return array, None, 0, lo
    padded = array == pad
    top = np.iinfo(array.dtype).max if array.dtype.kind in "iu" else np.inf
    lowest = float(np.min(array, where=~padded, initial=top))
    return (np.where(padded, np.asarray(PADDING_BELOW, array.dtype), array), pad, int(np.count_nonzero(padded)),
            lowest)


DENSEST_ON_BORDER = 0.5
"""Share of the image's border voxels in the densest class from which it is warned of: a scan
holds air, the table or the tissue around the part there (the head CT's bone 1.1 %; a bone cropped
to its shaft covers its two cut faces' cross-sections), an image with its contrast inverted its
air in the densest class (a negated CT phantom: 100 %)."""


def _border_warnings(labels: np.ndarray, names: list[str], lo: float) -> list[str]:
    """A warning when the densest class covers most of the border of an image that holds air's
    values in HU (``lo``, its lowest, at most ``NO_AIR_HU``): the contrast inverted (values negated:
    air taken for bone), or a CT cropped inside that class. A specimen filling an image of other
    units (a test plate of 0 and 1000) is not a CT in HU and is left alone."""
    if lo > NO_AIR_HU:
        return []
    border = np.concatenate([np.take(labels, end, axis=a).ravel() for a in range(labels.ndim) for end in (0, -1)])
    share = np.count_nonzero(border == len(names)) / max(border.size, 1)
    if share < DENSEST_ON_BORDER:
        return []
    return [f"class '{names[-1]}', the densest, covers {100 * share:.0f} % of the image's border, where a scan holds "
            "air, the table or the tissue around the part: if the image's contrast is inverted (air bright, bone dark: "
            f"negated values), its air is taken for '{names[-1]}'; check segmentation.png, and negate the image or "
            "set segment.thresholds"]


def _empty_class_warnings(info: dict, names: list[str], thresholds) -> list[str]:
    """A warning for each class left without a voxel: its material gets no elements."""
    warnings = []
    for i, name in enumerate(names):
        if info["classes"][name]["voxels"]:
            continue
        if not info["thresholded"][name]:
            upper = f" and below {thresholds[i + 1]:g}" if i + 1 < len(names) else ""
            warnings.append(f"class '{name}' holds no voxel: no image value lies at or above {thresholds[i]:g}"
                            f"{upper}, so material '{name}' gets no elements; check segment.thresholds "
                            "(or segment.ranges), or remove the material")
        else:
            warnings.append(f"class '{name}' holds no voxel after the morphology ({info['thresholded'][name]} "
                            "thresholded, removed by the opening, segment.keep or segment.min_component_size, or "
                            f"covered by the class inside it), so material '{name}' gets no elements; lower "
                            "segment.opening_radius or segment.min_component_size, or set segment.keep: all")
    return warnings


NOT_IN_HU = {"MR": "an MR", "PT": "a PET", "NM": "a nuclear-medicine image", "US": "an ultrasound",
             "CR": "a radiograph", "DX": "a radiograph", "MG": "a mammogram", "XA": "an angiogram"}
"""DICOM Modality values (0008,0060) of scans whose values are not HU, and what to call them."""


def check_modality(modality: str | None, method: str, thresholds, ranges, source: str) -> None:
    """Refuse CT's default thresholds in HU for a scan whose DICOM Modality says it is no CT.

    Parameters
    ----------
    modality : str or None
        The image's Modality (``Volume.modality``); None or another value passes.
    method, thresholds, ranges
        The ``segment:`` settings; ``otsu`` and ``multiotsu`` take no values and pass, as do
        values the user set (any but the schema's defaults).
    source : str
        The image's file name, for the message.

    Raises
    ------
    DicerError
        ``shape_connectivity`` with the default ``ranges``, or ``manual`` with the default
        ``thresholds``, on an image of a modality in :data:`NOT_IN_HU`.
    """
    kind = NOT_IN_HU.get(modality or "")
    key = _default_hu_key(method, thresholds, ranges)
    if kind is None or key is None:
        return
    default = section_defaults("segment")[key]
    raise DicerError(f"{source}: the scan is {kind} (DICOM Modality {modality}), not a CT, and segment.method "
                     f"{method} takes the default segment.{key} {json.dumps(default)}, which are CT values in HU; "
                     f"set segment.method: multiotsu (thresholds from the image's histogram, docs/segmentation.md), "
                     f"or segment.{key} for this image's values")


def _range_warnings(info: dict, names: list[str], lo: float, hi: float, spacing=()) -> list[str]:
    """Warnings for thresholds that suggest the image is not in the units the settings
    assume (an MR or a rescaled image under the CT defaults), or, in a CT with air, that its
    voxels average thin tissue with its surroundings (``spacing``, mm)."""
    warnings = []
    for name in names if "criterion" in info else ():
        candidates = info["criterion"][name]["thresholds"]
        t = info["thresholds"][names.index(name)]
        if len(candidates) > 2 and t in (candidates[0], candidates[-1]):
            low, high = info["ranges"][names.index(name)]
            if lo <= NO_AIR_HU:  # air's -1000: a CT in HU, whose large voxels average thin bone with soft tissue
                why = (f"the image holds air's -1000, so it is most likely a CT in HU: on voxels of "
                       f"{' x '.join(f'{v:g}' for v in spacing)} mm thin tissue averages with its surroundings "
                       "(partial volume) and its values move towards theirs; check segmentation.png and set "
                       "segment.thresholds, or segment.ranges")
            else:
                why = "if it is not CT in HU, set segment.ranges (or segment.thresholds) for its values"
            warnings.append(f"the threshold of '{name}' ({t:g}) lies at an end of its search range [{low:g}, "
                            f"{high:g}]: the best split may lie outside it; the image spans {lo:g} .. {hi:g}; "
                            f"{why}")
    background = info["classes"]["background"]["fraction"]
    if background < WHOLE_BOX:
        # no air's -1000 HU, bone's thousands: most likely a CT whose rescale intercept was lost
        offset = (f"; the image spans {lo:g} .. {hi:g}, with no value near air's -1000 HU: a CT stored as HU + 1024 "
                  "(its rescale intercept lost, air near 0) needs 1024 subtracted" if lo > -200 and hi > 1000 else "")
        warnings.append(f"only {100 * background:.2f} % of the image is background: the whole box is taken for "
                        "the body; if the scan has air or fluid around it (an MR or a rescaled image under the "
                        f"CT defaults), set segment.ranges (or segment.thresholds) for the image's values{offset}")
    return warnings


def _second_peak(thresholds: np.ndarray, values: np.ndarray, taken: int) -> int | None:
    """The candidate at the highest other peak of a class's criterion curve within
    AMBIGUOUS_CRITERION of the one taken (index ``taken``), a dip deeper than that between
    them; None if there is none."""
    v = np.asarray(values, float)
    if v.size < 3:
        return None
    left = np.r_[True, v[1:] >= v[:-1]]
    right = np.r_[v[:-1] >= v[1:], True]
    best = None
    for j in np.flatnonzero(left & right):  # a loop over the curve's few peaks, not over voxels
        if abs(int(j) - taken) <= 1 or v[taken] - v[j] > AMBIGUOUS_CRITERION:
            continue
        lo, hi = sorted((int(j), taken))
        if min(v[j], v[taken]) - v[lo:hi + 1].min() > AMBIGUOUS_CRITERION and (best is None or v[j] > v[best]):
            best = int(j)
    return best


def _ambiguity_warnings(info: dict, names: list[str], array: np.ndarray) -> list[str]:
    """Warnings (and ``info["ambiguous_thresholds"]``) for classes whose shape-connectivity
    criterion has a second peak as high as the one taken (:func:`_second_peak`), with the
    voxels of ``array`` that lie between the two thresholds."""
    if "criterion" not in info:
        return []
    said, found = [], {}
    for c, name in enumerate(names):
        curve = info["criterion"][name]
        t, v = np.asarray(curve["thresholds"], float), np.asarray(curve["values"], float)
        taken = int(np.argmin(np.abs(t - info["thresholds"][c])))
        other = _second_peak(t, v, taken)
        if other is None:
            continue
        a, b = sorted((float(t[taken]), float(t[other])))
        between = int(np.count_nonzero((array >= a) & (array < b)))
        found[name] = {"taken": float(t[taken]), "other": float(t[other]),
                       "criterion": [float(v[taken]), float(v[other])], "voxels_between": between}
        said.append(f"two thresholds of '{name}' score alike by the shape-connectivity criterion: {t[taken]:g} (taken, "
                    f"J {v[taken]:.6g}) and {t[other]:g} (J {v[other]:.6g}); the {between} voxels between them "
                    f"({100 * between / array.size:.2g} % of the image) change class with the choice, which a small "
                    f"change of the scan (its field of view, a table, noise) can swap: check segmentation.png, or set "
                    f"segment.thresholds")
    if found:
        info["ambiguous_thresholds"] = found
    return said


def _default_hu_key(method: str, thresholds, ranges) -> str | None:
    """``"ranges"`` or ``"thresholds"`` where ``method`` takes the schema's default values of
    that key (CT values in HU), else None."""
    if method not in ("shape_connectivity", "manual"):
        return None
    key, given = ("ranges", ranges) if method == "shape_connectivity" else ("thresholds", thresholds)
    default = section_defaults("segment")[key]
    if np.shape(given) != np.shape(default) or not np.array_equal(np.asarray(given, float), default):
        return None
    return key


def _default_hu_warnings(method: str, ranges, thresholds, array: np.ndarray, names: list[str], taken) -> list[str]:
    """A warning where the default CT settings (``segment.ranges`` of shape_connectivity,
    ``segment.thresholds`` of manual), values in HU, meet an image without air's HU: an MR
    offset or normalised to values below zero took its brain for bone without a word."""
    key = _default_hu_key(method, thresholds, ranges)
    if key is None:
        return []
    lowest = float(np.nanmin(array)) if array.size else 0.0
    if lowest <= NO_AIR_HU:
        return []
    classes = ", ".join(f"'{n}' from {float(t):g}" for n, t in zip(names, taken))
    return [f"the image holds no value below {NO_AIR_HU:g} (its lowest is {lowest:g}): no air in HU, so it is not a "
            f"CT in HU (an MR, or an image rescaled or normalised) or holds no air (cropped inside the body); the "
            f"default segment.{key} are CT values in HU and made {classes}: check segmentation.png; for an MR set "
            "segment.method: multiotsu (docs/segmentation.md), or segment.ranges for this image's values"]


def _histogram_warnings(method: str, array: np.ndarray, values, names: list[str], thresholds) -> list[str]:
    """Warnings for thresholds from the histogram alone (otsu, multiotsu) that cut through one
    tissue's peak (:func:`thresholds_in_a_mode`): the histogram is split into as many classes as
    there are materials whatever the scan holds, so a scan without bone has its air cut in two
    and the head becomes 'bone'; and an image without air in HU. ``values``: the
    thresholds' :func:`histogram_values`."""
    if method not in ("otsu", "multiotsu"):
        return []
    said = []
    cut = thresholds_in_a_mode(values, thresholds)
    if cut:
        which = ", ".join(f"'{names[i]}' ({float(thresholds[i]):g})" for i in cut)
        fewer = ("the scan holds fewer tissues than the materials listed, and the classes are not the tissues they "
                 "are named after; list only the materials the scan holds" if len(names) > 1 else
                 "the image holds one tissue and its background alike (noise, or a tissue filling the image), and "
                 f"'{names[0]}' is a part of its values, not a tissue; check segmentation.png")
        said.append(f"{method} put the threshold of {which} at a peak of the image's histogram, inside one tissue's "
                    f"values, not between two: {fewer}, or set segment.method: manual (or shape_connectivity with "
                    "segment.ranges)")
    lowest = float(np.nanmin(array)) if array.size else 0.0
    if lowest > NO_AIR_HU:
        # Otsu splits any values; the classes take the materials' names in order of intensity
        check = (f"named {', '.join(names)} in order of intensity: check that the brightest class is '{names[-1]}'"
                 if len(names) > 1 else f"named {names[0]}: check that it holds what '{names[0]}' names")
        said.append(f"the image holds no value below {NO_AIR_HU:g} (its lowest is {lowest:g}): no air in HU, so it is "
                    f"not a CT in HU (an MR?) or holds no air; {method} made {len(names)} class(es) of its values, "
                    f"{check} (an MR's bright tissue is not bone; correct an MR's bias field first, "
                    "docs/segmentation.md), or name the materials for this scan")
    return said


@takes_settings("segment")
def segment(image: Volume, *, names: list[str], method: str, thresholds, ranges, bins: int, opening_radius: int,
            closing_radius: int, keep, min_component_size, priority, source: str = "") -> tuple[Volume, dict]:
    """Classify voxels into the configured materials and clean the classes.

    The settings are keyword-only with no defaults here: the command line passes
    ``dicer.config.stage_kwargs(config, "segment")``. A library call may instead give a
    configuration as the second argument (and ``source`` third), or leave settings out;
    the schema's defaults fill them (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    image : Volume
        Grey-level image, (nx, ny[, nz]) array of int or float (HU for CT).
    names : list of str
        The material names, in order of increasing intensity (the ``materials`` section).
    method, thresholds, ranges, bins, opening_radius, closing_radius, keep, min_component_size, priority
        The ``segment:`` config section (see the schema).
    source : str
        The image's file name, used in error messages.

    Returns
    -------
    labels : Volume
        uint8 array of the image's shape (0 background, 1..K classes), same spacing,
        origin and direction.
    info : dict
        ``method``, ``thresholds`` (K floats, the lower bound of each class),
        ``classes`` (voxels and fraction per class after morphology),
        ``thresholded`` (voxels per class before morphology), ``removed_by_opening``,
        ``seconds``; for ``shape_connectivity`` also ``ranges`` and ``criterion``
        (the criterion curve per class boundary); ``padding`` (value and voxels) when a CT
        holds a padding value outside its field of view (:func:`padding_value`), which the
        threshold search takes as air.

    Raises
    ------
    DicerError
        Bad thresholds or ranges for the configured classes, an image with one grey
        level, no voxel in any class, or morphology that removes every voxel.
    """
    t0 = time.perf_counter()
    source = source or "image"
    k = len(names)
    lo, hi = _check_image(image, source)
    check_modality(image.modality, method, thresholds, ranges, source)
    array = image.array
    info: dict = {"method": method}
    values = None  # Otsu's histogram values (histogram_values)
    if method != "manual":
        array, pad, padded, lowest = _without_padding(array, lo)
        if pad is not None:  # outside the field of view: as air for the thresholds, background after them
            info["padding"] = {"value": pad, "voxels": padded}
            if method == "shape_connectivity":  # the ranges against the scan's own values, not the padding's -1024
                check_ranges(ranges, k, names, lowest, hi, source)
    if method == "manual":
        thresholds = check_thresholds(thresholds, k, names, source)
    elif method in ("otsu", "multiotsu"):
        values = histogram_values(array)  # one partition of the image, for the thresholds and their check
        thresholds = (otsu_thresholds if method == "otsu" else multiotsu_thresholds)(values, k, names, source)
    else:  # shape_connectivity (the schema knows no other method)
        thresholds, search = shape_connectivity_thresholds(array, ranges, names, source, bins=int(bins))
        info.update({key: value for key, value in search.items() if key != "seconds"})
        info["search_seconds"] = search["seconds"]
    # nine significant digits: the smoothing reads them back (an ADC map's 1e-9 mm2/s would round to 0)
    info["thresholds"] = [float(f"{float(t):.9g}") for t in thresholds]
    t_threshold = time.perf_counter()

    searched, array = array, image.array
    raw = classify(array, thresholds)
    if not raw.any():
        raise DicerError(f"{source}: no voxel >= {thresholds[0]:g} (the lower bound of class '{names[0]}'); "
                         f"the image spans {lo:g} .. {hi:g}; lower segment.thresholds")
    info["thresholded"] = {name: v["voxels"] for name, v in label_counts(raw, names).items()}

    options = morphology_options(names, opening_radius=opening_radius, closing_radius=closing_radius, keep=keep,
                                 min_component_size=min_component_size, priority=priority, source=source)
    check_radii(options, raw.shape, source)
    labels, minfo = clean_labels(raw, **options, spacing=image.spacing)
    if not labels.any():
        raise DicerError(f"{source}: the morphology removed every voxel (segment.opening_radius="
                         f"{options['opening_radius']} drops parts thinner than {2 * options['opening_radius'] + 1} "
                         "voxels, keep/min_component_size drop small parts); lower segment.opening_radius "
                         "or segment.min_component_size")
    info["removed_by_opening"] = {names[c - 1]: n for c, n in minfo["removed_by_opening"].items()}
    info["removed_parts"] = {names[c - 1]: p for c, p in minfo["removed_parts"].items() if p["parts"]}
    info["classes"] = label_counts(labels, names)
    warnings = (_empty_class_warnings(info, names, thresholds) + _range_warnings(info, names, lo, hi, image.spacing)
                + _histogram_warnings(method, searched, values, names, thresholds)
                + _default_hu_warnings(method, ranges, thresholds, searched, names, info["thresholds"])
                + _ambiguity_warnings(info, names, searched) + _border_warnings(labels, names, lo))
    for name, removed in info["removed_by_opening"].items():
        kept, thresholded = info["classes"][name]["voxels"], info["thresholded"][name]
        if kept and removed >= OPENED_AWAY * thresholded:  # an empty class has its own warning
            radii = axis_radii(options["opening_radius"], image.spacing, image.array.ndim)
            across = " x ".join(f"{(2 * r + 1) * sp:g}" for r, sp in zip(radii, image.spacing))
            warnings.append(f"the opening removed {removed} of the {thresholded} thresholded voxels of '{name}' "
                            f"({100 * removed / thresholded:.0f} %): parts narrower than {across} mm "
                            f"({'x'.join(str(2 * r + 1) for r in radii)} voxels) go; lower segment.opening_radius")
    for c, p in minfo["removed_parts"].items():
        # keep 'largest' (keep: body) drops the headrest and the table; a part of a size like
        # the one kept is more likely a second leg or hand scanned beside the first
        if p["largest"] >= LARGE_DROPPED_PART * p["largest_kept"] > 0:
            warnings.append(f"segment.keep dropped {p['parts']} part(s) of '{names[c - 1]}' and what lies inside "
                            f"them, the largest {p['largest']} voxels, {100 * p['largest'] / p['largest_kept']:.0f} % "
                            "of the part kept; if it is anatomy (a second limb), set segment.keep: all")
    if warnings:
        info["warnings"] = warnings
    info["seconds"] = {"thresholds": round(t_threshold - t0, 3),
                       "total": round(time.perf_counter() - t0, 3)}
    return Volume(labels, image.spacing, image.origin, image.direction), info
