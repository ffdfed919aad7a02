"""Array helpers shared by the stages (numpy only, so every part of dicer can import them)."""

from __future__ import annotations

import numpy as np

__all__ = ["argwhere", "nonzero"]


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
