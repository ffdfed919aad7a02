"""Boundary and interior smoothing (DICER Box 3 and section 2.6) with a quality guard.

1. **Boundary solve.** For every boundary node n (see ``dicer.mesh.boundary``)::

       x_n - (k_n / R_n) * sum_{j in N_b(n)} x_j = (1 - k_n) * x_n^0

   with R_n its boundary-edge count, N_b(n) its boundary neighbours and k_n the
   coefficient of its node class. Multiplying row n by R_n / k_n gives the symmetric,
   strictly diagonally dominant (so positive definite) system
   ``(R_n/k_n) x_n - sum x_j = R_n (1/k_n - 1) x_n^0``, solved for the three coordinates
   at once by Jacobi-preconditioned conjugate gradients (on displacements, in single
   precision). Nodes with k_n = 0 stay put. Nodes on a bounding plane of the image follow
   ``bounding_planes``: ``mirror`` (default) smooths them as in the model reflected
   across the plane (see below), ``fixed`` keeps them still, ``free`` smooths the cut
   face as a surface of its own (in the plane with ``keep_bounding_planes``). With ``shrink_compensation`` the solve S is
   applied twice, x = (2S - S^2) x0 ("twicing"): the stair steps go, the shrinkage of
   curved surfaces does not.
2. **Interior solve.** With boundary nodes fixed, the displacement u of interior nodes
   solves the graph Laplace equation u_n = mean of u over its edge neighbours; on the
   unmerged lattice that is exactly "every interior node at the centroid of its
   neighbours' final positions" (paper 2.6), and on a plane-merged mesh it keeps the
   graded spacing. The solve is restricted to the interior nodes within ``interior_band``
   edges of the boundary (u = 0 beyond; 0 = all interior nodes).
3. **Quality guard.** No element may end with a scaled Jacobian below
   ``min_scaled_jacobian`` (and never <= 0). Where one would, the coefficients of the
   boundary nodes of the offending elements (widening to their neighbours when those
   already stay put) are multiplied by ``backoff_factor``, or set to 0 in the last
   rounds, and both solves rerun. A mesh that still fails raises DicerError naming the
   worst element. (The scaled Jacobian before smoothing is computed only for elements
   that fail: an element already below the floor fails only if it got worse.)

**Mirror planes.** The bounding planes are treated as symmetry planes: the boundary
graph and node classes are those of the model reflected across them (``boundary_graph``
with ``mirror=True``), a plane node's neighbour off the plane counts once per reflected
copy, and the plane node keeps its normal coordinate (in the mirrored model symmetry
keeps it there). Both solves are then the mirrored model's solves restricted to the
image: the operator (row n: copies of j next to n) is self-adjoint in the inner product
that weighs node n by 2^-(planes it lies on), its share of the mirrored model, and the
conjugate gradients use that inner product, so their iterates are the mirrored model's
(to rounding), whatever the tolerance.

The arithmetic is single-threaded numpy and scipy.sparse (no BLAS calls, whose threaded
sums depend on the thread count): the same input gives the same output, bit for bit,
whatever the number of threads.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from dicer.arrays import any_per_row, nonzero, norm
from dicer.config import places_faces_by_scan, relaxes_staircase, section_defaults, takes_settings
from dicer.errors import DicerError
from dicer.mesh.boundary import (NODE_CLASSES, BoundaryGraph, boundary_graph, bounding_planes, class_counts,
                                 mirror_share, mirror_weights, plane_axes, plane_bits)
from dicer.mesh.metrics import (characteristic_length, corner_scaled_jacobians, element_volumes, hex_scaled_jacobian_t,
                                hex_volumes_t, scaled_jacobian)
from dicer.mesh.model import CHUNK, LEVEL_DATA, Mesh, is_graded, pieces
from dicer.mesh.topology import HEX_CORNERS, HEX_EDGES, QUAD_CORNERS, QUAD_EDGES

__all__ = ["DEFAULTS", "smooth_mesh", "smoothing_settings"]

log = logging.getLogger("dicer")

DEFAULTS = section_defaults("smooth")
"""The ``smooth:`` section's defaults, as the config schema gives them."""
_CLASS_LETTERS = ("A", "B", "C", "D", "E", "F")
_PULL_ROUNDS = 5  # guard rounds per solve that back off the pull onto the image's surface


@takes_settings("smooth", section=True)
def smoothing_settings(*, surface_from_image, image_sigma, surface_from_labels, label_surface_radius, fit_to_scan,
                       label_samples, coefficient, coefficients, bounding_planes, keep_bounding_planes, interior,
                       shrink_compensation, interior_band, min_scaled_jacobian, backoff_factor, max_backoff_rounds, pillow,
                       pillow_thickness, tolerance) -> dict:
    """The ``smooth:`` settings as the solves read them: a coefficient per node class.

    Types and ranges are the schema's to check (:func:`dicer.config.stage_kwargs`, through
    which a section or partial settings may be given); this adds what the schema cannot say.

    Parameters
    ----------
    surface_from_image, image_sigma, surface_from_labels, label_surface_radius, fit_to_scan, label_samples, \
coefficient, coefficients, bounding_planes, keep_bounding_planes, interior, shrink_compensation, interior_band, \
min_scaled_jacobian, backoff_factor, max_backoff_rounds, pillow, pillow_thickness, tolerance
        The ``smooth:`` config section (see the schema).

    Returns
    -------
    dict
        The settings; ``coefficients`` holds every class A-F as a float (``coefficient``,
        when not None, replaces them all, with a warning when the map differs from its
        defaults).

    Raises
    ------
    DicerError
        ``keep_bounding_planes: false`` without ``bounding_planes: free`` (checked with the
        settings, :func:`dicer.config.validate`).
    """
    # a map left at its defaults (config/config.yaml lists them) loses nothing to the one value
    mapped = [f"{c} {coefficients[c]:g}" for c in _CLASS_LETTERS
              if float(coefficients[c]) != float(DEFAULTS["coefficients"][c])]
    if coefficient is not None and mapped:
        log.warning("smooth: smooth.coefficient %g is used for every node class, so the smooth.coefficients map "
                    "given (%s) is not used; leave smooth.coefficient out (null) to smooth with the map",
                    coefficient, ", ".join(mapped))
    per_class = {c: float(coefficients[c] if coefficient is None else coefficient) for c in _CLASS_LETTERS}
    return {"surface_from_image": surface_from_image, "image_sigma": image_sigma,
            "surface_from_labels": surface_from_labels, "label_surface_radius": label_surface_radius,
            "fit_to_scan": fit_to_scan, "label_samples": label_samples, "coefficient": coefficient,
            "coefficients": per_class, "bounding_planes": bounding_planes,
            "keep_bounding_planes": keep_bounding_planes, "interior": interior,
            "shrink_compensation": shrink_compensation, "interior_band": interior_band,
            "min_scaled_jacobian": min_scaled_jacobian, "backoff_factor": backoff_factor,
            "max_backoff_rounds": max_backoff_rounds, "pillow": pillow, "pillow_thickness": pillow_thickness,
            "tolerance": tolerance}


# --- solvers -------------------------------------------------------------------------------
#
# Every reduction and vector update is a numpy ufunc or einsum, never a BLAS call:
# OpenBLAS splits dot and axpy between threads, so their results would depend on the
# number of threads (and the threads' hand-offs cost more than the sums on a busy machine).


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b of two vectors, in one thread."""
    return float(np.einsum("i,i->", a, b))


def _wdot(w: np.ndarray):
    """a . b weighted by w, in one thread."""
    return lambda a, b: float(np.einsum("i,i,i->", w, a, b))


def _pcg(apply, b: np.ndarray, inv_diag: np.ndarray | None, tol: float, maxiter: int,
         weight: np.ndarray | None = None, start: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Conjugate gradients on A x = b, ``apply(p)`` giving A p.

    ``b`` holds the columns of a block-diagonal system stacked into one vector (the block
    system is symmetric positive definite when each block is). Preconditioned by
    ``inv_diag`` (None: none), until ||r|| <= tol * ||b||. Vector updates are in place.
    ``weight``: the inner product sum w a b (A self-adjoint in it; None: w = 1).
    ``start``: the first iterate (None: 0); the stopping rule is the same either way.
    """
    _dot_ = _dot if weight is None else _wdot(weight)
    bnorm = float(np.sqrt(_dot_(b, b)))
    if bnorm == 0:
        return np.zeros_like(b), 0
    buf = np.empty_like(b)
    if start is None:
        x = np.zeros_like(b)
        r = b.copy()
    else:
        x = start.astype(b.dtype, copy=True)
        r = b - apply(x)
        if np.sqrt(_dot_(r, r)) <= tol * bnorm:
            return x, 0
    z = r if inv_diag is None else r * inv_diag
    p = z.copy()
    rz = _dot_(r, z)
    target = tol * bnorm
    for it in range(1, maxiter + 1):
        q = apply(p)
        pq = _dot_(p, q)
        if pq <= 0:
            return x, it
        alpha = rz / pq
        x += np.multiply(p, alpha, out=buf)
        r -= np.multiply(q, alpha, out=buf)
        rr = _dot_(r, r)
        if np.sqrt(rr) <= target:
            return x, it
        if inv_diag is None:
            rz_new = rr  # z is r
        else:
            np.multiply(r, inv_diag, out=z)
            rz_new = _dot_(r, z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, maxiter


def _csr_rows(col: np.ndarray, keep: np.ndarray, n_cols: int, dtype) -> sp.csr_matrix:
    """0/1 matrix with a one in row i at column col[i, j] for every keep[i, j], in that order."""
    indptr = np.zeros(col.shape[0] + 1, np.int64)
    np.cumsum(np.count_nonzero(keep, axis=1), out=indptr[1:])
    indices = col[keep]
    return sp.csr_matrix((np.ones(indices.size, dtype), indices, indptr), shape=(col.shape[0], n_cols))


class _BoundarySystem:
    """The boundary system for one set of coefficients ``k``, assembled once for its solves.

    A coordinate is fixed when ``fixed`` says so (a kept bounding plane) or its node has
    k = 0 or no boundary edge. The three coordinates are solved at once, stacked x | y | z,
    on the block-diagonal operator diag(R/k) - adjacency, whose block for a coordinate keeps
    only the edges between nodes free in it (a fixed coordinate's displacement is 0).
    With mirror planes ``adj`` holds the copies of a neighbour (not symmetric) and
    ``weight`` the nodes' shares of the mirrored model, the CG inner product.
    """

    def __init__(self, adj: sp.csr_matrix, degree: np.ndarray, k: np.ndarray, fixed: np.ndarray,
                 weight: np.ndarray | None = None):
        n = degree.size
        self.adj, self.degree = adj, degree
        self.fixed = fixed | (k <= 0)[:, None] | (degree == 0)[:, None]
        self.free = ~self.fixed
        kk = np.where(k > 0, k, 1.0)
        diag = (degree / kk).astype(np.float32)
        inv_diag = np.where(diag > 0, 1.0 / np.where(diag > 0, diag, 1.0), 1.0).astype(np.float32)
        self.inv_diag = np.tile(inv_diag, 3)
        self.weight = None if weight is None else np.tile(weight.astype(np.float32), 3)
        self.diag = np.where(self.free.T, diag, np.float32(1.0)).ravel()
        rows = np.repeat(np.arange(n), np.diff(adj.indptr))
        cols = adj.indices
        indices, counts, data = [], [], []
        for d in range(3):
            keep = self.free[rows, d] & self.free[cols, d]
            indices.append(cols[keep].astype(np.int64) + d * n)
            counts.append(np.bincount(rows[keep], minlength=n))
            data.append(adj.data[keep].astype(np.float32))  # copies of the neighbour: 1, 2, 4 or 8
        indptr = np.zeros(3 * n + 1, np.int64)
        np.cumsum(np.concatenate(counts), out=indptr[1:])
        indices = np.concatenate(indices)
        self.mat = sp.csr_matrix((np.concatenate(data), indices, indptr), shape=(3 * n, 3 * n))

    def step(self, y: np.ndarray, tol: float, start: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """The displacement S(y) - y of the boundary system applied to positions ``y``; ``start``
        (B, 3): a displacement to start from (a guard round's previous one: it changes few
        coefficients), None: 0.

        With x = y + delta, the system (R/k) x_n - sum x_j = R (1/k - 1) y_n becomes
        (R/k) delta_n - sum delta_j = sum_j (y_j - y_n): the right-hand side is the graph
        Laplacian of y (small numbers), so single precision and a relative residual of
        ``tol`` are ample. Fixed coordinates (and nodes with k = 0) get delta = 0.
        """
        n = y.shape[0]
        lap = self.adj @ y - self.degree[:, None] * y  # float64: positions are large, differences small
        rhs = np.where(self.free, lap, 0.0).astype(np.float32)
        b = np.ascontiguousarray(rhs.T).ravel()
        diag, out = self.diag, np.empty_like(b)
        blocks = _row_blocks(self.mat)

        def apply(v):
            def rows(job):
                a, b, block = job
                product = block @ v
                np.multiply(diag[a:b], v[a:b], out=out[a:b])
                np.subtract(out[a:b], product, out=out[a:b])

            _side_by_side(rows, blocks, len(blocks) > 1)
            return out

        if start is not None:
            start = np.ascontiguousarray(np.where(self.fixed, 0.0, start).T, np.float32).ravel()
        delta, it = _pcg(apply, b, self.inv_diag, tol, 2000, self.weight, start)
        return np.where(self.fixed, 0.0, delta.reshape(3, n).T.astype(np.float64)), it


# rows of the element array per block of the passes over all elements: a block's columns
# stay in the cache while each corner is read
_ROWS = 65536


def _touching(cells: np.ndarray, mark: np.ndarray) -> np.ndarray:
    """Indices of the elements with at least one node marked in ``mark`` (N,) bool."""
    return np.flatnonzero(any_per_row(mark[cells]))


def _corner_slots(cells: np.ndarray, n_points: int) -> np.ndarray:
    """(corners, N) int32: the element in which each node is corner c (-1: none).

    In a conforming mesh of lattice-aligned elements in VTK order (voxel and plane-merged
    meshes), a node is corner c of at most one element: the one in the matching octant.
    """
    m, per = cells.shape
    if m >= 2**31 - 1 or n_points >= 2**31 - 1:
        raise DicerError("the mesh is too large for smoothing (2^31 nodes or elements)")
    slots = np.full((per, n_points), -1, np.int32)
    for start in range(0, m, _ROWS):
        block = cells[start : start + _ROWS]
        ids = np.arange(start, start + block.shape[0], dtype=np.int32)
        for c in range(per):
            slots[c][block[:, c]] = ids
    if any(int(np.count_nonzero(row >= 0)) != m for row in slots):
        raise DicerError("the elements are not lattice-aligned with VTK corner order (a node is the same "
                         "corner of two elements); remesh from the labels with 'dicer mesh'")
    return slots


def _holding(slots: np.ndarray | None, nodes: np.ndarray, n_cells: int, cells: np.ndarray | None = None,
             n_points: int = 0) -> np.ndarray:
    """(n_cells,) bool: the elements holding any of ``nodes`` (from the corner table, or
    without one from ``cells`` of a mesh of ``n_points`` nodes)."""
    if slots is None:
        mark = np.zeros(n_points, bool)
        mark[nodes] = True
        out = np.zeros(n_cells, bool)
        for start in range(0, n_cells, _ROWS):
            out[start + _touching(cells[start : start + _ROWS], mark)] = True
        return out
    cand = slots[:, nodes].ravel()
    mark = np.zeros(n_cells, bool)
    mark[cand[cand >= 0]] = True
    return mark


def _mark_nodes(cells: np.ndarray, elements: np.ndarray, mark: np.ndarray) -> None:
    """Set ``mark`` at the nodes of ``elements``, a block of elements at a time."""
    for start in range(0, elements.size, _ROWS):
        mark[cells[elements[start : start + _ROWS]]] = True


def _band(cells: np.ndarray, slots: np.ndarray, boundary: np.ndarray, boundary_cells: np.ndarray, width: int):
    """Interior nodes within ``width`` element layers of the boundary (all interior nodes
    if 0) and the elements holding a boundary or band node."""
    if width == 0:
        return np.flatnonzero(~boundary), np.arange(cells.shape[0])
    n, m = boundary.size, cells.shape[0]
    seen = boundary.copy()
    in_cells = np.zeros(m, bool)
    in_cells[boundary_cells] = True
    layer_cells = boundary_cells
    for _ in range(width):
        mark = np.zeros(n, bool)
        _mark_nodes(cells, layer_cells, mark)
        mark &= ~seen
        nodes = np.flatnonzero(mark)
        if nodes.size == 0:
            break
        seen[nodes] = True
        holding = _holding(slots, nodes, m, cells, n)
        # the next layer: elements not met before (the nodes of the others are all seen)
        layer_cells = np.flatnonzero(holding & ~in_cells)
        in_cells |= holding
    return np.flatnonzero(seen & ~boundary), np.flatnonzero(in_cells)


# the corner a node is in its +++ element (0) and in its --- element (6), and the corners
# of those elements next to it: +x, +y, +z and -x, -y, -z (2D: corners 0 and 2)
_FORWARD = {8: (0, (1, 3, 4)), 4: (0, (1, 3))}
_BACKWARD = {8: (6, (7, 5, 2)), 4: (2, (3, 1))}


def _axis_neighbours(cells: np.ndarray, slots: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """(len(nodes), 2*dim) the neighbours along +x, +y, (+z), -x, -y, (-z) found in any
    element holding the node (-1: no element on that side), for nodes without a full block."""
    per = cells.shape[1]
    dim = 3 if per == 8 else 2
    corners = (HEX_CORNERS if per == 8 else QUAD_CORNERS)[:, :dim]
    code = corners @ (1 << np.arange(dim))
    corner_of = {int(c): i for i, c in enumerate(code)}
    out = np.full((nodes.size, 2 * dim), -1, np.int64)
    for a in range(dim):
        for side in (0, 1):  # 0: towards +a (the node is a low corner along a), 1: towards -a
            col = a + side * dim
            for c in np.flatnonzero(corners[:, a] == side):
                other = corner_of[int(code[c]) ^ (1 << a)]
                e = slots[c][nodes]
                take = (out[:, col] < 0) & (e >= 0)
                out[take, col] = cells[e[take], other]
    return out


_NEAR_HOPS = 12
"""Edges around the changed rows over which a repeated interior solve first solves for the change
(``_Interior._near_first``): the band is three layers thick between held ends, so a change fades
along it; on the head CT's pull rounds 12 edges leave the whole band's rule met at once or after
one iteration (6: four to six more iterations)."""


_SIDE_BY_SIDE_ENTRIES = 1 << 20
"""Stored entries of a matrix from which its product is formed in row blocks side by side."""


def _row_blocks(mat: sp.csr_matrix) -> list[tuple[int, int, sp.csr_matrix]]:
    """``mat`` cut into row blocks of about equal stored entries, one per core the process may
    use (``dicer.parallel.cores``, at most two), each sharing the matrix's arrays: (first row,
    end row, block). Each row's sum is formed as in the whole matrix, so products built from
    the blocks are the same to the bit."""
    from dicer.parallel import MAX_WORKERS, cores

    parts = min(MAX_WORKERS, cores()) if mat.nnz >= _SIDE_BY_SIDE_ENTRIES else 1
    rows = [0, *(int(np.searchsorted(mat.indptr, mat.nnz * i // parts)) for i in range(1, parts)), mat.shape[0]]
    blocks = []
    for a, b in zip(rows[:-1], rows[1:]):
        p, q = int(mat.indptr[a]), int(mat.indptr[b])
        blocks.append((a, b, sp.csr_matrix((mat.data[p:q], mat.indices[p:q], mat.indptr[a:b + 1] - p),
                                           shape=(b - a, mat.shape[1]), copy=False)))
    return blocks


def _side_by_side(work, items, threads: bool = True) -> None:
    """``work(item)`` for every item, in threads (``dicer.parallel.ordered_map``), or here without
    ``threads`` (a small system's solve calls it thousands of times). For work that writes its
    own rows of an output: the same bits as one pass."""
    from dicer.parallel import ordered_map

    for _ in ordered_map(work, items, workers=None if threads else 1):
        pass


_PIECE = CHUNK  # rows (nodes, elements) per piece of the guard's row-wise passes
_EDGE_PIECE = 1 << 15  # elements per piece of the edge lengths: the corners gathered once, temporaries small


def _in_pieces(n: int, work, size: int | None = None) -> None:
    """``work(piece)`` for the slices of ``range(n)`` (``dicer.mesh.model.pieces``, ``_PIECE`` rows
    each unless ``size``), side by side (``_side_by_side``)."""
    _side_by_side(work, pieces(n, _PIECE if size is None else size))


def _laplace(m_bb: sp.csr_matrix, deg, free: np.ndarray | None):
    """The interior operator v -> deg v - free * (m_bb v) on the coordinates stacked x | y | z
    ((3M,) float32; the returned array is reused by the next call). Its row blocks
    (``_row_blocks``) are worked on side by side: the products are the band solve's main cost."""
    m = m_bb.shape[0]
    out = np.empty(3 * m, np.float32)
    blocks = _row_blocks(m_bb)
    deg_rows = [deg if np.ndim(deg) == 0 else deg[a:b] for a, b, _ in blocks]

    def apply(v):
        def rows(job):
            d, (a, b, block), deg_ = job
            at = slice(d * m + a, d * m + b)
            nbrs = block @ v[d * m : (d + 1) * m]
            if free is not None:
                nbrs *= free[d, a:b]
            np.multiply(v[at], deg_, out=out[at])
            np.subtract(out[at], nbrs, out=out[at])

        _side_by_side(rows, [(d, blk, deg_) for d in range(3) for blk, deg_ in zip(blocks, deg_rows)],
                      len(blocks) > 1)
        return out

    return apply


def _reach(m_bb: sp.csr_matrix, rows: np.ndarray, hops: int, share: np.ndarray, limit: float) -> np.ndarray | None:
    """(K,) sorted: the rows ``rows`` and those within ``hops`` edges of them in the pattern of
    ``m_bb`` (symmetric), found frontier by frontier; None once their ``share`` (M,) sums to
    more than ``limit`` (the search stops there: a wide change is solved over the whole band)."""
    mark = np.zeros(m_bb.shape[0], bool)
    mark[rows] = True
    frontier, total = rows, float(share[rows].sum())
    for _ in range(hops):
        start, count = m_bb.indptr[frontier], np.diff(m_bb.indptr)[frontier]
        size = int(count.sum())
        if size == 0:
            break
        # the frontier rows' column indices, gathered in one go
        idx = np.repeat(start - np.cumsum(count) + count, count) + np.arange(size)
        nb = np.unique(m_bb.indices[idx])
        frontier = nb[~mark[nb]]
        mark[frontier] = True
        total += float(share[frontier].sum())
        if total > limit:
            return None
    return np.flatnonzero(mark)


class _Interior:
    """The interior Laplace system on a band of interior nodes, assembled once.

    An interior node has a full unit block, so its 2*dim edge neighbours are the
    neighbouring corners in its +++ and --- elements. ``m_bb`` couples band nodes,
    ``m_bB`` band nodes to boundary nodes (the nodes ``bnodes``, in that order).
    With mirror planes (``planes``, bits per node) an interior node on a plane has half
    (a quarter, an eighth) of its block: the neighbour missing across the plane is the
    mirror copy of the one opposite, so that one counts twice, and the normal coordinate
    of the node stays 0 (``free``); ``weight`` is the CG inner product (see _BoundarySystem).
    """

    _last_b: np.ndarray | None = None  # the last solve's right-hand side (3M,), for ``_near_first``

    def __init__(self, cells: np.ndarray, slots: np.ndarray, band_nodes: np.ndarray, boundary: np.ndarray,
                 bnodes: np.ndarray, planes: np.ndarray | None = None):
        n = boundary.size
        per = cells.shape[1]
        m = band_nodes.size
        self.nodes = band_nodes
        if m == 0:
            return
        # pos: a band node's number (>= 0), -2 - a boundary node's number, -1 for other nodes
        pos = np.full(n, -1, np.int32)  # n < 2^31 (checked by _corner_slots)
        pos[band_nodes] = np.arange(m, dtype=np.int32)
        pos[bnodes] = -2 - np.arange(bnodes.size, dtype=np.int32)
        dim = len(_FORWARD[per][1])
        nb = np.empty((m, 2 * dim), np.int32)  # neighbours, in pos numbers
        part = np.zeros(m, bool)  # band nodes without a full block
        j = 0
        for corner, nbrs in (_FORWARD[per], _BACKWARD[per]):
            owner = slots[corner][band_nodes]
            part |= owner < 0
            for c in nbrs:
                nb[:, j] = pos[cells[np.maximum(owner, 0), c]]
                j += 1
        bits = np.zeros(m, np.uint8) if planes is None else planes[band_nodes]
        if part.any():
            rows = np.flatnonzero(part)
            found = _axis_neighbours(cells, slots, band_nodes[rows])
            on = plane_axes(bits[rows])
            for a in range(dim):
                for col, opp in ((a, a + dim), (a + dim, a)):
                    mirror = (found[:, col] < 0) & on[:, a]
                    found[mirror, col] = found[mirror, opp]  # the reflected copy of the opposite neighbour
            if np.any(found < 0):
                raise DicerError("an interior node lacks a full unit block of elements; the mesh is not conforming")
            nb[rows] = pos[found]
        del pos
        self.m_bb = _csr_rows(nb, nb >= 0, m, np.float32)  # neighbours of another kind: no entry
        self.m_bB = _csr_rows(-2 - nb, nb <= -2, bnodes.size, np.float64)
        self.deg = np.float32(nb.shape[1])
        self._mirror(bits)

    def hold(self, rows: np.ndarray) -> None:
        """Keep the band nodes ``rows`` (numbers among the band's) where they are from the next
        solve on: all three coordinates held, as a mirror plane holds one."""
        if rows.size == 0 or self.nodes.size == 0:
            return
        if self.free is None:
            self.free = np.ones((3, self.nodes.size), np.float32)
        self.free[:, rows] = 0.0
        self._last_b = None  # the system changed: the next solve starts over the whole band

    def _mirror(self, bits: np.ndarray) -> None:
        """The free coordinates (3, m) and CG weights of the band nodes on mirror planes ``bits``."""
        self.free = self.weight = None
        if bits.any():
            self.free = (~plane_axes(bits)).T.astype(np.float32)
            self.weight = np.tile(mirror_share(bits), 3).astype(np.float32)

    def solve(self, u_boundary: np.ndarray, tol: float, start: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """Displacements (M, 3) of the band nodes given those of the boundary nodes (B, 3).

        ``start``: (M, 3) displacements to start from (a previous solve's: the guard's rounds
        move a few boundary nodes, so the last solution is close); None starts from 0. From the
        last solve's solution, with few right-hand sides changed (a pull round), the change is
        first solved for near them (``_near_first``): the same stopping rule then takes few
        iterations over the whole band, or none.
        """
        m = self.nodes.size
        if m == 0:
            return np.zeros((0, 3)), 0
        ub = np.ascontiguousarray(u_boundary.T)
        b = np.empty(3 * m, np.float32)
        for d in range(3):
            b[d * m : (d + 1) * m] = self.m_bB @ ub[d]
        if self.free is not None:
            b *= self.free.ravel()  # a plane node's normal displacement is 0
        apply = _laplace(self.m_bb, self.deg, self.free)
        x0 = None if start is None else np.ascontiguousarray(start.T, np.float32).ravel()
        it_near = 0
        if x0 is not None:
            if self.free is not None:
                x0 *= self.free.ravel()
            x0, it_near = self._near_first(b, x0, tol, apply)
        self._last_b = b
        u, it = _pcg(apply, b, None, tol, 5000, self.weight, x0)
        return u.reshape(3, m).T.astype(np.float64), it + it_near

    def _near_first(self, b: np.ndarray, x0: np.ndarray, tol: float, apply) -> tuple[np.ndarray, int]:
        """``x0`` (3M,) improved where the right-hand side ``b`` (3M,) differs from the last solve's
        (``x0`` its solution): the residual solved for on the band nodes within ``_NEAR_HOPS``
        edges of those rows, the others held, to half of what the whole solve's rule leaves
        beside the residual elsewhere."""
        last, self._last_b = self._last_b, None
        m = self.nodes.size
        if last is None:
            return x0, 0
        changed = np.flatnonzero((b != last).reshape(3, m).any(axis=0))
        # counted as shares of the mirrored model, so a cut model decides as the whole one does
        share = np.ones(m, np.float32) if self.weight is None else self.weight[:m]
        whole = float(share.sum())
        if changed.size == 0 or float(share[changed].sum()) > whole / 32:
            return x0, 0
        rows = _reach(self.m_bb, changed, _NEAR_HOPS, share, whole / 8)
        if rows is None:
            return x0, 0
        at = (rows[None, :] + m * np.arange(3)[:, None]).ravel()  # the rows' places in the stacked vectors
        weight = None if self.weight is None else self.weight[at]
        dot = _dot if self.weight is None else _wdot(self.weight)
        r = b - apply(x0)
        total2 = dot(r, r)
        r = r[at]
        inside2 = _dot(r, r) if weight is None else _wdot(weight)(r, r)
        # the rule's budget less the last solve's residual elsewhere (held), half of it here
        budget2 = (tol * tol) * dot(b, b) - (total2 - inside2)
        if budget2 <= 0 or inside2 <= 0.25 * budget2:
            return x0, 0
        target, rnorm = 0.5 * np.sqrt(budget2), np.sqrt(inside2)
        deg = self.deg if np.ndim(self.deg) == 0 else self.deg[rows]
        near = _laplace(self.m_bb[rows][:, rows], deg, None if self.free is None else self.free[:, rows])
        delta, it = _pcg(near, r, None, target / rnorm, 5000, weight)
        x0 = x0.copy()
        x0[at] += delta
        return x0, it


class _InteriorGraph(_Interior):
    """The interior Laplace system of a graded mesh (transition templates: nodes shared by
    any number of elements), from the unique element edges around the band nodes.

    A band node's displacement is the mean of its edge neighbours' (those beyond the band
    count as 0), as in ``_Interior``; only the neighbour count varies from node to node.
    A neighbour counts once per mirror copy (``mirror_weights``).
    """

    def __init__(self, cells: np.ndarray, band_nodes: np.ndarray, boundary: np.ndarray, bnodes: np.ndarray,
                 planes: np.ndarray | None = None):
        n = boundary.size
        m = band_nodes.size
        self.nodes = band_nodes
        if m == 0:
            return
        local = HEX_EDGES if cells.shape[1] == 8 else QUAD_EDGES
        near = _holding(None, band_nodes, cells.shape[0], cells, n)
        sub = cells[near]
        a = sub[:, local[:, 0]].ravel()
        b = sub[:, local[:, 1]].ravel()
        # each edge once: one int64 key per (low, high) node pair sorts like the pairs do,
        # and a 1-D unique is far cheaper than a unique of rows
        key = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
        key.sort()
        key = key[np.r_[True, key[1:] != key[:-1]]]
        lo, hi = np.divmod(key, n)
        a, b = np.concatenate([lo, hi]), np.concatenate([hi, lo])
        pos = np.full(n, -1, np.int64)
        pos[band_nodes] = np.arange(m)
        bpos = np.full(n, -1, np.int64)
        bpos[bnodes] = np.arange(bnodes.size)
        row = pos[a]
        keep = row >= 0
        row, col = row[keep], b[keep]
        w = np.ones(row.size) if planes is None else mirror_weights(planes[a[keep]], planes[col])
        deg = np.bincount(row, weights=w, minlength=m).astype(np.float32)
        in_band = pos[col] >= 0
        self.m_bb = sp.csr_matrix((w[in_band].astype(np.float32), (row[in_band], pos[col[in_band]])), shape=(m, m))
        on_b = bpos[col] >= 0
        self.m_bB = sp.csr_matrix((w[on_b], (row[on_b], bpos[col[on_b]])), shape=(m, bnodes.size))
        self.deg = deg
        self._mirror(np.zeros(m, np.uint8) if planes is None else planes[band_nodes])


def _template_nodes(mesh: Mesh, x0: np.ndarray) -> np.ndarray:
    """(N,) bool: the nodes of transition template elements (graded elements that are not
    boxes). The interior solve holds them where the templates put them: their quality on
    the lattice (0.23 and up) is the bound the templates give, and relaxing a node next to
    the band can take a template below the floor."""
    out = np.zeros(mesh.n_points, bool)
    if LEVEL_DATA not in mesh.cell_data:
        return out
    graded = np.flatnonzero(np.asarray(mesh.cell_data[LEVEL_DATA]) > 0)
    for start in range(0, graded.size, _ROWS):
        rows = mesh.cells[graded[start : start + _ROWS]]
        box = corner_scaled_jacobians(x0, rows).min(axis=1) > 1.0 - 1e-9
        out[rows[~box].ravel()] = True
    return out


# --- the stage -----------------------------------------------------------------------------


def _lattice_volumes(mesh: Mesh) -> np.ndarray:
    """Per element, the volume (2D: area) of its lattice box: exact before smoothing for the
    elements that are boxes (not for the chamfers of plane merging)."""
    far = 6 if mesh.dim == 3 else 2
    lattice = np.asarray(mesh.lattice)
    spacing = [float(mesh.spacing[d]) for d in range(mesh.dim)]
    out = np.empty(mesh.n_cells)
    for start in range(0, mesh.n_cells, _ROWS):
        block = mesh.cells[start : start + _ROWS]
        span = np.abs(lattice[block[:, far]] - lattice[block[:, 0]])
        vol = np.ones(block.shape[0])
        for d in range(mesh.dim):
            vol *= span[:, d] * spacing[d]
        out[start : start + _ROWS] = vol
    return out


class _Elements:
    """A set of elements (the checked ones) with their own numbering of the nodes they hold,
    so their metrics are computed from compact coordinate columns."""

    def __init__(self, cells: np.ndarray, elements: np.ndarray, n_points: int):
        self.cells, self.elements = cells, elements
        self.hex = cells.shape[1] == 8
        if not self.hex:
            return
        mark = np.zeros(n_points, bool)
        _mark_nodes(cells, elements, mark)
        self.nodes = np.flatnonzero(mark)
        del mark
        idx = np.int32 if n_points < 2**31 else np.int64
        pos = np.full(n_points, -1, idx)
        pos[self.nodes] = np.arange(self.nodes.size, dtype=idx)
        self.local = np.empty((8, elements.size), idx)
        for start in range(0, elements.size, _ROWS):
            self.local[:, start : start + _ROWS] = pos[cells[elements[start : start + _ROWS]]].T

    def holding(self, mark: np.ndarray) -> np.ndarray:
        """(C,) bool: the elements holding a node marked in ``mark`` (N,) bool."""
        if not self.hex:
            return any_per_row(mark[self.cells[self.elements]])
        local = mark[self.nodes]
        out = np.zeros(self.elements.size, bool)

        def rows(part):
            piece = out[part]
            for corner in self.local:
                piece |= local[corner[part]]

        _in_pieces(self.elements.size, rows)
        return out

    def columns(self, x: np.ndarray) -> list[np.ndarray]:
        """The coordinates of the elements' nodes: x, y and z arrays in local numbering."""
        return [x[self.nodes, d] for d in range(3)]

    def scaled_jacobian(self, x: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
        """Scaled Jacobian of the elements (or of elements[which]) at positions x (N, 3).
        The coordinate columns of the last whole pass are kept in ``self.last``."""
        if not self.hex:
            el = self.elements if which is None else self.elements[which]
            return scaled_jacobian(x, self.cells[el])
        if which is not None:
            return scaled_jacobian(x, self.cells[self.elements[which]])
        self.last = self.columns(x)
        return hex_scaled_jacobian_t(self.last, self.local)


def _check_input(mesh: Mesh) -> None:
    if mesh.n_cells == 0 or mesh.n_points == 0:
        raise DicerError("the mesh is empty (no elements); mesh a label volume with material voxels first")
    if mesh.lattice is None or np.asarray(mesh.lattice).shape != (mesh.n_points, 3):
        raise DicerError("the mesh has no 'lattice' point data (not made by 'dicer mesh'); "
                         "remesh from the labels with 'dicer mesh'")
    if not np.all(np.isfinite(mesh.points)):
        raise DicerError("the mesh has non-finite node coordinates; remesh from the labels")


@dataclass
class _Pull:
    """The pull of the boundary nodes onto the scan's iso-surfaces (``dicer.mesh.subvoxel``).

    Attributes
    ----------
    surface : ImageSurface or LabelSurface
        The scan's iso-surfaces, or the fit of the labels' staircase.
    sides : NodeSides
        The materials on either side of each boundary node.
    share : (B,) float64
        The share of its move onto the iso-surface a node makes (1, halved by the guard, 0).
    backed : (B,) bool
        Nodes whose pull the guard reduced.
    rounds : int
        Guard rounds that reduced the pull.
    target : (B, 3) float64 or None
        Positions on the iso-surfaces (mm) for the current boundary solve.
    info : dict or None
        ``project``'s report for the current boundary solve.
    found : (B,) bool or None
        Nodes whose target lies on an iso-surface (a crossing found near them).
    """

    surface: object
    sides: object
    share: np.ndarray
    backed: np.ndarray
    rounds: int = 0
    target: np.ndarray | None = None
    info: dict | None = None
    found: np.ndarray | None = None


@dataclass
class _Smoothing:
    """What the steps of ``smooth_mesh`` share: the set-up, then the state of the guard loop.

    B boundary nodes (``bnodes``), M band nodes (``band_nodes``); positions in mm, float64.
    ``k`` and the fields from ``backed`` on change as the solves and the guard run.
    """

    mesh: Mesh
    s: dict  # smoothing_settings
    x0: np.ndarray  # (N, 3) positions before smoothing
    g: BoundaryGraph
    graded: bool
    bnodes: np.ndarray  # (B,) int64, the boundary nodes in increasing order
    adj: sp.csr_matrix  # (B, B) boundary graph, mirror copies as weights
    degree: np.ndarray  # (B,) float64, R_n
    k: np.ndarray  # (B,) float64, the coefficient of each boundary node
    fixed: np.ndarray  # (B, 3) bool, coordinates held (bounding planes, 2D z)
    weight: np.ndarray | None  # (B,) the nodes' shares of the mirrored model, the CG weights (None: no mirrors)
    xb0: np.ndarray  # (B, 3) boundary positions before smoothing
    band_nodes: np.ndarray  # (M,) int64, interior nodes solved
    touched: np.ndarray  # sorted elements holding a boundary or band node: those the guard checks
    interior: _Interior | None
    x_band0: np.ndarray  # (M, 3) band positions before smoothing
    checked: _Elements
    pull: _Pull | None
    timings: dict
    backed: np.ndarray  # (B,) bool, nodes whose coefficient the guard reduced
    frozen: np.ndarray  # (B,) bool, boundary nodes kept where they were by _freeze_around_failures
    bpos: np.ndarray | None = None  # (N,) a node's number among the boundary nodes (-1: none)
    rounds: int = 0  # back-off rounds of the coefficients
    frozen_rounds: int = 0  # rounds after those that kept the elements around failures as they were
    x: np.ndarray | None = None  # (N, 3) current positions
    xb: np.ndarray | None = None  # (B, 3) current boundary positions
    x_band: np.ndarray | None = None  # (M, 3) current band positions
    sj: np.ndarray | None = None  # scaled Jacobian of the checked elements
    bad: np.ndarray | None = None  # the checked elements that fail the guard
    short: tuple | None = None  # with the pull: (checked rows, (R, E) bool) edges it shrank too far
    lengths0: np.ndarray | None = None  # with the pull: (C, E) float32 squared edge lengths before smoothing
    x_checked: np.ndarray | None = None  # (N, 3) the positions of the last check
    boundary_steps: tuple | None = None  # the last boundary solve's displacements (d1, d2), (B, 3) each
    share_checked: np.ndarray | None = None  # (B,) bool, with the pull: the nodes pulled at the last check
    it_b: int = 0  # conjugate-gradient iterations, boundary and interior
    it_i: int = 0
    t_solve: float = 0.0
    t_guard: float = 0.0
    surface: np.ndarray | None = None  # (B, 3) with pillow and the scan: its iso-surface before lift, mm
    layer: "_Layer | None" = None  # with pillow: the layer made (``_add_pillow``)

    def boundary_position(self) -> np.ndarray:
        """(N,) int64: a node's number among the boundary nodes (-1: none), made once."""
        if self.bpos is None:
            self.bpos = np.full(self.mesh.n_points, -1, np.int64)
            self.bpos[self.bnodes] = np.arange(self.bnodes.size)
        return self.bpos


# --- set-up: the scan's surfaces, node classes, coefficients, the interior band ----------------


def _pull_surface(mesh: Mesh, s: dict, image, thresholds, image_source: str, labels=None,
                  labels_source: str = "labels") -> tuple[object | None, float]:
    """The surface the boundary nodes are pulled onto: the scan's iso-surfaces for
    ``surface_from_image``, else the labels' fitted staircase for ``surface_from_labels``
    (of the label volume ``labels`` where given, else of the mesh's faces).

    Returns
    -------
    surface : ImageSurface, LabelSurface or None
        None with neither (or ``surface_from_image`` alone and no image).
    seconds : float
        Time taken.
    """
    if image is None or not s["surface_from_image"]:
        if not s["surface_from_labels"]:
            return None, 0.0
        from dicer.mesh.labelsurface import LabelSurface, check_labels_for_mesh

        t = time.perf_counter()
        scan = None
        if labels is not None:
            check_labels_for_mesh(labels, mesh, labels_source)
            if image is not None and places_faces_by_scan(s):  # the scan places the faces within their voxels
                scan = _image_surface(mesh, s, image, thresholds, image_source)
        def build():
            t = time.perf_counter()
            made = LabelSurface(mesh, s["label_surface_radius"], s["bounding_planes"] == "mirror", labels, scan,
                                relaxed=relaxes_staircase(s, scan is not None))
            return made, time.perf_counter() - t

        from dicer.parallel import cores, meanwhile

        if cores() > 1:  # built beside the classification of the nodes, which needs its thresholds only
            later = _SurfaceLater(meanwhile(build), int(np.max(mesh.material, initial=0)) + 1)
            return later, time.perf_counter() - t
        made, _ = build()
        return made, time.perf_counter() - t
    t = time.perf_counter()
    return _image_surface(mesh, s, image, thresholds, image_source), time.perf_counter() - t


@dataclass
class _SurfaceLater:
    """A ``LabelSurface`` being built on a thread (``result``: :func:`dicer.parallel.meanwhile`'s,
    giving the surface and the seconds it took); its ``thresholds`` (one per material, as
    LabelSurface has them) are known at once, so the nodes' sides are set up meanwhile."""

    result: object
    top: int

    def __post_init__(self):
        self.thresholds = np.arange(1, self.top, dtype=float)


def _image_surface(mesh: Mesh, s: dict, image, thresholds, image_source: str):
    """The scan smoothed by ``image_sigma`` around the mesh, with its checked thresholds."""
    from dicer.mesh.subvoxel import ImageSurface, check_thresholds_for_mesh

    if thresholds is None:
        raise DicerError(f"{image_source}: the thresholds segmentation chose are needed with the image")
    return ImageSurface(image, check_thresholds_for_mesh(thresholds, mesh, image_source), mesh, s["image_sigma"],
                        image_source)


def _classify(mesh: Mesh, s: dict, x0: np.ndarray, graded: bool
              ) -> tuple[BoundaryGraph, np.ndarray | None, float, float]:
    """Classify the nodes: the boundary graph and node classes (``boundary_graph``).

    The corner table of a lattice mesh, which the interior solve needs, serves the
    classification too (no pass over all elements there).

    Returns
    -------
    g : BoundaryGraph
        Of the mirrored model with ``bounding_planes: mirror``.
    slots : (corners, N) int32 or None
        The corner table (``_corner_slots``); None for a graded mesh or without the interior solve.
    t_slots, t_classify : float
        Seconds taken by the corner table and by the classification.
    """
    t0 = time.perf_counter()
    slots = slots_error = None
    if s["interior"] and not graded:
        try:
            slots = _corner_slots(mesh.cells, mesh.n_points)
        except DicerError as err:  # raised after the classification's own checks
            slots_error = err
    t_slots = time.perf_counter() - t0
    g = boundary_graph(mesh, x0, slots, mirror=s["bounding_planes"] == "mirror")
    if slots_error is not None:
        raise slots_error
    return g, slots, t_slots, time.perf_counter() - t0 - t_slots


def _coefficients(s: dict, node_class: np.ndarray) -> np.ndarray:
    """(B,) float64: the coefficient k_n of each node's class (``node_class`` codes, (B,) int8);
    irregular nodes (X) take the most cautious (smallest) one."""
    coef_by_code = np.zeros(len(NODE_CLASSES))
    for code, name in enumerate(NODE_CLASSES):
        if name in s["coefficients"]:
            coef_by_code[code] = s["coefficients"][name]
    coef_by_code[7] = min(s["coefficients"].values())
    return coef_by_code[node_class]


def _held_coordinates(mesh: Mesh, s: dict, on_plane: np.ndarray) -> np.ndarray:
    """(B, 3) bool: the coordinates the boundary solve holds, from ``bounding_planes`` and
    ``on_plane`` ((B, 3) bool, ``bounding_planes``); z is held in 2D."""
    mode = s["bounding_planes"]
    if mode == "fixed":
        fixed = np.repeat(on_plane.any(axis=1, keepdims=True), 3, axis=1)
    elif mode == "free" and not s["keep_bounding_planes"]:
        fixed = np.zeros((on_plane.shape[0], 3), bool)
    else:  # mirror (symmetry keeps plane nodes in their planes) or free in the plane
        fixed = on_plane.copy()
    if mesh.dim == 2:
        fixed[:, 2] = True
    return fixed


def _interior_band(mesh: Mesh, s: dict, g: BoundaryGraph, slots: np.ndarray | None, graded: bool,
                   x0: np.ndarray, bnodes: np.ndarray, planes: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, _Interior | None]:
    """The interior solve's band and system, and the elements the guard checks.

    Returns
    -------
    band_nodes : (M,) int64
        Interior nodes within ``interior_band`` layers (graded meshes: not template nodes).
    touched : sorted int64
        The elements holding a boundary or band node.
    interior : _Interior, _InteriorGraph or None
        None with ``interior: false``.
    """
    if not s["interior"]:
        return np.zeros(0, np.int64), g.boundary_cells, None
    band_nodes, touched = _band(mesh.cells, slots, g.boundary, g.boundary_cells, s["interior_band"])
    if graded:
        band_nodes = band_nodes[~_template_nodes(mesh, x0)[band_nodes]]
        interior = _InteriorGraph(mesh.cells, band_nodes, g.boundary, bnodes, planes)
    else:
        interior = _Interior(mesh.cells, slots, band_nodes, g.boundary, bnodes, planes)
    return band_nodes, touched, interior


def _set_up(mesh: Mesh, s: dict, surface, t0: float, t_img: float) -> _Smoothing:
    """Classify the nodes and assemble what both solves and the guard need.

    ``surface``: the scan's iso-surfaces or None; ``t0``: the stage's start;
    ``t_img``: seconds taken by the surfaces (both for the timings).
    """
    x0 = np.asarray(mesh.points, float)
    graded = is_graded(mesh)
    g, slots, t_slots, t_classify = _classify(mesh, s, x0, graded)
    timings = {"classify": t_classify}
    bnodes = np.flatnonzero(g.boundary)
    adj = g.adjacency(bnodes)
    degree = g.degree[bnodes].astype(float)
    k = _coefficients(s, g.node_class[bnodes])
    on_plane = bounding_planes(mesh, x0[bnodes])
    fixed = _held_coordinates(mesh, s, on_plane)
    planes = g.planes if s["bounding_planes"] == "mirror" and g.planes.any() else None
    weight = None if planes is None else mirror_share(planes[bnodes])

    t1 = time.perf_counter()
    band_nodes, touched, interior = _interior_band(mesh, s, g, slots, graded, x0, bnodes, planes)
    del slots
    checked = _Elements(mesh.cells, touched, mesh.n_points)
    timings["assemble"] = time.perf_counter() - t1 + t_slots
    pull = None
    if surface is not None:
        from dicer.mesh.subvoxel import NodeSides

        t2 = time.perf_counter()
        sides = NodeSides(mesh, bnodes, g.boundary_cells, x0, on_plane, fixed, surface.thresholds, planes is not None)
        pull = _Pull(surface, sides, (k > 0).astype(float), np.zeros(bnodes.size, bool))
        timings["image"] = time.perf_counter() - t2 + t_img
    return _Smoothing(mesh, s, x0, g, graded, bnodes, adj, degree, k, fixed, weight, x0[bnodes], band_nodes,
                      touched, interior, x0[band_nodes], checked, pull, timings, np.zeros(bnodes.size, bool),
                      np.zeros(bnodes.size, bool))


# --- the solves and the quality guard ---------------------------------------------------------


def _boundary_solve(st: _Smoothing) -> np.ndarray:
    """The boundary solve (Box 3) for the current coefficients, twiced with ``shrink_compensation``.

    Returns
    -------
    xb : (B, 3) float64
        The boundary nodes' positions from the labels, mm.
    """
    tol = st.s["tolerance"]
    system = _BoundarySystem(st.adj, st.degree, st.k, st.fixed, st.weight)
    last = st.boundary_steps or (None, None)  # a guard round starts from the last round's steps
    d1, it = system.step(st.xb0, tol, last[0])
    st.it_b += it
    if not st.s["shrink_compensation"]:
        st.boundary_steps = (d1, None)
        return st.xb0 + d1
    # twicing: x = (2S - S^2) x0 = x0 - (S(d1) - d1) with d1 = S(x0) - x0; the
    # low-frequency part of the displacement (the shrinkage) is taken back
    d2, it = system.step(d1, tol, last[1])
    st.it_b += it
    st.boundary_steps = (d1, d2)
    return st.xb0 - d2


def _pull_onto_image(st: _Smoothing, xb_labels: np.ndarray) -> None:
    """Targets on the scan's iso-surfaces (``dicer.mesh.subvoxel.project``) or the labels' fitted
    staircase (``LabelSurface.project``) for the boundary positions ``xb_labels`` (B, 3) mm; the
    guard backs this move off first."""
    from dicer.mesh.subvoxel import ImageSurface, lift, pairs_not_helped, project

    if isinstance(st.pull.surface, _SurfaceLater):
        st.pull.surface, seconds = st.pull.surface.result()
        st.timings["image"] += seconds
    if isinstance(st.pull.surface, ImageSurface):
        on_surface, st.pull.info = project(st.pull.surface, st.pull.sides, st.adj, st.degree, st.x0, st.bnodes,
                                           xb_labels)
    elif st.pull.target is not None:  # the labels' fit is made once: its targets stand
        return
    else:  # progress: the fit is the stage's longest step (a minute for an atlas of a million surface nodes)
        t = time.perf_counter()
        log.info("smooth: fitting %d boundary nodes to the labels' staircase (smooth.surface_from_labels, radius %g "
                 "voxels)", int(st.pull.sides.usable.sum()), float(st.s["label_surface_radius"]))
        on_surface, st.pull.info = st.pull.surface.project(st.pull.sides, st.x0, st.bnodes, xb_labels)
        log.info("smooth: fitted in %.1f s", time.perf_counter() - t)
    found = np.any(on_surface != xb_labels, axis=1)
    if st.surface is None and st.s["pillow"]:
        st.surface = on_surface
    target = lift(st.pull.sides, on_surface, float(st.s["min_scaled_jacobian"]), st.weight)
    stay, pairs = pairs_not_helped(st.pull.sides, found, on_surface, target, xb_labels, st.weight)
    target[stay] = xb_labels[stay]
    st.pull.found = found & ~stay
    st.pull.target = target
    st.pull.info["nodes_moved"] = int(np.count_nonzero(st.pull.found))  # over every pass, not the last one's
    st.pull.info["pairs_left_to_the_labels"] = pairs


def _interior_solve(st: _Smoothing, xb_labels: np.ndarray) -> None:
    """Place the boundary nodes (the labels' positions ``xb_labels`` (B, 3) mm moved by their
    share of the pull) and solve the interior band for them (paper 2.6): sets ``x``, ``xb``
    and ``x_band``."""
    xb = xb_labels
    if st.pull is not None:
        xb = xb_labels + st.pull.share[:, None] * (st.pull.target - xb_labels)
    if st.x is None:
        st.x = st.x0.copy()
    _solve_band(st, xb)


def _solve_band(st: _Smoothing, xb: np.ndarray) -> None:
    """Put the boundary nodes at ``xb`` (B, 3) mm in ``st.x`` and solve the interior band for
    them: sets ``st.xb`` and ``st.x_band``."""
    st.x[st.bnodes] = st.xb = xb
    if st.interior is not None and st.band_nodes.size:
        # from the last solve's displacements: a guard round changes few boundary nodes
        start = None if st.x_band is None else st.x_band - st.x_band0
        u, it = st.interior.solve(xb - st.xb0, st.s["tolerance"], start)
        st.it_i += it
        st.x_band = x_band = np.empty_like(u)

        def rows(part):  # the band's millions of rows: placed side by side
            np.add(st.x_band0[part], u[part], out=x_band[part])
            st.x[st.band_nodes[part]] = x_band[part]

        _in_pieces(u.shape[0], rows)


_SHORTEST_EDGE = 0.05
"""An edge of a checked element may not shrink below this share of its length before smoothing
(an edge ratio of about 20, where the quality report calls an element stretched)."""


def _edge_lengths2(cells: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(M, E) float64: the squared lengths of the elements' edges at positions ``x``."""
    edges = HEX_EDGES if cells.shape[1] == 8 else QUAD_EDGES
    out = np.empty((cells.shape[0], edges.shape[0]))

    def rows(part):
        corner = x[cells[part]]  # (b, k, 3)
        d = corner[:, edges[:, 1]] - corner[:, edges[:, 0]]
        out[part] = np.einsum("bei,bei->be", d, d)

    _in_pieces(cells.shape[0], rows, _EDGE_PIECE)
    return out


def _short_edges(cells: np.ndarray, x: np.ndarray, x0: np.ndarray | None, moved: np.ndarray,
                 before: np.ndarray | None = None) -> np.ndarray:
    """(M, E) bool: the elements' edges with an end in ``moved`` (N,) bool, shorter than
    ``_SHORTEST_EDGE`` of their length at ``x0`` (or their squared lengths ``before``, (M, E)).

    A pull onto an iso-surface can bring an edge's two ends together (a riser of the staircase,
    both ends projected onto one flat patch): its corners stay square, so the scaled Jacobian
    passes an element a solver cannot condition."""
    edges = HEX_EDGES if cells.shape[1] == 8 else QUAD_EDGES
    before = _edge_lengths2(cells, x0) if before is None else before
    m = moved[cells]
    return (_edge_lengths2(cells, x) < _SHORTEST_EDGE**2 * before) & (m[:, edges[:, 0]] | m[:, edges[:, 1]])


_RECHECK_MOVE = 1e-3
"""A guard round rechecks the elements with a node moved more than this (voxels of the finest
axis) since the last check: a round changes few nodes much, and the interior solve the rest
only to its tolerance."""
_RECHECK_MARGIN = 0.01
"""... and those the last check put below the floor + this (+ ``_NEAR_FLOOR`` without the pull):
a move under ``_RECHECK_MOVE`` changes a scaled Jacobian by less, so a stale value decides
nothing a whole check would decide otherwise."""


def _moved_farther(x: np.ndarray, start: np.ndarray, reach: float, or_as_far: bool = False) -> np.ndarray:
    """(N,) bool: the nodes farther than ``reach`` (mm; or as far) from their ``start`` (N, 3).

    Over all nodes: only the boundary and band nodes move, and contiguous rows are several times
    quicker than gathering those (4.6 M of the atlas's 6.4 M nodes)."""
    out = np.empty(x.shape[0], bool)

    def rows(part):
        step = x[part] - start[part]
        d2 = np.einsum("ij,ij->i", step, step)
        out[part] = d2 >= reach * reach if or_as_far else d2 > reach * reach

    _in_pieces(x.shape[0], rows)
    return out


def _rechecked(st: _Smoothing) -> tuple[np.ndarray, np.ndarray] | None:
    """The checked elements whose guard test a round must repeat (``_RECHECK_MOVE``,
    ``_RECHECK_MARGIN``): (C,) bool those holding a node that moved (or whose pull changed), and
    (C,) bool those and the ones near the floor; None for all of them (the first check)."""
    if st.sj is None or st.x_checked is None:
        return None
    reach = _RECHECK_MOVE * float(np.min(np.asarray(st.mesh.spacing, float)[: st.mesh.dim]))
    moved = _moved_farther(st.x, st.x_checked, reach)
    if st.pull is not None:  # a node whose pull changed: its edges' test changes with it
        moved[st.bnodes[(st.pull.share > 0) != st.share_checked]] = True
    rows = st.checked.holding(moved)
    margin = _RECHECK_MARGIN + (_NEAR_FLOOR if st.pull is None else 0.0)
    return rows, rows | (st.sj < float(st.s["min_scaled_jacobian"]) + margin)


_WORSE = 0.005
"""An element already below the floor before smoothing passes while it loses less than this:
its boundary nodes can be held (k = 0) but not the interior band's, which the relaxation moves
by a few thousandths of a voxel for the rest of the surface (merging's chamfers at 0.29 under a
floor of 0.3 then failed every round, and the back-off spent its rounds around them)."""


def _check_quality(st: _Smoothing, whole: bool = False) -> bool:
    """The guard's test: sets ``sj`` and ``bad``, the checked elements below ``min_scaled_jacobian``
    (or <= 0) except those already below it before smoothing that did not get worse (``_WORSE``); with the
    pull, also those with an edge shrunk below ``_SHORTEST_EDGE`` of its length.

    Unless ``whole``, only the elements ``_rechecked`` names are tested again: the guard accepts
    positions only after a whole check (``_solve_with_guard``). Returns True when every checked
    element was tested."""
    floor = float(st.s["min_scaled_jacobian"])
    again = None if whole else _rechecked(st)
    if again is None:
        sj = st.checked.scaled_jacobian(st.x)
    else:
        moved_rows, again = again
        sj = st.sj.copy()
        which = np.flatnonzero(again)
        sj[which] = st.checked.scaled_jacobian(st.x, which)
    bad = (sj < floor) | (sj <= 0)
    if bad.any():
        # their value before smoothing is needed only here
        which = np.flatnonzero(bad)
        before = st.checked.scaled_jacobian(st.x0, which)
        after = sj[which]
        bad[which] = ~((before < floor) & (after >= before - _WORSE) & (after > 0))
    if st.pull is not None:
        moved = np.zeros(st.mesh.n_points, bool)
        moved[st.bnodes[st.pull.share > 0]] = True  # only edges with a pulled end: those it shortens
        # an edge falls below _SHORTEST_EDGE of its length only when one of its ends moved at
        # least half the rest of it: the elements of such nodes only (a few of every check's)
        reach = 0.5 * (1 - _SHORTEST_EDGE) * float(np.min(np.asarray(st.mesh.spacing, float)[: st.mesh.dim]))
        pulled = np.flatnonzero(st.checked.holding(_moved_farther(st.x, st.x0, reach, True)))
        kept = None
        if again is not None and st.short is not None:  # the last check's verdicts where nothing moved
            rows, short = st.short
            kept = ~moved_rows[rows]
            pulled = pulled[moved_rows[pulled]]
        if st.lengths0 is None:  # the checked elements' edges before smoothing, once
            st.lengths0 = _edge_lengths2(st.mesh.cells[st.touched], st.x0).astype(np.float32)
        new = _short_edges(st.mesh.cells[st.touched[pulled]], st.x, None, moved, st.lengths0[pulled])
        if kept is not None:
            pulled, new = np.concatenate([rows[kept], pulled]), np.concatenate([short[kept], new])
        st.short = (pulled, new)
        bad[pulled[new.any(axis=1)]] = True
        st.share_checked = st.pull.share > 0
    st.sj, st.bad = sj, bad
    st.x_checked = st.x.copy()  # for the next round's check
    return again is None


def _back_off_pull(st: _Smoothing) -> bool:
    """Halve (then drop) the pull of the boundary nodes at the failing corners; the labels'
    solution stays as it is. Returns False when no such node is pulled any more."""
    floor = float(st.s["min_scaled_jacobian"])
    bpos = st.boundary_position()
    failing = st.mesh.cells[st.touched[st.bad]]
    corner = corner_scaled_jacobians(st.x, failing)
    pulled = bpos[failing[(corner < floor) | (corner <= 0)]]
    if st.short is not None:  # and both ends of every edge the pull shrank too far
        rows, short = st.short
        e, k = nonzero(short)
        ends = st.mesh.cells[st.touched[rows[e]]][:, (HEX_EDGES if short.shape[1] == 12 else QUAD_EDGES)]
        ends = ends[np.arange(e.size), k]
        pulled = np.concatenate([pulled, bpos[ends.ravel()]])
    pulled = np.unique(pulled[pulled >= 0])
    share = st.pull.share
    pulled = pulled[(share[pulled] > 0) & st.pull.found[pulled]]  # a node not pulled has no pull to back off
    if pulled.size == 0:
        return False
    share[pulled] *= 0.5
    share[pulled[share[pulled] < 0.1]] = 0.0
    st.pull.backed[pulled] = True
    st.pull.rounds += 1
    return True


_NEAR_FLOOR = 0.05
"""From the second back-off round on (without the pull), the elements within this of the floor
are backed off with the failing ones."""


def _nodes_to_back_off(st: _Smoothing) -> np.ndarray:
    """(S,) int64 boundary-node numbers: the failing elements' boundary nodes that still move
    (k > 0, or pulled), widened to their neighbours (at most 4 times) when none does.

    From the second round on, the elements within ``_NEAR_FLOOR`` of the floor count as
    failing too: backing off one element moves others towards the floor, and a row of such
    elements (merged elements under 6 mm slices) then failed one element a round, more rounds
    than the guard has. Not with the pull onto a scan: its corner sharpening leaves thousands
    of elements at the floor + 0.02 by design (the head CT: 31 % of the boundary nodes
    backed off)."""
    cells = st.mesh.cells
    bpos = st.boundary_position()
    bad = st.bad
    if st.rounds >= 2 and st.pull is None:  # counted before the round
        bad = bad | (st.sj < float(st.s["min_scaled_jacobian"]) + _NEAR_FLOOR)
    nodes = np.unique(cells[st.touched[bad]].ravel())
    for _ in range(4):
        sel = bpos[nodes]
        sel = sel[(sel >= 0)]
        sel = sel[(st.k[sel] > 0) | (st.pull.share[sel] > 0)] if st.pull is not None else sel[st.k[sel] > 0]
        if sel.size:
            break
        mark = np.zeros(st.mesh.n_points, bool)
        mark[nodes] = True
        nodes = np.unique(cells[_touching(cells, mark)].ravel())
    return sel


def _freeze(st: _Smoothing) -> None:
    """Failing elements that were below the floor before smoothing pass only as they were: their
    boundary nodes stop at once (k = 0, no pull; halving k round by round took six rounds).
    Those and the failing elements none of whose boundary nodes moves any more fail by their
    interior band nodes, which the relaxation moves for the rest of the surface: those are held
    where they were."""
    bad = np.flatnonzero(st.bad)
    cells = st.mesh.cells[st.touched[bad]]
    b = st.boundary_position()[cells]
    low = st.checked.scaled_jacobian(st.x0, bad) < float(st.s["min_scaled_jacobian"])
    _keep_in_place(st, b[low][b[low] >= 0])
    moving = (b >= 0) & (st.k[np.maximum(b, 0)] > 0)
    if st.pull is not None:
        moving |= (b >= 0) & (st.pull.share[np.maximum(b, 0)] > 0)
    mark = np.zeros(st.mesh.n_points, bool)
    mark[cells[~moving.any(axis=1)]] = True
    _keep_in_place(st, np.zeros(0, np.int64), mark)


def _keep_in_place(st: _Smoothing, boundary: np.ndarray, band: np.ndarray | None = None) -> None:
    """The boundary nodes ``boundary`` (numbers among the boundary's) stop (k = 0, no pull), and
    the band nodes marked in ``band`` (N,) bool are held where they were."""
    st.k[boundary] = 0.0
    st.backed[boundary] = True
    if st.pull is not None:
        st.pull.share[boundary] = 0.0
    if band is not None and st.interior is not None and st.band_nodes.size:
        st.interior.hold(np.flatnonzero(band[st.band_nodes]))


_FREEZE_ROUNDS = 20
"""Rounds after ``max_backoff_rounds`` that keep the failing elements and their neighbours as
they were before smoothing, before the guard gives up."""


def _freeze_around_failures(st: _Smoothing) -> None:
    """After the back-off rounds: the failing elements and the elements around them keep their
    nodes where they were before smoothing (boundary nodes k = 0 and no pull, band nodes held).

    Backing off a node moves its neighbours' elements towards the floor, and on strongly
    anisotropic merged elements (6 mm slices) a new few failed every round until the rounds ran
    out; an element whose nodes all stay is as it was, so these rounds end (at worst the
    unsmoothed mesh, which passes)."""
    mark = np.zeros(st.mesh.n_points, bool)
    mark[st.mesh.cells[st.touched[st.bad]]] = True
    mark[st.mesh.cells[st.touched[st.checked.holding(mark)]]] = True  # and one ring of elements around
    b = st.boundary_position()[np.flatnonzero(mark)]
    b = b[b >= 0]
    st.frozen[b] = True
    _keep_in_place(st, b, mark)


def _back_off(st: _Smoothing) -> None:
    """One back-off round: the failing elements' nodes lose their pull and their coefficient is
    multiplied by ``backoff_factor`` (0 in the last rounds, and below 0.02); the interior band
    nodes of failing elements with nothing left to back off are held (``_freeze``)."""
    s, k = st.s, st.k
    _freeze(st)
    last = st.rounds >= max(1, s["max_backoff_rounds"] - 2)
    sel = _nodes_to_back_off(st)
    if sel.size == 0:
        st.rounds = s["max_backoff_rounds"]  # nothing left to back off: report on the next pass
        return
    if st.pull is not None:
        st.pull.share[sel] = 0.0  # then the labels' smoothing backs off as without an image
    k[sel] = 0.0 if last else k[sel] * s["backoff_factor"]
    k[sel[k[sel] < 0.02]] = 0.0
    st.backed[sel] = True


def _guard_failure(st: _Smoothing) -> DicerError:
    """The error naming the worst failing element, when the back-off rounds are used up."""
    mesh, sj, bad = st.mesh, st.sj, st.bad
    worst = int(np.argmin(np.where(bad, sj, np.inf)))
    e = int(st.touched[worst])
    centre = st.x[mesh.cells[e]].mean(axis=0)
    if mesh.direction is not None:  # where the exported model and a viewer of the scan put it
        from dicer.mesh.frame import to_scanner

        centre = to_scanner(centre[None], mesh.spacing, mesh.origin, mesh.direction)[0]
    return DicerError(
        f"smoothing cannot keep element {e + 1} (material {int(mesh.material[e])}, centre "
        f"{', '.join(f'{c:.2f}' for c in centre[: mesh.dim])} mm) at a scaled Jacobian of at least "
        f"{float(st.s['min_scaled_jacobian']):g} (it reaches {sj[worst]:.3f}, {int(bad.sum())} element(s) fail); "
        "lower smooth.coefficient or smooth.min_scaled_jacobian, or raise smooth.max_backoff_rounds")


def _solve_with_guard(st: _Smoothing) -> None:
    """Both solves under the quality guard, with back-off rounds until no checked element fails.

    A round first backs off the pull onto the image (up to ``_PULL_ROUNDS`` times for one
    boundary solve), then the coefficients (``_back_off``) and solves again.

    Raises
    ------
    DicerError
        When elements still fail after ``max_backoff_rounds`` rounds.
    """
    while True:
        ts = time.perf_counter()
        xb_labels = _boundary_solve(st)
        if st.pull is not None:
            _pull_onto_image(st, xb_labels)
        for pull_round in range(_PULL_ROUNDS + 1):
            _interior_solve(st, xb_labels)
            tg = time.perf_counter()
            st.t_solve += tg - ts
            # a round moves few nodes much (a pull round's, a back-off round's): only the elements
            # it moved are checked again, and positions are accepted on a whole check only
            if not _check_quality(st) and not st.bad.any():
                _check_quality(st, whole=True)
            ts = time.perf_counter()
            st.t_guard += ts - tg
            if st.pull is None or not st.bad.any() or pull_round >= _PULL_ROUNDS or not _back_off_pull(st):
                break
        if not st.bad.any():
            return
        log.info("smooth: %d element(s) below smooth.min_scaled_jacobian=%g: back-off round %d", int(st.bad.sum()),
                 float(st.s["min_scaled_jacobian"]), st.rounds + st.frozen_rounds + 1)
        if st.rounds >= st.s["max_backoff_rounds"]:
            if st.s["max_backoff_rounds"] == 0 or st.frozen_rounds >= _FREEZE_ROUNDS:
                raise _guard_failure(st)
            st.frozen_rounds += 1
            _freeze_around_failures(st)
            continue
        st.rounds += 1
        _back_off(st)


# --- the pillow layer --------------------------------------------------------------------------

_PILLOW_ROUNDS = 40  # guard rounds of the layer
_PILLOW_LAST_ROUNDS = 4  # the rounds before the last, where the faces at every failing element leave the layer
_PILLOW_ROOM = 0.02  # with the layer the smoothing keeps its elements this far above the floor: room for the move
_PILLOW_THINNEST = (0.5, 0.125)
"""No copy comes closer to its node than the first share of smooth.pillow_thickness or the
second of a voxel, whichever is less: an edge ratio of at most about 8 on a voxel's face
(a copy pulled inward holds there; near a gap in the layer it stands out so far)."""
_PILLOW_STRETCH = float(section_defaults("quality")["stretched_edge_ratio"])
"""A new element's longest edge is at most this many times its shortest: the edge ratio above
which the quality report calls an element stretched (quality.stretched_edge_ratio's default, 20)."""
_PILLOW_LENGTH = 0.8
"""A new element's characteristic length (volume over largest face) is at least this share of
its nodes' least thickness: a sheared one is thinner than its nodes' distances from their
copies, and an explicit solver's time step follows the thinnest element."""


@dataclass
class _Layer:
    """The pillow layer's result: the mesh with it and the report's figures."""

    mesh: Mesh
    info: dict


def _layer_mesh(st: _Smoothing, nodes: np.ndarray, outer: np.ndarray, cells: np.ndarray, owner: np.ndarray) -> Mesh:
    """The smoothed mesh with the layer: the surface nodes' copies (positions ``outer``) after
    the nodes, the layer's ``cells`` after the elements, each copy and new element carrying
    the data (lattice, node class, point and cell data, material) of its original."""
    mesh = st.mesh
    n = mesh.n_points
    point_data = {k: np.concatenate([v, v[nodes]]) for k, v in mesh.point_data.items()}
    point_data["node_class"] = np.concatenate([st.g.node_class, st.g.node_class[nodes]])
    cell_data = {k: np.concatenate([v, v[owner]]) for k, v in mesh.cell_data.items()}
    dtype = np.int32 if mesh.cells.dtype == np.int32 and n + nodes.size < 2**31 else np.int64
    return Mesh(np.concatenate([st.x, outer]), np.concatenate([np.asarray(mesh.cells, dtype), cells.astype(dtype)]),
                np.concatenate([mesh.material, mesh.material[owner]]),
                np.concatenate([mesh.lattice, mesh.lattice[nodes]]), mesh.spacing.copy(), mesh.origin.copy(),
                mesh.grid_shape.copy(), point_data, cell_data, list(mesh.names))


def _move_under_layer(st: _Smoothing, x: np.ndarray, xb: np.ndarray, b: np.ndarray, move: np.ndarray) -> None:
    """Move the boundary nodes ``b`` (numbers among the boundary nodes) by ``move`` (mm) from the
    smoothed positions ``x``, ``xb``, solve the interior band for it; sets ``st.x``, ``st.xb``,
    ``st.x_band``."""
    inner = xb.copy()
    inner[b] += move
    st.x = x.copy()
    _solve_band(st, inner)


def _under_layer_sj(st: _Smoothing, last: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """(C,) the checked elements' scaled Jacobian at ``st.x``: recomputed for those holding a
    node moved more than ``_RECHECK_MOVE`` since ``last`` (positions (N, 3) and their values)
    or within ``_RECHECK_MARGIN`` + ``_NEAR_FLOOR`` of the floor, as the guard's rounds do; the
    others keep their value (None: all computed). A round of the layer changes the depth near
    a few new gaps, and the band moves by its solve's tolerance elsewhere."""
    if last is None:
        return st.checked.scaled_jacobian(st.x)
    x_last, sj = last
    reach = _RECHECK_MOVE * float(np.min(np.asarray(st.mesh.spacing, float)[: st.mesh.dim]))
    again = st.checked.holding(_moved_farther(st.x, x_last, reach))
    again |= sj < float(st.s["min_scaled_jacobian"]) + _RECHECK_MARGIN + _NEAR_FLOOR
    sj = sj.copy()
    which = np.flatnonzero(again)
    sj[which] = st.checked.scaled_jacobian(st.x, which)
    return sj


_TAPER = 3  # surface edges over which the depth of the nodes under the layer grows from a gap in it
_TAPER_SHEAR = 3.0
"""A step of d voxels in the depth between two nodes of an element under the layer changes its
scaled Jacobian by up to about this x d (measured up to 3.1 on the coarse head phantom: its
staircase corners, flattened by the smoothing to just above the floor, have six or seven nodes
on the surface and fail on a third of the default depth's step, 0.08 voxel)."""
_TAPER_LEAST = 0.05  # the least share of the depth the taper grows by across an element


def _taper_graph(st: _Smoothing, at: np.ndarray, nodes: np.ndarray, sj: np.ndarray) -> sp.csr_matrix:
    """(P, P) the steps of the taper: the share of the full depth by which it may grow between
    two surface nodes (rows of ``nodes``). Two nodes of a face: 1 / _TAPER. Two nodes of a
    checked element with less room above the floor (``sj``, the checked elements' scaled
    Jacobian after the smoothing): that room / (``_TAPER_SHEAR`` x the depth in voxels), at
    least ``_TAPER_LEAST`` (the smallest step between two nodes counts)."""
    size = nodes.size
    step = 1.0 / _TAPER
    pair_a, pair_b = np.triu_indices(at.shape[1], 1)
    a, b, w = at[:, pair_a].ravel(), at[:, pair_b].ravel(), np.full(at.shape[0] * pair_a.size, step)
    room = (sj - float(st.s["min_scaled_jacobian"])) / (_TAPER_SHEAR * float(st.s["pillow_thickness"]))
    allowed = np.clip(room, _TAPER_LEAST, step)
    frail = np.flatnonzero(allowed < step)
    if frail.size:
        row = np.full(st.mesh.n_points, -1, np.int64)
        row[nodes] = np.arange(size)
        corner = row[st.mesh.cells[st.touched[frail]]]
        pair_a, pair_b = np.triu_indices(corner.shape[1], 1)
        ea, eb = corner[:, pair_a].ravel(), corner[:, pair_b].ravel()
        ew = np.repeat(allowed[frail], pair_a.size)
        both = (ea >= 0) & (eb >= 0)
        a, b, w = np.r_[a, ea[both]], np.r_[b, eb[both]], np.r_[w, ew[both]]
    a, b = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((w, b, a))
    a, b, w = a[order], b[order], w[order]
    first = np.r_[True, (a[1:] != a[:-1]) | (b[1:] != b[:-1])][: a.size]  # the smallest step of each pair
    return sp.csr_matrix((w[first], (a[first], b[first])), shape=(size, size))


_DEPTHS = (1.0, 0.5, 0.25)
"""The shares of the full depth a node under the layer steps down through, a step a round,
where an element under it fails, before the layer's faces there are dropped. A copy keeps
``_PILLOW_THINNEST`` from its node (at a quarter of the default depth: up to a sixteenth of a
voxel beyond where the smoothing put the surface). On the head CT a quarter of the depth
covers 94 % of the exterior faces where half covers 90 %, in 11 rounds instead of 13, with the
copies 0.031 voxel from the fitted surface on average either way; an eighth covers 95 % at
0.033."""


def _taper(layered: np.ndarray, steps: sp.csr_matrix, level: np.ndarray | None = None) -> np.ndarray:
    """(P,) the share of the full depth each surface node moves inward: 0 off the layer (a node
    of faces without it), ``_DEPTHS[level]`` at each node ((P,) int, steps down the ladder),
    then growing by the ``steps`` (``_taper_graph``) along the shortest way from such a node, 1
    at most: k / _TAPER at k edges from a gap where the elements under the surface can take it,
    less steep across those the smoothing left near the floor. A depth that jumps between
    neighbours would shear the elements under them.

    ``layered``: (P,) bool, nodes of faces with the layer."""
    from scipy.sparse.csgraph import dijkstra

    share = np.ones(layered.size)
    if not layered.all():
        share = np.minimum(dijkstra(steps, directed=False, indices=np.flatnonzero(~layered), min_only=True,
                                    limit=1.0), 1.0)
    if level is not None:
        for k in range(1, len(_DEPTHS)):
            if (level == k).any():
                start = _DEPTHS[k]
                share = np.minimum(share, start + dijkstra(steps, directed=False, indices=np.flatnonzero(level == k),
                                                           min_only=True, limit=1.0 - start))
    share[~layered] = 0.0
    return share


def _fails_under_layer(sj: np.ndarray, sj_accepted: np.ndarray, floor: float, shrunk: np.ndarray) -> np.ndarray:
    """(C,) bool: the checked elements the layer's move fails: below the floor (or inverted)
    and worse than the smoothing left them (an element may stay below the floor where the
    smoothing left it so), or with an edge it shrank (``shrunk``, their rows)."""
    bad = ((sj < floor) | (sj <= 0)) & (sj < sj_accepted - 1e-12)
    bad[shrunk] = True
    return bad


def _hold_thickness(share: np.ndarray, rows: np.ndarray, start: np.ndarray, goal: np.ndarray, under: np.ndarray,
                    thinnest: np.ndarray) -> None:
    """Lower ``share[rows]`` where a copy at ``start + share (goal - start)`` would lie closer than
    ``thinnest`` to its node at ``under`` (all (R, 3), mm): to the first share at which its
    distance falls to 1.001 ``thinnest``; to 0 where ``start`` already lies that close (near a
    gap the taper's depth is less: the copy is then pushed out along the normal instead)."""
    d = goal - start
    w = start - under
    a = np.einsum("ij,ij->i", d, d)
    half_b = np.einsum("ij,ij->i", w, d)
    c = np.einsum("ij,ij->i", w, w) - (1.001 * thinnest) ** 2
    s = share[rows]
    dist2 = a * s * s + 2 * half_b * s + c  # |copy - under|^2 - (1.001 thinnest)^2
    close = (dist2 < 0) & (a > 0)
    if not close.any():
        return
    a, half_b, c = a[close], half_b[close], c[close]
    first = (-half_b - np.sqrt(np.maximum(half_b * half_b - a * c, 0.0))) / a  # the smaller root (< 0 if c < 0)
    share[rows[close]] = np.clip(first, 0.0, s[close])


def _add_pillow(st: _Smoothing) -> None:
    """Put a pillow layer over the smoothed mesh's exterior surface (``dicer.mesh.pillow``).

    The surface nodes are copied: the copies become the surface, on the scan's iso-surface
    before ``lift`` (``st.surface``) or, without the scan, where the smoothing put the nodes;
    the nodes under them move inward along the surface direction by ``pillow_thickness``
    voxels (less near a gap in the layer: ``_taper``), and the interior band is
    solved again for that move. The guard checks the elements the move touches and the new
    ones: a failing new element's nodes take half their move onto the iso-surface (none
    below a tenth); a new element that fails with its nodes back on the smoothed surface
    loses its place in the layer; around a failing element under it the nodes go less deep
    (``_DEPTHS``), then the layer's faces there leave it (their nodes then stay where the
    smoothing put them: on thin or sharply folded parts the layer leaves gaps, its sides there
    part of the surface). The smoothing before it kept
    its elements ``_PILLOW_ROOM`` above the floor. Sets ``st.layer``, and ``st.x``, ``st.xb``,
    ``st.x_band``, ``st.sj`` (the checked elements, then the new ones) for the report.

    In the last ``_PILLOW_LAST_ROUNDS`` rounds every failing element's faces leave the layer;
    where an element still fails after ``_PILLOW_ROUNDS`` rounds, the stage warns and keeps the
    smoothing without the layer (``given_up`` in the report).
    """
    from dicer.mesh.pillow import one_fan_per_node, outward_normals, pillow_cells, surface_faces

    t0 = time.perf_counter()
    mesh, s = st.mesh, st.s
    dim, n = mesh.dim, mesh.n_points
    faces, owner = surface_faces(mesh.cells, dim, n, plane_bits(mesh, st.x0), (st.bnodes, st.g.boundary_cells))
    nodes = np.unique(faces)
    at = np.searchsorted(nodes, faces)  # the faces' nodes as rows of nodes
    b = st.boundary_position()[nodes]  # every exterior node is a boundary node
    held = bounding_planes(mesh, st.x0[nodes])  # the layer meets a bounding plane at right angles
    on_plane = held.any(axis=1)
    held[:, 2] |= dim == 2
    normal = outward_normals(st.x, faces, nodes, held)
    spacing = np.asarray(mesh.spacing, float)
    # mm: voxels along the normal, the same everywhere in isotropic voxels
    voxel = norm(normal * spacing, axis=1)  # mm: a voxel along the normal
    move = -(float(s["pillow_thickness"]) * voxel)[:, None] * normal
    # the share of its move onto st.surface a copy makes (without the scan: no move)
    share = np.zeros(nodes.size) if st.surface is None else np.ones(nodes.size)
    # faces with an element of the layer; with bounding_planes: fixed, none at a plane's nodes,
    # which keep their place (the layer ends short of the plane, its side there the surface)
    kept = ~on_plane[at].any(axis=1) if s["bounding_planes"] == "fixed" else np.ones(faces.shape[0], bool)
    at_fixed_planes = int(np.count_nonzero(~kept))
    # progress: the layer's rounds take tens of seconds on a head
    log.info("smooth: a pillow layer over %d exterior faces, %g voxel thick (smooth.pillow)", faces.shape[0],
             float(s["pillow_thickness"]))
    x, xb, sj_accepted = st.x, st.xb, st.sj
    floor = float(s["min_scaled_jacobian"])
    goal = st.xb[b] if st.surface is None else st.surface[b]  # without the scan: the smoothed surface
    solved = None
    steps = _taper_graph(st, at, nodes, sj_accepted)
    # the elements under the layer that any copy's node is in, and their edges before the
    # layer (at x) and before smoothing (at st.x0): a round measures only their edges at st.x
    surface = np.zeros(n, bool)
    surface[nodes] = True
    near_all = np.flatnonzero(st.checked.holding(surface))
    near_all_cells = mesh.cells[st.touched[near_all]]
    lengths0 = _edge_lengths2(near_all_cells, st.x0)
    short_before = _edge_lengths2(near_all_cells, x) < _SHORTEST_EDGE**2 * lengths0
    del surface
    # every face's element of the layer before smoothing: a copy's position then is its node's
    layer_lengths0 = _edge_lengths2(pillow_cells(faces, np.arange(n)), st.x0)
    last = None  # the positions and values of the last scaled Jacobian of the elements under the layer
    level = np.zeros(nodes.size, np.int8)  # the surface nodes' steps down _DEPTHS
    fanned = None  # the faces one_fan_per_node last returned: unchanged, it returns them again
    given_up = False
    for rounds in range(_PILLOW_ROUNDS + 2):
        if fanned is None or not np.array_equal(fanned, kept):
            kept = one_fan_per_node(faces, kept, mesh.material[owner])
            fanned = kept.copy()
        layered = np.zeros(nodes.size, bool)
        layered[at[kept]] = True
        rows = np.flatnonzero(layered)
        if solved is None or not (np.array_equal(solved[0], layered) and np.array_equal(solved[1], level)):
            depth = _taper(layered, steps, level)[rows, None] * move[rows]
            _move_under_layer(st, x, xb, b[rows], depth)
            sj_under, whole = _under_layer_sj(st, last), last is None
            last = (st.x, sj_under)
            # the layer's least thickness (_PILLOW_THINNEST)
            thinnest = np.zeros(nodes.size)
            thinnest[rows] = min(_PILLOW_THINNEST[0] * float(s["pillow_thickness"]), _PILLOW_THINNEST[1]) * voxel[rows]
            # the elements under the layer whose edges its move brought together (not those the
            # smoothing left so), and the copies' start: where their nodes were
            moved = np.zeros(n, bool)
            moved[nodes[rows]] = True
            sub = np.flatnonzero(any_per_row(moved[near_all_cells]))
            shrunk = near_all[sub[(_short_edges(near_all_cells[sub], st.x, None, moved, lengths0[sub])
                                   & ~short_before[sub]).any(axis=1)]]
            solved = (layered, level.copy())
        new_id = np.full(n, -1, np.int64)
        new_id[nodes[rows]] = n + np.arange(rows.size)
        cells = pillow_cells(faces[kept], new_id)
        # a copy pulled onto an iso-surface below the smoothed one thins the layer, and a sliver
        # passes the scaled Jacobian (its corners stay square) but not a solver's conditioning
        # nor an explicit solver's time step: such a copy stops where the layer is still
        # ``thinnest`` thick
        _hold_thickness(share, rows, xb[b[rows]], goal[rows], st.x[nodes[rows]], thinnest[rows])
        outer = xb[b[rows]] + share[rows, None] * (goal[rows] - xb[b[rows]])
        # where the taper leaves the layer thinner than that (near a gap), its copy stands that
        # far out from its node instead: the surface moves out by less than that
        least = thinnest[rows]
        w = outer - st.x[nodes[rows]]
        gap = np.einsum("ij,ij->i", w, w) - least * least
        thin = np.flatnonzero(gap < 0)
        if thin.size:  # out along the normal until the copy is that far from its node
            up = np.einsum("ij,ij->i", w[thin], normal[rows[thin]])
            outer[thin] += (np.sqrt(up * up - gap[thin]) - up)[:, None] * normal[rows[thin]]
        x_layer = np.concatenate([st.x, outer])
        sj_layer = scaled_jacobian(x_layer, cells)
        bad_under = _fails_under_layer(sj_under, sj_accepted, floor, shrunk)
        bad_sj = (sj_layer < floor) | (sj_layer <= 0)
        # and edges brought together on the copies' face
        lengths = _edge_lengths2(cells, x_layer)
        bad_short = (lengths < _SHORTEST_EDGE**2 * layer_lengths0[kept]).any(axis=1)
        # and no new element stretched (a thin layer under a long merged face)
        bad_stretch = lengths.max(axis=1) > _PILLOW_STRETCH**2 * lengths.min(axis=1)
        least_at = np.zeros(n)
        least_at[nodes[rows]] = thinnest[rows]
        bad_thin = characteristic_length(x_layer, cells) < _PILLOW_LENGTH * least_at[faces[kept]].min(axis=1)
        bad_layer = bad_sj | bad_short | bad_stretch | bad_thin
        if not (bad_under.any() or bad_layer.any() or whole):  # the layer is accepted on a whole check only
            sj_under, whole = st.checked.scaled_jacobian(st.x), True
            last = (st.x, sj_under)
            bad_under = _fails_under_layer(sj_under, sj_accepted, floor, shrunk)
        if not (bad_under.any() or bad_layer.any()):
            break
        if rounds >= _PILLOW_ROUNDS:
            error = _pillow_failure(st, sj_under, bad_under, sj_layer, bad_sj,
                                    {f"an edge shorter than {_SHORTEST_EDGE:g} of its length before": bad_short,
                                     f"its longest edge over {_PILLOW_STRETCH:g} times its shortest": bad_stretch,
                                     "thinner than the layer's least thickness": bad_thin})
            if given_up:  # without a layer the smoothing's own elements fail: not the layer's doing
                raise error
            # the layer did not settle: the mesh is smoothed without it rather than stopped
            log.warning("smooth: no pillow layer: after %d guard rounds %s; the surface is the smoothing's without "
                        "it (thin or sharply folded parts; set smooth.pillow: false to skip the layer's rounds)",
                        rounds, str(error).split("; set smooth.pillow")[0])
            given_up = True
            kept[:] = False
            continue
        log.info("smooth: pillow layer round %d: %d element(s) under it and %d of it fail the guard", rounds + 1,
                 int(bad_under.sum()), int(bad_layer.sum()))
        failing = np.flatnonzero(kept)[bad_layer]
        pulled = np.unique(at[failing])
        pulled = pulled[share[pulled] > 0]
        share[pulled] *= 0.5
        share[pulled[share[pulled] < 0.1]] = 0.0
        drop = failing[(share[at[failing]] == 0).all(axis=1)]
        if bad_under.any():
            # the layer's faces near the failing elements: at their nodes and those of the
            # elements around them (the band's nodes move with the surface's) go a step down
            # _DEPTHS; where they were all at its last already, the faces at a failing
            # element's own nodes leave the layer (all of those faces, where no failing element
            # has a node on them: an element a layer deeper)
            own = np.zeros(n, bool)
            own[mesh.cells[st.touched[bad_under]]] = True
            under = own.copy()
            under[mesh.cells[_touching(mesh.cells, under)]] = True
            near = np.flatnonzero(kept & any_per_row(under[faces]))
            lower = (level[at[near]] < len(_DEPTHS) - 1).any(axis=1)
            stepped = at[near[lower]].ravel()
            level[stepped] = np.minimum(level[stepped] + 1, len(_DEPTHS) - 1)
            again = near[~lower]
            at_own = again[any_per_row(own[faces[again]])]
            drop = np.union1d(drop, at_own if at_own.size else again)
            if rounds >= _PILLOW_ROUNDS - _PILLOW_LAST_ROUNDS:
                drop = np.union1d(drop, near)
        if rounds >= _PILLOW_ROUNDS - _PILLOW_LAST_ROUNDS:
            # a layer that halving and stepping down did not settle: the faces there leave it
            # (their nodes back where the smoothing put them, its elements as accepted), so the
            # default smoothing does not stop on a thin part
            drop = np.union1d(drop, failing)
        kept[drop] = False
    st.sj = np.concatenate([sj_under, sj_layer])
    from dicer.mesh.labelsurface import LabelSurface

    from_scan = st.pull is not None and not isinstance(st.pull.surface, LabelSurface)
    info = {"surface": "image" if from_scan else "labels", "elements_added": int(cells.shape[0]),
            "nodes_added": int(rows.size), "faces_without_layer": int(np.count_nonzero(~kept)),
            "given_up": given_up,
            "faces_at_fixed_planes": at_fixed_planes,
            "thickness_voxels": float(s["pillow_thickness"]), "guard_rounds": rounds,
            "nodes_held_off_the_surface": 0 if st.surface is None else int(np.count_nonzero(share[rows] < 1.0)),
            "nodes_at_half_depth": int(np.count_nonzero(level[rows] == 1)),
            "nodes_at_quarter_depth": int(np.count_nonzero(level[rows] == 2)),
            "min_scaled_jacobian": float(sj_layer.min()) if sj_layer.size else 1.0}
    st.layer = _Layer(_layer_mesh(st, nodes[rows], outer, cells, owner[kept]), info)
    st.timings["pillow"] = time.perf_counter() - t0
    log.info("smooth: the pillow layer holds %d of the %d exterior faces after %d guard round(s), in %.1f s",
             int(np.count_nonzero(kept)), faces.shape[0], rounds, st.timings["pillow"])


def _pillow_failure(st: _Smoothing, sj_under: np.ndarray, bad_under: np.ndarray, sj_layer: np.ndarray,
                    bad_sj: np.ndarray, shapes: dict[str, np.ndarray]) -> DicerError:
    """The error naming the worst failing element (numbered as in the mesh with the layer) and
    the check it fails: the scaled Jacobian's floor, or one of ``shapes`` (reason -> (E,) bool
    over the layer's elements) where no element fails the floor."""
    failing = int(bad_under.sum() + np.logical_or.reduce([bad_sj, *shapes.values()]).sum())
    under = np.where(bad_under, sj_under, np.inf)
    layer = np.where(bad_sj, sj_layer, np.inf)
    if not (np.isfinite(under).any() or np.isfinite(layer).any()):
        reason, bad = next((r, b) for r, b in shapes.items() if b.any())
        number = st.mesh.n_cells + int(np.flatnonzero(bad)[0]) + 1
        return DicerError(
            f"the pillow layer cannot keep element {number} (of the layer) in shape: {reason} ({failing} element(s) "
            "fail); set smooth.pillow: false, or change smooth.pillow_thickness")
    if under.size and (not layer.size or under.min() <= layer.min()):
        worst, number, what = float(under.min()), int(st.touched[np.argmin(under)]) + 1, "under the layer"
    else:
        worst, number, what = float(layer.min()), st.mesh.n_cells + int(np.argmin(layer)) + 1, "of the layer"
    return DicerError(
        f"the pillow layer cannot keep element {number} ({what}) at a scaled Jacobian of at least "
        f"{float(st.s['min_scaled_jacobian']):g} (it reaches {worst:.3f}, {failing} "
        "element(s) fail); set smooth.pillow: false, or lower smooth.pillow_thickness or smooth.min_scaled_jacobian")


# --- the result and the report ------------------------------------------------------------------


def _smoothed_mesh(st: _Smoothing) -> Mesh:
    """The smoothed mesh: the input's topology arrays (cells, material, lattice) shared, point
    data ``node_class`` added (or the mesh with its pillow layer)."""
    if st.layer is not None:
        return st.layer.mesh
    mesh = st.mesh
    point_data = dict(mesh.point_data)
    point_data["node_class"] = st.g.node_class
    return Mesh(st.x, mesh.cells, mesh.material, mesh.lattice, mesh.spacing.copy(), mesh.origin.copy(),
                mesh.grid_shape.copy(), point_data, dict(mesh.cell_data), list(mesh.names))


def _volume_change(st: _Smoothing) -> tuple[np.ndarray, float, np.ndarray]:
    """Each material's volume change and its volume before smoothing.

    The volume a mesh (and each material) encloses depends on its boundary nodes only: it is
    measured on the elements holding a boundary node with only the boundary nodes moved.
    With a pillow layer the surface is its outer nodes': every element of the result counts.

    Returns
    -------
    change : (max material + 1,) float64
        Change of each material's volume, mm^3 (2D: area, mm^2).
    total : float
        The whole mesh's change, mm^3 (mm^2).
    base : (max material + 1,) float64
        Each material's volume before smoothing, mm^3 (mm^2).
    """
    mesh, g, checked, x0, bc = st.mesh, st.g, st.checked, st.x0, st.g.boundary_cells
    if checked.hex:  # the boundary cells' volumes from the checked elements' coordinate columns
        local = checked.local[:, np.searchsorted(st.touched, bc)]  # bc is a subset of touched
        columns = checked.columns(x0)
        v0 = hex_volumes_t(columns, local)
    else:
        v0 = element_volumes(x0, mesh.cells[bc])
    if st.graded:
        before = element_volumes(x0, mesh.cells)
    else:  # lattice boxes, but merging's chamfers are no boxes: they lie at the boundary, measured there
        before = _lattice_volumes(mesh)
        before[bc] = v0
    base = np.bincount(mesh.material, weights=before)
    del before
    if st.layer is not None:
        out = st.layer.mesh
        after = np.bincount(out.material, weights=element_volumes(out.points, out.cells), minlength=base.size)
        change = after[: base.size] - base
        return change, float(change.sum()), base
    if checked.hex:
        on_boundary = g.boundary[checked.nodes]
        for c1, c0 in zip(checked.last, columns):  # only the boundary nodes moved
            np.copyto(c0, c1, where=on_boundary)
        dv = hex_volumes_t(columns, local) - v0
        del local, columns
    else:
        xb_only = x0.copy()
        xb_only[st.bnodes] = st.x[st.bnodes]
        dv = element_volumes(xb_only, mesh.cells[bc]) - v0
        del xb_only
    return np.bincount(mesh.material[bc], weights=dv, minlength=base.size), float(dv.sum()), base


def _pull_report(st: _Smoothing) -> dict:
    """The ``surface_from_image`` (or ``surface_from_labels``) part of the report (empty without the pull)."""
    if st.pull is None:
        return {}
    from dicer.mesh.subvoxel import ImageSurface

    p = st.pull
    common = {"pull_backoff_rounds": p.rounds, "pull_backed_off_nodes": int(p.backed.sum())}
    on = int(np.count_nonzero((p.share == 1.0) & p.found))
    if not isinstance(p.surface, ImageSurface):
        return {"surface_from_labels": {**p.info, **common, "nodes_on_the_fitted_surface": on}}
    return {"surface_from_image": {**p.info, "image_sigma": st.s["image_sigma"], **common,
                                   "nodes_on_the_image_surface": on}}


def _report(st: _Smoothing, t0: float, labels=None) -> dict:
    """The stage's report (see docs/smoothing.md); ``t0``: the stage's start, for the timings;
    ``labels``: the label volume the fit took, whose volumes the result is compared with."""
    mesh, g, s, sj = st.mesh, st.g, st.s, st.sj
    change, total, base = _volume_change(st)
    volume_change = {str(kind): float(change[kind] / base[kind]) for kind in np.flatnonzero(base)}
    bdisp = norm(st.xb - st.xb0, axis=1)
    idisp = norm(st.x_band - st.x_band0, axis=1) if st.band_nodes.size else np.zeros(0)
    max_disp = max(float(bdisp.max()) if bdisp.size else 0.0, float(idisp.max()) if idisp.size else 0.0)
    return {
        "nodes": mesh.n_points,
        "elements": mesh.n_cells,
        "boundary_nodes": int(st.bnodes.size),
        "boundary_edges": int(g.edges.shape[0]),
        "node_classes": class_counts(g.node_class),
        "coefficients": dict(s["coefficients"]),
        "interior_nodes_solved": int(st.band_nodes.size),
        "interior_band": s["interior_band"],
        "bounding_planes": s["bounding_planes"],
        "boundary_iterations": int(st.it_b),
        "interior_iterations": int(st.it_i),
        "backoff_rounds": st.rounds,
        "backed_off_nodes": int(st.backed.sum()),
        # only when the back-off rounds did not suffice: nodes kept where they were (the staircase)
        **({"frozen_rounds": st.frozen_rounds, "frozen_nodes": int(st.frozen.sum())} if st.frozen_rounds else {}),
        "min_scaled_jacobian": float(sj.min()) if sj.size else 1.0,
        "checked_elements": int(st.touched.size),
        "inverted_elements": int(np.count_nonzero(sj <= 0)),
        "volume_change": total / float(base.sum()) if base.sum() else 0.0,  # 0: a mesh of no volume
        "volume_change_by_material": volume_change,
        **({} if labels is None else
           {"volume_change_from_labels_by_material": _change_from_labels(change, base, labels, mesh)}),
        "max_displacement_mm": max_disp,
        "mean_boundary_displacement_mm": float(bdisp.mean()) if bdisp.size else 0.0,
        **_pull_report(st),
        **({"pillow": {**st.layer.info, "nodes": st.layer.mesh.n_points, "elements": st.layer.mesh.n_cells}}
           if st.layer is not None else {}),
        "seconds": {**{k_: round(v, 3) for k_, v in st.timings.items()}, "solve": round(st.t_solve, 3),
                    "guard": round(st.t_guard, 3), "total": round(time.perf_counter() - t0, 3)},
    }


@takes_settings("smooth", section=True)
def smooth_mesh(mesh: Mesh, *, surface_from_image, image_sigma, surface_from_labels, label_surface_radius,
                fit_to_scan, label_samples, coefficient, coefficients, bounding_planes, keep_bounding_planes, interior,
                shrink_compensation, interior_band, min_scaled_jacobian, backoff_factor, max_backoff_rounds, pillow,
                pillow_thickness, tolerance, image=None, thresholds=None, image_source: str = "image", labels=None,
                labels_source: str = "labels") -> tuple[Mesh, dict]:
    """Smooth ``mesh``: node classes, boundary solve, pull onto the image, interior solve, guard.

    The settings are keyword-only, with no defaults here: the command line passes
    ``dicer.config.stage_kwargs(config, "smooth")``. A library call may instead give
    the ``smooth:`` section (or part of it) as the second argument, or leave settings
    out; the schema's defaults fill them (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    mesh : Mesh
        A mesh made by 'dicer mesh' (voxel, plane-merged or graded), with ``lattice`` point data.
    surface_from_image, image_sigma, surface_from_labels, label_surface_radius, fit_to_scan, label_samples, \
coefficient, coefficients, bounding_planes, keep_bounding_planes, interior, shrink_compensation, interior_band, \
min_scaled_jacobian, backoff_factor, max_backoff_rounds, pillow, pillow_thickness, tolerance
        The ``smooth:`` config section (see the schema and :func:`smoothing_settings`).
    image : dicer.image.Volume, optional
        The scan the labels were segmented from; with ``surface_from_image`` the boundary nodes
        move onto its iso-surfaces after the boundary solve (``dicer.mesh.subvoxel``). Without
        it, ``surface_from_labels`` moves them onto a fit of the labels' staircase
        (``dicer.mesh.labelsurface``), whose faces the scan places within their voxels first
        (``fit_to_scan``, with ``labels`` and ``label_samples`` faces).
    thresholds : sequence of float, optional
        The lower bound of each material 1..K in the image's units, as segmentation chose them.
    image_source : str
        The image's name in messages.
    labels : dicer.image.Volume, optional
        The label volume the mesh was made from (before merging or grading): ``surface_from_labels``
        fits its staircase, not the mesh's faces, whose merged steps (chamfers) lie off it.
    labels_source : str
        The labels' name in messages.

    Returns
    -------
    mesh : Mesh
        Same topology, smoothed positions (mm), point data ``node_class`` (N,) int8.
    report : dict
        Counts, iterations, back-off, quality, volume change, displacements, seconds.

    Raises
    ------
    DicerError
        Bad settings, an empty mesh, a mesh without lattice data, an image, thresholds or labels
        that do not fit the mesh, or a mesh the guard cannot bring above ``min_scaled_jacobian``.
    """
    s = smoothing_settings.__wrapped__(
        surface_from_image=surface_from_image, image_sigma=image_sigma, surface_from_labels=surface_from_labels,
        label_surface_radius=label_surface_radius, fit_to_scan=fit_to_scan, label_samples=label_samples,
        coefficient=coefficient,
        coefficients=coefficients,
        bounding_planes=bounding_planes, keep_bounding_planes=keep_bounding_planes, interior=interior,
        shrink_compensation=shrink_compensation, interior_band=interior_band,
        min_scaled_jacobian=min_scaled_jacobian, backoff_factor=backoff_factor,
        max_backoff_rounds=max_backoff_rounds, pillow=pillow, pillow_thickness=pillow_thickness, tolerance=tolerance)
    _check_input(mesh)
    surface, t_img = _pull_surface(mesh, s, image, thresholds, image_source, labels, labels_source)
    surface_from_scan = image is not None and s["surface_from_image"]
    t0 = time.perf_counter()
    if s["pillow"]:  # the smoothing leaves room above the floor for the layer's move inward
        st = _set_up(mesh, {**s, "min_scaled_jacobian": min(s["min_scaled_jacobian"] + _PILLOW_ROOM, 0.99)}, surface,
                     t0, t_img)
        _solve_with_guard(st)
        st.s = s
        _add_pillow(st)
    else:
        st = _set_up(mesh, s, surface, t0, t_img)
        _solve_with_guard(st)
    # the labels as the fit took them (not beside a scan's surface)
    return _smoothed_mesh(st), _report(st, t0, labels if surface is not None and not surface_from_scan else None)


def _change_from_labels(change: np.ndarray, base: np.ndarray, labels, mesh: Mesh) -> dict:
    """Each material's smoothed volume (``base`` + ``change``, by material) against its voxels'
    in ``labels``, relative: the labels before merging, so a merge's chamfers count."""
    after = base + change
    voxel = float(np.prod(np.asarray(mesh.spacing, float)[:mesh.dim]))
    counts = np.bincount(np.asarray(labels.array).ravel(), minlength=after.size)[:after.size] * voxel
    return {str(kind): float(after[kind] / counts[kind] - 1.0) for kind in np.flatnonzero(counts[1:]) + 1}
