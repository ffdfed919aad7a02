"""Global thresholds: manual, Otsu, multi-Otsu and classification by thresholds.

A threshold list ``t_1 < t_2 < ... < t_K`` (image units, HU for CT) splits the image
into K material classes plus background: a voxel of value ``v`` gets label
``c = #{i : v >= t_i}``, i.e. class c holds ``t_c <= v < t_{c+1}`` and background
holds ``v < t_1`` (and NaN).
"""

from __future__ import annotations

import contextlib
import time
import warnings

import numpy as np
from skimage.exposure import histogram
from skimage.filters import threshold_otsu

from dicer.errors import DicerError

__all__ = [
    "classify", "check_thresholds", "histogram_values", "otsu_thresholds", "multiotsu_thresholds", "value_range",
    "thresholds_in_a_mode",
    "check_ranges", "candidate_edges", "whole_valued", "bin_image", "cooccurrence", "shape_connectivity_thresholds",
]


def value_range(array: np.ndarray) -> tuple[float, float]:
    """Smallest and largest finite value of ``array`` (float, float)."""
    a = np.asarray(array)
    if np.issubdtype(a.dtype, np.floating):
        finite = a[np.isfinite(a)] if not np.isfinite(a).all() else a
        if finite.size == 0:
            return float("nan"), float("nan")
        return float(finite.min()), float(finite.max())
    return float(a.min()), float(a.max())


def classify(array: np.ndarray, thresholds) -> np.ndarray:
    """Label each voxel by the number of thresholds it reaches.

    Parameters
    ----------
    array : (nx, ny[, nz]) ndarray of int or float
        Image intensities.
    thresholds : sequence of K floats, strictly increasing
        Lower bound of each class.

    Returns
    -------
    labels : ndarray of uint8 (int16 when K > 254), same shape as ``array``
        0 below ``thresholds[0]`` (and NaN), c where ``t_c <= value < t_{c+1}``.
    """
    t = [float(x) for x in thresholds]
    dtype = np.uint8 if len(t) < 255 else np.int16
    labels = np.zeros(array.shape, dtype=dtype)
    for ti in t:  # a loop over classes: K passes of a vectorised comparison
        labels += array >= ti
    return labels


def check_thresholds(thresholds, k: int, names: list[str], source: str, key: str = "segment.thresholds") -> list[float]:
    """Validate K strictly increasing thresholds; return them as floats.

    Raises
    ------
    DicerError
        Wrong count or not strictly increasing; the message names ``source``, the key,
        the classes and the fix.
    """
    t = [float(x) for x in thresholds]
    if len(t) != k:
        raise DicerError(f"{source}: {key} has {len(t)} value(s) but the config names {k} material(s) "
                         f"({', '.join(names)}); give one lower bound per material")
    for i in range(1, k):
        if not t[i] > t[i - 1]:
            raise DicerError(f"{source}: {key} must increase strictly: class '{names[i]}' starts at {t[i]:g}, "
                             f"not above class '{names[i - 1]}' at {t[i - 1]:g}; order the materials by intensity")
    return t


def _finite_values(array: np.ndarray) -> np.ndarray:
    a = np.asarray(array)
    if np.issubdtype(a.dtype, np.floating) and not np.isfinite(a).all():
        return a[np.isfinite(a)]
    return a


@contextlib.contextmanager
def _quiet():
    """scikit-image's histograms of extreme values (1e30) warn on standard error; dicer says
    what is wrong itself (no voxel in a class, a class the morphology emptied)."""
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


OUTLIER_SHARE = 1e-3
"""Share of voxels at each end of the grey values that Otsu's histograms clip: a few metal
voxels at 30,000 HU spread the 256 bins so wide that skull and soft tissue shared a few."""


def _clipped(values: np.ndarray) -> np.ndarray:
    """``values`` (flattened) clipped to their quantiles OUTLIER_SHARE and 1 - OUTLIER_SHARE."""
    flat = np.ravel(values)
    if flat.size < 2:
        return flat
    k = int(OUTLIER_SHARE * (flat.size - 1))
    lo, hi = np.partition(flat, (k, flat.size - 1 - k))[[k, flat.size - 1 - k]]
    return np.clip(flat, lo, hi)


def histogram_values(array: np.ndarray) -> np.ndarray:
    """The values Otsu's histograms are taken of: the finite ones, clipped to their
    OUTLIER_SHARE quantiles (one partition of the image: made once, shared by the
    thresholds and their check).

    Parameters
    ----------
    array : ndarray
        Image intensities.

    Returns
    -------
    (P,) ndarray
    """
    return _clipped(_finite_values(array))


def otsu_thresholds(values: np.ndarray, k: int, names: list[str], source: str) -> list[float]:
    """Otsu's threshold for one material class.

    Parameters
    ----------
    values : ndarray
        Image intensities as :func:`histogram_values` gives them.
    k : int
        Number of material classes; must be 1.

    Returns
    -------
    thresholds : list of 1 float
    """
    if k != 1:
        raise DicerError(f"{source}: segment.method=otsu finds one threshold but the config names {k} materials "
                         f"({', '.join(names)}); use segment.method=multiotsu or shape_connectivity")
    with _quiet():
        threshold = float(threshold_otsu(values))
        counts, centres = histogram(np.asarray(values, np.float64).reshape(-1), 256, source_range="image")
    return mid_gap([threshold], counts, centres)


def mid_gap(thresholds, counts: np.ndarray, centres: np.ndarray) -> list[float]:
    """Thresholds moved to the middle of the empty bins they end at.

    Otsu's criterion is the same for any threshold in a gap of the histogram, and the search
    takes its first bin: the lower class's own value. The voxels' classes are the same
    anywhere in the gap, but a surface placed at the threshold's level in the image
    (``smooth.fit_to_scan``) lies midway between the classes only at its middle (a ball of
    value 1000 on 0, radius 8 voxels: 2,391 mm^3 against its 2,145 at the gap's lower end, 2,157 at
    its middle).

    Parameters
    ----------
    thresholds : sequence of float
        Each at the centre of a filled bin or between two.
    counts, centres : (B,) ndarray
        The histogram the thresholds were found on.

    Returns
    -------
    list of float
    """
    filled = np.flatnonzero(counts)
    at = centres[filled]
    out = []
    for t in thresholds:  # K thresholds, a few
        i = int(np.searchsorted(at, t, side="right"))  # filled[i - 1]: the last filled bin at or below t
        if 0 < i < filled.size and filled[i] - filled[i - 1] > 1:
            t = 0.5 * (at[i - 1] + at[i])
        out.append(float(t))
    return out


def multiotsu_thresholds(values: np.ndarray, k: int, names: list[str], source: str) -> list[float]:
    """Multi-Otsu thresholds for K material classes (K + 1 classes with background).

    The thresholds that maximise Otsu's between-class variance on a 256-bin histogram of
    ``values`` (the image's clipped to their 0.1 % and 99.9 % quantiles,
    :func:`histogram_values`: a few metal voxels would stretch the bins over tens of
    thousands of HU), found exactly by :func:`multiotsu_bins`, at the centres of the bins
    :func:`skimage.exposure.histogram` gives.

    Returns
    -------
    thresholds : list of K floats, increasing
    """
    values = np.asarray(values).reshape(-1)
    if not np.issubdtype(values.dtype, np.floating):  # scikit-image bins integers one value a bin
        values = values.astype(np.float64)
    with _quiet():
        counts, centres = histogram(values, 256, source_range="image")
    filled = np.flatnonzero(counts)
    if filled.size < k + 1:
        few = filled.size == np.unique(values[: 1 << 20]).size  # a label image or a mask: few values indeed
        why = ("" if few else f": its values crowd into {filled.size} of the 256 bins, the histogram stretched to "
               f"{float(centres[filled[-1]]):g} by {int(counts[filled[-1]])} voxels far above the others (above the "
               "99.9 % quantile at which it is clipped); remove or clip them first (metal, a scanner's marker value)")
        raise DicerError(f"{source}: multi-Otsu cannot split the image into {k + 1} classes (its 256-bin histogram "
                         f"holds {filled.size} values{why}); use fewer materials or segment.method=manual")
    bins = filled[:-1] if filled.size == k + 1 else multiotsu_bins(counts, k)
    return mid_gap(centres[bins], counts, centres)


def multiotsu_bins(counts: np.ndarray, thresholds: int) -> np.ndarray:
    """The histogram bins that end each class but the last, maximising Otsu's between-class
    variance (Liao, Chen and Chung 2001: the sum over classes of (sum of i n_i)^2 / sum of n_i).

    Exact, by dynamic programming over where each class ends: in O(K B^2) for K thresholds on
    B bins, where an exhaustive search takes O(B^K) (skimage's: 3 s for four thresholds, hours
    for five). Equal splits are told apart the same way on every run.

    Parameters
    ----------
    counts : (B,) int or float ndarray
        Histogram counts.
    thresholds : int
        K >= 1.

    Returns
    -------
    (K,) int ndarray
        Increasing bin indices: class j holds the bins after threshold j - 1 up to threshold j.
    """
    counts = np.asarray(counts, np.float64)
    b = counts.size
    n = np.concatenate([[0.0], np.cumsum(counts)])
    moment = np.concatenate([[0.0], np.cumsum(counts * np.arange(b))])
    # score[a, e]: one class on bins a .. e - 1, for a < e
    weight = n[None, :] - n[:, None]
    first = moment[None, :] - moment[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.where(weight > 0, first * first / weight, 0.0)
    score[np.tril_indices(b + 1)] = -np.inf
    best, starts = score[0], []  # best[e]: the classes so far on bins 0 .. e - 1
    for _ in range(thresholds):
        total = best[:, None] + score  # the next class on bins a .. e - 1
        start = np.argmax(total, axis=0)
        starts.append(start)
        best = total[start, np.arange(b + 1)]
    ends, end = [], b
    for start in reversed(starts):
        end = int(start[end])
        ends.append(end - 1)
    return np.array(ends[::-1], np.int64)


MODE_SHARE = 0.25
"""A histogram threshold at which the image's value density (256 bins) is at least this share
of its highest bin's lies in a populated mode, not in a valley between two."""


def thresholds_in_a_mode(values: np.ndarray, thresholds) -> list[int]:
    """The thresholds (their indices) that cut through a populated mode of the histogram.

    Otsu's criterion splits the values into the classes asked for whatever they hold: with
    more classes than the scan has tissues (a scan without bone) one tissue is cut in two, at
    its own peak. A threshold between two tissues lies in a valley of the histogram.

    Parameters
    ----------
    values : ndarray
        Image intensities as :func:`histogram_values` gives them.
    thresholds : sequence of float

    Returns
    -------
    list of int
    """
    with _quiet():
        counts, edges = np.histogram(values, bins=256)
    if not counts.size or counts.max() == 0:
        return []
    # the bin of the threshold and its neighbours: one noisy bin does not decide
    near = np.convolve(counts, np.ones(3) / 3, mode="same")
    at = np.clip(np.searchsorted(edges, np.asarray(thresholds, float), side="right") - 1, 0, counts.size - 1)
    return [i for i, b in enumerate(at) if near[b] >= MODE_SHARE * counts.max()]


# --- shape connectivity (Lie) -------------------------------------------------------------


def _as_label_file(source: str) -> str:
    """What a label volume in a file --labels does not read (a PNG, a TIFF, a DICOM folder)
    must become first."""
    from dicer.io import LABEL_SUFFIXES

    name = str(source).lower()
    return "" if name.endswith(LABEL_SUFFIXES) else " after saving it as NIfTI (.nii.gz), which --labels reads"


def _few_whole_values(values, lo: float, hi: float) -> int:
    """How many distinct whole values an image of 0 .. 255 holds when they are few (64 at most,
    as a label volume's), else 0."""
    if values is None or lo != 0 or hi > 255 or not float(hi).is_integer():
        return 0
    distinct = np.unique(np.asarray(values))
    return int(distinct.size) if distinct.size <= 64 and np.array_equal(distinct, np.round(distinct)) else 0


def check_ranges(ranges, k: int, names: list[str], lo: float, hi: float, source: str,
                 values: np.ndarray | None = None) -> list[tuple[float, float]]:
    """Validate the shape-connectivity search ranges against the classes and the image.

    Parameters
    ----------
    ranges : list of K [low, high] pairs or None
        Grey-level range of each class's lower threshold (image units).
    k : int
        Number of material classes.
    names : list of str
        Class names, for messages.
    lo, hi : float
        The image's smallest and largest finite value.
    source : str
        File named in error messages.
    values : ndarray, optional
        The image's values: for the advice when no range fits (few whole values: a label
        volume given as the image).

    Returns
    -------
    ranges : list of K (float, float)

    Raises
    ------
    DicerError
        Missing ranges, a range with low >= high, ranges that overlap or are out of
        order, or a range outside the image's values.
    """
    key = "segment.ranges"
    given = list(ranges or [])
    if len(given) != k:
        missing = ", ".join(f"'{n}'" for n in names[len(given):])
        which = (f"missing: {missing}" if missing else
                 f"{len(given) - k} more than the materials: the materials section lists fewer than segment.ranges")
        raise DicerError(f"{source}: {key} has {len(given)} range(s) for {k} material(s) ({', '.join(names)}); "
                         f"give one [low, high] per material ({which})")
    out = []
    for name, r in zip(names, given):
        if len(r) != 2:
            raise DicerError(f"{source}: {key} entry for class '{name}' must be [low, high], got {r}")
        a, b = float(r[0]), float(r[1])
        if not a < b:
            raise DicerError(f"{source}: {key} for class '{name}' is [{a:g}, {b:g}]; low must be below high")
        if b <= lo or a >= hi:
            # no negative values up to a thousand and more: a CT whose rescale intercept was lost
            # (stored as HU + 1024, air near 0) more often than not; no value near air's -1000 HU
            # at all: an MR, or a scan in other units (0 .. 1, a windowed 8-bit export)
            shifted = (f"; an image of {few} whole values from 0 is most likely a label volume: give it with "
                       f"--labels (dicer run --labels, dicer labels){_as_label_file(source)}"
                       if (few := _few_whole_values(values, lo, hi))
                       else "; a CT stored as HU + 1024 (its rescale intercept lost: air near 0) needs 1024 "
                       "subtracted, or ranges shifted by +1024 for every material; an MR needs ranges in its own "
                       "values, or segment.method: multiotsu" if lo > -50 and hi > 1000 else
                       "; the image has no value near air's -1000 HU: if it is an MR, or a scan in other units "
                       "than HU, give segment.ranges (or segment.thresholds) in its own values, or segment.method: "
                       "multiotsu" if lo > -500 else "")
            raise DicerError(f"{source}: {key} for class '{name}' is [{a:g}, {b:g}] but the image's values span "
                             f"{lo:g} .. {hi:g}; move the range inside the image's values{shifted}")
        out.append((a, b))
    for i in range(1, k):
        if out[i][0] < out[i - 1][1]:
            raise DicerError(f"{source}: {key} for class '{names[i]}' [{out[i][0]:g}, {out[i][1]:g}] overlaps or "
                             f"precedes class '{names[i - 1]}' [{out[i - 1][0]:g}, {out[i - 1][1]:g}]; ranges must "
                             "not overlap and must increase with the materials' order")
    return out


def candidate_edges(ranges, bins: int, integer: bool) -> list[np.ndarray]:
    """Candidate thresholds per range: equal steps from low up to high (``bins + 1`` values for float images).

    With ``integer`` (images of whole grey levels) the candidates and the step are whole
    numbers (step at least 1).

    Returns
    -------
    edges : list of K 1D float64 arrays, each increasing
    """
    out = []
    for a, b in ranges:
        if integer:
            a, b = np.ceil(a), np.floor(b)
            step = max(1.0, np.ceil((b - a) / bins))
            e = np.arange(a, b + 0.5 * step, step)
            e = e[e <= b] if e.size > 1 else np.array([a])
        else:
            e = np.linspace(a, b, bins + 1)
        out.append(e.astype(np.float64))
    return out


def whole_valued(array: np.ndarray) -> bool:
    """True for integer images and float images whose finite values are all whole numbers."""
    a = np.asarray(array)
    if np.issubdtype(a.dtype, np.integer):
        return True
    with np.errstate(invalid="ignore"):
        return bool(np.all((np.floor(a) == a) | ~np.isfinite(a)))


def bin_image(array: np.ndarray, edges: np.ndarray, whole: bool | None = None) -> np.ndarray:
    """Bin index of every voxel: ``b`` such that ``edges[b-1] <= value < edges[b]``.

    Parameters
    ----------
    array : ndarray of int or float
    edges : 1D float64 array, strictly increasing (length E)
    whole : bool, optional
        Whether the image holds whole grey levels only (see :func:`whole_valued`);
        computed when omitted.

    Returns
    -------
    binned : ndarray of uint16 (E < 65535), same shape; NaN goes to bin 0
    """
    a = np.asarray(array)
    lo, hi = value_range(a)
    if np.isfinite(lo) and a.size > 4 * (hi - lo + 1) and hi - lo < 2**24:
        # whole grey levels (integer images, or float images holding whole numbers): a lookup table
        if whole is None:
            whole = whole_valued(a)
        if whole and np.isfinite(a).all():
            vmin, vmax = int(lo), int(hi)
            levels = np.arange(vmin, vmax + 1, dtype=np.float64)
            lut = np.searchsorted(edges, levels, side="right").astype(np.uint16)
            return lut[a.astype(np.int32) - np.int32(vmin)]
    binned = np.searchsorted(edges, a.ravel(), side="right").astype(np.uint16).reshape(a.shape)
    if np.issubdtype(a.dtype, np.floating):
        binned[np.isnan(a)] = 0
    return binned


def cooccurrence(binned: np.ndarray, nbins: int, slab: int = 32) -> np.ndarray:
    """Symmetric grey-level co-occurrence counts over face-neighbour voxel pairs.

    Every unordered pair of face neighbours (along each axis, in 2D or 3D) with bins
    ``(i, j)`` adds 1 to ``C[i, j]`` and 1 to ``C[j, i]`` (a pair within one bin adds 2
    to ``C[i, i]``), so ``C.sum()`` is twice the number of pairs and row ``i`` sums the
    neighbours of all voxels in bin ``i``. Computed with ``np.bincount`` in slabs of
    ``slab`` planes along the first axis to bound memory.

    Parameters
    ----------
    binned : (nx, ny[, nz]) ndarray of int
        Bin index per voxel, ``0 <= b < nbins``.
    nbins : int

    Returns
    -------
    C : (nbins, nbins) ndarray of int64, symmetric
    """
    counts = np.zeros(nbins * nbins, dtype=np.int64)
    n0 = binned.shape[0]
    ndim = binned.ndim
    for start in range(0, n0, slab):
        stop = min(start + slab, n0)
        block = binned[start:stop].astype(np.int32)
        pairs = []
        if stop < n0 or stop - start > 1:  # axis-0 pairs, including the one into the next slab
            nxt = binned[start + 1:min(stop + 1, n0)].astype(np.int32)
            pairs.append((block[:nxt.shape[0]], nxt))
        for axis in range(1, ndim):
            lo = [slice(None)] * ndim
            hi = [slice(None)] * ndim
            lo[axis] = slice(None, -1)
            hi[axis] = slice(1, None)
            pairs.append((block[tuple(lo)], block[tuple(hi)]))
        for a, b in pairs:
            if a.size:
                counts += np.bincount((a * nbins + b).ravel(), minlength=nbins * nbins)
    c = counts.reshape(nbins, nbins)
    return c + c.T


class _Blocks:
    """O(1) sums of square diagonal blocks and row bands of a co-occurrence matrix."""

    def __init__(self, c: np.ndarray):
        n = c.shape[0]
        self.p = np.zeros((n + 1, n + 1), dtype=np.float64)
        self.p[1:, 1:] = np.cumsum(np.cumsum(c, axis=0), axis=1)
        self.r = np.concatenate([[0.0], np.cumsum(c.sum(axis=1), dtype=np.float64)])

    def same(self, a, b):
        """Pair ends inside bins [a, b) with the partner also inside [a, b)."""
        p = self.p
        return p[b, b] - p[a, b] - p[b, a] + p[a, a]

    def total(self, a, b):
        """All pair ends of voxels in bins [a, b)."""
        return self.r[b] - self.r[a]

    def solidity(self, a, b):
        """Fraction of the face neighbours of the voxels in bins [a, b) that lie in [a, b) too (0 if empty)."""
        t = self.total(a, b)
        s = self.same(a, b)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(t > 0, s / np.where(t > 0, t, 1), 0.0)


def _plateau_centre(values: np.ndarray) -> int:
    """Index in the middle of the first run of maximal values (deterministic tie break)."""
    best = values.max()
    top = values >= best - 1e-12 * max(1.0, abs(best))
    first = int(np.argmax(top))
    run = int(np.argmin(top[first:])) if not top[first:].all() else top.size - first
    return first + (run - 1) // 2


def _candidate_bins(ranges: list[tuple[float, float]], bins: int, whole: bool
                    ) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """The candidate thresholds of each class and the bin edges they make.

    Returns
    -------
    cands : list of K 1D float64 arrays
        Each class's candidates (``candidate_edges``), image units.
    cand_idx : list of K 1D int arrays
        Each candidate's place in ``edges``: a threshold at ``edges[j]`` starts bin j + 1.
    edges : 1D float64 array
        All candidates, sorted and distinct (the bin edges).
    """
    cands = candidate_edges(ranges, bins, whole)
    edges, inverse = np.unique(np.concatenate(cands), return_inverse=True)
    offsets = np.cumsum([0] + [len(c) for c in cands])
    cand_idx = [inverse[offsets[i]:offsets[i + 1]] for i in range(len(cands))]
    return cands, cand_idx, edges


def _bin_starts(cand_idx: list[np.ndarray], choice: list[int], nbins: int) -> list[int]:
    """The first bin of classes 0..K for the chosen candidates, and ``nbins`` at the end."""
    return [0] + [int(cand_idx[i][choice[i]]) + 1 for i in range(len(cand_idx))] + [nbins]


def _coordinate_search(blocks: _Blocks, cand_idx: list[np.ndarray], nbins: int, max_sweeps: int
                       ) -> tuple[list[int], int]:
    """Maximise J one threshold at a time from the middle of each range (see
    ``shape_connectivity_thresholds``).

    Returns
    -------
    choice : list of K int
        The chosen candidate of each class (index into its candidates).
    sweeps : int
        Sweeps made (the last one moved nothing, unless ``max_sweeps`` ran out).
    """
    k = len(cand_idx)
    choice = [len(c) // 2 for c in cand_idx]
    sweeps = 0
    for sweeps in range(1, max_sweeps + 1):
        moved = False
        for c in range(k):
            s = _bin_starts(cand_idx, choice, nbins)
            j = cand_idx[c] + 1  # candidate bin starts of class c + 1 (label c + 1)
            j = np.clip(j, s[c], s[c + 2])  # stay between the neighbouring thresholds
            values = blocks.solidity(s[c], j) + blocks.solidity(j, s[c + 2])
            best = _plateau_centre(values)
            if best != choice[c]:
                choice[c] = best
                moved = True
        if not moved:
            break
    return choice, sweeps


def _criterion_curves(blocks: _Blocks, cands: list[np.ndarray], cand_idx: list[np.ndarray], choice: list[int],
                      names: list[str], nbins: int) -> tuple[float, dict]:
    """J at the chosen thresholds, and J along each class's candidates with the others there.

    Returns
    -------
    total : float
        J at the result (at most K + 1).
    curves : dict
        Per class name: ``{"thresholds": [...], "values": [...]}`` (rounded to 4 and 6 digits).
    """
    k = len(names)
    s = _bin_starts(cand_idx, choice, nbins)
    total = float(sum(blocks.solidity(s[c], s[c + 1]) for c in range(k + 1)))
    curves = {}
    for c in range(k):
        j = np.clip(cand_idx[c] + 1, s[c], s[c + 2])
        rest = total - float(blocks.solidity(s[c], s[c + 1]) + blocks.solidity(s[c + 1], s[c + 2]))
        values = blocks.solidity(s[c], j) + blocks.solidity(j, s[c + 2]) + rest
        curves[names[c]] = {"thresholds": [round(float(x), 4) for x in cands[c]],
                            "values": [round(float(x), 6) for x in values]}
    return total, curves


def shape_connectivity_thresholds(array: np.ndarray, ranges, names: list[str], source: str,
                                  bins: int = 128, max_sweeps: int = 20) -> tuple[list[float], dict]:
    """Class thresholds by Lie's shape-connectivity criterion on face-neighbour co-occurrences.

    Criterion. For thresholds ``t_1 < ... < t_K`` the image splits into classes
    0..K (class c holds ``t_c <= v < t_{c+1}``, class 0 is background). Count every
    pair of face-neighbouring voxels (6 neighbours in 3D, 4 in 2D). For class c let
    ``S_c`` be the number of neighbour slots of its voxels that hold a voxel of class c
    too (a pair inside c counts twice) and ``B_c`` the slots that hold another class
    (the "busy" pairs straddling one of c's thresholds). The solidity of class c is
    ``P_c = S_c / (S_c + B_c)`` (0 for an empty class): the probability that a face
    neighbour of a class-c voxel is in class c. The thresholds maximise

        ``J(t_1, ..., t_K) = sum_{c=0..K} P_c``  (at most K + 1),

    which rewards solid classes and penalises busy, speckled splits; normalising per
    class keeps a threshold from running to the edge of its range to make one class
    tiny. All counts come from one grey-level co-occurrence matrix ``C`` over the
    binned intensities (bins edged by the candidate thresholds), so ``S_c`` is the sum
    of a diagonal block of ``C`` and ``S_c + B_c`` a band of its rows.

    Search. Each ``t_c`` is searched over the candidates of its range
    (``bins`` equal steps; whole grey levels when the image holds whole numbers). Moving ``t_c`` changes
    only classes c-1 and c, so ``J`` is maximised one threshold at a time over all its
    candidates (vectorised), with the others fixed, sweeping c = 1..K until no
    threshold moves. The start is the middle of each range. Among equal maxima the
    middle of the first plateau is taken.

    Parameters
    ----------
    array : (nx, ny[, nz]) ndarray of int or float
        Image intensities (HU for CT).
    ranges : list of K [low, high]
        Search range of each class's lower threshold, increasing and not overlapping.
    names : list of K str
        Class names (messages and the returned curves).
    source : str
        File named in error messages.
    bins : int
        Candidate steps per range.
    max_sweeps : int
        Upper bound on the coordinate sweeps.

    Returns
    -------
    thresholds : list of K float
    search : dict
        ``ranges``; ``criterion`` per class name: ``{"thresholds": [...], "values": [...]}``,
        J along that class's candidates with the other thresholds at their final
        values; ``criterion_max`` (J at the result); ``sweeps``; ``bins``; ``seconds``.
    """
    t0 = time.perf_counter()
    k = len(names)
    lo, hi = value_range(array)
    checked = check_ranges(ranges, k, names, lo, hi, source, array)
    whole = whole_valued(array)
    cands, cand_idx, edges = _candidate_bins(checked, int(bins), whole)
    nbins = edges.size + 1
    binned = bin_image(array, edges, whole)
    t_bin = time.perf_counter()
    blocks = _Blocks(cooccurrence(binned, nbins))
    del binned
    t_cooc = time.perf_counter()
    choice, sweeps = _coordinate_search(blocks, cand_idx, nbins, max_sweeps)
    total, curves = _criterion_curves(blocks, cands, cand_idx, choice, names, nbins)
    thresholds = [float(cands[c][choice[c]]) for c in range(k)]
    search = {
        "ranges": [[a, b] for a, b in checked],
        "bins": int(bins),
        "criterion": curves,
        "criterion_max": round(total, 6),
        "sweeps": sweeps,
        "seconds": {"binning": round(t_bin - t0, 3), "cooccurrence": round(t_cooc - t_bin, 3),
                    "search": round(time.perf_counter() - t_cooc, 3)},
    }
    return thresholds, search
