"""Boundary edges, the boundary graph and the node classes A-F (paper section 2.4, Fig. 5).

Everything is derived from the mesh's topology (which elements share a node or an
edge) and its node coordinates, never from lattice positions, so it works the same on
voxel meshes and on plane-merged meshes.

* A node is a *boundary node* unless it is shared by eight elements of one material (or is
  a node of a coarse cell or transition template of a graded mesh: cell data
  ``coarsening_level`` > 0, all inside one material).
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

* With ``mirror=True`` the image's bounding planes are mirrors (symmetry cuts): every
  count is taken in the model reflected across the planes a node or edge lies on, so a
  plane node gets the kind, class and boundary edges it has in the whole, mirrored model.
  A node on k planes sees 2^k copies of its elements; a neighbour off one of those planes
  is seen 2 (or 4, 8) times, once per reflection (the edge weights of ``adjacency``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dicer.arrays import any_per_row
from dicer.errors import DicerError
from dicer.mesh.model import LEVEL_DATA, Mesh
from dicer.mesh.topology import HEX_EDGES, QUAD_EDGES

__all__ = ["NODE_CLASSES", "BoundaryGraph", "boundary_graph", "classify_nodes", "with_node_classes",
           "node_cell_counts", "class_counts", "bounding_planes", "plane_bits",
           "plane_axes", "mirror_weights", "mirror_share"]

NODE_CLASSES = ("interior", "A", "B", "C", "D", "E", "F", "X")
"""Names of the ``node_class`` codes 0..7."""

_PACKED_KINDS = 20  # materials the packed per-edge histogram holds (3 bits each in an int64); more are sorted
_KEY_MAX = 2**63 - 1  # largest sort key (edge, material) packed in one int64


@dataclass
class BoundaryGraph:
    """The boundary graph of a mesh.

    boundary : (N,) bool, boundary nodes.
    edges : (E, 2) int64 node pairs (first < second), the boundary edges.
    degree : (N,) int64, boundary edges per node (R in the smoothing equation).
    node_class : (N,) int8, codes of NODE_CLASSES.
    boundary_cells : sorted indices of the elements holding a boundary node.
    planes : (N,) uint8, the mirror planes a node lies on (``plane_bits``; all 0 without mirrors).
    """

    boundary: np.ndarray
    edges: np.ndarray
    degree: np.ndarray
    node_class: np.ndarray
    boundary_cells: np.ndarray
    planes: np.ndarray | None = None

    def adjacency(self, nodes: np.ndarray | None = None) -> "scipy.sparse.csr_matrix":
        """Adjacency of the boundary graph, restricted to ``nodes`` (default: the boundary
        nodes, in increasing order); rows and columns follow ``nodes``. Entry (n, j) is the
        number of mirror copies of j next to n (``mirror_weights``): 1 without mirrors,
        when the matrix is symmetric; its row sums are ``degree``."""
        if nodes is None:
            nodes = np.flatnonzero(self.boundary)
        pos = np.full(self.boundary.size, -1, np.int32 if self.boundary.size < 2**31 else np.int64)
        pos[nodes] = np.arange(nodes.size)
        a, b = pos[self.edges[:, 0]], pos[self.edges[:, 1]]
        keep = (a >= 0) & (b >= 0)
        a, b = a[keep], b[keep]
        if self.planes is None or not self.planes.any():
            w = np.ones(2 * a.size)
        else:
            ea, eb = self.edges[keep, 0], self.edges[keep, 1]
            w = np.concatenate([mirror_weights(self.planes[ea], self.planes[eb]),
                                mirror_weights(self.planes[eb], self.planes[ea])])
        import scipy.sparse as sp  # here: the processes that only export or check never load scipy (0.2 s)

        return sp.csr_matrix((w, (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(nodes.size, nodes.size))


PLANE_TOLERANCE = 1e-6
"""A node within this many voxels of a bounding plane lies on it (smoothing, exports)."""


def _plane_tests(mesh: Mesh, points: np.ndarray | None):
    """Yield (axis, high, on) for each bounding plane of the image: ``on`` (N,) bool, the
    node lies on the low (lattice 0) or high (grid_shape) plane normal to ``axis``, within
    PLANE_TOLERANCE voxel; never along z in 2D. ``on`` is one buffer, overwritten per plane."""
    pts = mesh.points if points is None else points
    lo = np.asarray(mesh.origin, float)
    hi = lo + np.asarray(mesh.grid_shape, float) * np.asarray(mesh.spacing, float)
    tol = PLANE_TOLERANCE * np.asarray(mesh.spacing, float)
    distance = np.empty(pts.shape[0])
    on = np.empty(pts.shape[0], bool)
    for axis in range(mesh.dim):  # a column at a time, one temporary: 2-4 times faster at 6 M nodes
        for high, plane in ((False, lo[axis]), (True, hi[axis])):
            np.subtract(pts[:, axis], plane, out=distance)
            np.abs(distance, out=distance)
            np.less_equal(distance, tol[axis], out=on)
            yield axis, high, on


def _plane_sides(mesh: Mesh, points: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) bool twice: the node lies on the image's low / high bounding plane normal to
    that axis (:func:`_plane_tests`)."""
    n = (mesh.points if points is None else points).shape[0]
    on_lo, on_hi = np.zeros((n, 3), bool), np.zeros((n, 3), bool)
    for axis, high, on in _plane_tests(mesh, points):
        (on_hi if high else on_lo)[:, axis] = on
    return on_lo, on_hi


def bounding_planes(mesh: Mesh, points: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) bool: the node lies on a bounding plane of the image normal to that axis."""
    on_lo, on_hi = _plane_sides(mesh, points)
    return on_lo | on_hi


def plane_bits(mesh: Mesh, points: np.ndarray | None = None) -> np.ndarray:
    """(N,) uint8: bit a set for a node on the low bounding plane normal to axis a, bit
    3 + a on the high one (the two planes of an axis are two mirrors: a slab one voxel
    thick, mirrored at both, is endless). One byte per node, no (N, 6) tables."""
    bits = np.zeros((mesh.points if points is None else points).shape[0], np.uint8)
    for axis, high, on in _plane_tests(mesh, points):
        bits[on] |= np.uint8(1 << (axis + 3 * high))
    return bits


def plane_axes(planes: np.ndarray) -> np.ndarray:
    """(N, 3) bool from ``plane_bits``: the node lies on a plane normal to that axis."""
    either = (planes | (planes >> 3)) & 7
    return ((either[:, None] >> np.arange(3, dtype=np.uint8)) & 1) == 1


_POPCOUNT = np.array([bin(i).count("1") for i in range(64)], np.int64)


def mirror_weights(planes_n: np.ndarray, planes_j: np.ndarray) -> np.ndarray:
    """Copies of node j next to node n in the mirrored model: one per reflection across
    the planes n lies on and j does not (2^count; 1 without mirrors)."""
    return np.left_shift(1, _POPCOUNT[planes_n & ~planes_j & 63]).astype(np.float64)


def mirror_share(planes: np.ndarray) -> np.ndarray:
    """A node's share of the mirrored model relative to a node on no plane: 2^-(its planes)."""
    return np.ldexp(1.0, -_POPCOUNT[planes & 63])


_ROWS = 65536  # elements per block of the passes over all elements (a block stays in the cache)


def _kinds(material: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct material values, each element's rank among them (no sorting) and the
    number of elements of each."""
    m = np.asarray(material)
    if m.dtype.kind not in "iu":
        m = m.astype(np.int64)
    if m.size and m.min() < 0:
        raise DicerError("material values must not be negative; renumber the materials")
    present = np.bincount(m) if m.size else np.zeros(0, np.int64)
    kinds = np.flatnonzero(present)
    lut = np.zeros(present.size, np.int8 if kinds.size <= 127 else np.int32)
    lut[kinds] = np.arange(kinds.size)
    return kinds, lut[m], present[kinds]


def _uniform(cells: np.ndarray, rank: np.ndarray, n: int, n_kinds: int) -> np.ndarray:
    """Per node: whether all elements sharing it have one material rank.

    Every element writes its rank to its nodes (the last write stays), then every
    element compares: a node where some element finds another rank is mixed.
    """
    if n_kinds <= 1:
        return np.ones(n, bool)
    kind_of = np.zeros(n, rank.dtype)
    for start in range(0, cells.shape[0], _ROWS):
        kind_of[cells[start : start + _ROWS]] = rank[start : start + _ROWS, None]
    mixed = np.zeros(n, bool)
    for start in range(0, cells.shape[0], _ROWS):
        block = cells[start : start + _ROWS]
        other = kind_of[block] != rank[start : start + _ROWS, None]
        if other.any():
            mixed[block[other]] = True
    return ~mixed


def node_cell_counts(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Per node: the number of elements sharing it, and whether they all have one material."""
    n = mesh.n_points
    cnt = np.bincount(mesh.cells.ravel(), minlength=n)
    kinds, rank, _ = _kinds(mesh.material)
    return cnt, _uniform(mesh.cells, rank, n, kinds.size)


def _check(mesh: Mesh) -> None:
    if mesh.n_cells == 0 or mesh.n_points == 0:
        raise DicerError("the mesh has no elements; mesh a label volume with material voxels first")
    if mesh.cells.ndim != 2 or mesh.cells.shape[1] not in (4, 8):
        raise DicerError(f"elements have {mesh.cells.shape[1]} nodes; hexahedra (8) or quads (4) are needed")
    if mesh.material.shape != (mesh.n_cells,):
        raise DicerError("material data do not match the element count; the mesh file is inconsistent")


def _slot_counts(slots: np.ndarray, rank: np.ndarray, n_kinds: int) -> tuple[np.ndarray, np.ndarray]:
    """node_cell_counts (counts as int8) from the corner table ``slots`` (see boundary_graph)."""
    cnt = np.zeros(slots.shape[1], np.int8)  # at most 8
    if n_kinds <= 1:
        for row in slots:
            cnt += row >= 0
        return cnt, np.ones(slots.shape[1], bool)
    big = np.iinfo(rank.dtype).max
    low = np.full(slots.shape[1], big, rank.dtype)
    high = np.full(slots.shape[1], -1, rank.dtype)
    for row in slots:
        present = row >= 0
        cnt += present
        r = rank[row]  # row -1: the last element's rank, masked below
        np.minimum(low, np.where(present, r, big), out=low)
        np.maximum(high, np.where(present, r, -1), out=high)
    return cnt, (low == high) | (high < 0)


def _edge_counts_packed(lo: np.ndarray, hi: np.ndarray, rank: np.ndarray, n: int, n_kinds: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per distinct edge: its two nodes, its element count and the most elements of one material.

    lo, hi : (P,) int, the two node numbers (lo <= hi < n) of every edge of every element.
    rank : (P,) int, the material rank (0 .. n_kinds - 1, n_kinds <= _PACKED_KINDS) of its element.
    Returns (first, second, total, top), each (E,), edges in increasing (first, second) order.

    Every material gets a 3-bit counter in an int64 and a sparse matrix sums the
    duplicates: one linear pass, faster than a sort for few materials.
    """
    import scipy.sparse as sp

    code = np.left_shift(np.int64(1), 3 * np.arange(n_kinds, dtype=np.int64))
    hist = sp.csr_matrix((code[rank], (lo, hi)), shape=(n, n))
    hist.sum_duplicates()  # rows and columns sorted: edges in increasing (first, second) order
    first = np.repeat(np.arange(n, dtype=lo.dtype), np.diff(hist.indptr))
    h = hist.data.astype(np.int64)
    if not h.size:
        return first, hist.indices, np.zeros(0, np.int64), np.zeros(0, np.int64)
    counts = np.stack([(h >> (3 * r)) & 7 for r in range(n_kinds)], axis=1)
    return first, hist.indices, counts.sum(axis=1), counts.max(axis=1)


def _edge_counts_sorted(lo: np.ndarray, hi: np.ndarray, rank: np.ndarray, n: int, n_kinds: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``_edge_counts_packed`` for any number of materials: (edge, material) pairs sorted
    and counted in runs."""
    if lo.size == 0:
        empty = np.zeros(0, np.int64)
        return lo, hi, empty, empty
    new_edge = np.ones(lo.size, bool)  # first entry of an edge in sorted order
    new_pair = np.ones(lo.size, bool)  # first entry of an (edge, material) pair
    if n * n * n_kinds <= _KEY_MAX:  # Python ints: no overflow in the test
        # one int64 key per entry holds all three values: sorting the keys is all the sorting
        key = (lo.astype(np.int64) * n + hi) * n_kinds + rank
        key.sort(kind="stable")  # runs of sorted keys (elements come in order): timsort is quick
        edge = key // n_kinds
        np.not_equal(key[1:], key[:-1], out=new_pair[1:])
        np.not_equal(edge[1:], edge[:-1], out=new_edge[1:])
        del key
        starts = np.flatnonzero(new_edge)
        first, second = np.divmod(edge[starts], n)
        del edge
    else:
        order = np.lexsort((rank, hi, lo))
        a, b, r = lo[order], hi[order], rank[order]
        del order
        np.not_equal(a[1:], a[:-1], out=new_edge[1:])
        new_edge[1:] |= b[1:] != b[:-1]
        np.not_equal(r[1:], r[:-1], out=new_pair[1:])
        new_pair |= new_edge
        starts = np.flatnonzero(new_edge)
        first, second = a[starts].astype(np.int64), b[starts].astype(np.int64)
        del a, b, r
    total = np.diff(np.append(starts, lo.size))
    pair_starts = np.flatnonzero(new_pair)
    run = np.diff(np.append(pair_starts, lo.size))  # elements of one material on one edge
    first_run = np.cumsum(new_pair)[starts] - 1  # each edge's first pair
    top = np.maximum.reduceat(run, first_run)
    return first.astype(lo.dtype), second.astype(hi.dtype), total, top


def _node_counts(mesh: Mesh, pts: np.ndarray, slots: np.ndarray | None, rank: np.ndarray, n_kinds: int,
                 mirror: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boundary nodes by their element counts (the first test of the module notes).

    Returns
    -------
    boundary : (N,) bool
        Nodes not shared by a full unit block of one material (nor inside a coarse cell).
    maybe : (N,) bool
        Plane nodes with a full block of one material, whose edges decide (see below).
    planes : (N,) uint8
        ``plane_bits`` with ``mirror``, else 0.
    """
    n, cells = mesh.n_points, mesh.cells
    full = 8 if cells.shape[1] == 8 else 4
    if slots is None:
        cnt = np.bincount(cells.ravel(), minlength=n)
        uniform = _uniform(cells, rank, n, n_kinds)
    else:
        cnt, uniform = _slot_counts(slots, rank, n_kinds)
    planes = plane_bits(mesh, pts) if mirror else np.zeros(n, np.uint8)
    if planes.any():
        # a node on k mirror planes holds 2^k copies of each of its elements
        cnt = cnt.astype(np.int64) << _POPCOUNT[planes]
    boundary = (cnt > 0) & ~((cnt == full) & uniform)
    level = mesh.cell_data.get(LEVEL_DATA)
    if level is not None and np.any(level > 0):
        # nodes of coarse cells and transition templates lie inside one material (their
        # element count is not 8 there)
        inner = np.zeros(n, bool)
        inner[cells[np.asarray(level) > 0]] = True
        boundary &= ~(inner & uniform)
    # a plane node can count a full block of one material and still lie on a boundary edge
    # (a chamfer of a merged mesh meeting the plane at an angle leaves a gap in its fan):
    # its edges are examined too, and it is a boundary node if one is a boundary edge
    maybe = (planes != 0) & (cnt > 0) & ~boundary
    return boundary, maybe, planes


def _edges_of(sub: np.ndarray, ranks: np.ndarray, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(first, second, material rank) of the element edges of ``sub`` (elements' nodes in some
    numbering, -1: a node left out) between two numbered nodes, first <= second."""
    a, b = sub[:, local[:, 0]], sub[:, local[:, 1]]
    keep = (a >= 0) & (b >= 0)
    return np.minimum(a, b)[keep], np.maximum(a, b)[keep], np.broadcast_to(ranks[:, None], a.shape)[keep]


def _element_edges(cells: np.ndarray, n: int, pre: np.ndarray, slots: np.ndarray | None, rank: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The edges between two of the nodes ``pre`` of the elements holding one of them.

    Parameters
    ----------
    cells : (C, 8) or (C, 4) int
    n : int
        Number of nodes.
    pre : (P,) int64, sorted
        The candidate boundary nodes.
    slots : (corners, N) int32 or None
        The corner table (see ``boundary_graph``).
    rank : (C,) int
        Material rank of each element.

    Returns
    -------
    lo, hi : (L,) int32 (int64 for 2^31 nodes or more)
        Both ends of every such edge of every element, numbered among ``pre``, lo <= hi.
    mat : (L,) int
        The material rank of the element.
    cand : sorted int64
        The elements holding a node of ``pre``.
    """
    per = cells.shape[1]
    local = HEX_EDGES if per == 8 else QUAD_EDGES
    idx = np.int32 if n < 2**31 else np.int64
    p = np.full(n, -1, idx)
    p[pre] = np.arange(pre.size, dtype=idx)
    parts = []  # per block of elements: (first, second, material rank) of its edges
    if slots is None:
        has = np.empty(cells.shape[0], bool)
        for start in range(0, cells.shape[0], _ROWS):
            sub = p[cells[start : start + _ROWS]]
            on = (sub >= 0).any(axis=1)
            has[start : start + _ROWS] = on
            parts.append(_edges_of(sub[on], rank[start : start + _ROWS][on], local))
        cand = np.flatnonzero(has)
    else:
        has = np.zeros(cells.shape[0], bool)
        for row in slots:
            e = row[pre]
            has[e[e >= 0]] = True
        cand = np.flatnonzero(has)
        for start in range(0, cand.size, _ROWS):
            part = cand[start : start + _ROWS]
            parts.append(_edges_of(p[cells[part]], rank[part], local))
    del p, has
    if not parts:
        parts.append(_edges_of(np.zeros((0, per), idx), np.zeros(0, rank.dtype), local))
    lo, hi, mat = (np.concatenate(column) for column in zip(*parts))
    return lo, hi, mat, cand


@dataclass
class _Edges:
    """The boundary edges, with their ends numbered among the candidate nodes ``pre``.

    nodes : (E, 2) int64, node pairs (first < second).
    a, b : (E,) int, the first and second node's number among ``pre`` (later: among the boundary nodes).
    biggest : (E,) int64, the most element slots of one kind (empty slots one kind) around the edge.
    w_ab, w_ba : (E,) float64 or None, copies of b next to a and of a next to b (mirror planes only).
    """

    nodes: np.ndarray
    a: np.ndarray
    b: np.ndarray
    biggest: np.ndarray
    w_ab: np.ndarray | None = None
    w_ba: np.ndarray | None = None


def _boundary_edges(lo: np.ndarray, hi: np.ndarray, mat: np.ndarray, pre: np.ndarray, planes: np.ndarray,
                    n_kinds: int, edge_slots: int) -> _Edges:
    """The boundary edges among the element edges ``lo``, ``hi`` (with material ranks ``mat``,
    see ``_element_edges``): those without ``edge_slots`` elements of one material (4; 2D: 2),
    counted in the mirrored model when ``planes`` (N,) uint8 has bits set."""
    idx = np.int32 if planes.size < 2**31 else np.int64
    count_edges = _edge_counts_packed if n_kinds <= _PACKED_KINDS else _edge_counts_sorted
    e_lo, e_hi, total, top = count_edges(lo, hi, mat, pre.size, n_kinds)
    if planes.any():
        # an edge lying in k mirror planes has 2^k copies of each of its element slots
        shift = _POPCOUNT[planes[pre[e_lo]] & planes[pre[e_hi]]]
        top, total = top.astype(np.int64) << shift, total.astype(np.int64) << shift
    is_b = top < edge_slots
    biggest = np.maximum(top, edge_slots - total)  # empty slots are one more kind
    ea, eb = e_lo[is_b], e_hi[is_b].astype(idx)
    edges = _Edges(np.stack([pre[ea], pre[eb]], axis=1), ea, eb, biggest[is_b])
    if planes.any():
        # the copies of each neighbour in the mirrored model (w_ab: copies of b next to a)
        edges.w_ab = mirror_weights(planes[edges.nodes[:, 0]], planes[edges.nodes[:, 1]])
        edges.w_ba = mirror_weights(planes[edges.nodes[:, 1]], planes[edges.nodes[:, 0]])
    return edges


def _degrees(edges: _Edges, pre: np.ndarray, boundary: np.ndarray, maybe: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Boundary edges per node (R), and the boundary nodes made exactly the nodes on boundary edges.

    ``boundary`` (N,) bool is updated in place, and ``edges.a``, ``edges.b`` renumbered among
    the boundary nodes.

    Returns
    -------
    degree : (N,) int64
        R of every node (mirror copies counted).
    deg : (B,) int64
        R of the boundary nodes, in increasing node order.
    """
    ea, eb = edges.a, edges.b
    if edges.w_ab is not None:
        deg = (np.bincount(ea, weights=edges.w_ab, minlength=pre.size)
               + np.bincount(eb, weights=edges.w_ba, minlength=pre.size)).astype(np.int64)
    else:
        deg = np.bincount(ea, minlength=pre.size) + np.bincount(eb, minlength=pre.size)
    degree = np.zeros(boundary.size, np.int64)
    degree[pre] = deg
    # boundary nodes are exactly the nodes on boundary edges (a node of a single-material
    # unit block with empty slots has them); keep the two definitions in step
    if maybe.any():
        boundary[pre[deg > 0]] = True
    on_edge = deg > 0
    if not on_edge.all():
        boundary[pre[~on_edge]] = False
        renumber = np.cumsum(on_edge, dtype=np.int64) - 1
        edges.a, edges.b = renumber[ea], renumber[eb]
        deg = deg[on_edge]
    return degree, deg


def _flat_nodes(pts: np.ndarray, edges: _Edges, bn: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(B,) bool: the unit vectors along a boundary node's boundary edges (mirror copies
    included) nearly cancel (|sum| < 0.5); ``bn`` (B,) the boundary nodes, ``pts`` (N, 3) mm."""
    ea, eb = edges.a, edges.b
    d = pts[edges.nodes[:, 1]] - pts[edges.nodes[:, 0]]
    length = np.sqrt(np.einsum("ij,ij->i", d, d))
    if np.any(length <= 0):
        raise DicerError("the mesh has boundary edges of zero length; it is degenerate")
    u = d / length[:, None]
    usum = np.zeros((bn.size, 3))
    for c in range(3):
        if edges.w_ab is None:
            usum[:, c] = np.bincount(ea, weights=u[:, c], minlength=bn.size) - np.bincount(
                eb, weights=u[:, c], minlength=bn.size)
        else:
            usum[:, c] = np.bincount(ea, weights=edges.w_ab * u[:, c], minlength=bn.size) - np.bincount(
                eb, weights=edges.w_ba * u[:, c], minlength=bn.size)
    if planes.any():
        # the reflected copies cancel the components normal to the node's planes
        usum[plane_axes(planes[bn])] = 0.0
    return np.einsum("ij,ij->i", usum, usum) < 0.25


def _node_classes(per: int, deg: np.ndarray, flat: np.ndarray, edges: _Edges) -> np.ndarray:
    """(B,) int8: the class codes of the boundary nodes (see NODE_CLASSES) from their
    boundary-edge counts ``deg``, ``flat`` (``_flat_nodes``) and the edges' splits; ``per``:
    nodes per element (8: hexahedra, 4: quads)."""
    cb = np.full(deg.size, 7, np.int8)
    if per == 8:
        split = np.zeros(deg.size, bool)  # some boundary edge split two/two
        two = edges.biggest <= 2
        split[edges.a[two]] = True
        split[edges.b[two]] = True
        cb[deg == 3] = 1
        cb[(deg == 4) & ~flat] = 2
        cb[deg == 5] = 3
        cb[(deg == 4) & flat] = 4
        cb[(deg == 6) & split] = 5
        cb[(deg == 6) & ~split] = 6
    else:
        cb[(deg == 2) & ~flat] = 2
        cb[(deg == 2) & flat] = 4
    return cb


def boundary_graph(mesh: Mesh, points: np.ndarray | None = None, slots: np.ndarray | None = None,
                   mirror: bool = False) -> BoundaryGraph:
    """Boundary nodes, boundary edges, their counts and the node classes of ``mesh``.

    Parameters
    ----------
    mesh : Mesh
        Hexahedra or quads.
    points : (N, 3) float64, optional
        The geometry (mm) used to tell B from D (and corner from flat in 2D); default
        ``mesh.points``. Pass the unsmoothed positions.
    slots : (corners, N) int32, optional
        The element in which each node is corner c (-1: none), for a mesh in which a node is
        corner c of at most one element (lattice-aligned elements, as made by 'dicer mesh');
        with it no pass over all elements is needed. Same result.
    mirror : bool
        The bounding planes are mirrors (see the module notes): ``degree`` and the classes
        are those of the mirrored model, ``planes`` says which nodes lie on which plane.

    Returns
    -------
    BoundaryGraph
    """
    _check(mesh)
    n, cells = mesh.n_points, mesh.cells
    per = cells.shape[1]
    pts = mesh.points if points is None else points
    kinds, rank, _ = _kinds(mesh.material)
    boundary, maybe, planes = _node_counts(mesh, pts, slots, rank, kinds.size, mirror)
    # the elements holding a candidate node, and their edges between two candidates
    pre = np.flatnonzero(boundary | maybe)
    lo, hi, mat, cand = _element_edges(cells, n, pre, slots, rank)
    edges = _boundary_edges(lo, hi, mat, pre, planes, kinds.size, 4 if per == 8 else 2)
    del lo, hi, mat
    degree, deg = _degrees(edges, pre, boundary, maybe)
    bn = np.flatnonzero(boundary)
    flat = _flat_nodes(pts, edges, bn, planes)
    cls = np.zeros(n, np.int8)
    cls[bn] = _node_classes(per, deg, flat, edges)
    if maybe.any():  # elements held only by plane nodes that turned out interior are not boundary cells
        cand = cand[any_per_row(boundary[cells[cand]])]
    return BoundaryGraph(boundary, edges.nodes, degree, cls, cand, planes)


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
