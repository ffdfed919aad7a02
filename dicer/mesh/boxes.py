"""Elements that are axis-aligned boxes of the lattice (voxel meshes, most of a plane-merged
one): tested through one integer per lattice point, without a loop over elements."""

from __future__ import annotations

import numpy as np

from dicer.mesh.model import pieces
from dicer.mesh.topology import HEX_CORNERS, QUAD_CORNERS


def linear_index(index: np.ndarray, strides) -> np.ndarray:
    """``index @ strides`` for an (n, d) integer array, as int64.

    A column at a time, in pieces of rows: numpy's integer matmul takes no BLAS and runs
    several times slower, and no temporary is of the whole size.

    Parameters
    ----------
    index : (n, d) int ndarray
    strides : sequence of d int

    Returns
    -------
    (n,) int64 ndarray
    """
    strides = [np.int64(v) for v in strides]
    out = np.empty(index.shape[0], np.int64)
    for part in pieces(index.shape[0]):
        piece = out[part]
        np.multiply(index[part, 0], strides[0], out=piece)
        for axis in range(1, len(strides)):
            if strides[axis]:
                piece += index[part, axis] * strides[axis]
    return out


def _corner_extents(cells: np.ndarray, lattice: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corner 0 of each element and its far corner's offset from it, (p, d) each."""
    lo = np.take(lattice, cells[:, 0], axis=0)  # take: about twice as fast as indexing for rows
    return lo, np.take(lattice, cells[:, 6 if cells.shape[1] == 8 else 2], axis=0) - lo


def _corners_placed(cells: np.ndarray, ext: np.ndarray, node_index: np.ndarray, strides):
    """Per corner k = 1 .. c-1: (where the box puts it, where it is), both as (p,) lattice
    point integers, one corner at a time (a caller may stop at the first mismatch)."""
    dim = ext.shape[1]
    corners = (HEX_CORNERS if cells.shape[1] == 8 else QUAD_CORNERS)[:, :dim]
    lo_index = node_index[cells[:, 0]]
    step = [ext[:, a] * np.int64(strides[a]) for a in range(dim)]
    for k in range(1, len(corners)):
        want = lo_index.copy()
        for a in np.flatnonzero(corners[k]):
            want += step[a]
        yield want, node_index[cells[:, k]]


def box_extents(cells: np.ndarray, lattice: np.ndarray, node_index: np.ndarray, strides) -> tuple | None:
    """Corner 0 and extent of each element when every one is a box of the lattice, else None.

    An element is such a box when its far corner (6 of a hexahedron, 2 of a quad) lies at
    least one lattice step beyond corner 0 along every axis and each corner sits where
    the box puts it in VTK order.

    Parameters
    ----------
    cells : (p, 8) or (p, 4) int ndarray
        Some elements.
    lattice : (N, d) int ndarray
        Lattice index of every node (d = 3, or 2 for quads).
    node_index : (N,) int64 ndarray
        ``linear_index(lattice, strides)``: one integer per lattice point.
    strides : sequence of d int

    Returns
    -------
    (lo, ext) : two (p, d) int ndarrays, or None
    """
    lo, ext = _corner_extents(cells, lattice)
    if ext.size and ext.min() < 1:
        return None
    for want, got in _corners_placed(cells, ext, node_index, strides):
        if not np.array_equal(got, want):
            return None
    return lo, ext


def box_flags(cells: np.ndarray, lattice: np.ndarray, node_index: np.ndarray, strides
              ) -> tuple[np.ndarray, np.ndarray]:
    """Which elements are boxes of the lattice (as :func:`box_extents` tests them), each one's
    answer: for a mesh of mostly boxes (a plane-merged one).

    Parameters
    ----------
    cells, lattice, node_index, strides
        As :func:`box_extents` takes them.

    Returns
    -------
    ok : (p,) bool ndarray
    ext : (p, d) int ndarray
        The extent of each element that is a box (the others' rows mean nothing).
    """
    _, ext = _corner_extents(cells, lattice)
    ok = ext[:, 0] >= 1  # column by column: a reduction along rows of 3 is slow
    for a in range(1, ext.shape[1]):
        ok &= ext[:, a] >= 1
    for want, got in _corners_placed(cells, ext, node_index, strides):
        ok &= got == want
    return ok, ext
