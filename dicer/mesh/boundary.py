"""Boundary edges, the boundary graph and the node classes A-F (paper section 2.4, Fig. 5).

Everything is derived from the mesh's topology (which elements share a node or an
edge) and its node coordinates, never from lattice positions, so it works the same on
voxel meshes and on plane-merged meshes.

* A node is a *boundary node* unless it is shared by eight elements of one material.
* An edge is a *boundary edge* unless four elements of one material share it (2D: two).
* The boundary nodes and boundary edges form the *boundary graph*; a node's boundary
  neighbours are its neighbours in that graph.
* Node classes (point data ``node_class``), by the number R of boundary edges:

  ====  =====  ==========================================================================
  code  class  rule
  ====  =====  ==========================================================================
  0     -      interior node
  1     A      R = 3 (corner: one element of a kind in the unit block)
  2     B      R = 4 and the unit vectors along the four boundary edges do not cancel (ridge)
  3     C      R = 5
  4     D      R = 4 and the four unit vectors cancel: flat (the neighbours' centroid is the node)
  5     E      R = 6 and some boundary edge has its four elements split two/two (staircase)
  6     F      R = 6 and every boundary edge has three of its four element slots alike (triple corner)
  7     X      any other count (only in meshes that skipped the connectivity fixes)
  ====  =====  ==========================================================================

  In 2D (quads) every boundary node of a fixed mesh has R = 2: collinear edges give D
  (flat), perpendicular ones B (corner); other counts are X.
  Empty element slots (background, or outside the image) count as one more kind.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from dicer.errors import DicerError
from dicer.mesh.model import Mesh

__all__ = ["NODE_CLASSES", "BoundaryGraph", "boundary_graph", "classify_nodes", "with_node_classes",
           "HEX_EDGES", "QUAD_EDGES", "node_cell_counts", "class_counts"]

NODE_CLASSES = ("interior", "A", "B", "C", "D", "E", "F", "X")
"""Names of the ``node_class`` codes 0..7."""

HEX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])
QUAD_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])

_MAX_KINDS = 20  # material kinds the per-edge histogram holds (3 bits each in an int64)


@dataclass
class BoundaryGraph:
    """The boundary graph of a mesh.

    boundary : (N,) bool, boundary nodes.
    edges : (E, 2) int64 node pairs (first < second), the boundary edges.
    degree : (N,) int64, boundary edges per node (R in the smoothing equation).
    node_class : (N,) int8, codes of NODE_CLASSES.
    boundary_cells : sorted indices of the elements holding a boundary node.
    """

    boundary: np.ndarray
    edges: np.ndarray
    degree: np.ndarray
    node_class: np.ndarray
    boundary_cells: np.ndarray

    def adjacency(self, nodes: np.ndarray | None = None) -> sp.csr_matrix:
        """Symmetric 0/1 adjacency of the boundary graph, restricted to ``nodes`` (default:
        the boundary nodes, in increasing order); rows and columns follow ``nodes``."""
        if nodes is None:
            nodes = np.flatnonzero(self.boundary)
        pos = np.full(self.boundary.size, -1, np.int64)
        pos[nodes] = np.arange(nodes.size)
        a, b = pos[self.edges[:, 0]], pos[self.edges[:, 1]]
        keep = (a >= 0) & (b >= 0)
        a, b = a[keep], b[keep]
        ones = np.ones(2 * a.size)
        return sp.csr_matrix((ones, (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(nodes.size, nodes.size))


def _kinds(material: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct material values and each element's rank among them (no sorting)."""
    m = material.astype(np.int64)
    if m.size and m.min() < 0:
        raise DicerError("material values must not be negative; renumber the materials")
    present = np.bincount(m) if m.size else np.zeros(0, np.int64)
    kinds = np.flatnonzero(present)
    lut = np.zeros(present.size, np.int64)
    lut[kinds] = np.arange(kinds.size)
    return kinds, lut[m], present[kinds]


def node_cell_counts(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per node: the number of elements sharing it, and whether they all have one material."""
    n = mesh.n_points
    cnt = np.bincount(mesh.cells.ravel(), minlength=n)
    kinds, rank, sizes = _kinds(mesh.material)
    if kinds.size <= 1:
        return cnt, np.ones(n, bool)
    uniform = np.zeros(n, bool)
    rest = cnt.copy()
    biggest = int(np.argmax(sizes))
    for r in range(kinds.size):
        if r == biggest:
            continue
        ck = np.bincount(mesh.cells[rank == r].ravel(), minlength=n)
        uniform |= ck == cnt
        rest -= ck
    uniform |= rest == cnt
    return cnt, uniform


def _check(mesh: Mesh) -> None:
    if mesh.n_cells == 0 or mesh.n_points == 0:
        raise DicerError("the mesh has no elements; mesh a label volume with material voxels first")
    if mesh.cells.ndim != 2 or mesh.cells.shape[1] not in (4, 8):
        raise DicerError(f"elements have {mesh.cells.shape[1]} nodes; hexahedra (8) or quads (4) are needed")
    if mesh.material.shape != (mesh.n_cells,):
        raise DicerError("material data do not match the element count; the mesh file is inconsistent")


def boundary_graph(mesh: Mesh, points: np.ndarray | None = None) -> BoundaryGraph:
    """Boundary nodes, boundary edges, their counts and the node classes of ``mesh``.

    ``points`` (default ``mesh.points``) is the geometry used to tell B from D (and
    corner from flat in 2D); pass the unsmoothed positions.
    """
    _check(mesh)
    n = mesh.n_points
    cells = mesh.cells
    per = cells.shape[1]
    full = 8 if per == 8 else 4
    edge_slots = 4 if per == 8 else 2
    local = HEX_EDGES if per == 8 else QUAD_EDGES
    pts = mesh.points if points is None else points

    cnt, uniform = node_cell_counts(mesh)
    boundary = ~((cnt == full) & uniform)
    boundary &= cnt > 0

    kinds, rank, _ = _kinds(mesh.material)
    if kinds.size > _MAX_KINDS:
        raise DicerError(f"the mesh has {kinds.size} materials; node classification handles up to {_MAX_KINDS}")
    code = np.left_shift(np.int64(1), 3 * rank.astype(np.int64))  # one 3-bit counter per material

    cand = np.flatnonzero(boundary[cells].any(axis=1))
    sub = cells[cand]
    a = sub[:, local[:, 0]].ravel()
    b = sub[:, local[:, 1]].ravel()
    val = np.repeat(code[cand], local.shape[0])
    keep = boundary[a] & boundary[b]
    a, b, val = a[keep], b[keep], val[keep]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    hist = sp.csr_matrix((val, (lo, hi)), shape=(n, n))  # duplicates summed: per-edge histogram
    hist.sum_duplicates()
    e_lo = np.repeat(np.arange(n, dtype=np.int64), np.diff(hist.indptr))
    e_hi = hist.indices.astype(np.int64)
    h = hist.data.astype(np.int64)
    counts = np.stack([(h >> (3 * r)) & 7 for r in range(kinds.size)], axis=1) if h.size else np.zeros((0, kinds.size), np.int64)
    total = counts.sum(axis=1)
    top = counts.max(axis=1) if counts.size else np.zeros(0, np.int64)
    is_b = top < edge_slots
    biggest = np.maximum(top, edge_slots - total)  # empty slots are one more kind
    edges = np.stack([e_lo[is_b], e_hi[is_b]], axis=1)
    biggest = biggest[is_b]

    degree = np.bincount(edges.ravel(), minlength=n).astype(np.int64)
    # boundary nodes are exactly the nodes on boundary edges (a node of a single-material
    # unit block with empty slots has them); keep the two definitions in step
    boundary &= degree > 0

    # unit vectors along the boundary edges, summed per node
    d = pts[edges[:, 1]] - pts[edges[:, 0]]
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    if np.any(length <= 0):
        raise DicerError("the mesh has boundary edges of zero length; it is degenerate")
    u = d / length[:, None]
    bn = np.flatnonzero(boundary)
    bpos = np.full(n, -1, np.int64)
    bpos[bn] = np.arange(bn.size)
    ea, eb = bpos[edges[:, 0]], bpos[edges[:, 1]]
    usum = np.zeros((bn.size, 3))
    for c in range(3):
        usum[:, c] = np.bincount(ea, weights=u[:, c], minlength=bn.size) - np.bincount(
            eb, weights=u[:, c], minlength=bn.size)
    flat = np.zeros(n, bool)
    flat[bn] = np.einsum("ij,ij->i", usum, usum) < 0.25

    cls = np.zeros(n, np.int8)
    if per == 8:
        split = np.zeros(n, bool)  # some boundary edge split two/two
        two = biggest <= 2
        split[edges[two, 0]] = True
        split[edges[two, 1]] = True
        cls[boundary] = 7
        cls[boundary & (degree == 3)] = 1
        cls[boundary & (degree == 4) & ~flat] = 2
        cls[boundary & (degree == 5)] = 3
        cls[boundary & (degree == 4) & flat] = 4
        cls[boundary & (degree == 6) & split] = 5
        cls[boundary & (degree == 6) & ~split] = 6
    else:
        cls[boundary] = 7
        cls[boundary & (degree == 2) & ~flat] = 2
        cls[boundary & (degree == 2) & flat] = 4
    return BoundaryGraph(boundary, edges, degree, cls, cand)


def classify_nodes(mesh: Mesh) -> np.ndarray:
    """``node_class`` codes (N,) int8 of the mesh's nodes (see NODE_CLASSES)."""
    return boundary_graph(mesh).node_class


def with_node_classes(mesh: Mesh) -> tuple[Mesh, dict]:
    """A copy of ``mesh`` with point data ``node_class``, and the count of nodes per class."""
    g = boundary_graph(mesh)
    out = mesh.copy()
    out.point_data["node_class"] = g.node_class
    return out, class_counts(g.node_class)


def class_counts(node_class: np.ndarray) -> dict:
    """{class name: node count} for every class, interior included."""
    n = np.bincount(node_class.astype(np.int64), minlength=len(NODE_CLASSES))
    return {name: int(n[i]) for i, name in enumerate(NODE_CLASSES)}
