"""Plane merging (DICER Box 2): merge pairs of element layers where that is topologically safe.

A merge along axis ``a`` joins an element layer to the layer above it by deleting the
nodes of the plane between them that *top* one axis-parallel edge and *bottom* another.
Every element that held such a node takes the far end of that edge instead: the lower
element is stretched up, the upper one down. Two stacked elements whose shared face
loses all its nodes become identical and are kept once (one element two layers tall);
an element with no partner that loses only some of its face nodes becomes a *chamfer*
(a step of the surface turned into a slope). ``docs/merging.md`` gives the exact rules.

Beyond the paper (which handles one material): a stacked pair of two different
materials never merges. Conformity then forbids deleting any node of its shared face,
and because a stacked pair merges only whole, the refusal spreads to every stacked
pair connected to it through shared nodes. The unit of every decision is therefore a
*merge region*: a connected set of stacked pairs in one merge plane. A region merges or
keeps its plane; the paper's "drop the plane" is ``granularity="plane"``.

The trial mesh of every step is checked where it changed (Box 2 steps 12-14, widened):
no node with more than 6 (2D: 4) neighbours or in more than 8 (4) elements, no face of
three elements, no node that is the same corner of two elements, no two elements of one
material touching along an edge only, and no element whose corner scaled Jacobian on the
lattice falls below ``min_scaled_jacobian``; at the image's bounding planes they count the
mirror images, as smoothing mirrors there, so a model cut at its symmetry planes merges as
the whole one. A failing
element is first repaired through its *rim nodes* (plane nodes on one side only): each
moves one lattice step across the plane, or joins the node already at that corner, so
the element fills the empty voxel beside it. What still fails makes its merge region
keep the plane, and the step is tried again.

Arrays are numpy throughout; loops run only over axes, passes, retry rounds and the few
sizes of merged faces.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from dicer.arrays import all_per_row, any_per_row
from dicer.config import section_defaults, takes_settings
from dicer.errors import DicerError
from dicer.parallel import import_meanwhile, meanwhile, ordered_map
from dicer.mesh.boundary import mirror_share, mirror_weights
from dicer.mesh.metrics import corner_scaled_jacobians, element_volumes
from dicer.mesh.model import CHUNK, Mesh, nodes_off_lattice, pieces
from dicer.mesh.topology import (HEX_AXIS_CORNERS, HEX_CORNERS, HEX_EDGES, HEX_FACES, QUAD_AXIS_CORNERS,
                                 QUAD_CORNERS, QUAD_EDGES)

__all__ = ["merge_planes", "merge_mesh", "thick_elements", "DEFAULTS"]

_AXIS_NAMES = "xyz"
log = logging.getLogger("dicer")  # the command line's logger: progress of long merges


def _unique(a: np.ndarray) -> np.ndarray:
    """Sorted distinct values of a 1-D integer array (sorting beats numpy's hashed unique here)."""
    a = np.sort(np.asarray(a).ravel())
    return a[np.r_[True, a[1:] != a[:-1]]] if a.size else a


def _union(*arrays) -> np.ndarray:
    return _unique(np.concatenate([np.asarray(x).ravel() for x in arrays]))


def _rows_per_piece(index: np.ndarray) -> int:
    return max(1, CHUNK // max(1, int(np.prod(index.shape[1:], dtype=np.int64))))


def _each_piece(fn, n: int, step: int | None = None) -> None:
    """``fn(part)`` for every piece of ``range(n)`` (``step`` rows, default ``CHUNK``), on two
    threads when there are several (``fn`` writes only its own rows; numpy leaves the
    interpreter lock in each)."""
    step = CHUNK if step is None else step
    if n <= step:
        if n:
            fn(slice(0, n))
        return
    for _ in ordered_map(fn, pieces(n, step)):
        pass


def _take(table: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``table[index]`` for a 1-D ``table`` and an integer ``index`` of any shape, in pieces of rows.

    numpy first copies a non-intp index (the int32 node ids here) to intp in full: for the
    cells of a large mesh that is twice their size in fresh memory per gather. Pieces keep
    that copy small.
    """
    if index.dtype == np.intp or index.size <= CHUNK:
        return table[index]
    out = np.empty(index.shape, dtype=table.dtype)

    def gather(part: slice) -> None:
        np.take(table, index[part], out=out[part])  # np.take: about twice as fast as fancy indexing
    _each_piece(gather, index.shape[0], _rows_per_piece(index))
    return out


def _put(table: np.ndarray, index: np.ndarray, values) -> None:
    """``table[index] = values`` (a scalar or an array shaped like ``index``) in pieces of rows,
    in the same order (later entries win), without a full intp copy of ``index``."""
    if index.dtype == np.intp or index.size <= CHUNK:
        table[index] = values
        return
    step = _rows_per_piece(index)
    scalar = np.ndim(values) == 0
    for part in pieces(index.shape[0], step):
        table[index[part]] = values if scalar else values[part]


def _copy_as(a: np.ndarray, dtype) -> np.ndarray:
    """A copy of ``a`` in ``dtype``, made in pieces on threads (fresh memory is the cost here)."""
    out = np.empty(a.shape, dtype=dtype)

    def copy(part: slice) -> None:
        out[part] = a[part]
    _each_piece(copy, a.shape[0], _rows_per_piece(a))
    return out


def _put_same(table: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
    """``table[index] = values`` (``values`` (R, 1) or shaped like ``index`` (R, k)) where every
    entry for one position writes the same value: in any order, so in pieces on threads."""
    def put(part: slice) -> None:
        table[index[part]] = values[part]
    _each_piece(put, index.shape[0], _rows_per_piece(index))


def _any_at(mask: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(R,) bool: rows of ``index`` (R, k) holding a node flagged in ``mask``, in pieces of rows."""
    if index.size <= CHUNK:
        return any_per_row(mask[index])
    out = np.empty(index.shape[0], dtype=bool)

    def flag(part: slice) -> None:
        out[part] = any_per_row(np.take(mask, index[part]))  # np.take: about twice as fast as fancy indexing
    _each_piece(flag, index.shape[0], _rows_per_piece(index))
    return out


def _check_passes(passes, dim: int) -> tuple[int, int, int]:
    """Merges per axis as three ints (the schema checked the values): z is 0 for a 2D mesh;
    a 3D mesh needs all three (two would leave z unmerged without a word)."""
    if dim == 3 and len(passes) < 3:
        raise DicerError(f"merge.passes={[int(p) for p in passes]}: {len(passes)} values for a 3D mesh; "
                         "give three, one per axis [x, y, z] (0 leaves an axis alone)")
    values = ([int(p) for p in passes] + [0])[:3]
    if dim == 2:
        values[2] = 0  # a quad mesh has no element layers along z
    return tuple(values)


def thick_elements(mesh: Mesh, min_thickness: float) -> np.ndarray:
    """The elements lying in a part of their material at least ``min_thickness`` voxels thick.

    A voxel is *thick* when a ball of diameter ``min_thickness`` (in voxels) that lies
    entirely inside its material covers it: the morphological opening of the material
    mask by that ball, computed from two Euclidean distance transforms. The material
    mask is rasterised from the elements' lattice boxes (exact for a voxel mesh). An
    element is thick when the voxel at its lowest lattice corner is.

    Parameters
    ----------
    mesh : Mesh
    min_thickness : float
        Voxels.

    Returns
    -------
    (M,) bool ndarray
    """
    m = mesh.n_cells
    if min_thickness <= 0:
        return np.ones(m, dtype=bool)
    dim = mesh.dim
    shape = tuple(int(v) for v in mesh.grid_shape[:dim])
    lo = mesh.lattice[mesh.cells[:, 0], :dim].copy()
    hi = lo.copy()
    for c in range(1, mesh.cells.shape[1]):
        corner = mesh.lattice[mesh.cells[:, c], :dim]
        np.minimum(lo, corner, out=lo)
        np.maximum(hi, corner, out=hi)
    if np.any(lo < 0) or np.any(hi > np.array(shape)):
        raise DicerError("mesh lattice indices lie outside grid_shape; the mesh's field data is inconsistent")
    labels = np.zeros(shape, dtype=np.int32)
    span = hi - lo
    # elements of one lattice-box size at a time (a voxel mesh has only unit boxes)
    sizes, which = np.unique(span, axis=0, return_inverse=True)
    which = which.ravel()
    for k, size in enumerate(sizes):
        rows = np.flatnonzero(which == k)
        for off in np.ndindex(*[max(int(v), 1) for v in size]):
            idx = tuple(lo[rows, d] + min(off[d], max(int(size[d]) - 1, 0)) for d in range(dim))
            labels[idx] = mesh.material[rows]
    from scipy import ndimage  # here: a merge without min_thickness or regions need not load it

    radius = 0.5 * float(min_thickness)
    thick_vox = np.zeros(shape, dtype=bool)
    # each material inside its bounding box (one pass finds them all): the distance
    # transforms cover the materials' extents, not the grid once per material
    for mat, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        mask = labels[box] == mat
        # the padding stands for the voxels around the box, none of this material
        inside = ndimage.distance_transform_edt(np.pad(mask, 1))[(slice(1, -1),) * dim]
        centres = inside >= radius  # centres of balls of the given radius inside the material
        if not centres.any():
            continue
        reach = ndimage.distance_transform_edt(~centres)
        thick_vox[box] |= mask & (reach < radius)
    return thick_vox[tuple(lo[:, d] for d in range(dim))]


def _match_faces(a: np.ndarray, b: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows i of ``a`` and j of ``b`` (both (K, c) node ids in corresponding order) with a[i] == b[j].

    Faces are looked up by their first node; the few first nodes shared by several rows
    of ``b`` are matched by sorting the full faces.
    """
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    b0 = b[:, 0]
    owner = np.full(n, -1, dtype=np.int32 if b.shape[0] < 2**31 - 1 else np.int64)
    rows_b = np.arange(b.shape[0], dtype=owner.dtype)
    _put(owner, b0, rows_b)
    # a first node held by several rows of b: its owner is the last of them, not the others
    shared = np.zeros(n, dtype=bool)

    def flag(part: slice) -> None:
        f = b0[part]
        shared[f[np.take(owner, f) != rows_b[part]]] = True  # both threads write True only
    _each_piece(flag, b.shape[0])
    del rows_b

    def find(part: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rows of ``a`` in ``part`` (a piece that stays in cache): its first node's owner, checked whole."""
        f = a[part, 0]
        j = np.take(owner, f)
        on_shared = np.take(shared, f)
        ok = j >= 0
        ok &= ~on_shared
        i = np.flatnonzero(ok)
        j = j[i].astype(np.intp)
        i += part.start
        same = all_per_row(np.take(a, i, axis=0) == np.take(b, j, axis=0))
        return i[same], j[same], np.flatnonzero(on_shared) + part.start
    found_i, found_j, hard = zip(*ordered_map(find, pieces(a.shape[0], CHUNK)))
    i, j = np.concatenate(found_i), np.concatenate(found_j)
    hard_a = np.concatenate(hard)
    if hard_a.size:
        hard_b = np.flatnonzero(_take(shared, b0))
        fa, fb = a[hard_a], b[hard_b]
        both = np.concatenate([fa, fb])
        src = np.r_[np.zeros(len(fa), np.int8), np.ones(len(fb), np.int8)]
        row = np.r_[hard_a, hard_b]
        order = np.lexsort((src,) + tuple(both[:, k] for k in range(both.shape[1] - 1, -1, -1)))
        both, src, row = both[order], src[order], row[order]
        hit = np.all(both[:-1] == both[1:], axis=1) & (src[:-1] == 0) & (src[1:] == 1)
        i = np.r_[i, row[:-1][hit]]
        j = np.r_[j, row[1:][hit]]
    return i, j


def _merge_regions(faces: np.ndarray, box: np.ndarray, cand_idx: np.ndarray, cmap: np.ndarray, lattice: np.ndarray,
                   axis: int, far: int, dim: int) -> tuple[int, np.ndarray]:
    """Connected components of the candidate nodes, linked through the stacked faces.

    faces : (K, c) node ids of each stacked face (c = 4 in 3D, 2 in 2D), its first corner
        the lowest and corner ``far`` the highest when the face is a lattice rectangle.
    box : (K,) bool, faces of two lattice boxes (so the face is a lattice rectangle).
    cand_idx, cmap : the candidate nodes, and the candidate number of every node (-1 for others).
    Returns the number of components and the component number of every candidate.

    Rectangles are joined by labelling the unit squares (2D: unit segments) they cover,
    touching diagonally included: in a conforming mesh two faces touch exactly when they
    share a node, and labelling a grid is far cheaper than a graph of every face. Other
    faces (of earlier chamfers) join their nodes, and the rectangles' components, through
    a small graph.
    """
    other = [d for d in range(dim) if d != axis]
    n_labels = 0
    rows = np.flatnonzero(box)
    on_box = np.full(lattice.shape[0], -1, dtype=np.int32)  # node -> its rectangles' component
    if rows.size:
        whole = rows.size == box.size
        # the lattice rows of the faces' first and far corners only (far fewer than the
        # nodes), gathered in pieces that stay in cache, kept as int32 columns
        plane = np.empty(rows.size, dtype=np.int32)
        start = [np.empty(rows.size, dtype=np.int32) for _ in other]
        size = [np.empty(rows.size, dtype=np.int32) for _ in other]

        def corners(part: slice) -> None:
            sel = faces[part] if whole else np.take(faces, rows[part], axis=0)
            low = np.take(lattice, sel[:, 0], axis=0)
            high = np.take(lattice, sel[:, far], axis=0)
            plane[part] = low[:, axis]
            for x, w, d in zip(start, size, other):
                x[part] = low[:, d]
                np.subtract(high[:, d], low[:, d], out=w[part], casting="unsafe")
        _each_piece(corners, rows.size)
        for x in start:
            x -= int(x.min())
        plane -= int(plane.min())
        used = np.bincount(plane) > 0
        pid = (np.cumsum(used, dtype=np.int32) - 1)[plane]
        shape = (int(used.sum()), *[int((x + w).max()) for x, w in zip(start, size)])
        grid = np.zeros(shape, dtype=bool)
        # each face's lowest unit square as one flat index into the grid
        cell = pid.astype(np.intp)
        for d, x in enumerate(start, start=1):
            cell *= shape[d]
            cell += x
        del pid, plane
        flat = grid.reshape(-1)
        if all(int(w.min()) == int(w.max()) for w in size):  # one size (unit squares in a voxel mesh)
            packed, kinds = None, [None]
        else:
            packed = size[0].astype(np.int64) if dim == 2 else size[0] * np.int64(int(size[1].max()) + 1) + size[1]
            kinds = np.flatnonzero(np.bincount(packed))
        for kind in kinds:  # faces of one size at a time
            pick = None if packed is None else packed == kind
            sel = slice(None) if len(kinds) == 1 else np.flatnonzero(pick)
            one = 0 if pick is None else int(np.argmax(pick))
            for off in np.ndindex(*[int(w[one]) for w in size]):
                shift = int(np.ravel_multi_index((0, *off), shape)) if off else 0
                flat[cell[sel] + shift if shift else cell[sel]] = True
        structure = np.zeros((3,) * dim, dtype=bool)
        structure[1] = True  # neighbours within a plane only, diagonals included
        from scipy import ndimage

        labels, n_labels = ndimage.label(grid, structure)
        found = np.take(labels.reshape(-1), cell)
        found -= 1
        # every node of a rectangle gets its component: the same from each rectangle at the node
        _put_same(on_box, faces if whole else faces[rows], found[:, None])
    vid = on_box[cand_idx].astype(np.int64)
    rest = np.flatnonzero(vid < 0)
    vid[rest] = n_labels + np.arange(rest.size)
    f = vid[cmap[faces[~box]]]
    k = f.shape[1] - 1
    n_vertices = n_labels + rest.size
    if f.shape[0] == 0:  # no edges: every vertex is its own component, numbered in order
        return int(n_vertices), vid.astype(np.int32)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(f.shape[0] * k, dtype=np.int8), (np.repeat(f[:, 0], k), f[:, 1:].ravel())),
                       shape=(n_vertices, n_vertices))
    n_comp, comp = connected_components(graph, directed=True, connection="weak")
    return int(n_comp), comp[vid]


def _face_edge_positions(dim: int, axis: int) -> np.ndarray:
    """Pairs of positions in the (bottom or top) corner list of ``axis`` that form the face's edges."""
    corners = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)
    pos = (HEX_AXIS_CORNERS if dim == 3 else QUAD_AXIS_CORNERS)[axis][0]
    off = corners[pos]
    return np.array([(i, j) for i in range(len(pos)) for j in range(i + 1, len(pos))
                     if np.abs(off[i] - off[j]).sum() == 1])


def _clashes(plane: _Plane, irregular: np.ndarray, lattice: np.ndarray, dim: int) -> np.ndarray:
    """Candidate nodes where a lower and an upper element that are not a stacked pair, one
    of them irregular, meet on the same side of their shared edge (2D: node): deleting
    the edge would stretch both over the same ground.

    Parameters
    ----------
    plane : _Plane
        The step's merge nodes and stacked pairs.
    irregular : (M,) bool ndarray
        Elements that are not lattice boxes.
    lattice : (N, 3) int64 ndarray
        Lattice index of every node.
    dim : int
        2 or 3.

    Returns
    -------
    (K,) int64 ndarray
        The nodes, ascending.
    """
    l_top, u_bot = plane.l_top, plane.u_bot
    irr_l, irr_u = irregular[plane.lo], irregular[plane.up]
    near = np.zeros(plane.n, dtype=bool)
    near[l_top[irr_l]] = True
    near[u_bot[irr_u]] = True
    near &= plane.cand
    if not near.any():
        return np.empty(0, dtype=np.int64)
    other = [d for d in range(dim) if d != plane.axis]
    pairs = _face_edge_positions(dim, plane.axis) if dim == 3 else np.array([[0, 0], [1, 1]])
    lk, lrow, le = _plane_edges(l_top, near, pairs)
    uk, urow, _ = _plane_edges(u_bot, near, pairs)
    order = np.argsort(uk, kind="stable")
    uk, urow = uk[order], urow[order]
    first = np.searchsorted(uk, lk, side="left")
    last = np.searchsorted(uk, lk, side="right")
    partner = np.full(l_top.shape[0], -1, dtype=np.int64)
    partner[plane.li] = plane.ui
    found = []
    for extra in range(2):  # an edge of the plane borders at most two upper faces
        j = first + extra
        ok = np.flatnonzero(j < last)
        lr, ur = lrow[ok], urow[j[ok]]
        maybe = (partner[lr] != ur) & (irr_l[lr] | irr_u[ur])
        ok, lr, ur = ok[maybe], lr[maybe], ur[maybe]
        same = _side_of_edges(lattice, l_top[lr], le[ok], other) * _side_of_edges(lattice, u_bot[ur], le[ok], other) > 0
        found.append(le[ok][same].ravel())
    return _unique(np.concatenate(found))


def _plane_edges(face: np.ndarray, near: np.ndarray, pairs: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The edges (2D: nodes) of the faces ``face`` (K, c/2) whose two ends are ``near`` ((N,) bool).

    ``pairs`` (E, 2) are the positions in a face of its edges' ends. Returns, per edge
    found, its key (lower end * N + upper end, int64), the row of ``face`` it belongs to
    (int64) and its ends ((., 2) int64, ascending).
    """
    n64 = np.int64(near.shape[0])
    rows = np.flatnonzero(_any_at(near, face))
    e = face[rows][:, pairs]  # (K, E, 2)
    ok = all_per_row(near[e].reshape(-1, 2)).reshape(e.shape[:2])
    row = np.broadcast_to(rows[:, None], ok.shape)[ok]
    e = np.sort(e[ok], axis=1).astype(np.int64)
    return e[:, 0] * n64 + e[:, 1], row, e


def _side_of_edges(lattice: np.ndarray, face: np.ndarray, e: np.ndarray, other: list[int]) -> np.ndarray:
    """(E,) float64 whose sign tells on which side of each edge ``e`` (E, 2) (2D: node) the
    centre of its face ``face`` (E, c/2) lies, within the plane's axes ``other``."""
    centre = lattice[face][:, :, other].mean(axis=1)
    p = lattice[e[:, 0]][:, other].astype(np.float64)
    if len(other) == 1:
        return centre[:, 0] - p[:, 0]
    d = lattice[e[:, 1]][:, other] - p
    return d[:, 0] * (centre[:, 1] - p[:, 1]) - d[:, 1] * (centre[:, 0] - p[:, 0])


def _crowded_faces(sub: np.ndarray, n: int, dim: int) -> np.ndarray:
    """Rows of ``sub`` with a face (2D: edge) that three or more rows share."""
    faces = sub[:, HEX_FACES] if dim == 3 else sub[:, QUAD_EDGES]
    k = faces.shape[1]
    f = np.sort(faces.reshape(-1, faces.shape[2]), axis=1).astype(np.int64)
    n64 = np.int64(n)
    key1 = f[:, 0] * n64 + f[:, 1]
    key2 = f[:, 2] * n64 + f[:, 3] if dim == 3 else np.zeros_like(key1)
    order = np.lexsort((key2, key1))
    k1, k2 = key1[order], key2[order]
    start = np.r_[True, (k1[1:] != k1[:-1]) | (k2[1:] != k2[:-1])]
    group = np.cumsum(start) - 1
    size = np.bincount(group)
    crowded = order[size[group] > 2] // k
    return _unique(crowded)


def _shared_corners(local: np.ndarray, k: int, changed: np.ndarray) -> np.ndarray:
    """Rows of ``local`` (R, c; node numbers 0 .. k-1) holding a node at the same corner as
    another row, where one of the two is a ``changed`` row ((R,) bool): a clash already in
    the input is not the step's to refuse."""
    c = local.shape[1]
    key = local.astype(np.int64) * c + np.arange(c)
    count = np.bincount(key.ravel(), minlength=k * c)
    mine = key[changed].ravel()
    clash = np.zeros(k * c, dtype=bool)
    clash[mine[count[mine] > 1]] = True
    return np.flatnonzero(any_per_row(clash[key]))


@dataclass(frozen=True)
class _Faces:
    """The faces of a trial's elements (R, c), sorted so that a face's twins lie next to it:
    ``facets`` (R, F, k) corners, ``order`` (RF,) the sort, ``same_face`` (RF - 1,) where
    neighbours in it are one face, ``same_material`` where they are also of one material."""

    facets: np.ndarray
    order: np.ndarray
    same_face: np.ndarray
    same_material: np.ndarray


def _sorted_faces(sub: np.ndarray, material: np.ndarray, n: int, dim: int) -> _Faces:
    """:class:`_Faces` of the elements ``sub`` (R, c) of ``material`` (R,), nodes < ``n``."""
    facets = sub[:, HEX_FACES] if dim == 3 else sub[:, QUAD_EDGES]  # (R, F, k)
    f = np.sort(facets.reshape(-1, facets.shape[2]), axis=1).astype(np.int64)
    n64 = np.int64(n)
    mat = np.repeat(material.astype(np.int64), facets.shape[1])
    key1 = f[:, 0] * n64 + f[:, 1]
    key2 = f[:, 2] * n64 + f[:, 3] if dim == 3 else np.zeros_like(key1)
    order = np.lexsort((mat, key2, key1))
    same_face = (key1[order][1:] == key1[order][:-1]) & (key2[order][1:] == key2[order][:-1])
    return _Faces(facets, order, same_face, same_face & (mat[order][1:] == mat[order][:-1]))


def _pinches(sub: np.ndarray, material: np.ndarray, inside: np.ndarray, changed: np.ndarray, dim: int,
             faces: _Faces, local: np.ndarray | None = None, bits: np.ndarray | None = None) -> np.ndarray:
    """Rows of ``sub`` (R, c) where two elements of one material touch along an edge only
    (2D: at a node only), at an edge (node) of a ``changed`` row ((R,) bool).

    Such a contact leaves the material's surface open (four of its faces at one edge), as
    ``dicer fix`` removes it from the labels. Counted at the edges with both ends
    ``inside`` ((N,) bool): every element at them is in ``sub``, so the count is exact.
    ``material`` (R,) gives each row's material, ``faces`` their sorted faces
    (:func:`_sorted_faces`). With ``bits`` ((k,) uint8 ``_plane_bits`` of the nodes ``local``
    (R, c) numbers) counted in the model mirrored at the bounding planes: a face on a plane
    meets its mirror image (not surface), an edge on planes has 2^planes images of every other
    face at it.
    """
    facets, order, same = faces.facets, faces.order, faces.same_material
    per = facets.shape[1]
    n64 = np.int64(inside.shape[0])
    inner = np.zeros(order.shape[0], dtype=bool)  # a face between two elements of one material
    inner[order[1:][same]] = True
    inner[order[:-1][same]] = True
    outer = np.flatnonzero(~inner)
    if dim == 3:  # the outer faces' edges, both ends inside
        ring = facets.reshape(-1, 4)[outer]
        a, b = ring.ravel(), ring[:, [1, 2, 3, 0]].ravel()
        lo_end, hi_end = np.minimum(a, b).astype(np.int64), np.maximum(a, b).astype(np.int64)
        ok = (lo_end != hi_end) & inside[lo_end] & inside[hi_end]
        ridge = lo_end * n64 + hi_end
        owner = np.repeat(outer, 4)
    else:  # the outer edges' nodes
        ridge = facets.reshape(-1, 2)[outer].ravel().astype(np.int64)
        ok = inside[ridge]
        owner = np.repeat(outer, 2)
    weight = None
    if bits is not None:
        lf = (local[:, HEX_FACES] if dim == 3 else local[:, QUAD_EDGES]).reshape(-1, facets.shape[2])[outer]
        flat = np.bitwise_and.reduce(bits[lf], axis=1) != 0  # the face lies on a bounding plane
        on = bits[lf] & bits[lf[:, [1, 2, 3, 0]]] if dim == 3 else bits[lf]  # the planes each ridge lies on
        weight = np.where(np.repeat(flat, lf.shape[1]), 0.0, mirror_weights(on.ravel(), np.uint8(0)))[ok]
    ridge, owner = ridge[ok], owner[ok] // per
    if ridge.size == 0:
        return np.empty(0, dtype=np.int64)
    rmat = material[owner].astype(np.int64)
    order = np.lexsort((rmat, ridge))
    ridge, owner, rmat = ridge[order], owner[order], rmat[order]
    start = np.r_[True, (ridge[1:] != ridge[:-1]) | (rmat[1:] != rmat[:-1])]
    group = np.cumsum(start) - 1
    size = np.bincount(group) if weight is None else np.bincount(group, weights=weight[order])
    touched = np.bincount(group, weights=changed[owner]) > 0
    pinched = (size[group] > 2) & touched[group]
    return _unique(owner[pinched])


def _node_pinches(sub: np.ndarray, material: np.ndarray, inside: np.ndarray, changed: np.ndarray,
                  faces: _Faces, local: np.ndarray, bits: np.ndarray | None = None) -> np.ndarray:
    """Rows of the hexahedra ``sub`` (R, 8) at a node where a material's surface, or the
    exterior, is pinched: its faces around the node form two fans or more that meet at the node
    only. Counted at the nodes ``inside`` ((N,) bool: all their elements in ``sub``) that a
    ``changed`` row ((R,) bool) holds; ``material`` (R,), ``faces`` (:func:`_sorted_faces`). With
    ``bits`` ((k,) uint8 plane bits of the nodes ``local`` (R, 8) numbers) a face in a bounding
    plane is no surface (it meets its mirror image); the fans' count is then the mirrored
    model's."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    facets = faces.facets.reshape(-1, 4).astype(np.int64)  # (6R, 4)
    order, same_face, same_mat = faces.order, faces.same_face, faces.same_material
    top = np.int64(int(material.max(initial=0)) + 2)  # the exterior's group: top - 1
    mat = np.repeat(material.astype(np.int64), 6)
    flat = np.zeros(facets.shape[0], dtype=bool)
    if bits is not None:  # a face in a bounding plane meets its mirror image
        lf = local[:, HEX_FACES].reshape(-1, 4)
        flat = np.bitwise_and.reduce(bits[lf], axis=1) != 0
    # only the nodes a changed element holds, inside: the others are not this step's
    near = np.zeros(inside.shape[0], dtype=bool)
    near[sub[changed].ravel()] = True
    near &= inside
    at_near = near[facets].any(axis=1)
    faces_of, groups = [], []
    for link, group in ((same_mat, mat), (same_face, np.full(mat.shape, top - 1))):  # each material, the exterior
        inner = flat.copy()
        inner[order[1:][link]] = True
        inner[order[:-1][link]] = True
        outer = np.flatnonzero(~inner & at_near)
        faces_of.append(outer)
        groups.append(group[outer])
    outer, group = np.concatenate(faces_of), np.concatenate(groups)
    node = facets[outer].ravel()  # one incidence per face corner, with its two edges at the corner
    keep = np.flatnonzero(near[node])
    face_of = keep // 4
    node, g4 = node[keep], group[face_of]
    if node.size == 0:
        return np.empty(0, dtype=np.int64)
    f = facets[outer]
    corner = keep % 4
    ends = np.concatenate([f[face_of, (corner + 3) % 4], f[face_of, (corner + 1) % 4]])
    incidence = np.arange(node.size)
    at_node, at_group = np.concatenate([node, node]), np.concatenate([g4, g4])
    order = np.lexsort((at_group, ends, at_node))  # columns, not one key: no overflow on any mesh
    a, e, g = at_node[order], ends[order], at_group[order]
    link = (a[1:] == a[:-1]) & (e[1:] == e[:-1]) & (g[1:] == g[:-1])  # an edge two incidences share: one fan
    who = np.concatenate([incidence, incidence])[order]
    graph = coo_matrix((np.ones(int(np.count_nonzero(link))), (who[:-1][link], who[1:][link])),
                       shape=(node.size, node.size))
    _, fan = connected_components(graph, directed=False)
    # the fans of each (node, group): sorted by both, a new fan where either changes
    order = np.lexsort((fan, g4, node))
    n_s, g_s, f_s = node[order], g4[order], fan[order]
    new_pair = np.r_[True, (n_s[1:] != n_s[:-1]) | (g_s[1:] != g_s[:-1])]
    new_fan = new_pair | np.r_[True, f_s[1:] != f_s[:-1]]
    pair = np.cumsum(new_pair) - 1
    split = np.bincount(pair, weights=new_fan)[pair] > 1
    rows = np.repeat(outer // 6, 4)[keep][order]
    touched = np.zeros(int(pair[-1]) + 1, dtype=bool)
    touched[pair[split & changed[rows]]] = True  # a pinch already in the input is not the step's
    return _unique(rows[split & touched[pair]])


def _plane_bits(lat: np.ndarray, high: np.ndarray, dim: int) -> np.ndarray:
    """(K,) uint8 for lattice positions ``lat`` (K, 3): bit a set on the image's low bounding
    plane normal to axis a (index 0), bit 3 + a on the high one (index ``high[a]``), as
    ``dicer.mesh.boundary.plane_bits``. Smoothing mirrors the model there (a cut model is
    a part of the whole one), so the merge's checks count the mirror images too."""
    bits = np.zeros(lat.shape[0], dtype=np.uint8)
    for a in range(dim):
        bits |= (lat[:, a] == 0).astype(np.uint8) << np.uint8(a)
        bits |= (lat[:, a] == high[a]).astype(np.uint8) << np.uint8(a + 3)
    return bits


def _degrees(sub: np.ndarray, nodes_mask: np.ndarray, edges: np.ndarray, bits: np.ndarray | None = None,
             ids: np.ndarray | None = None):
    """Distinct edge neighbours and element count of the nodes of the elements ``sub`` (R, c).

    Returns (R, c) node numbers local to ``sub`` (0 .. k-1, in node id order) and, per local
    node, its degree and count (0 for nodes outside ``nodes_mask``, which is (n,) bool).
    ``bits`` (k,) uint8, the local nodes' ``_plane_bits``: counted in the model mirrored at
    the bounding planes (a node on k planes is in 2^k times the elements; an edge has one
    image per plane its node lies on and its other end does not). ``ids``: ``sub``'s node ids,
    ascending, if the caller has them.
    """
    ids = _unique(sub) if ids is None else ids
    local = np.searchsorted(ids, sub)
    k = np.int64(ids.size)
    inside = nodes_mask[ids]
    count = np.bincount(local[inside[local]], minlength=ids.size)
    # the distinct edges, each once (lower end first): half the keys to sort of listing
    # both directions; a node's degree is the number of them it ends
    e = local[:, edges].reshape(-1, 2)
    key = _unique(np.minimum(e[:, 0], e[:, 1]).astype(np.int64) * k + np.maximum(e[:, 0], e[:, 1]))
    a, b = key // k, key % k
    if bits is None:
        degree = np.bincount(a, minlength=ids.size) + np.bincount(b[b != a], minlength=ids.size)
    else:
        count = (count / mirror_share(bits)).astype(count.dtype)  # 2^planes images of each element
        wa = mirror_weights(bits[a], bits[b])
        two = b != a
        wb = mirror_weights(bits[b[two]], bits[a[two]])
        degree = (np.bincount(a, weights=wa, minlength=ids.size)
                  + np.bincount(b[two], weights=wb, minlength=ids.size)).astype(np.int64)
    degree[~inside] = 0  # counted for the nodes of nodes_mask only
    return local, degree, count


def _replace_face_nodes(face, hit, far, snapped, snap):
    """Rows of ``face`` (K, c) with nodes deleted (``hit``, (K, c) bool) or snapped, with each
    deleted node replaced by the far end ``far`` of its axis edge and each snapped node by its
    snap target. Returns (row indices (R,), new faces (R, c))."""
    any_snapped = bool(snapped.any())
    rows = np.flatnonzero(any_per_row(hit) | _any_at(snapped, face) if any_snapped else any_per_row(hit))
    nodes = np.take(face, rows, axis=0)
    h = np.take(hit, rows, axis=0)
    nodes[h] = far[nodes[h]]
    if any_snapped:
        h = snapped[nodes]
        nodes[h] = snap[nodes[h]]
    return rows, nodes


def _gather_corners(cells: np.ndarray, layers: list[tuple[np.ndarray, int, np.ndarray, np.ndarray]],
                    spare: list[np.ndarray] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per entry ``(select, count, first, second)`` of ``layers``: columns ``first`` and
    ``second`` of the rows of ``cells`` (M, c) flagged in ``select`` ((M,) bool, ``count``
    of them), as two (count, len) arrays, rows in order, in buffers taken from ``spare``
    where they fit (an earlier step's, every row written again).

    One pass over ``cells`` in pieces of rows: each piece is read once and compressed into
    small blocks that stay in cache (np.compress: several times faster than a gather of
    row numbers), and no (count, c) copy of the rows is made.
    """
    spare = [] if spare is None else spare

    def buffer(shape: tuple[int, int]) -> np.ndarray:
        size = shape[0] * shape[1]
        fits = [i for i, b in enumerate(spare) if b.dtype == cells.dtype and b.size >= size]
        if not fits:
            return np.empty(shape, dtype=cells.dtype)
        return spare.pop(fits[0])[:size].reshape(shape)

    outs = [(buffer((count, first.size)), buffer((count, second.size))) for _, count, first, second in layers]
    step = _rows_per_piece(cells)
    # where each piece's rows go: the selected rows before it, per layer
    starts = [np.r_[0, np.cumsum(np.add.reduceat(select, np.arange(0, cells.shape[0], step), dtype=np.int64))]
              for select, *_ in layers]

    def gather(part: slice) -> None:
        rows = cells[part]
        for (select, _, first, second), (a, b), start in zip(layers, outs, starts):
            block = np.compress(select[part], rows, axis=0)
            at = int(start[part.start // step])
            k = block.shape[0]
            np.take(block, first, axis=1, out=a[at:at + k], mode="clip")  # valid columns: no buffered copy
            np.take(block, second, axis=1, out=b[at:at + k], mode="clip")
    _each_piece(gather, cells.shape[0], step)
    return outs


def _far_ends_disagree(far: np.ndarray, face: np.ndarray, other: np.ndarray, out: np.ndarray) -> None:
    """Flag in ``out`` ((N,) bool) the nodes of ``face`` (K, c) whose entry in ``far`` is not
    the node at the same place in ``other`` (K, c), in pieces of rows that stay in cache."""
    def flag(part: slice) -> None:
        f = face[part]
        out[f[far[f] != other[part]]] = True  # both threads write True only
    _each_piece(flag, face.shape[0], _rows_per_piece(face))


def _compact(rows: np.ndarray, keep: np.ndarray, new_id: np.ndarray | None = None) -> np.ndarray:
    """``rows[keep]`` (mapped through ``new_id`` when given), written over the front of
    ``rows`` (M, ...) itself: (K, ...), a view.

    Rows only move forward, and each piece is read before anything is written over it, so
    the step needs no second copy (fresh memory costs more than the copy itself).
    """
    out = 0
    for part in pieces(rows.shape[0], _rows_per_piece(rows)):
        # np.compress: a boolean selection several times faster than a[mask]
        piece = np.compress(keep[part], rows[part], axis=0)
        if new_id is not None:
            piece = np.take(new_id, piece)  # np.take: faster than new_id[...]
        rows[out:out + piece.shape[0]] = piece
        out += piece.shape[0]
    return rows[:out]


_STEP_FIGURES = ("merged_pairs", "chamfered_elements", "regions", "regions_merged", "blocked_material",
                 "blocked_thin", "blocked_overlap", "blocked_connectivity", "rim_nodes_refused", "retry_rounds",
                 "overconnected_nodes", "inverted_elements", "crowded_faces", "shared_corners", "pinched_edges",
                 "pinched_nodes")
"""The figures of every step's report (a step that merges also counts rim nodes moved and joined)."""


@dataclass(frozen=True)
class _Settings:
    """The checked options of one merge (see ``merge_planes``).

    Attributes
    ----------
    dim : int
        2 (quads) or 3 (hexahedra).
    granularity : str
        "region" or "plane": what a failed check refuses.
    min_scaled_jacobian : float
        Lowest corner scaled Jacobian a changed element may have, in [-1, 1).
    rim_moves : bool
        Repair failing elements through their rim nodes before refusing their regions.
    spacing : (3,) float64 ndarray
        Voxel size, mm.
    mirror_planes : (3,) int64 ndarray or None
        Lattice index of the image's high bounding plane along each axis (the low one is 0)
        when a node lies on a bounding plane, else None: the checks count the mirror images
        there (``_plane_bits``).
    """

    dim: int
    granularity: str
    min_scaled_jacobian: float
    rim_moves: bool
    spacing: np.ndarray
    mirror_planes: np.ndarray | None = None

    @property
    def min_corner(self) -> float:
        """The Jacobian floor as tested: 0 still refuses inverted corners only."""
        msj = self.min_scaled_jacobian
        return msj if msj > 0 else msj - 1e-9


@dataclass
class _Work:
    """The mesh being merged, carried from step to step (``_apply_step`` updates it).

    Attributes
    ----------
    cells : (M, c) int32 ndarray (int64 from 2**31 - 1 nodes on)
        Node ids of every element, c = 8 (2D: 4), VTK order.
    material : (M,) int32 ndarray
        Material label of every element.
    thick : (M,) bool ndarray
        Elements in a part of their material thick enough to merge (``thick_elements``).
    irregular : (M,) bool ndarray
        Elements that are not lattice boxes (chamfers of earlier steps).
    size : (M,) int64 ndarray
        Volume of every lattice box in lattice units (0 for other elements).
    layer : (M,) int32 ndarray or None
        Element layer along the axis being merged, counted from 0.
    lattice : (N, 3) int64 ndarray
        Lattice index of every node.
    n_input : int
        Nodes of the input mesh, N0.
    node_id : (N,) int ndarray or None
        The input node every node is (None: the same numbering); coordinates and point
        data are gathered once, at the end (``_final_points``), not copied every step.
    moves : list of (int, float, (N0,) int8 ndarray)
        Per step that moved rim nodes: its axis, voxel size along it (mm) and the move of
        every input node, lattice units.
    cell_data : dict of str to ndarray
        Arrays of M rows; they follow the elements kept.
    spare : list of 1-D ndarray
        The last step's face tables, to hold the next step's (``_gather_corners``).
    """

    cells: np.ndarray
    material: np.ndarray
    thick: np.ndarray
    irregular: np.ndarray
    size: np.ndarray
    layer: np.ndarray | None
    lattice: np.ndarray
    n_input: int
    node_id: np.ndarray | None
    moves: list
    cell_data: dict
    spare: list = field(default_factory=list)


@dataclass
class _Plane:
    """What a merge step finds before its first trial: the nodes to delete and the nodes
    that replace them (Box 2 steps 4-8), the stacked pairs and the merge regions. The step
    merges element layer ``s`` of every group of layers along ``axis`` into the layers below.

    Attributes
    ----------
    axis, s, n : int
        Merge axis (0, 1, 2), the layer merged within its group, number of nodes N.
    in_group : (M,) int8 ndarray (int32 for groups of 128 layers or more)
        Layer of every element within its group.
    lo, up : (L,), (U,) int64 ndarray
        Rows of the elements below and above the merge planes, ascending.
    top_cols, bottom_cols : (c/2,) int ndarray
        Corner positions of an element's top and bottom face along the axis.
    l_top, l_bot : (L, c/2) ndarray of node ids
        Top (on the plane) and bottom faces of the lower elements.
    u_bot, u_top : (U, c/2) ndarray of node ids
        Bottom (on the plane) and top faces of the upper elements.
    cand : (N,) bool ndarray
        Candidates for deletion: top of one axis edge and bottom of another (steps 5-6).
    rim_lo, rim_up : (N,) bool ndarray
        Rim nodes: on a lower element's top face only (may move up), on an upper
        element's bottom face only (may move down).
    down, upn : (N,) ndarray of node ids
        Far end of every node's axis edge downwards and upwards, -1 for none (step 8).
    inconsistent : (N,) bool ndarray
        Nodes with two different far ends one way.
    bent : (N,) bool ndarray
        Candidates whose axis edge is not straight along the axis (edges of chamfers).
    any_bent : bool
        Whether any candidate is bent.
    unit : (3,) int64 ndarray
        One lattice step along the axis.
    li, ui : (P,) int64 ndarray
        Rows of ``lo`` and ``up`` that form the stacked pairs.
    faces : (P, c/2) ndarray of node ids
        The shared face of every stacked pair.
    cand_idx : (C,) int64 ndarray
        The candidate nodes, ascending.
    cmap : (N,) int32 ndarray (int64 from 2**31 - 1 nodes on)
        Candidate number of every node, -1 for others.
    comp : (C,) int64 ndarray
        Merge region of every candidate.
    region_of : (R,) bool ndarray
        Regions holding a stacked pair (the others hold rim nodes only).
    """

    axis: int
    s: int
    n: int
    in_group: np.ndarray
    lo: np.ndarray
    up: np.ndarray
    top_cols: np.ndarray
    bottom_cols: np.ndarray
    l_top: np.ndarray
    l_bot: np.ndarray
    u_bot: np.ndarray
    u_top: np.ndarray
    cand: np.ndarray
    rim_lo: np.ndarray
    rim_up: np.ndarray
    down: np.ndarray
    upn: np.ndarray
    inconsistent: np.ndarray
    bent: np.ndarray
    any_bent: bool
    unit: np.ndarray
    li: np.ndarray | None = None
    ui: np.ndarray | None = None
    faces: np.ndarray | None = None
    cand_idx: np.ndarray | None = None
    cmap: np.ndarray | None = None
    comp: np.ndarray | None = None
    region_of: np.ndarray | None = None


@dataclass
class _Trial:
    """The state of a merge step's trials (Box 2 steps 10-14), changed round by round.

    Attributes
    ----------
    blocked : (R,) bool ndarray
        Merge regions that keep their plane.
    base_blocked : (R,) bool ndarray
        Those refused before any trial (materials, thin parts, overlaps).
    keep : (M,) bool ndarray
        Elements of the trial: the upper element of a merged stacked pair is not.
    delete, snapped : (N,) bool ndarray
        Nodes the trial deletes; rim nodes it joins to another node.
    flags : list of two (3, L) and (3, U) bool ndarrays
        Per side (lower, upper): whether any, all, or a bent one of an element's face
        corners went.
    shift : (N,) int8 ndarray
        Move of every rim node along the axis, lattice units (-1, 0, 1).
    snap : (N,) int32 ndarray (int64 from 2**31 - 1 nodes on)
        The node every rim node joins, -1 for none.
    tried : (N,) bool ndarray
        Rim nodes moved once (and maybe put back): never again.
    node_at, dims : ndarray or None
        The node at every lattice corner, a dense grid of shape ``dims`` (see
        ``_corner_keys``), built on first use.
    merged : (P,) bool ndarray
        Stacked pairs merged in the trial.
    checked : (E,) int64 ndarray
        Elements the trial changed other than by a clean stacked merge, ascending.
    first_round : bool
        No trial built yet.
    """

    blocked: np.ndarray
    base_blocked: np.ndarray
    keep: np.ndarray
    delete: np.ndarray
    snapped: np.ndarray
    flags: list
    shift: np.ndarray
    snap: np.ndarray
    tried: np.ndarray
    node_at: np.ndarray | None = None
    dims: np.ndarray | None = None
    merged: np.ndarray | None = None
    checked: np.ndarray | None = None
    first_round: bool = True


def _merge_axis(work: _Work, settings: _Settings, axis: int, g: int, step_mm: float) -> list[dict]:
    """Box 2 step 1 along one axis: join every group of ``g`` element layers into one, the
    first two layers of the group first, then the result with the next layer, and so on.

    Parameters
    ----------
    work : _Work
        The mesh, updated step by step.
    settings : _Settings
        The merge's options.
    axis, g : int
        Merge axis (0, 1, 2) and group size in element layers (2 or more).
    step_mm : float
        Voxel size along ``axis``, mm.

    Returns
    -------
    list of dict
        The report of every step: element and node counts before and after, the step's
        figures and its time in seconds.
    """
    column = work.lattice[:, axis]
    low = int(column.min())
    # the layer fits int32 (a lattice index span): half the memory of int64, the same values
    layer = np.empty(work.cells.shape[0], dtype=np.int32)
    for part in pieces(layer.size, CHUNK):
        np.subtract(column[work.cells[part, 0]], low, out=layer[part], casting="unsafe")
    layer -= layer.min()
    work.layer = layer
    steps = []
    for s in range(1, g):
        t0 = time.perf_counter()
        n_before, m_before = work.lattice.shape[0], work.cells.shape[0]
        keep, delete, shift, info = _merge_step(work, settings, axis, g, s)
        _apply_step(work, keep, delete, shift, axis, step_mm)
        steps.append({
            "axis": _AXIS_NAMES[axis], "pass": s, "elements_before": m_before,
            "elements_after": int(work.cells.shape[0]), "nodes_before": n_before,
            "nodes_after": int(work.lattice.shape[0]), **info,
            "seconds": round(time.perf_counter() - t0, 3)})
        log.info("merge: %s pass %d: %d -> %d elements, %d of %d regions merged (%.1f s)",
                 _AXIS_NAMES[axis], s, m_before, work.cells.shape[0], info["regions_merged"], info["regions"],
                 time.perf_counter() - t0)
    return steps


_RIM_ROUNDS = 16
"""Retry rounds of a merge step that move rim nodes and refuse them before their regions
(then neither: the regions of failing elements are refused at once)."""


def _merge_step(work: _Work, settings: _Settings, axis: int, g: int, s: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Merge element layer ``s`` of every group of ``g`` layers along ``axis`` into the layers below it.

    Parameters
    ----------
    work : _Work
        The mesh. ``work.cells`` is changed in place (rows of removed elements stay),
        and so are ``work.irregular`` and ``work.size``.
    settings : _Settings
        The merge's options.
    axis, g, s : int
        Merge axis (0, 1, 2), group size in element layers, the layer merged (1 .. g-1).

    Returns
    -------
    keep : (M,) bool ndarray
        Rows of ``work.cells`` kept.
    delete : (N,) bool ndarray
        Nodes deleted.
    shift : (N,) int8 ndarray
        Move of every node along the axis, lattice units (-1, 0, 1).
    info : dict
        The step's figures for the report.
    """
    n = int(work.lattice.shape[0])
    info = dict.fromkeys(_STEP_FIGURES, 0)
    keep = np.ones(work.cells.shape[0], dtype=bool)
    plane = _find_merge_nodes(work, settings.dim, axis, g, s, settings.mirror_planes)
    if plane is None:
        return keep, np.zeros(n, dtype=bool), np.zeros(n, dtype=np.int8), info
    _find_merge_pairs(plane, work, settings)
    info["regions"] = int(plane.region_of.sum())
    blocked = _refuse_unmergeable(plane, work, settings.dim, info)
    trial = _Trial(blocked=blocked, base_blocked=blocked.copy(), keep=keep,
                   delete=np.zeros(n, dtype=bool), snapped=np.zeros(n, dtype=bool),
                   flags=[np.zeros((3, face.shape[0]), dtype=bool) for face in (plane.l_top, plane.u_bot)],
                   shift=np.zeros(n, dtype=np.int8), snap=np.full(n, -1, dtype=work.cells.dtype),
                   tried=np.zeros(n, dtype=bool))
    while True:
        info["retry_rounds"] += 1
        _build_trial(plane, trial, work.cells)  # steps 10-11
        _find_changed_elements(plane, trial, work.irregular, info)
        bad_rows = _check_trial(plane, trial, work, settings, info)  # step 12
        late = info["retry_rounds"] > _RIM_ROUNDS
        if bad_rows.size and settings.rim_moves and not late and _move_rim_nodes(plane, trial, work, bad_rows):
            continue  # try the repaired elements
        if bad_rows.size == 0:  # step 13 (applied by the caller)
            break
        # step 14, then try again; after _RIM_ROUNDS rounds no more rim moves and whole regions
        # go at once: moving rim nodes and back a few a round took 282 rounds (22 s) on one
        # step of a head CT at 6 mm slices
        _drop_offending_regions(plane, trial, work, bad_rows, late)
    outcome = _finish_step(plane, trial, work, info)
    # the four face tables' memory, for the next step's (fresh pages cost more than the copy)
    work.spare = [(a if a.base is None else a.base).reshape(-1)
                  for a in (plane.l_top, plane.l_bot, plane.u_bot, plane.u_top)]
    return outcome


def _find_merge_nodes(work: _Work, dim: int, axis: int, g: int, s: int,
                      mirror_planes: np.ndarray | None = None) -> _Plane | None:
    """Box 2 steps 4-8: the elements either side of the merge planes, the nodes to delete
    (top of one axis edge, bottom of another) and the far ends of their edges.

    Parameters
    ----------
    work : _Work
        The mesh, ``work.layer`` set for ``axis``.
    dim, axis, g, s : int
        Dimension, merge axis, group size in layers, the layer merged.
    mirror_planes : (3,) int64 ndarray or None
        ``_Settings.mirror_planes``.

    Returns
    -------
    _Plane or None
        Without the pair and region fields; None when the step has nothing to merge.
    """
    lattice, cells = work.lattice, work.cells
    n = int(lattice.shape[0])
    bc, tc = (HEX_AXIS_CORNERS if dim == 3 else QUAD_AXIS_CORNERS)[axis]
    in_group = np.empty(work.layer.shape, dtype=np.int8 if g < 128 else np.int32)  # g - 1 merges
    np.remainder(work.layer, g, out=in_group, casting="unsafe")
    below, above = in_group < s, in_group == s
    lo = np.flatnonzero(below)
    up = np.flatnonzero(above)
    if lo.size == 0 or up.size == 0:
        return None
    # the two layers' corners, split into the faces on the plane and the far faces: only
    # the face columns change in this step, so these four are all it needs of the rows
    (l_top, l_bot), (u_bot, u_top) = _gather_corners(cells, [(below, lo.size, tc, bc), (above, up.size, bc, tc)],
                                                     work.spare)
    del below, above
    # Step 8: the far ends of the axis edges (one each way, checked consistent below).
    def far_ends(face: np.ndarray, other: np.ndarray) -> np.ndarray:
        far = np.full(n, -1, dtype=cells.dtype)
        _put(far, face, other)
        return far
    down = meanwhile(far_ends, l_top, l_bot)  # the two on two threads
    upn = far_ends(u_bot, u_top)
    down = down()
    # Steps 5-6: nodes at the top of an axis edge (of a lower element) and the bottom of
    # another (of an upper element) are the candidates for deletion: the nodes with a far
    # end each way.
    is_top = down >= 0
    is_bot = upn >= 0
    cand = is_top & is_bot
    if not cand.any():
        return None
    inconsistent = np.zeros(n, dtype=bool)
    _far_ends_disagree(down, l_top, l_bot, inconsistent)
    _far_ends_disagree(upn, u_bot, u_top, inconsistent)
    # Replacements that are not straight along the axis (edges of earlier chamfers).
    other = [d for d in range(3) if d != axis]
    near = np.zeros(n, dtype=bool)  # only edges of irregular elements can be bent
    near[l_top[np.take(work.irregular, lo)]] = True
    near[u_bot[np.take(work.irregular, up)]] = True
    cidx = np.flatnonzero(cand & near)
    bent = np.zeros(n, dtype=bool)
    for far in (upn, down):
        bent[cidx] |= np.any(lattice[far[cidx]][:, other] != lattice[cidx][:, other], axis=1)
    if mirror_planes is not None and cidx.size:
        # a bent edge leaving a mirror plane that its node lies on has a mirror image, a
        # second far end: the whole mirrored model finds the node inconsistent
        on = _plane_bits(lattice[cidx], mirror_planes, dim)
        for far in (upn, down):
            inconsistent[cidx] |= (on & ~_plane_bits(lattice[far[cidx]], mirror_planes, dim)) != 0
    unit = np.zeros(3, dtype=np.int64)
    unit[axis] = 1
    return _Plane(axis, s, n, in_group, lo, up, tc, bc, l_top, l_bot, u_bot, u_top, cand,
                  rim_lo=is_top & ~is_bot, rim_up=is_bot & ~is_top, down=down, upn=upn,
                  inconsistent=inconsistent, bent=bent, any_bent=bool(bent.any()), unit=unit)


def _find_merge_pairs(plane: _Plane, work: _Work, settings: _Settings) -> None:
    """The stacked pairs (a lower element whose top face is an upper element's bottom face)
    and the merge regions: the candidates linked through the pairs' faces, or (granularity
    "plane") all candidates of a plane. Fills in the pair and region fields of ``plane``.
    """
    li, ui = _match_faces(plane.l_top, plane.u_bot, plane.n)
    faces = np.take(plane.l_top, li, axis=0)
    cand_idx = np.flatnonzero(plane.cand)
    cmap = np.full(plane.n, -1, dtype=np.int32 if plane.n < 2**31 - 1 else np.int64)  # half the memory
    cmap[cand_idx] = np.arange(cand_idx.size, dtype=cmap.dtype)
    if settings.granularity == "plane":
        lattice_a = work.lattice[:, plane.axis]
        planes = _unique(lattice_a[cand_idx])
        comp = np.searchsorted(planes, lattice_a[cand_idx])
        n_comp = planes.size
    else:
        far_corner = list(plane.top_cols).index(6 if settings.dim == 3 else 2)
        box = ~(work.irregular[plane.lo[li]] | work.irregular[plane.up[ui]])
        n_comp, comp = _merge_regions(faces, box, cand_idx, cmap, work.lattice, plane.axis, far_corner,
                                      settings.dim)
    region_of = np.zeros(n_comp, dtype=bool)
    region_of[comp[cmap[faces[:, 0]]]] = True
    plane.li, plane.ui, plane.faces = li, ui, faces
    plane.cand_idx, plane.cmap, plane.comp, plane.region_of = cand_idx, cmap, comp, region_of


def _refuse_unmergeable(plane: _Plane, work: _Work, dim: int, info: dict) -> np.ndarray:
    """The merge regions that keep their plane whatever the trial, counted in ``info``.

    A region is refused when it holds a stacked pair of two materials or in a thin part
    (``work.thick``), a candidate whose far ends disagree, or an edge where an earlier
    chamfer meets an element of the other side that is not its stacked partner.

    Returns
    -------
    (R,) bool ndarray
        The regions refused.
    """
    comp, cmap, faces = plane.comp, plane.cmap, plane.faces
    lower, upper = plane.lo[plane.li], plane.up[plane.ui]
    mergeable = work.material[lower] == work.material[upper]
    thin = ~(work.thick[lower] & work.thick[upper])
    n_comp = plane.region_of.size
    blocked = np.zeros(n_comp, dtype=bool)
    by_material = np.zeros(n_comp, dtype=bool)
    by_material[comp[cmap[faces[~mergeable]].ravel()]] = True
    by_thin = np.zeros(n_comp, dtype=bool)
    by_thin[comp[cmap[faces[mergeable & thin]].ravel()]] = True
    blocked |= by_material | by_thin
    blocked[comp[cmap[np.flatnonzero(plane.inconsistent & plane.cand)]]] = True
    # An irregular element (a chamfer of an earlier step) sharing an edge of the plane with
    # an element of the other side that is not its stacked partner: deleting the edge would
    # stretch both over the same ground, so its region keeps the plane.
    clash = _clashes(plane, work.irregular, work.lattice, dim)
    by_clash = np.zeros(n_comp, dtype=bool)
    by_clash[comp[cmap[clash]]] = True
    info["blocked_overlap"] = int((by_clash & ~blocked).sum())
    blocked |= by_clash
    info["blocked_material"] = int(by_material.sum())
    info["blocked_thin"] = int((by_thin & ~by_material).sum())
    return blocked


def _build_trial(plane: _Plane, trial: _Trial, cells: np.ndarray) -> None:
    """Box 2 steps 10-11: the trial connectivity, written into ``cells`` (M, c) in place.

    Every node of a region not blocked is replaced by the far end of its axis edge (a
    joined rim node by the node it joins); a stacked pair whose face went becomes a
    duplicate and only its lower element is kept. After the first round only the rows
    at a node whose fate changed are redone. Updates ``trial.delete``, ``snapped``,
    ``flags``, ``merged`` and ``keep``.
    """
    now = np.zeros(plane.n, dtype=bool)
    now[plane.cand_idx] = ~trial.blocked[plane.comp]
    snapped_now = trial.snap >= 0
    dirty = None if trial.first_round else (now != trial.delete) | (snapped_now != trial.snapped)
    trial.delete, trial.snapped, trial.first_round = now, snapped_now, False
    sides = ((plane.l_top, plane.lo, plane.upn, plane.top_cols), (plane.u_bot, plane.up, plane.down, plane.bottom_cols))
    for flags, (face, idx, far, cols) in zip(trial.flags, sides):
        rows = slice(None) if dirty is None else np.flatnonzero(_any_at(dirty, face))
        f = face[rows]
        if dirty is not None:
            cells[idx[rows][:, None], cols] = f  # undo the previous round there
        h = _take(now, f)
        flags[0, rows] = any_per_row(h)
        flags[1, rows] = all_per_row(h)
        flags[2, rows] = any_per_row(h & _take(plane.bent, f)) if plane.any_bent else False
        done, nodes = _replace_face_nodes(f, h, far, snapped_now, trial.snap)
        cells[idx[rows][done][:, None], cols] = nodes
    trial.merged = now[plane.faces[:, 0]]
    trial.keep[:] = True
    trial.keep[plane.up[plane.ui[trial.merged]]] = False


def _find_changed_elements(plane: _Plane, trial: _Trial, irregular: np.ndarray, info: dict) -> None:
    """The elements the trial changed other than by a clean stacked merge, into ``trial.checked``.

    They are the chamfers (some face corners went, counted in ``info``), changed elements
    that were already irregular or have a bent edge, elements stretched whole without a
    partner (a filled notch) and the elements at moved or joined rim nodes.
    """
    (any_l, all_l, bent_l), (any_u, all_u, bent_u) = trial.flags
    lo, up = plane.lo, plane.up
    chamfer = np.concatenate([lo[any_l & ~all_l], up[any_u & ~all_u]])
    info["chamfered_elements"] = int(chamfer.size)
    # changed elements that were already irregular: a merged old chamfer gains edges too
    reshaped = np.concatenate([lo[(any_l & irregular[lo]) | bent_l], up[(any_u & irregular[up]) | bent_u]])
    # elements stretched whole without a partner: their new face need not match the faces beyond it
    paired_l = np.zeros(lo.size, dtype=bool)
    paired_l[plane.li[trial.merged]] = True
    paired_u = np.zeros(up.size, dtype=bool)
    paired_u[plane.ui[trial.merged]] = True
    filled = np.concatenate([lo[all_l & ~paired_l], up[all_u & ~paired_u]])
    checked = _union(chamfer, reshaped, filled)
    moved = np.flatnonzero((trial.shift != 0) | (trial.snap >= 0))
    if moved.size:  # elements at moved or joined rim nodes change too
        at = np.zeros(plane.n, dtype=bool)
        at[moved] = True
        checked = _union(checked, lo[_any_at(at, plane.l_top)], up[_any_at(at, plane.u_bot)])
    trial.checked = checked


def _check_trial(plane: _Plane, trial: _Trial, work: _Work, settings: _Settings, info: dict) -> np.ndarray:
    """Box 2 step 12 (widened): the elements of the trial at fault, counted in ``info``.

    Around the changed elements (``trial.checked``): no node with more than 6 (2D: 4)
    neighbours or in more than 8 (4) elements, no face of three elements, no corner
    scaled Jacobian below the floor; on a trial that passes these, no node the same
    corner of two elements, then no two elements of one material touching along an edge
    only (2D: at a node only).

    Returns
    -------
    (B,) int64 ndarray
        Rows of ``work.cells`` at fault, ascending; empty when the trial passes.
    """
    checked, cells, n, dim = trial.checked, work.cells, plane.n, settings.dim
    bad_rows = np.empty(0, dtype=np.int64)
    if checked.size == 0:
        return bad_rows
    max_neighbours, max_elements = (6, 8) if dim == 3 else (4, 4)
    in_s = np.zeros(n, dtype=bool)
    in_s[cells[checked]] = True
    rows = np.flatnonzero(trial.keep & _any_at(in_s, cells))
    sub = cells[rows]
    crowded = meanwhile(_crowded_faces, sub, n, dim)  # faces of three or more elements
    bits = ids = None
    if settings.mirror_planes is not None:  # a cut model is checked as the whole mirrored one
        ids = _unique(sub)
        lat = work.lattice[ids]
        lat[:, plane.axis] += trial.shift[ids]  # where the trial puts moved rim nodes
        bits = _plane_bits(lat, settings.mirror_planes, dim)
        if not bits.any():
            bits = None
    local, degree, count = _degrees(sub, in_s, HEX_EDGES if dim == 3 else QUAD_EDGES, bits, ids)
    bad_node = (degree > max_neighbours) | (count > max_elements)
    crowded = crowded()
    info["crowded_faces"] += int(crowded.size)
    if crowded.size:
        bad_rows = rows[crowded]
    info["overconnected_nodes"] += int(np.count_nonzero(bad_node))
    if bad_node.any():
        bad_rows = _union(bad_rows, rows[any_per_row(bad_node[local])])
    corners = (work.lattice[cells[checked]] + trial.shift[cells[checked]][:, :, None] * plane.unit) * settings.spacing
    jac = corner_scaled_jacobians(corners.reshape(-1, 3),
                                  np.arange(corners.shape[0] * corners.shape[1]).reshape(checked.size, -1))
    flat = checked[(jac < settings.min_corner).any(axis=1)]
    info["inverted_elements"] += int(flat.size)
    bad_rows = _union(bad_rows, flat)
    if bad_rows.size == 0:
        # A node is corner c of at most one element (the one in its c-th octant):
        # smoothing's corner table relies on it. Two chamfers of different axes can
        # pass every test above yet split one empty voxel, both holding the node at
        # its corner as the same corner. Tested last, on a trial that passes the
        # rest, so that steps the other tests settle merge exactly as before.
        pos = np.minimum(np.searchsorted(checked, rows), checked.size - 1)
        changed = checked[pos] == rows
        shared = _shared_corners(local, degree.size, changed)
        info["shared_corners"] += int(shared.size)
        bad_rows = rows[shared]
    if bad_rows.size == 0:
        # A chamfer or a moved rim node can leave two elements of one material touching
        # along an edge only, a contact ``dicer fix`` took out: the material's surface
        # would not be closed there.
        faces = _sorted_faces(sub, work.material[rows], n, dim)
        pinched = _pinches(sub, work.material[rows], in_s, changed, dim, faces, local, bits)
        info["pinched_edges"] += int(pinched.size)
        bad_rows = rows[pinched]
        if bad_rows.size == 0 and dim == 3:
            # and at a node only (a filled notch beside another material): the paper's type B,
            # which ``dicer fix`` took out too; each material's surface and the exterior
            pinched = _node_pinches(sub, work.material[rows], in_s, changed, faces, local, bits)
            info["pinched_nodes"] += int(pinched.size)
            bad_rows = rows[pinched]
    return bad_rows


def _corner_keys(lat: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """(K,) int64: flat indices of lattice positions ``lat`` (K, 3) in a grid of shape ``dims``
    (3,) that has one spare layer before the lattice's first position along each axis."""
    return ((lat[:, 0] + 1) * dims[1] + lat[:, 1] + 1) * dims[2] + lat[:, 2] + 1


def _original_corners(plane: _Plane, cells: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(K, c): the corners the elements ``rows`` (K,) had before this step's trials (only
    their face columns change)."""
    out = cells[rows]
    for idx, face, cols in ((plane.lo, plane.l_top, plane.top_cols), (plane.up, plane.u_bot, plane.bottom_cols)):
        pos = np.minimum(np.searchsorted(idx, rows), idx.size - 1)
        inside = np.flatnonzero(idx[pos] == rows)
        out[inside[:, None], cols] = face[pos[inside]]
    return out


def _move_rim_nodes(plane: _Plane, trial: _Trial, work: _Work, bad_rows: np.ndarray) -> int:
    """Repair the elements ``bad_rows`` through their rim nodes, before refusing them.

    Each rim node of theirs used only as a face corner of the merged layers, and not
    moved before, moves one lattice step across the plane to an empty corner, or joins
    the node already at that corner (one that stays): the element then fills the empty
    voxel beside it. Updates ``trial.shift``, ``snap``, ``tried`` and ``node_at``.

    Returns
    -------
    int
        The number of rim nodes moved or joined.
    """
    lattice, n = work.lattice, plane.n
    if trial.node_at is None:  # node at every lattice corner (a dense grid, built on first use)
        trial.dims = np.array([int(lattice[:, d].max()) + 3 for d in range(3)], dtype=np.int64)
        trial.node_at = np.full(int(np.prod(trial.dims)), -1, dtype=np.int32 if n < 2**31 - 1 else np.int64)
        trial.node_at[_corner_keys(lattice, trial.dims)] = np.arange(n, dtype=trial.node_at.dtype)
    node_at, dims = trial.node_at, trial.dims
    c_all = _unique(_original_corners(plane, work.cells, bad_rows))
    c_all = c_all[(plane.rim_up[c_all] | plane.rim_lo[c_all]) & ~trial.tried[c_all]]
    mask = np.zeros(n, dtype=bool)
    mask[c_all] = True
    confined = np.ones(n, dtype=bool)  # no corner of theirs other than a face corner on the plane
    for other_corners in (plane.l_bot, plane.u_top, work.cells[plane.in_group > plane.s]):
        confined[other_corners[_take(mask, other_corners)]] = False
    moved = 0
    for rim, step in ((plane.rim_up, -1), (plane.rim_lo, 1)):
        c = c_all[rim[c_all] & confined[c_all]]
        if not c.size:
            continue
        target = _corner_keys(lattice[c] + step * plane.unit, dims)
        order = np.argsort(target, kind="stable")
        target, c = target[order], c[order]
        first = np.ones(target.size, dtype=bool)
        first[1:] = target[1:] != target[:-1]
        target, c = target[first], c[first]
        occupant = node_at[target]
        free = occupant < 0
        usable = free | ~trial.delete[np.maximum(occupant, 0)]
        c, target, occupant, free = c[usable], target[usable], occupant[usable], free[usable]
        trial.tried[c] = True
        trial.shift[c[free]] = step  # move to the empty corner
        node_at[target[free]] = c[free]
        trial.snap[c[~free]] = occupant[~free]  # or join the node already there
        node_at[_corner_keys(lattice[c], dims)] = -1
        moved += c.size
    return moved


def _drop_offending_regions(plane: _Plane, trial: _Trial, work: _Work, bad_rows: np.ndarray,
                            whole_regions: bool = False) -> None:
    """Box 2 step 14 (per merge region): refuse what made the elements ``bad_rows`` fail.

    A deleted node of theirs on no stacked face (a rim node: it only makes chamfers) is
    refused on its own first; the merge region of a bad element is refused only when it
    has no such node left, or at once with ``whole_regions``. Their moved and joined rim
    nodes go back to their places. Updates ``trial.blocked``, ``shift``, ``snap`` and
    ``node_at``.
    """
    shift, snap, blocked = trial.shift, trial.snap, trial.blocked
    before = _original_corners(plane, work.cells, bad_rows)
    rows_rep = np.repeat(np.arange(bad_rows.size), work.cells.shape[1])
    corners = before.ravel()
    sel = trial.delete[corners]
    rows_rep, ccomp = rows_rep[sel], plane.comp[plane.cmap[corners[sel]]]
    rim = ~plane.region_of[ccomp]
    has_rim = np.zeros(bad_rows.size, dtype=bool)
    if not whole_regions:
        has_rim[rows_rep[rim]] = True
    newly = _unique(ccomp[rim | ~has_rim[rows_rep]])
    newly = newly[~blocked[newly]]
    back = _unique(before)
    back = back[(shift[back] != 0) | (snap[back] >= 0)]
    if newly.size == 0 and back.size == 0:  # cannot happen for a consistent mesh
        blocked[:] = True
        back = np.flatnonzero((shift != 0) | (snap >= 0))
    else:
        blocked[newly] = True
    if back.size:
        moved_back = back[shift[back] != 0]
        lattice = work.lattice
        trial.node_at[_corner_keys(lattice[moved_back] + shift[moved_back][:, None] * plane.unit, trial.dims)] = -1
        trial.node_at[_corner_keys(lattice[back], trial.dims)] = back
        shift[back] = 0
        snap[back] = -1


def _finish_step(plane: _Plane, trial: _Trial, work: _Work, info: dict
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The outcome of the trial that passed: the step's figures in ``info``, the nodes
    deleted, and ``work.irregular`` and ``work.size`` of the elements kept updated.

    Returns
    -------
    keep, delete, shift, info
        As ``_merge_step`` returns them.
    """
    blocked, keep, shift, snap, region_of = trial.blocked, trial.keep, trial.shift, trial.snap, plane.region_of
    refused = blocked & ~trial.base_blocked
    info["blocked_connectivity"] = int((refused & region_of).sum())
    info["rim_nodes_refused"] = int((refused & ~region_of).sum())
    info["regions_merged"] = int((~blocked & region_of).sum())
    info["merged_pairs"] = int(np.count_nonzero(~keep))
    delete = np.zeros(plane.n, dtype=bool)
    delete[plane.cand_idx] = ~blocked[plane.comp]
    info["rim_nodes_moved"] = int(np.count_nonzero(shift))
    info["rim_nodes_joined"] = int(np.count_nonzero(snap >= 0))
    if (snap >= 0).any():
        delete |= snap >= 0
        if delete[work.cells[keep]].any():  # a joined rim node outside the merged layers
            raise DicerError("internal error in plane merging (a joined rim node is still in use); "
                             "rerun with merge.rim_moves=false and report the input")
    irregular, size = work.irregular, work.size
    irregular[trial.checked] = True
    merged_lo, merged_up = plane.lo[plane.li[trial.merged]], plane.up[plane.ui[trial.merged]]
    irregular[merged_lo] |= irregular[merged_up]
    size[merged_lo] += size[merged_up]
    return keep, delete, shift, info


def _check_settings(mesh: Mesh, passes, granularity, min_scaled_jacobian, rim_moves, axes
                    ) -> tuple[tuple[int, int, int], _Settings]:
    """The options of ``merge_planes`` as the steps read them: merges per axis (3 ints) and the settings.

    The schema checked the settings' types and ranges (:func:`dicer.config.stage_kwargs`);
    raises ``DicerError`` for bad ``axes`` (not a setting) or a mesh that cannot be merged.
    """
    counts = _check_passes(passes, mesh.dim)
    if sorted(axes) != [0, 1, 2]:
        raise DicerError(f"merge.axes={axes!r}: give a permutation of 0, 1, 2")
    if mesh.n_cells == 0:
        raise DicerError("the mesh has no elements; nothing to merge")
    if int(mesh.material.min()) < 0:
        raise DicerError("the mesh has negative material labels; materials are numbered 1..K")
    # Nodes move only within the mesh's extent (a rim node to the next plane of its group),
    # so a mesh off every bounding plane stays off them: its checks need no mirror images.
    high = np.asarray(mesh.grid_shape, dtype=np.int64)
    lat = mesh.lattice[:, :mesh.dim]
    touches = bool(((lat == 0) | (lat == high[:mesh.dim])).any())  # (graded meshes: -1 between lattice points)
    return counts, _Settings(mesh.dim, granularity, float(min_scaled_jacobian), bool(rim_moves),
                             np.asarray(mesh.spacing, dtype=np.float64), high if touches else None)


def _apply_step(work: _Work, keep: np.ndarray, delete: np.ndarray, shift: np.ndarray, axis: int,
                step_mm: float) -> None:
    """Box 2 step 13: the trial that passed becomes the mesh.

    Parameters
    ----------
    work : _Work
        The mesh after ``_merge_step``; its arrays are replaced (the input mesh's arrays
        are never written).
    keep : (M,) bool ndarray
        Elements kept.
    delete : (N,) bool ndarray
        Nodes deleted; the others are renumbered in order.
    shift : (N,) int8 ndarray
        Move of every node along ``axis``, lattice units.
    axis : int
        Merge axis.
    step_mm : float
        Voxel size along ``axis``, mm.
    """
    moved = bool(shift.any())
    if moved:  # recorded by input node: the coordinates move once, at the end, in step order
        by_input = np.zeros(work.n_input, dtype=np.int8)
        by_input[slice(None) if work.node_id is None else work.node_id] = shift
        work.moves.append((axis, step_mm, by_input))
    if delete.any():
        kept_nodes = ~delete
        new_id = np.cumsum(kept_nodes, dtype=work.cells.dtype)
        new_id -= 1
        work.cells = _compact(work.cells, keep, new_id)
        # the work's own arrays, in place; the input mesh's are copied (the first step)
        work.material, work.thick, work.layer, work.irregular, work.size = (
            _compact(a, keep) for a in (work.material, work.thick, work.layer, work.irregular, work.size))
        if work.node_id is None:
            work.lattice = np.compress(kept_nodes, work.lattice, axis=0)
            work.node_id = np.flatnonzero(kept_nodes).astype(work.cells.dtype)
        else:
            work.lattice = _compact(work.lattice, kept_nodes)
            work.node_id = _compact(work.node_id, kept_nodes)
        work.cell_data = {k: np.compress(keep, v, axis=0) for k, v in work.cell_data.items()}
        if moved:
            shift = np.compress(kept_nodes, shift)
    elif moved and work.node_id is None:  # still the input's
        work.lattice = work.lattice.copy()
    if moved:
        work.lattice[:, axis] += shift


def _final_points(mesh: Mesh, work: _Work) -> tuple[np.ndarray, dict]:
    """The coordinates (N, 3) float64, mm, and point data of the merged mesh's nodes: the
    input's rows of the nodes kept, each step's rim moves added in step order (the same
    sums as moving every step's copy)."""
    if work.node_id is None:
        points = mesh.points.copy() if work.moves else mesh.points
        point_data = dict(mesh.point_data)
    else:
        points = np.take(mesh.points, work.node_id, axis=0)
        point_data = {k: np.take(v, work.node_id, axis=0) for k, v in mesh.point_data.items()}
    for axis, step_mm, by_input in work.moves:
        shift = by_input if work.node_id is None else np.take(by_input, work.node_id)
        points[:, axis] += shift * step_mm
    return points, point_data


def _volume_report(before: dict[int, float], after: dict[int, float]) -> dict[str, dict]:
    """Volume of every material before and after, mm^3 (2D: mm^2), and its change in percent."""
    return {str(k): {"before": before[k], "after": after.get(k, 0.0),
                     "change_percent": round(100.0 * (after.get(k, 0.0) - before[k]) / before[k], 4)
                     if before[k] else 0.0}
            for k in sorted(before)}


@takes_settings("merge")
def merge_planes(mesh: Mesh, *, passes, min_thickness: float, granularity: str, min_scaled_jacobian: float,
                 rim_moves: bool, axes=(0, 1, 2)) -> tuple[Mesh, dict]:
    """Merge element layers along each axis (DICER Box 2, multi-material, optionally selective).

    The settings are the ``merge:`` section's (``passes`` ... ``rim_moves``), keyword-only
    with no defaults here; settings left out take the schema's defaults, and every value
    given is checked against the schema (:func:`dicer.config.takes_settings`).

    Nodes keep their coordinates and integer lattice indices; a moved rim node gets the
    index of the lattice corner it moved to; merged elements span two or more lattice
    units along the merge axis.

    Parameters
    ----------
    mesh : Mesh
        A voxel mesh (:func:`~dicer.mesh.voxel.voxel_mesh`), hexahedral or quad, one or
        several materials.
    passes : sequence of int
        Merges per axis (px, py[, pz]). ``p`` merges join every group of ``p + 1``
        element layers into one: the first two layers of the group, then the result
        with the next layer, and so on. Groups start at the mesh's first element layer.
    min_thickness : float
        Selective merging. 0 merges wherever it is safe; t > 0 refuses every merge region
        that holds an element lying in a part of its material thinner than ``t`` voxels
        (see :func:`thick_elements`).
    granularity : {"region", "plane"}
        "region" refuses only the connected merge region that failed a check; "plane"
        refuses the whole plane, as the paper does.
    min_scaled_jacobian : float
        Lowest corner scaled Jacobian (measured on the lattice) a changed element may
        have; 0.2 matches the smoothing floor. 0 allows flat corners, -1 switches the test
        off (the paper checks connectivity only).
    rim_moves : bool
        Repair an element that fails a check by moving its rim nodes one lattice step
        across the plane, or joining them to the node already there (the element then
        fills the empty voxel beside it), before refusing its region.
    axes : sequence of int, optional
        Order in which the axes are merged.

    Returns
    -------
    merged : Mesh
    report : dict
        Element and node counts per axis and pass, and the volume of every material
        before and after.
    """
    counts, settings = _check_settings(mesh, passes, granularity, min_scaled_jacobian, rim_moves, axes)
    t_start = time.perf_counter()
    if granularity == "region" or min_thickness > 0:  # loaded while the mesh is prepared
        import_meanwhile("scipy.ndimage", "scipy.sparse.csgraph")
    index = np.int32 if mesh.n_points < 2**31 - 1 else np.int64  # halves memory traffic
    cells = _copy_as(mesh.cells, index)
    box0, size = _lattice_boxes(cells, mesh.lattice, settings.dim)
    _refuse_irregular_input(mesh, cells[~box0], settings.dim)
    on_lattice = _on_lattice(mesh)
    vol_before = _material_volumes(mesh, box0, on_lattice, size)
    report = {"passes": list(counts), "granularity": granularity, "min_thickness": float(min_thickness),
              "min_scaled_jacobian": settings.min_scaled_jacobian, "rim_moves": settings.rim_moves,
              "elements_before": mesh.n_cells, "nodes_before": mesh.n_points, "steps": []}
    work = _Work(cells, mesh.material.copy(), thick_elements(mesh, min_thickness), ~box0, size, None, mesh.lattice,
                 mesh.n_points, None, [], dict(mesh.cell_data))
    for axis in axes:
        if counts[axis]:
            report["steps"] += _merge_axis(work, settings, axis, counts[axis] + 1, mesh.spacing[axis])
    work.spare = []  # not held while the result is made
    points, point_data = _final_points(mesh, work)
    out = Mesh(points, work.cells, work.material, work.lattice, mesh.spacing.copy(),
               mesh.origin.copy(), mesh.grid_shape.copy(), point_data, work.cell_data, list(mesh.names))
    report["elements_after"] = out.n_cells
    report["nodes_after"] = out.n_points
    report["element_ratio"] = round(mesh.n_cells / max(out.n_cells, 1), 4)
    report["volume"] = _volume_report(vol_before, _material_volumes(out, ~work.irregular, on_lattice, work.size))
    report["seconds"] = round(time.perf_counter() - t_start, 3)
    return out, report


DEFAULTS = section_defaults("merge")
"""The ``merge:`` config section's defaults, as the config schema gives them (see
docs/merging.md and docs/coarsening.md)."""


@takes_settings("merge", section=True)
def merge_mesh(mesh: Mesh, *, method: str, templates: dict, passes, min_thickness: float, granularity: str,
               min_scaled_jacobian: float, rim_moves: bool) -> tuple[Mesh, dict]:
    """The merge stage driven by the ``merge:`` settings.

    Plane merging (``method: planes``, :func:`merge_planes`) or graded coarsening by
    transition templates (``method: templates``, :func:`dicer.mesh.coarsen.coarsen_mesh`).
    The settings are keyword-only with no defaults here: the command line passes
    ``dicer.config.stage_kwargs(config, "merge")``. A library call may instead give the
    ``merge:`` section (or part of it) as the second argument, or leave settings out; the
    schema's defaults fill them (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    mesh : Mesh
        A voxel mesh.
    method, templates, passes, min_thickness, granularity, min_scaled_jacobian, rim_moves
        The ``merge:`` config section (see the schema).

    Returns
    -------
    merged : Mesh
    report : dict
    """
    if method == "templates":
        from dicer.mesh.coarsen import coarsen_mesh

        return coarsen_mesh(mesh, levels=templates["levels"], min_distance=templates["min_distance"],
                            keep_fine=list(templates["keep_fine"]))
    moved = nodes_off_lattice(mesh)
    if moved:  # the checks judge elements on the lattice: a smoothed mesh's would pass below the floor
        raise DicerError(f"{moved} of the mesh's {mesh.n_points} nodes lie off their lattice points (a smoothed "
                         "mesh): plane merging works on meshes from dicer mesh or dicer merge; merge before "
                         "smoothing")
    return merge_planes.__wrapped__(mesh, passes=passes, min_thickness=float(min_thickness), granularity=granularity,
                                    min_scaled_jacobian=float(min_scaled_jacobian), rim_moves=rim_moves)


def _refuse_irregular_input(mesh: Mesh, irregular: np.ndarray, dim: int) -> None:
    """Refuse elements that are no lattice box in VTK order (``irregular``, their cells; a
    merged mesh's chamfers are few) where they are lattice boxes with their corners in another
    order, or inside out: merging took a whole mesh of turned corners for irregular elements
    (912 elements merged to 880 where they merge to 816, without a word)."""
    if irregular.shape[0] == 0:
        return
    corners = mesh.lattice[irregular][..., :dim]  # (K, corners, dim)
    lo, hi = corners.min(axis=1, keepdims=True), corners.max(axis=1, keepdims=True)
    at_ends = ((corners == lo) | (corners == hi)).all(axis=(1, 2)) & (hi > lo).all(axis=(1, 2))
    code = ((corners == hi) * (1 << np.arange(dim))).sum(axis=2)  # which corner of the box each is
    turned = int(np.count_nonzero(at_ends & (np.sort(code, axis=1) == np.arange(1 << dim)).all(axis=1)))
    if turned:
        raise DicerError(f"{turned} element(s) are lattice boxes with their corners in another order than VTK's "
                         "(turned or mirrored by the tool that wrote them), which merging would take for irregular "
                         "elements; remesh from the labels with 'dicer mesh'")
    flat = int(np.count_nonzero(corner_scaled_jacobians(mesh.points, irregular).min(axis=1) <= 0))
    if flat:
        raise DicerError(f"{flat} element(s) of the mesh are degenerate or inverted (a corner's scaled Jacobian of 0 "
                         "or less); merging takes the meshes of dicer mesh and dicer merge: remesh from the labels "
                         "with 'dicer mesh'")


def _lattice_boxes(cells: np.ndarray, lattice: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(M,) bool: elements whose corners sit on the corners of a lattice box, in VTK order;
    and (M,) int64: each box's volume in lattice units (0 for others).

    Lattice positions are packed into one integer key each (one-to-one inside the
    lattice's bounding box). An element is a box when its corner keys are its first
    corner's key plus the right sums of its extent along each axis times that axis's
    key stride, with every extent positive.
    """
    far = 6 if dim == 3 else 2
    out = np.ones(cells.shape[0], dtype=bool)
    size = np.zeros(cells.shape[0], dtype=np.int64)
    if lattice.shape[0] == 0:
        return out, size
    bounds = [(int(lattice[:, d].min()), int(lattice[:, d].max())) for d in range(dim)]
    base = [b for b, _ in bounds]
    extent = [t - b + 1 for b, t in bounds]
    small = (int(np.prod(extent, dtype=np.float64)) < 2**31 - 1
             and all(-2**31 < b and t < 2**31 - 1 for b, t in bounds))
    kind = np.int32 if small else np.int64  # halves memory traffic
    # contiguous columns made once, straight in the key's type (no int64 copies first)
    lat = [lattice[:, d].astype(kind) for d in range(dim)]
    stride = [int(np.prod(extent[d + 1:], dtype=np.int64)) for d in range(dim)]
    key = np.zeros(lattice.shape[0], dtype=kind)
    for d in range(dim):
        part = lat[d] - kind(base[d])
        part *= kind(stride[d])
        key += part
    del part
    # corner -> the axes it is offset along (VTK order): corner = corner 0 + those steps
    steps = [[d for d in range(dim) if off[d]] for off in (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim]]

    def check(part: slice) -> None:
        c = cells[part]
        first, last = c[:, 0], c[:, far]
        span = [x[last] - x[first] for x in lat]
        ok = span[0] > 0
        for d in range(1, dim):
            ok &= span[d] > 0
        kc = key[c]
        step = [span[d] * kind(stride[d]) for d in range(dim)]
        for corner in range(1, c.shape[1]):
            expected = kc[:, 0].copy()
            for d in steps[corner]:
                expected += step[d]
            ok &= kc[:, corner] == expected
        out[part] = ok
        volume = span[0].astype(np.int64)
        for d in range(1, dim):
            volume *= span[d]
        size[part] = np.where(ok, volume, 0)
    _each_piece(check, cells.shape[0], _rows_per_piece(cells))
    return out, size


def _material_volumes(mesh: Mesh, box: np.ndarray, on_lattice: bool, size: np.ndarray) -> dict[int, float]:
    """Volume (area in 2D) of every material, mm^3: lattice boxes (``box``) from their
    ``size`` in lattice units when the nodes sit on the lattice, every other element from
    its corners (``element_volumes``)."""
    cells = mesh.cells
    box = box if on_lattice else np.zeros(cells.shape[0], dtype=bool)
    # every row from its size first (no gather); the other elements' rows are written over below
    vol = size * float(np.prod(mesh.spacing[:mesh.dim]))
    other = np.flatnonzero(~box)
    if other.size:
        vol[other] = element_volumes(mesh.points, cells[other])
    sums = np.bincount(mesh.material, weights=vol)
    return {int(k): float(sums[k]) for k in np.flatnonzero(np.bincount(mesh.material))}


def _on_lattice(mesh: Mesh) -> bool:
    """True when every node sits at origin + lattice * spacing."""
    largest = np.zeros((2, -(-mesh.points.shape[0] // CHUNK)))  # per piece: largest |x| and largest offset

    def measure(part: slice) -> None:  # in pieces that stay in cache
        p = mesh.points[part]
        x = mesh.lattice[part] * mesh.spacing
        x += mesh.origin
        x -= p
        largest[:, part.start // CHUNK] = np.abs(p).max(initial=0.0), np.abs(x).max(initial=0.0)
    _each_piece(measure, mesh.points.shape[0], CHUNK)
    return bool(largest[1].max(initial=0.0) <= 1e-9 * max(1.0, float(largest[0].max(initial=0.0))))
