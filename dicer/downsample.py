"""Resolution reduction of a label volume by a vote that keeps thin classes.

The fine volume is cut into blocks of ``f_x * f_y * f_z`` voxels (after padding
with background at the high end of each axis to a multiple of the factor); each
block becomes one coarse voxel by this vote:

1. every non-background class that fills at least ``min_fraction`` of the block
   (padding counts as background) is a candidate; the candidate first in the class
   priority (``segment.priority``, default densest first) wins;
2. if no class qualifies, the most frequent value of the block wins, background
   included (ties: the class first in the priority, background last).

With ``downsample.vote: plurality`` (the default for label volumes made elsewhere: an
atlas's label numbers order nothing) rule 1 goes by count: when the non-background
classes together fill ``min_fraction`` of the block, the most frequent of them wins.

A two-voxel bone plate in 4-voxel blocks fills half of each block it crosses, so it
survives a vote that plain majority would lose. The coarse spacing is the fine
spacing times the factor; the origin (corner of voxel 0) is unchanged. Opening by
reconstruction and closing then run again (``downsample.morphology``), with the
``segment`` section's options, to mend thin sections, as the paper does.
"""

from __future__ import annotations

import numpy as np

from dicer.config import takes_settings
from dicer.errors import DicerError
from dicer.image import Volume, regridded_origin
from dicer.segment import check_radii, label_counts, morphology_options
from dicer.segment.morphology import clean_labels

__all__ = ["downsample", "reduction_factor", "vote"]


def reduction_factor(spacing, *, factor, voxel_size, source: str = "") -> tuple[int, ...]:
    """Integer reduction factor per axis from ``downsample.factor`` or ``downsample.voxel_size``.

    Parameters
    ----------
    spacing : sequence of float
        Voxel size in mm, one per axis.
    factor : int or list of int
        ``downsample.factor``: one for all axes or one per axis.
    voxel_size : float or list of float or None
        ``downsample.voxel_size`` in mm; when set it wins: factor =
        ``max(1, round(voxel_size / spacing))`` per axis.
    source : str, optional
        File named in error messages.

    Returns
    -------
    factor : tuple of int, one per axis

    Raises
    ------
    DicerError
        A list of another length than the volume's axes.
    """
    ndim = len(spacing)
    if voxel_size is not None:
        t = list(voxel_size) if isinstance(voxel_size, (list, tuple)) else [voxel_size] * ndim
        if len(t) != ndim:
            raise DicerError(f"{source}: downsample.voxel_size has {len(t)} values for a {ndim}D volume; "
                             f"give one value or {ndim}")
        return tuple(max(1, int(np.floor(float(a) / float(s) + 0.5))) for a, s in zip(t, spacing))
    f = list(factor) if isinstance(factor, (list, tuple)) else [factor] * ndim
    if len(f) != ndim:
        raise DicerError(f"{source}: downsample.factor has {len(f)} values for a {ndim}D volume; "
                         f"give one value or {ndim}")
    return tuple(int(x) for x in f)


VOXEL_SIZE_ROUNDED = 0.2
"""Relative difference between ``downsample.voxel_size`` and the voxels it gives (a whole number
of the volume's per axis, none finer) above which it is said."""


def _say_rounded_voxel_size(voxel_size, spacing, factor) -> None:
    """Warn when the voxels a ``downsample.voxel_size`` gives differ from it by more than
    VOXEL_SIZE_ROUNDED on an axis: 0.7 mm asked of 0.5 mm voxels gives 0.5 mm, 0.25 mm gives 0.5 mm
    (downsampling does not refine)."""
    asked = list(voxel_size) if isinstance(voxel_size, (list, tuple)) else [voxel_size] * len(spacing)
    got = [f * float(s) for f, s in zip(factor, spacing)]
    if all(abs(g / float(a) - 1) <= VOXEL_SIZE_ROUNDED for g, a in zip(got, asked)):
        return
    import logging

    size = lambda v: " x ".join(f"{float(x):g}" for x in v)  # noqa: E731
    logging.getLogger("dicer").warning(
        "downsample: voxel_size %s mm gives voxels of %s mm, a whole number of the volume's %s mm voxels per axis "
        "(factor %s; downsampling never makes them finer)", size(asked), size(got), size(spacing), list(factor))


def vote(labels: np.ndarray, factor, n_classes: int, min_fraction: float, priority=None,
         plurality: bool = False) -> np.ndarray:
    """Reduce a label array by the thin-class vote (see the module notes).

    Parameters
    ----------
    labels : (nx, ny[, nz]) ndarray of int
        0 background, 1..K classes.
    factor : sequence of int
        Block size per axis.
    n_classes : int
        K.
    min_fraction : float
        Fraction of a block, in [0, 1], a class must fill to be a candidate.
    priority : sequence of int, optional
        Class labels, highest priority first; default ``K, ..., 1``.
    plurality : bool, optional
        Rule 1 by count: when the non-background classes together fill ``min_fraction``,
        the most frequent of them wins (ties: the first in the priority).

    Returns
    -------
    coarse : ndarray, dtype of ``labels``, shape ``ceil(n / factor)`` per axis
    """
    k = int(n_classes)
    f = tuple(int(x) for x in factor)
    prio = list(priority) if priority is not None else list(range(k, 0, -1))
    work = labels.view(np.uint8) if labels.dtype == bool else labels
    pad = [(0, (-n) % fi) for n, fi in zip(labels.shape, f)]
    padded = np.pad(work, pad) if any(p[1] for p in pad) else work
    coarse_shape = tuple(n // fi for n, fi in zip(padded.shape, f))
    block = int(np.prod(f))
    order = prio + [0]  # the tie-break order of rule 2
    top = max(int(padded.max(initial=0)), k)
    rank = np.full(top + 1, len(order), np.int64)  # position in ``order``; len(order): not in it
    rank[order] = np.arange(len(order))
    out = np.empty(coarse_shape, dtype=labels.dtype)
    step = max(1, _VOXELS // max(1, padded[: f[0]].size))  # coarse planes along x per slab
    for x0 in range(0, coarse_shape[0], step):
        slab = padded[x0 * f[0] : (x0 + step) * f[0]]
        odd = None
        if plurality:  # the blocks' checkerboard parity: which way a tie goes
            grid = np.indices((min(step, coarse_shape[0] - x0),) + coarse_shape[1:]).sum(axis=0) + x0
            odd = (grid % 2 == 1).ravel()
        out[x0 : x0 + step] = _vote_blocks(_blocks(slab, f), rank, np.asarray(order), min_fraction * block,
                                           plurality, odd).reshape((-1,) + coarse_shape[1:])
    return out


_thin_class_vote = vote  # for downsample, whose setting of that name hides it


_VOXELS = 1 << 22  # fine voxels per slab of the vote: its temporaries stay small


def _blocks(a: np.ndarray, f: tuple[int, ...]) -> np.ndarray:
    """(blocks, voxels per block): the voxels of each ``f`` block of ``a`` (shape a multiple of
    ``f``) in one row, blocks in C order of the coarse grid."""
    coarse = tuple(n // fi for n, fi in zip(a.shape, f))
    split = tuple(x for pair in zip(coarse, f) for x in pair)
    nd = len(f)
    return a.reshape(split).transpose(tuple(range(0, 2 * nd, 2)) + tuple(range(1, 2 * nd, 2))).reshape(
        int(np.prod(coarse)), int(np.prod(f)))


def _vote_blocks(rows: np.ndarray, rank: np.ndarray, order: np.ndarray, need: float,
                 plurality: bool = False, odd: np.ndarray | None = None) -> np.ndarray:
    """The vote of every row of ``rows`` (blocks, voxels): one pass over the sorted rows.

    rank : position of each value in ``order`` (prio then background; len(order) for
    values outside it). Sorting each row turns its classes into runs, so the counts of
    every class present come out together, however many classes there are.
    """
    n, width = rows.shape
    flat = np.sort(rows, axis=1).ravel()
    start = np.ones(flat.size, dtype=bool)
    np.not_equal(flat[1:], flat[:-1], out=start[1:])
    start[::width] = True  # every row starts a run
    runs = np.flatnonzero(start)
    count = np.diff(np.append(runs, flat.size))
    r = rank[flat[runs]]
    first = np.searchsorted(runs, np.arange(n) * width)  # each row's first run
    outside = len(order)
    # rule 2: the most frequent value of ``order``, ties to the first in it
    score = np.where(r < outside, count * (outside + 1) + (outside - r), 0)
    plural = np.maximum.reduceat(score, first)
    plural_rank = np.where(plural > 0, outside - plural % (outside + 1), 0)
    classes = r < outside - 1  # runs of a class of the priority (not the background)
    if plurality:
        # rule 1 by count: the classes together fill ``need``: the most frequent of them; a tie
        # goes to the first in the priority in every other block (``odd`` False) and to the
        # last in the others, so that no class wins the ties of a whole atlas by its number
        filled = np.add.reduceat(np.where(classes, count, 0), first)
        tie = np.where(odd[runs // width], r + 1, outside - r) if odd is not None else outside - r
        top = np.maximum.reduceat(np.where(classes, count * (outside + 1) + tie, 0), first)
        top = np.where(top > 0, np.where(odd[np.arange(n)], top % (outside + 1) - 1, outside - top % (outside + 1))
                       if odd is not None else outside - top % (outside + 1), outside)
        best = np.where(filled >= need, top, outside)
    else:
        # rule 1: among the classes of the priority filling ``need`` (and at least one voxel), the first
        cand = (count >= need) & (count > 0) & classes
        best = np.minimum.reduceat(np.where(cand, r, outside), first)
    return order[np.where(best < outside, best, plural_rank)].astype(rows.dtype)


@takes_settings("downsample")
def downsample(labels: Volume, *, names: list[str], factor, voxel_size, min_fraction: float, morphology: bool,
               vote: str | None, opening_radius: int, closing_radius: int, keep, min_component_size, priority,
               source: str = "") -> tuple[Volume, dict]:
    """Reduce a label volume's resolution, keeping thin classes, then clean it again.

    The settings are keyword-only with no defaults here: the command line passes
    ``dicer.config.stage_kwargs(config, "downsample")``. A library call may instead give
    a configuration as the second argument (and ``source`` third), or leave settings
    out; the schema's defaults fill them (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    labels : Volume
        (nx, ny[, nz]) integer labels, 0 background, 1..K classes; spacing in mm.
    names : list of str
        The material names (the ``materials`` section); label i is ``names[i - 1]``.
    factor, voxel_size, min_fraction, morphology, vote
        The ``downsample:`` config section (see the schema).
    opening_radius, closing_radius, keep, min_component_size, priority
        Those keys of the ``segment:`` section: the vote's class priority and the
        cleaning after the reduction.
    source : str
        The label file's name, used in error messages.

    Returns
    -------
    reduced : Volume
        Coarse labels, same dtype; spacing multiplied by the factor, same origin.
        With factor 1 on every axis the input is returned unchanged.
    info : dict
        ``factor``, ``shape_before``, ``shape_after``, ``spacing_after``, ``voxels_before`` /
        ``voxels_after`` per class name, and per axis how far the coarse grid reaches beyond
        the image (``beyond_image_mm``) and whether material lies in that last layer
        (``material_beyond_image``).
    """
    source = source or "labels"
    k = len(names)
    array = labels.array
    if array.ndim not in (2, 3):
        raise DicerError(f"{source}: a {array.ndim}D label volume; give a 2D or 3D one")
    if not (np.issubdtype(array.dtype, np.integer) or array.dtype == bool):
        if not np.array_equal(array, np.round(array)):
            raise DicerError(f"{source}: label volume holds non-integer values; give the output of dicer segment")
        array = array.astype(np.int16)
    if array.size and (int(array.min()) < 0 or int(array.max()) > k):
        raise DicerError(f"{source}: labels span {int(array.min())} .. {int(array.max())} but the config names "
                         f"{k} material(s) (labels 0..{k}); use the config the labels were segmented with")
    factor = reduction_factor(labels.spacing, factor=factor, voxel_size=voxel_size, source=source)
    if voxel_size is not None:
        _say_rounded_voxel_size(voxel_size, labels.spacing, factor)
    morphology = True if morphology is None else bool(morphology)  # null: a scan's default (for_label_volume)
    before = {n: v["voxels"] for n, v in label_counts(array, names).items()}
    info = {"factor": list(factor), "shape_before": list(array.shape), "vote": vote or "priority",
            "morphology": morphology}
    if all(f == 1 for f in factor):
        info.update(shape_after=list(array.shape), spacing_after=list(labels.spacing),
                    voxels_before=before, voxels_after=before)
        return labels, info
    after = [-(-n // f) for n, f in zip(array.shape, factor)]
    if min(after) < 2:
        axis = int(np.argmin(after))
        what = "downsample.voxel_size" if voxel_size is not None else "downsample.factor"
        raise DicerError(f"{source}: {what} gives a factor {'x'.join(map(str, factor))} that leaves "
                         f"{'x'.join(map(str, after))} voxels of the {'x'.join(map(str, array.shape))} label "
                         f"volume; dicer needs at least 2 voxels per axis: use a factor of at most "
                         f"{max(array.shape[axis] // 2, 1)} along axis {'xyz'[axis]}")
    options = morphology_options(names, opening_radius=opening_radius, closing_radius=closing_radius, keep=keep,
                                 min_component_size=min_component_size, priority=priority, source=source)
    if morphology:
        check_radii(options, after, source)
    coarse = _thin_class_vote(array, factor, k, float(min_fraction), options["priority"],
                              plurality=vote == "plurality")  # null: a scan's default (for_label_volume)
    if morphology:
        cleaned, _ = clean_labels(coarse, **options,
                                  spacing=[v * f for v, f in zip(labels.spacing, factor)])
        if coarse.any() and not cleaned.any():
            raise DicerError(f"{source}: the morphology after downsampling removed every voxel; lower "
                             "segment.opening_radius or the downsample factor, or set downsample.morphology=false")
        coarse = cleaned
    spacing = tuple(s * f for s, f in zip(labels.spacing, factor))
    # a shape that is no multiple of the factor: the last coarse layer reaches beyond the
    # image, and material voted into it grows the model by that much
    beyond = [((-n) % f) * float(sp) for n, f, sp in zip(array.shape, factor, labels.spacing)]
    grown = [bool(b > 0 and np.take(coarse, -1, axis=d).any()) for d, b in enumerate(beyond)]
    voxels_after = {n: v["voxels"] for n, v in label_counts(coarse, names).items()}
    block = int(np.prod(factor))  # fine voxels per coarse voxel
    info.update(shape_after=list(coarse.shape), spacing_after=[round(s, 6) for s in spacing],
                beyond_image_mm=[round(b, 6) for b in beyond], material_beyond_image=grown,
                voxels_before=before, voxels_after=voxels_after,
                volume_change_percent={n: round(100.0 * (voxels_after.get(n, 0) * block - v) / v, 2)
                                       for n, v in before.items() if v})
    return Volume(coarse, spacing, regridded_origin(labels, spacing), labels.direction), info
