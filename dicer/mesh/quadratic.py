"""Quadratic elements: one mid-edge node per mesh edge, shared by every element around the edge.

A 20-node hexahedron (8-node quad in 2D) keeps its 8 (4) corners and adds the
mid-edge nodes in VTK order, which is also Abaqus's: bottom edges 0-1, 1-2, 2-3,
3-0, top edges 4-5, 5-6, 6-7, 7-4, then the vertical edges 0-4, 1-5, 2-6, 3-7
(quad: 0-1, 1-2, 2-3, 3-0). Mid-edge nodes sit at the midpoint of their edge's
end nodes, on the (smoothed) geometry of the linear mesh, and are numbered after
the corner nodes.

Edges are identified once for the whole mesh. An edge along a lattice axis (smoothing
moves points, not lattice indices) is the pair (axis, doubled lattice index of its
midpoint), looked up in one dense grid per axis; mid-edge nodes are numbered by axis
(x, y, z) and in C order of that grid. Only the edges off the lattice lines (plane
merging's chamfers, graded templates) or sharing a grid slot (a pillow layer's copies)
are sorted by their end-node pair, and numbered after the others in ascending order of
the pair. The result depends only on the mesh.
"""

from __future__ import annotations

import logging

import numpy as np

from dicer.arrays import nonzero, norm
from dicer.mesh.boundary import plane_bits
from dicer.mesh.metrics import element_volumes
from dicer.mesh.model import Mesh
from dicer.mesh.topology import HEX_EDGE_AXES, HEX_EDGES, HEX_FACE_EDGES, QUAD_EDGE_AXES, QUAD_EDGES, QUAD_SIDE_EDGES


def edges_by_lattice(mesh: Mesh, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Unique edges of a mesh, found through the lattice indices of their end nodes.

    An edge whose ends differ in one lattice index is the pair (axis, doubled lattice index
    of its midpoint), looked up in one dense grid per axis: no sort. Edges that run off the
    lattice lines (plane merging's chamfers, graded templates) and edges whose grid slot another
    edge already holds (a pillow layer's copies share their nodes' indices) are sorted by their
    end-node pair. Numbering: the grid edges by axis (x, y, z) and in C order of the grid, then
    the others in ascending order of the pair. Depends only on the mesh.

    Parameters
    ----------
    mesh : Mesh
    cells : (M, 8) or (M, 4) int64 ndarray
        ``mesh.cells``.

    Returns
    -------
    edges : (E, 2) int64 ndarray
        End nodes, smaller first.
    index : (M, 12) or (M, 4) int64 ndarray
        The edge of each element edge slot.
    along_lines : bool
        Every element edge runs along its own lattice axis (voxel and plane-merged meshes
        without chamfers): :func:`curved_midpoints` applies.
    """
    dim = mesh.dim
    table, slot_axes = (HEX_EDGES, HEX_EDGE_AXES) if dim == 3 else (QUAD_EDGES, QUAD_EDGE_AXES)
    n = mesh.n_points
    lattice = mesh.lattice
    shape = np.asarray(mesh.grid_shape, np.int64).copy()
    if dim == 2:
        shape[2] = 0
    if n == 0 or cells.shape[0] == 0 or lattice.min() < 0 or np.any(lattice.max(axis=0) > shape) \
            or shape.max() >= 2**20:
        edges, index = mesh_edges(cells, n)
        return edges, index, False
    m, slots = cells.shape[0], table.shape[0]
    lattice_code = (lattice[:, 0] << 42) | (lattice[:, 1] << 21) | lattice[:, 2]  # one gather per end node
    grids = []  # grid a: doubled index along a, plain ones across; laid end to end
    for a in range(dim):
        gshape = shape + 1
        gshape[a] = 2 * shape[a] + 1
        grids.append(gshape)
    base = np.cumsum([0] + [int(np.prod(g)) for g in grids])
    key = np.empty((m, slots), np.int64)  # grid slot of each element edge, -1 off the lattice lines
    used = np.zeros(int(base[-1]), bool)
    along_lines = True
    for c in range(0, m, _CHUNK):  # chunks keep the temporaries in cache
        ends = lattice_code[cells[c:c + _CHUNK][:, table]]
        total = ends[..., 0] + ends[..., 1]  # no carry: every index < 2 ** 20
        moved = [((ends[..., 0] ^ ends[..., 1]) >> shift) & _FIELD for shift in (42, 21, 0)]
        doubled = [(total >> shift) & _FIELD for shift in (42, 21, 0)]
        k = np.full(total.shape, -1, np.int64)
        for a in range(dim):
            on = (moved[a] != 0) & (moved[(a + 1) % 3] == 0) & (moved[(a + 2) % 3] == 0)
            g = grids[a]
            x = [doubled[d] if d == a else doubled[d] >> 1 for d in range(3)]  # across: both ends alike
            np.copyto(k, base[a] + (x[0] * g[1] + x[1]) * g[2] + x[2], where=on)
            along_lines = along_lines and bool(np.all(on == (slot_axes == a)))
        key[c:c + _CHUNK] = k
        used[k[k >= 0]] = True
    count = int(np.count_nonzero(used))
    number = np.cumsum(used, dtype=np.int64 if used.size >= 2**31 else np.int32) - 1
    del used
    index = np.empty((m, slots), np.int64)
    edges = np.empty((count + 1, 2), np.int64)  # row count: a sink for the edges off the lines
    for c in range(0, m, _CHUNK):
        ends = cells[c:c + _CHUNK][:, table]
        k = key[c:c + _CHUNK]
        i = np.where(k >= 0, number[np.maximum(k, 0)], count)
        index[c:c + _CHUNK] = i
        edges[i, 0], edges[i, 1] = ends.min(axis=2), ends.max(axis=2)
    rest = []
    for c in range(0, m, _CHUNK):  # off the lines, or another pair holds the grid slot (copies share indices)
        ends = cells[c:c + _CHUNK][:, table]
        i = index[c:c + _CHUNK]
        held = (edges[i, 0] != ends.min(axis=2)) | (edges[i, 1] != ends.max(axis=2)) | (i == count)
        rows, cols = nonzero(held)
        rest.append((rows + c) * slots + cols)
    rest = np.concatenate(rest)
    edges = [edges[:count]]
    if rest.size:
        along_lines = False
        e, s = np.divmod(rest, slots)
        lo = np.minimum(cells[e, table[s, 0]], cells[e, table[s, 1]])
        hi = np.maximum(cells[e, table[s, 0]], cells[e, table[s, 1]])
        unique, inverse = np.unique(lo * np.int64(n) + hi, return_inverse=True)
        index.reshape(-1)[rest] = count + inverse.ravel()
        edges.append(np.column_stack([unique // n, unique % n]))
    return np.concatenate(edges), index, along_lines


_FIELD = (1 << 21) - 1  # one lattice index (doubled: < 2 ** 21) in a packed node code
_CHUNK = 1 << 15
"""Elements per chunk of :func:`edges_by_lattice` (about 10 MB of temporaries)."""


def mesh_edges(cells: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges of a linear hex/quad mesh.

    Parameters
    ----------
    cells : (M, 8) or (M, 4) int ndarray
    n_points : int

    Returns
    -------
    edges : (E, 2) int64 ndarray
        End nodes, smaller first, rows ascending.
    index : (M, 12) or (M, 4) int64 ndarray
        The edge of each element edge slot.
    """
    table = HEX_EDGES if cells.shape[1] == 8 else QUAD_EDGES
    a = cells[:, table[:, 0]]
    b = cells[:, table[:, 1]]
    keys = np.minimum(a, b) * np.int64(n_points) + np.maximum(a, b)
    unique, index = np.unique(keys.ravel(), return_inverse=True)
    edges = np.column_stack([unique // n_points, unique % n_points])
    return edges, index.reshape(keys.shape)


def _boundary_edges(mesh: Mesh, edges: np.ndarray, index: np.ndarray, boundary_faces: np.ndarray) -> np.ndarray:
    """(E,) bool: the edge lies on a boundary face."""
    slots = HEX_FACE_EDGES if mesh.dim == 3 else QUAD_SIDE_EDGES
    on_boundary = np.zeros(edges.shape[0], bool)
    for f in range(slots.shape[0]):
        e = np.flatnonzero(boundary_faces[:, f])
        on_boundary[index[e[:, None], slots[f]].ravel()] = True
    return on_boundary


def curved_midpoints(mesh: Mesh, edges: np.ndarray, index: np.ndarray, boundary_faces: np.ndarray) -> np.ndarray:
    """Mid-edge node positions with boundary edges bent onto the curve of the boundary.

    A boundary edge a-b whose lattice line continues on the boundary at both ends,
    a'-a-b-b', gets the cubic (Catmull-Rom) point (9 (x_a + x_b) - (x_a' + x_b')) / 16;
    with one continuation, the parabola through the three nodes, e.g.
    (6 x_a + 3 x_b - x_a') / 8; every other edge keeps its midpoint. On a straight line of
    nodes both are the midpoint, so flat faces and cut planes stay flat.

    Parameters
    ----------
    mesh : Mesh
    edges, index : ndarray
        From :func:`edges_by_lattice`.
    boundary_faces : (M, F) bool ndarray
        The element faces on a boundary.

    Returns
    -------
    (E, 3) float64 ndarray
        mm.
    """
    x = mesh.points
    mid = 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])
    on_boundary = _boundary_edges(mesh, edges, index, boundary_faces)
    n = mesh.n_points
    lo, hi = np.minimum(edges[:, 0], edges[:, 1]), np.maximum(edges[:, 0], edges[:, 1])
    keys = lo * np.int64(n) + hi
    order = np.argsort(keys)
    sorted_keys = keys[order]

    def boundary_edge(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        k = np.minimum(p, q) * np.int64(n) + np.maximum(p, q)
        at = np.clip(np.searchsorted(sorted_keys, k), 0, keys.size - 1)
        return (sorted_keys[at] == k) & on_boundary[order[at]]

    lattice = mesh.lattice
    shape = lattice.max(axis=0) + 2
    strides = np.array([shape[1] * shape[2], shape[2], 1], np.int64)
    node_at = np.full(int(np.prod(shape)), -1, np.int64)
    node_at[lattice @ strides] = np.arange(n)

    def node(lat: np.ndarray) -> np.ndarray:
        inside = np.all((lat >= 0) & (lat < shape), axis=1)
        out = np.full(lat.shape[0], -1, np.int64)
        out[inside] = node_at[lat[inside] @ strides]
        return out

    cand = np.flatnonzero(on_boundary)
    a, b = edges[cand, 0], edges[cand, 1]
    step = lattice[b] - lattice[a]
    ap, bp = node(lattice[a] - step), node(lattice[b] + step)
    has_a, has_b = ap >= 0, bp >= 0
    has_a[has_a] = boundary_edge(ap[has_a], a[has_a])
    has_b[has_b] = boundary_edge(b[has_b], bp[has_b])
    both = has_a & has_b
    mid[cand[both]] = (9.0 * (x[a[both]] + x[b[both]]) - (x[ap[both]] + x[bp[both]])) / 16.0
    one = has_a & ~has_b  # the parabola through a', a, b at the middle of a-b
    mid[cand[one]] = (6.0 * x[a[one]] + 3.0 * x[b[one]] - x[ap[one]]) / 8.0
    one = has_b & ~has_a
    mid[cand[one]] = (3.0 * x[a[one]] + 6.0 * x[b[one]] - x[bp[one]]) / 8.0
    return mid


_ARC_TURN = 45.0
"""Largest turn (degrees) from a boundary edge to the next one that :func:`arc_midpoints`
follows as one curve; a sharper turn is a crease, not a curve."""


def _grouped_pairs(keys: np.ndarray, rows: int = 1 << 18):
    """Every ordered pair (i, j), i != j, of entries with the same key, in pieces: for each run
    of ``rows`` entries i (ascending), its i and j (each i's in the order of a stable sort of
    the keys)."""
    order = np.argsort(keys, kind="stable")
    ranked = keys[order]
    first = np.searchsorted(ranked, keys, "left")
    counts = np.searchsorted(ranked, keys, "right") - first
    for start in range(0, keys.size, rows):
        stop = min(start + rows, keys.size)
        n = counts[start:stop]
        i = np.repeat(np.arange(start, stop), n)
        within = np.arange(i.size) - np.repeat(np.cumsum(n) - n, n)
        j = order[np.repeat(first[start:stop], n) + within]
        keep = i != j
        yield start, stop, i[keep], j[keep]


def _sagitta(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(K, 3): from the midpoint of chord a-b to the middle of its arc on the circle through
    p, a and b (p beyond a or b); zero where the three are in a line. Rows are points, mm."""
    chord = b - a
    length = norm(chord, axis=1)
    along = chord / np.maximum(length, 1e-300)[:, None]
    w = p - 0.5 * (a + b)
    across = w - np.sum(w * along, axis=1)[:, None] * along  # the circle's centre side of the chord
    width = norm(across, axis=1)
    # curvature 1/R = 2 sin(angle at a) / |p - b|, the angle between p - a and the chord
    u = p - a
    sine = norm(np.cross(u, chord), axis=1) / np.maximum(norm(u, axis=1) * length, 1e-300)
    k = 2.0 * sine / np.maximum(norm(p - b, axis=1), 1e-300)
    half = np.minimum(0.5 * k * length, 1.0)
    depth = 0.5 * half * length / (1.0 + np.sqrt(1.0 - half * half))
    straight = width <= 1e-12 * np.maximum(length, 1e-300)
    return np.where(straight[:, None], 0.0, -(depth / np.where(straight, 1.0, width))[:, None] * across)


def _first_smallest(group: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Per group, the index of its smallest value (the first on ties; NaN never chosen
    unless the group holds nothing else): ``np.lexsort((value, group))``'s first of each
    group, from a stable sort of the groups alone (``group`` is mostly sorted runs)."""
    if group.size == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(group, kind="stable")
    ranked = group[order]
    starts = np.flatnonzero(np.r_[True, ranked[1:] != ranked[:-1]])
    least = np.fmin.reduceat(value[order], starts)
    ends = np.r_[starts[1:], order.size]
    hit = value[order] == np.repeat(least, ends - starts)
    # the first hit of each group; a group of NaN only takes its first entry
    first = np.minimum.reduceat(np.where(hit, np.arange(order.size), order.size), starts)
    return order[np.where(first < ends, first, starts)]


def arc_midpoints(mesh: Mesh, edges: np.ndarray, index: np.ndarray, boundary_faces: np.ndarray) -> np.ndarray:
    """Mid-edge node positions with boundary edges bent onto the boundary's curve, on any mesh.

    For meshes whose edges leave the lattice lines (plane merging's chamfers, graded
    templates, a pillow layer) and whose edge lengths vary. A boundary edge a-b continues
    beyond a along the boundary edge a-a' most nearly opposite to it (turning by at most
    ``_ARC_TURN``, 45 degrees, a' on every bounding plane a and b share); beyond a bounding
    plane that a lies on and b does not, along b's mirror image in it. The mid-edge node goes to the middle of
    the arc of the circle through a', a and b, and of the one through a, b and b', averaged
    where both exist; a boundary edge with no continuation, and every other edge, keeps its
    midpoint. Nodes in a line keep the midpoint, so flat faces and cut planes stay flat; on a
    circle the nodes lie on, the mid-edge nodes do too.

    Parameters
    ----------
    mesh : Mesh
    edges, index : ndarray
        From :func:`edges_by_lattice`.
    boundary_faces : (M, F) bool ndarray
        The element faces on a boundary.

    Returns
    -------
    (E, 3) float64 ndarray
        mm.
    """
    x = mesh.points
    mid = 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])
    cand = np.flatnonzero(_boundary_edges(mesh, edges, index, boundary_faces))
    if cand.size == 0:
        return mid
    # directed boundary edges src -> dst; for each, the continuation beyond src
    src = np.concatenate([edges[cand, 0], edges[cand, 1]])
    dst = np.concatenate([edges[cand, 1], edges[cand, 0]])
    bits = plane_bits(mesh)
    xs, xd = x[src], x[dst]
    # mirror images across the planes src lies on and dst does not (the mirrored model's edges)
    mirrors = []
    for axis in range(mesh.dim):
        for high in (0, 3):
            bit = np.uint8(1 << (axis + high))
            on = np.flatnonzero((bits[src] & bit).astype(bool) & ~(bits[dst] & bit).astype(bool))
            image = xd[on].copy()
            image[:, axis] = 2.0 * xs[on, axis] - image[:, axis]
            mirrors.append((on, image))
    chord = xd - xs
    length = norm(chord, axis=1)  # once per directed edge, not per continuation
    offset = np.zeros((src.size, 3))
    found = np.zeros(src.size, bool)
    # a piece of directed edges at a time: each edge's candidates, the other boundary edges from
    # its source and its mirror images, in the same order whatever the pieces
    for start, stop, i, j in _grouped_pairs(src):
        shared = bits[src[i]] & bits[dst[i]]
        ok = (shared & ~bits[dst[j]]) == 0
        i, j = i[ok], j[ok]
        beyond = [xd[j]]
        owner = [i]
        for on, image in mirrors:
            lo, hi = np.searchsorted(on, [start, stop])
            beyond.append(image[lo:hi])
            owner.append(on[lo:hi])
        beyond, owner = np.concatenate(beyond), np.concatenate(owner)
        u = beyond - xs[owner]
        cosine = np.sum(u * chord[owner], axis=1) / np.maximum(norm(u, axis=1) * length[owner], 1e-300)
        best = _first_smallest(owner, cosine)  # per directed edge, the most nearly opposite
        best = best[cosine[best] <= -np.cos(np.radians(_ARC_TURN))]
        offset[owner[best]] = _sagitta(xs[owner[best]], xd[owner[best]], beyond[best])
        found[owner[best]] = True
    both = offset[: cand.size] + offset[cand.size:]
    count = found[: cand.size].astype(np.int64) + found[cand.size:]
    mid[cand] += both / np.maximum(count, 1)[:, None]
    return mid


# natural coordinates of the nodes of the 20-node hexahedron and 8-node quad, VTK (= Abaqus) order
_HEX_CORNERS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float)
_HEX_NODES = np.concatenate([_HEX_CORNERS, 0.5 * (_HEX_CORNERS[HEX_EDGES[:, 0]] + _HEX_CORNERS[HEX_EDGES[:, 1]])])
_QUAD_NODES = np.concatenate([_HEX_CORNERS[:4, :2],
                              0.5 * (_HEX_CORNERS[QUAD_EDGES[:, 0], :2] + _HEX_CORNERS[QUAD_EDGES[:, 1], :2])])


def _serendipity_gradients(nodes: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(P, K, d) derivatives of the serendipity shape functions of the K ``nodes`` (natural
    coordinates, (K, d): corners at +-1, mid-edge nodes with one 0) at the points ``at`` (P, d).

    Each function is a product of one factor per axis, 1 + x c (1 - x^2 along a mid-edge
    node's own axis), over 2^d (2^(d-1) for mid-edge nodes), a corner's times
    (sum x c - d + 1)."""
    d = nodes.shape[1]
    x, c = at[:, None, :], nodes[None, :, :]
    along = nodes == 0  # (K, d): a mid-edge node's own axis
    corner = ~along.any(axis=1)
    factor = np.where(along, 1 - x * x, 1 + x * c)  # (P, K, d)
    slope = np.where(along, -2 * x, c)
    extra = np.where(corner, (x * c).sum(axis=2) - (d - 1), 1.0)  # (P, K)
    scale = np.where(corner, 2.0 ** -d, 2.0 ** (1 - d))
    out = np.empty(factor.shape)
    for a in range(d):
        others = np.prod(np.delete(factor, a, axis=2), axis=2)
        out[..., a] = scale * others * (slope[..., a] * extra + np.where(corner, factor[..., a] * c[..., a], 0.0))
    return out


def _check_points(dim: int) -> np.ndarray:
    """The points where a quadratic element's Jacobian must stay positive: the 3^d Gauss
    points of full integration, the 2^d of reduced integration, the nodes (corners, mid-edge
    and face centres: a curve folds an element at its faces first) and the 3^(d-1) Gauss
    points of each face, where a pressure load is integrated."""
    g3, g2 = np.sqrt(0.6), 1 / np.sqrt(3.0)
    gauss = np.array([-g3, 0.0, g3])

    def grid(values: np.ndarray, d: int) -> np.ndarray:
        return np.stack(np.meshgrid(*[values] * d, indexing="ij"), axis=-1).reshape(-1, d)

    face = grid(gauss, dim - 1)
    sides = [np.insert(face, a, side, axis=1) for a in range(dim) for side in (-1.0, 1.0)]
    # once each: the face centres are nodes too
    return np.unique(np.concatenate([grid(gauss, dim), grid(np.array([-g2, g2]), dim),
                                     grid(np.array([-1.0, 0.0, 1.0]), dim), *sides]), axis=0)


_BLOCK = 1024  # elements checked at a time: their Jacobians (some 8 MB) stay in the cache

_CURVED_FLOOR = 0.1
"""Smallest Jacobian determinant over a curved element's check points, relative to its
largest, that keeps its curved mid-edge nodes (the quality guard's kind of margin: a
solver needs det J > 0 at every integration point)."""


def _block_dets(points: np.ndarray, block: np.ndarray, rows: np.ndarray, dim: int, screen: bool) -> np.ndarray:
    """(P, B) Jacobian determinants of the quadratic elements ``block`` (B, K) at the P points
    whose shape-function gradients ``rows`` (P d_a, K) hold.

    ``screen``: by a BLAS matrix product of the nodes' offsets from the element's first node,
    about three times faster; BLAS picks its kernels by the CPU, so these last bits vary from
    CPU to CPU. Else by numpy's einsum, node by node in the same order on every CPU."""
    k, b = block.shape[1], block.shape[0]
    p = rows.shape[0] // dim
    if screen:
        # (K, d_c, B): each coordinate gathered whole, less the first node's (the element's
        # size, not its distance from the origin, sets the error), then one matrix product
        x = np.empty((k, dim, b))
        for c in range(dim):
            x[:, c] = points[block.T, c]
        x -= x[:1].copy()
        jac = (rows @ x.reshape(k, dim * b)).reshape(p, dim, dim, b)  # dx_c / dxi_a at (P, a, c, B)
    else:
        x = points[block, :dim]  # (B, K, d_c)
        jac = np.einsum("qk,kn->qn", rows, np.ascontiguousarray(x.transpose(1, 0, 2)).reshape(k, b * dim),
                        optimize=False).reshape(p, dim, b, dim).transpose(0, 1, 3, 2)
    if dim == 3:
        a, bb, c = jac[:, 0], jac[:, 1], jac[:, 2]  # (P, c, B)
        return (a[:, 0] * (bb[:, 1] * c[:, 2] - bb[:, 2] * c[:, 1])
                - a[:, 1] * (bb[:, 0] * c[:, 2] - bb[:, 2] * c[:, 0])
                + a[:, 2] * (bb[:, 0] * c[:, 1] - bb[:, 1] * c[:, 0]))
    return jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]


def _gradient_rows(grads: np.ndarray, dim: int) -> np.ndarray:
    """(P d_a, K): the shape functions' gradients ``grads`` (P, K, d) as matrix rows."""
    return np.ascontiguousarray(grads.transpose(0, 2, 1).reshape(grads.shape[0] * dim, grads.shape[1]))


def _det_ratio(points: np.ndarray, cells: np.ndarray, grads: np.ndarray, dim: int, screen: bool = False) -> np.ndarray:
    """(M,) float: the smallest Jacobian determinant of each quadratic element (``cells``
    (M, K), node positions ``points`` mm) over the check points, relative to its largest;
    -inf where the largest is not positive.

    ``screen``: the Jacobians by BLAS (:func:`_block_dets`), whose last bits vary from CPU to
    CPU: only :func:`_failing`'s screen reads them; the exact sums decide which mid-edge nodes
    a deck gets."""
    rows = _gradient_rows(grads, dim)
    out = np.empty(cells.shape[0])
    for start in range(0, cells.shape[0], _BLOCK):
        det = _block_dets(points, cells[start:start + _BLOCK], rows, dim, screen)
        big = det.max(axis=0)  # det: (P, B)
        out[start:start + _BLOCK] = np.where(big > 0, det.min(axis=0) / np.where(big > 0, big, 1.0), -np.inf)
    return out


def folded_elements(points: np.ndarray, cells: np.ndarray, dim: int) -> np.ndarray:
    """Quadratic elements whose Jacobian determinant is not positive at one of the check
    points (the Gauss points of full and reduced integration, the nodes, the faces' Gauss
    points).

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Node positions, mm.
    cells : (M, 20) or (M, 8) int ndarray
        Quadratic hexahedra or quads, VTK order.
    dim : {2, 3}

    Returns
    -------
    (M,) bool ndarray
    """
    grads = _serendipity_gradients(_HEX_NODES if dim == 3 else _QUAD_NODES, _check_points(dim))
    return ~(_det_ratio(points, cells, grads, dim) > 0)


def _gauss_volumes(points: np.ndarray, cells: np.ndarray, dim: int) -> np.ndarray:
    """(M,) volumes (2D: areas) of quadratic elements (``cells`` (M, K), node positions
    ``points`` mm) by 3^d-point Gauss quadrature of their Jacobian determinant.

    By BLAS, as the fold check's screen (:func:`_block_dets`): the volumes feed a warning, not
    the deck."""
    g, w = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)]), np.array([5.0, 8.0, 5.0]) / 9.0
    at = np.stack(np.meshgrid(*[g] * dim, indexing="ij"), axis=-1).reshape(-1, dim)
    weight = np.prod(np.stack(np.meshgrid(*[w] * dim, indexing="ij"), axis=-1).reshape(-1, dim), axis=1)
    rows = _gradient_rows(_serendipity_gradients(_HEX_NODES if dim == 3 else _QUAD_NODES, at), dim)
    out = np.empty(cells.shape[0])
    for start in range(0, cells.shape[0], _BLOCK):
        out[start:start + _BLOCK] = weight @ _block_dets(points, cells[start:start + _BLOCK], rows, dim, True)
    return out


def curving_volume_change(mesh: Mesh, points: np.ndarray, cells: np.ndarray, curved: np.ndarray
                          ) -> dict[int, float]:
    """What curved mid-edge nodes add to each material's volume: {material: change relative to
    the linear mesh's volume of it (which quality reports)}, for the materials whose elements
    hold a curved one.

    Parameters
    ----------
    mesh : Mesh
        The linear mesh.
    points, cells, curved : ndarray
        Its quadratic mesh and the elements holding a curved mid-edge node
        (:func:`curved_quadratic_mesh`).

    Returns
    -------
    dict
        {material number: (volume with the curved nodes - linear volume) / linear volume}.
    """
    if curved.size == 0:
        return {}
    linear = np.asarray(mesh.cells)
    volume = element_volumes(mesh.points, linear)
    added = _gauss_volumes(points, cells[curved], mesh.dim) - volume[curved]
    material = np.asarray(mesh.material, np.int64)
    own = np.bincount(material, weights=volume)
    gained = np.bincount(material[curved], weights=added, minlength=own.size)
    return {int(m): float(gained[m] / own[m]) for m in np.unique(material[curved]) if own[m] > 0}


_SCREEN_MARGIN = 1e-6
"""How far above ``_CURVED_FLOOR`` the screen's ratio must lie for an element to pass without
the exact sums: the two differ by some 1e-12 (at most 3.5e-12 over the head CT's 596,038 curved
elements; twenty products of element-sized numbers, the exact sums' coordinates some hundred
element sizes from the origin), so the decisions are the exact sums' on every CPU."""


def _failing(points: np.ndarray, cells: np.ndarray, grads: np.ndarray, dim: int,
             straight: np.ndarray | None = None) -> np.ndarray:
    """(M,) bool: quadratic elements whose Jacobian determinant at the check points falls
    below ``_CURVED_FLOOR`` of their largest (:func:`_det_ratio`) and, given ``straight`` (the
    node positions with every mid-edge node at its midpoint), below the same element's ratio
    with straight edges too: an element the linear mesh already has under the floor (plane
    merging's chamfers next to short edges) may keep curved nodes that do not make it worse.
    The elements the screen clears by ``_SCREEN_MARGIN`` pass; the others are decided by the
    exact sums."""
    ratio = _det_ratio(points, cells, grads, dim, screen=True)
    near = np.flatnonzero(~(ratio >= _CURVED_FLOOR + _SCREEN_MARGIN))
    ratio[near] = _det_ratio(points, cells[near], grads, dim)
    fails = ~(ratio >= _CURVED_FLOOR)
    if straight is not None and fails.any():
        under = np.flatnonzero(fails)
        fails[under] = ~(ratio[under] >= _det_ratio(straight, cells[under], grads, dim))
    return fails


def _straighten_folds(mesh: Mesh, edges: np.ndarray, index: np.ndarray, mid: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``mid`` with the curved mid-edge nodes of elements that the curve folds put back at
    their edge's midpoint, until no element with a curved node fails (:func:`_failing`: under
    the floor and worse than with straight edges), and (E,) bool: the mid-edge nodes left
    curved. An element whose mid-edge nodes are all midpoints is the linear mesh's, which the
    smoothing's guard checked. After the first pass only the elements around the nodes put back
    are checked again (the others did not change)."""
    x = mesh.points
    straight = 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])
    curved = np.any(mid != straight, axis=1)
    dim = mesh.dim
    grads = _serendipity_gradients(_HEX_NODES if dim == 3 else _QUAD_NODES, _check_points(dim))
    n = mesh.n_points
    linear = np.concatenate([x, straight])  # every mid-edge node at its midpoint
    changed = curved  # the mid-edge nodes whose elements are (re)checked
    reset = 0
    while True:
        holding = np.flatnonzero(changed[index].any(axis=1) & curved[index].any(axis=1))
        if holding.size == 0:
            break
        cells = np.concatenate([mesh.cells[holding], index[holding] + n], axis=1)
        bad = holding[_failing(np.concatenate([x, mid]), cells, grads, dim, linear)]
        if bad.size == 0:
            break
        back = np.unique(index[bad])
        back = back[curved[back]]
        mid[back] = straight[back]
        curved[back] = False
        changed = np.zeros(edges.shape[0], bool)
        changed[back] = True
        reset += back.size
    if reset:
        logging.getLogger("dicer").info("export: %d curved mid-edge node(s) put back at their edge's midpoint (the "
                                        "curve would fold their elements)", reset)
    return mid, curved


def quadratic_mesh(mesh: Mesh, boundary_faces: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, 20-node (8-node) cells and doubled lattice indices of the quadratic mesh.

    Parameters
    ----------
    mesh : Mesh
    boundary_faces : (M, F) bool ndarray, optional
        As for :func:`curved_quadratic_mesh`.

    Returns
    -------
    points, cells, lattice2 : ndarray
        As :func:`curved_quadratic_mesh` gives them (without the elements it curved).
    """
    return curved_quadratic_mesh(mesh, boundary_faces)[:3]


def curved_quadratic_mesh(mesh: Mesh, boundary_faces: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points, 20-node (8-node) cells and doubled lattice indices of the quadratic mesh, and
    the elements holding a curved mid-edge node.

    Parameters
    ----------
    mesh : Mesh
    boundary_faces : (M, F) bool ndarray, optional
        The element faces (2D: edges) on a boundary (exterior or material interface), in
        Abaqus face order; their edges get :func:`curved_midpoints` placement (every edge
        along a lattice line) or :func:`arc_midpoints` (any other mesh). None: every
        mid-edge node at its edge's midpoint.

    Returns
    -------
    points : (N + E, 3) float64 ndarray
        The corner nodes, then one mid-edge node per edge.
    cells : (M, 20) or (M, 8) int64 ndarray
        VTK/Abaqus node order.
    lattice2 : (N + E, 3) int64 ndarray
        Twice the lattice index (a mid-edge node: the sum of its ends' indices), so
        bounding-plane tests stay exact.
    curved : (C,) int64 ndarray
        The elements holding a mid-edge node off its edge's midpoint, ascending.
    """
    cells = np.asarray(mesh.cells, dtype=np.int64)
    n = mesh.n_points
    edges, index, along_lines = edges_by_lattice(mesh, cells)
    if boundary_faces is not None:  # along lattice lines where every edge runs on one, else by arcs
        place = curved_midpoints if along_lines else arc_midpoints
        mid_points, bent = _straighten_folds(mesh, edges, index, place(mesh, edges, index, boundary_faces))
        curved = np.flatnonzero(bent[index].any(axis=1))
        del bent
    else:
        mid_points = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
        curved = np.zeros(0, np.int64)
    # the results built in place, a column at a time: no (E, 3) or (M, 12) temporaries beside them
    points = np.concatenate([mesh.points, mid_points])
    del mid_points
    lattice = mesh.lattice
    lattice2 = np.empty((n + edges.shape[0], lattice.shape[1]), np.int64)
    np.multiply(lattice, 2, out=lattice2[:n])
    for c in range(lattice.shape[1]):
        np.add(lattice[edges[:, 0], c], lattice[edges[:, 1], c], out=lattice2[n:, c])
    del edges
    quadratic = np.empty((cells.shape[0], cells.shape[1] + index.shape[1]), np.int64)
    quadratic[:, :cells.shape[1]] = cells
    np.add(index, n, out=quadratic[:, cells.shape[1]:])
    return points, quadratic, lattice2, curved
