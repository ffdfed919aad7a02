"""Array helpers shared by the stages (numpy only, so every part of dicer can import them)."""

from __future__ import annotations

import numpy as np

__all__ = ["all_per_row", "any_per_row", "argwhere", "nonzero", "norm"]


def nonzero(mask: np.ndarray) -> tuple[np.ndarray, ...]:
    """The indices of the true entries of ``mask``, per axis: ``np.nonzero(mask)``.

    The same arrays (int64, C order), from the flat indices: numpy's nonzero walks an
    n-dimensional array several times more slowly (measured 18 ms against 0.9 ms on a
    257 x 257 x 108 mask with 2,000 entries, 46 ms against 6 ms on a (2.27 M, 6) one with 1 %).

    Parameters
    ----------
    mask : ndarray
        Any shape; its truth is taken.

    Returns
    -------
    tuple of (N,) int64 ndarray
        One per axis.
    """
    mask = np.asarray(mask)
    if mask.ndim < 2:
        return np.nonzero(mask)
    return np.unravel_index(np.flatnonzero(mask), mask.shape)


def argwhere(mask: np.ndarray) -> np.ndarray:
    """(N, ndim) int64 ndarray: the indices of the true entries, a row each: ``np.argwhere(mask)``."""
    mask = np.asarray(mask)
    return np.stack(nonzero(mask), axis=1) if mask.ndim else np.argwhere(mask)


_SHORT = 7
"""Longest vector :func:`norm` sums itself: numpy's reduction adds up to seven terms in order,
and more in blocks (pairwise summation), whose order it would have to copy."""


def norm(v: np.ndarray, axis: int = -1, keepdims: bool = False) -> np.ndarray:
    """The Euclidean lengths of the vectors along ``axis``: ``np.linalg.norm(v, axis=axis)``.

    The same bytes for float32 and float64 vectors of one to seven components (their squares
    summed in order, as numpy's reduction sums so few), an elementwise product and sum per
    component: numpy's general reduction over a short axis is an order of magnitude slower
    (measured 1.62 s against 0.13 s on (2 M, 8, 3), 0.12 s against 0.011 s on (600 k, 3, 3)).
    Other vectors, and a single vector, go to numpy.

    Parameters
    ----------
    v : ndarray
        Vectors along ``axis``.
    axis : int, optional
    keepdims : bool, optional
        Keep ``axis`` with length 1.

    Returns
    -------
    ndarray
        ``v``'s shape without ``axis`` (with it of length 1: ``keepdims``).
    """
    v = np.asarray(v)
    if v.ndim < 2 or v.dtype not in (np.float32, np.float64) or not 1 <= v.shape[axis] <= _SHORT:
        return np.linalg.norm(v, axis=axis, keepdims=keepdims)
    parts = np.moveaxis(v, axis, 0)
    total = parts[0] * parts[0]
    for part in parts[1:]:
        total += part * part
    np.sqrt(total, out=total)
    return np.expand_dims(total, axis) if keepdims else total


_ROW_WORDS = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


def any_per_row(mask: np.ndarray) -> np.ndarray:
    """(M,) bool: ``mask.any(axis=1)`` of an (M, k) mask.

    For k of 1, 2, 4 or 8 (a voxel's, a face's or an element's nodes), each row's bytes read
    as one unsigned integer: numpy's reduction over so short an axis takes about twice as long
    (measured 0.06 s against 0.03 s with the gather, on a head's 2.27 M elements). Other widths
    go to numpy.

    Parameters
    ----------
    mask : (M, k) ndarray
        Its truth is taken.

    Returns
    -------
    (M,) bool ndarray
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.shape[1] not in _ROW_WORDS:
        return mask.any(axis=1)
    rows = np.ascontiguousarray(mask, dtype=bool)
    return rows.view(_ROW_WORDS[rows.shape[1]])[:, 0] != 0


def all_per_row(mask: np.ndarray) -> np.ndarray:
    """(M,) bool: ``mask.all(axis=1)`` of an (M, k) mask, as :func:`any_per_row`."""
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.shape[1] not in _ROW_WORDS:
        return mask.all(axis=1)
    return ~any_per_row(~np.asarray(mask, dtype=bool))
