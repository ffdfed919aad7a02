"""Morphology on label volumes: opening by reconstruction, closing, component filters.

Material classes in a CT are nested: bone lies inside soft tissue, which lies inside
the body outline. Cleaning each class mask on its own would let the closing of soft
tissue fill thin bone, or the opening of soft tissue strip a thin scalp off the skull.
This module therefore works on *cumulative* masks ``M_c = labels >= c`` (c = 1..K),
one per class, from the outermost (c = 1, the whole body) inwards:

1. ``M'_1 = clean(M_1)`` and ``M'_c = clean(M_c & M'_{c-1})`` for c = 2..K, so that a
   part dropped from an outer class (a headrest) takes its inner classes with it;
2. ``clean`` = opening by reconstruction (radius ``r_o``), then the component filters
   (``min_component_size``, ``keep='largest'``), then closing (radius ``r_c``): the parts are
   chosen before the closing can bridge a voxel's gap between them (a CT table a voxel
   below the head was kept with it);
3. a voxel's label is the highest-priority class c that *claims* it, where class c
   claims v when ``v in M'_c`` and ``v not in M'_{c+1}`` (``M'_{K+1}`` is empty);
   a voxel no class claims is background. With nested results (the usual case) exactly
   one class claims each voxel, so the label is the largest c with ``v in M'_c``; the
   priority only settles the rare non-nested voxels (a bone closing reaching beyond
   the body mask, or a middle class removed between two kept ones for K >= 3).

Components are face-connected (6-neighbours in 3D, 4 in 2D), as the hexahedral mesh
joins elements by faces. Structuring elements are Euclidean balls (disks in 2D) of the
given radius in voxels of the image's finest axis: on longer voxels the ball keeps its size
in mm, ``round(r * finest / spacing)`` voxels along each axis (:func:`axis_radii`), so a
radius of one voxel on 0.3 x 0.3 x 5 mm slices erodes in-plane only instead of by 5 mm
across the slices. Objects touching the image border are treated as if they went on beyond
it (the erosion uses ``border_value=1``, the closing pads by edge values), so cut planes do
not erode.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage as ndi

__all__ = [
    "axis_radii",
    "ball",
    "ellipsoid",
    "opening_by_reconstruction",
    "closing",
    "filter_components",
    "clean_mask",
    "clean_labels",
]


def ball(radius: int, ndim: int) -> np.ndarray:
    """Euclidean ball (disk in 2D) structuring element.

    Parameters
    ----------
    radius : int
        Radius in voxels, >= 1. Radius 1 gives the face cross (6 neighbours in 3D).
    ndim : int
        2 or 3.

    Returns
    -------
    footprint : (2r+1,)*ndim ndarray of bool
    """
    r = int(radius)
    grid = np.ogrid[tuple(slice(-r, r + 1) for _ in range(ndim))]
    return sum(g.astype(np.int64) ** 2 for g in grid) <= r * r


def axis_radii(radius: int, spacing, ndim: int) -> tuple[int, ...]:
    """Radii along each axis, in that axis's voxels, of a ball of ``radius`` voxels of the finest axis.

    Parameters
    ----------
    radius : int
        Voxels of the finest axis.
    spacing : sequence of float or None
        Voxel size per axis, mm; None: isotropic.
    ndim : int
        2 or 3.

    Returns
    -------
    radii : tuple of int
        ``floor(radius * finest / spacing_i + 0.5)`` per axis (0: no extent along it).
    """
    if spacing is None:
        return (int(radius),) * ndim
    size = np.asarray(spacing, dtype=np.float64)[:ndim]
    return tuple(int(v) for v in np.floor(int(radius) * size.min() / size + 0.5))


def ellipsoid(radii) -> np.ndarray:
    """Structuring element of the lattice points within an axis-aligned ellipsoid.

    Parameters
    ----------
    radii : sequence of int
        Semi-axes in voxels, >= 0 (0: one voxel thick along that axis).

    Returns
    -------
    footprint : (2 r_i + 1, ...) ndarray of bool
        Equal radii give :func:`ball`.
    """
    radii = [int(r) for r in radii]
    grid = np.ogrid[tuple(slice(-r, r + 1) for r in radii)]
    wide = [r for r in radii if r > 0]
    whole = int(np.prod(np.square(wide, dtype=np.int64)))  # exact in integers: sum x_i^2 / r_i^2 <= 1
    total = sum(g.astype(np.int64) ** 2 * (whole // (r * r)) for g, r in zip(grid, radii) if r > 0)
    return np.broadcast_to(np.asarray(total <= whole), tuple(2 * r + 1 for r in radii)).copy()


def _radii(radius, ndim: int) -> tuple[int, ...]:
    """A radius (int) or per-axis radii as a tuple of ``ndim`` ints."""
    if np.ndim(radius) == 0:
        return (int(radius),) * ndim
    return tuple(int(r) for r in radius)


def _copy_when_idle(operation):
    """Wrap ``operation(mask, radius)``: it gets ``mask`` as a bool array and ``radius`` as
    per-axis radii (:func:`_radii`), and radii of 0 or less, or an empty mask, return a copy
    of ``mask`` without calling it."""

    @functools.wraps(operation)
    def wrapped(mask: np.ndarray, radius) -> np.ndarray:
        mask = np.asarray(mask, dtype=bool)
        radii = _radii(radius, mask.ndim)
        if max(radii) <= 0 or not mask.any():
            return mask.copy()
        return operation(mask, radii)

    return wrapped


_EDT_RADIUS = 4
"""From this radius on, erosion and dilation by a ball go through a distance transform: its
cost does not grow with the ball (a ball of radius 15 has 14,000 voxels; scipy's binary
erosion visits each of them per voxel: 255 s on the head CT)."""


def _within(mask: np.ndarray, radii: tuple[int, ...]) -> np.ndarray:
    """The voxels within the ellipsoid of ``radii`` of a ``mask`` voxel, by the exact Euclidean
    distance transform (axes scaled so that the ellipsoid is a ball; an axis of radius 0 by
    more than the ball, so that no step along it stays inside)."""
    big = max(radii)
    if min(radii) == big:  # a ball: squared distances are whole numbers
        distance = ndi.distance_transform_edt(~mask)
        return np.rint(distance * distance) <= big * big
    sampling = [big / r if r > 0 else big + 1.0 for r in radii]
    distance = ndi.distance_transform_edt(~mask, sampling=sampling)
    return distance * distance <= big * big * (1 + 1e-9)


def dilate(mask: np.ndarray, radius, by_distance: bool | None = None) -> np.ndarray:
    """Binary dilation of ``mask`` by :func:`ellipsoid` (``radius``: an int for a ball, or
    per-axis radii), nothing beyond the image.

    ``by_distance`` (default: from ``_EDT_RADIUS`` on): every voxel within the ellipsoid of a
    ``mask`` voxel, by the exact Euclidean distance transform; the same voxels as scipy's
    binary dilation by the structuring element."""
    radii = _radii(radius, mask.ndim)
    if by_distance if by_distance is not None else max(radii) >= _EDT_RADIUS:
        if not mask.any():
            return np.zeros_like(mask)
        return _within(mask, radii)
    return ndi.binary_dilation(mask, structure=ellipsoid(radii))


def erode(mask: np.ndarray, radius, by_distance: bool | None = None) -> np.ndarray:
    """Binary erosion of ``mask`` by :func:`ellipsoid` (``radius`` as in :func:`dilate`),
    beyond the image counting as ``mask`` (scipy's ``border_value=1``); ``by_distance`` as in
    :func:`dilate`."""
    radii = _radii(radius, mask.ndim)
    if by_distance if by_distance is not None else max(radii) >= _EDT_RADIUS:
        if mask.all():
            return mask.copy()
        return ~_within(~mask, radii)
    return ndi.binary_erosion(mask, structure=ellipsoid(radii), border_value=1)


def _face_structure(ndim: int) -> np.ndarray:
    return ndi.generate_binary_structure(ndim, 1)


@_copy_when_idle
def opening_by_reconstruction(mask: np.ndarray, radius: int) -> np.ndarray:
    """Keep the connected components of ``mask`` that survive an erosion.

    Equal to morphological reconstruction by dilation of the eroded mask under the
    mask (Vincent & Soille), computed by component labelling: a component is kept
    whole when at least one of its voxels remains after erosion by a ball of
    ``radius`` voxels, and removed whole otherwise. Thin parts attached to a thick
    part therefore stay intact; isolated specks thinner than ``2*radius + 1`` go.

    Parameters
    ----------
    mask : (nx, ny[, nz]) ndarray of bool
    radius : int or tuple of int
        Erosion radius in voxels, or per-axis radii (:func:`axis_radii`); 0 returns a copy of
        ``mask``.

    Returns
    -------
    opened : ndarray of bool, same shape as ``mask``
    """
    eroded = erode(mask, radius)
    comp, n = ndi.label(mask, structure=_face_structure(mask.ndim))
    keep = np.zeros(n + 1, dtype=bool)
    keep[comp[eroded]] = True
    keep[0] = False
    return keep[comp]


@_copy_when_idle
def closing(mask: np.ndarray, radius: int) -> np.ndarray:
    """Morphological closing by a ball of ``radius`` voxels.

    The mask is padded by the radius along each axis with its own edge values first, so that
    objects cut by the image border are not eroded there.

    Parameters
    ----------
    mask : (nx, ny[, nz]) ndarray of bool
    radius : int or tuple of int
        Voxels, or per-axis radii (:func:`axis_radii`); 0 returns a copy of ``mask``.

    Returns
    -------
    closed : ndarray of bool, same shape as ``mask``
    """
    padded = np.pad(mask, [(r, r) for r in radius], mode="edge")
    closed = erode(dilate(padded, radius), radius)
    return closed[tuple(slice(r, closed.shape[a] - r) for a, r in enumerate(radius))]


def filter_components(mask: np.ndarray, keep: str = "all", min_size: int = 0, dropped: list | None = None
                      ) -> np.ndarray:
    """Drop face-connected components by size.

    Parameters
    ----------
    mask : (nx, ny[, nz]) ndarray of bool
    keep : {'all', 'largest'}
        'largest' keeps only the largest component (the lowest label among equals).
    min_size : int
        Components with fewer voxels are dropped.
    dropped : list, optional
        Receives the voxel counts of the components dropped, largest first, and then
        (as its last entry) that of the largest component kept (0 if none).

    Returns
    -------
    filtered : ndarray of bool, same shape as ``mask``
    """
    mask = np.asarray(mask, dtype=bool)
    if (keep == "all" and min_size <= 1) or not mask.any():
        if dropped is not None:
            dropped.append(0)
        return mask.copy()
    comp, n = ndi.label(mask, structure=_face_structure(mask.ndim))
    sizes = np.bincount(comp.ravel(), minlength=n + 1)
    sizes[0] = 0
    flags = sizes >= max(min_size, 1)
    if keep == "largest":
        flags[:] = False
        flags[int(np.argmax(sizes))] = True
    flags[0] = False
    if dropped is not None:
        gone = sizes[1:][~flags[1:]]
        dropped.extend(int(v) for v in np.sort(gone)[::-1])
        dropped.append(int(sizes[flags].max(initial=0)))
    return flags[comp]


def clean_mask(mask: np.ndarray, opening_radius: int, closing_radius: int,
               keep: str = "all", min_size: int = 0, spacing=None) -> np.ndarray:
    """Opening by reconstruction, closing, then the component filters, in that order.

    Parameters
    ----------
    mask : (nx, ny[, nz]) ndarray of bool
    opening_radius, closing_radius : int
        Radii in voxels of the finest axis; 0 skips the step.
    keep : {'all', 'largest'}
    min_size : int
    spacing : sequence of float, optional
        Voxel size per axis, mm (:func:`axis_radii`); None: isotropic.

    Returns
    -------
    cleaned : ndarray of bool, same shape as ``mask``
    """
    out = opening_by_reconstruction(mask, axis_radii(opening_radius, spacing, mask.ndim))
    out = closing(out, axis_radii(closing_radius, spacing, mask.ndim))
    return filter_components(out, keep, min_size)


def _per_class(value, k: int, name: str) -> list:
    if isinstance(value, (list, tuple)):
        if len(value) != k:
            raise ValueError(f"{name}: {len(value)} values for {k} classes")
        return list(value)
    return [value] * k


def clean_labels(labels: np.ndarray, n_classes: int, opening_radius: int, closing_radius: int,
                 keep="all", min_size=0, priority=None, spacing=None) -> tuple[np.ndarray, dict]:
    """Clean a label volume class by class on cumulative masks (see the module notes).

    Parameters
    ----------
    labels : (nx, ny[, nz]) ndarray of int
        0 background, 1..K material classes in order of increasing density.
    n_classes : int
        K.
    opening_radius, closing_radius : int
        Radii in voxels of the finest axis for every class; 0 skips the step.
    keep : {'all', 'largest'} or list of K of them
        Per class (1..K) component filter on the class's cumulative mask.
    min_size : int or list of K ints
        Per class minimum component size in voxels.
    priority : sequence of int, optional
        Class labels, highest priority first; default ``K, K-1, ..., 1``.
    spacing : sequence of float, optional
        Voxel size per axis, mm: on longer voxels the balls keep their size in mm
        (:func:`axis_radii`); None: isotropic.

    Returns
    -------
    cleaned : ndarray, same shape and dtype as ``labels``
    info : dict
        ``removed_by_opening``: per class (1..K) the voxels the opening removed from its
        cumulative mask; ``removed_parts``: per class, the parts ``keep``/``min_size``
        dropped from it (count, voxels, the largest, and the largest kept).
    """
    k = int(n_classes)
    keeps = _per_class(keep, k, "keep")
    sizes = _per_class(min_size, k, "min_component_size")
    prio = list(priority) if priority is not None else list(range(k, 0, -1))
    opening = axis_radii(opening_radius, spacing, labels.ndim)
    closing_radii = axis_radii(closing_radius, spacing, labels.ndim)
    masks = []
    removed = {}
    parts = {}
    outer = None
    for c in range(1, k + 1):
        m = labels >= c
        if outer is not None:
            m &= outer
        before = int(np.count_nonzero(m))
        opened = opening_by_reconstruction(m, opening)
        removed[c] = before - int(np.count_nonzero(opened))
        dropped: list[int] = []
        # the parts chosen before the closing, which would bridge a table a voxel from the body
        m = closing(filter_components(opened, keeps[c - 1], sizes[c - 1], dropped), closing_radii)
        parts[c] = {"parts": len(dropped) - 1, "voxels": sum(dropped[:-1]),
                    "largest": dropped[0] if len(dropped) > 1 else 0, "largest_kept": dropped[-1]}
        masks.append(m)
        outer = m
    out = np.zeros_like(labels)
    assigned = np.zeros(labels.shape, dtype=bool)
    for c in prio:  # highest priority first: the first class that claims a voxel keeps it
        claim = masks[c - 1] & ~masks[c] if c < k else masks[c - 1]
        claim &= ~assigned
        out[claim] = c
        assigned |= claim
    return out, {"removed_by_opening": removed, "removed_parts": parts}
