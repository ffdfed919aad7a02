"""Face neighbours of hexahedral and quadrilateral meshes: which element (or material) lies
across each face.

Two ways: a material grid over the lattice when every element is an axis-aligned box of
it (voxel and plane-merged meshes), else a sort of face keys (any conforming mesh).
Faces are numbered as in :mod:`dicer.mesh.topology` (S1..S6, 2D: edges S1..S4).
"""

from __future__ import annotations

import numpy as np

from dicer.arrays import norm
from dicer.mesh.boxes import box_extents, linear_index
from dicer.mesh.model import Mesh, pieces
from dicer.parallel import ordered_map
from dicer.mesh.topology import HEX_CORNERS, HEX_FACE_PLANES, HEX_FACES, QUAD_CORNERS, QUAD_EDGES, QUAD_SIDE_PLANES


def _neighbour_materials_by_lattice(mesh: Mesh) -> np.ndarray | None:
    """(M, F) material of the element across each face, 0 for none, from a voxel -> material grid
    (uint8, or uint16 for labels above 255).

    Valid when every element is an axis-aligned box of the lattice (voxel meshes and
    plane-merged meshes; smoothing moves points, not lattice indices); None otherwise.
    """
    dim = mesh.dim
    cells, material = mesh.cells, mesh.material
    m = cells.shape[0]
    if m == 0 or int(material.max()) > 65535:
        return None
    kind = np.uint8 if int(material.max()) < 256 else np.uint16
    far = 6 if dim == 3 else 2
    shape = np.asarray(mesh.grid_shape, np.int64)[:dim]
    lattice = mesh.lattice[:, :dim]
    strides = np.array([int(np.prod(shape[i + 1 :])) for i in range(dim)], np.int64)
    nstrides = np.array([int(np.prod(shape[i + 1 :] + 1)) for i in range(dim)], np.int64)
    node_lin = linear_index(lattice, nstrides)
    grid = np.zeros(int(np.prod(shape)), kind)

    def fill(part: slice) -> int | None:  # the boxes' voxels of one piece: their count, None if not boxes
        c = cells[part]
        boxes = box_extents(c, lattice, node_lin, nstrides)  # every corner where the box puts it
        if boxes is None:
            return None
        lo, ext = boxes
        if lo.min() < 0 or np.any(lo + ext > shape) or ext.max() >= 64:
            return None
        base = linear_index(lo, strides)
        code = linear_index(ext, 64 ** np.arange(dim))
        mat = material[part].astype(kind)
        covered = 0
        # a few distinct box sizes (1 x 1 x 1 before plane merging: no sort needed)
        for cc in (code[:1] if code.min() == code.max() else np.unique(code)):
            sel = code == cc
            e = [(int(cc) // 64**i) % 64 for i in range(dim)]
            b, v = base[sel], mat[sel]
            for off in np.ndindex(*e):
                grid[b + int(np.dot(off, strides))] = v
            covered += b.size * int(np.prod(e))
        return covered

    # pieces side by side (numpy leaves the interpreter lock); boxes of different pieces
    # that overlap write the same voxels, which the count below finds whatever the order
    counts = list(ordered_map(fill, pieces(m)))
    if any(c is None for c in counts) or np.count_nonzero(grid) != sum(counts):  # overlapping boxes
        return None
    axes = HEX_FACE_PLANES if dim == 3 else QUAD_SIDE_PLANES
    nb = np.empty((m, len(axes)), kind)

    def across(part: slice) -> None:
        c = cells[part]
        lo = np.take(lattice, c[:, 0], axis=0)
        ext = np.take(lattice, c[:, far], axis=0) - lo
        base = linear_index(lo, strides)
        for f, (axis, side) in enumerate(axes):
            if side == 0:
                inside = lo[:, axis] > 0
                idx = base - strides[axis]
            else:
                inside = lo[:, axis] + ext[:, axis] < shape[axis]
                idx = base + ext[:, axis] * strides[axis]
            np.putmask(idx, ~inside, 0)
            got = grid[idx]
            got[~inside] = 0
            nb[part, f] = got

    for _ in ordered_map(across, pieces(m)):
        pass
    return nb


def _distinct(values: np.ndarray, size: int) -> bool:
    """Whether the integers ``values`` in [0, size) are all different: at once when they
    increase (the order the voxel mesher writes nodes and elements in), else by flags."""
    if np.all(values[1:] > values[:-1]):
        return True
    seen = np.zeros(size, bool)
    seen[values] = True
    return int(np.count_nonzero(seen)) == values.size


def voxel_elements(mesh: Mesh) -> np.ndarray | None:
    """Each element's voxel, when the mesh is a voxel mesh of its lattice (smoothed or not).

    Valid when every element is the unit box of one voxel with its corners at that voxel's
    lattice corners, no two elements share a voxel and no two nodes share a lattice point.
    Then two elements share a face exactly when their voxels share one (a voxel's face has
    one set of four nodes), so face neighbours and face-connected parts come from the
    voxel grid, without matching faces by their nodes. Smoothing moves points, not lattice
    indices, so a smoothed voxel mesh qualifies; a merged or graded mesh does not.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    (M,) int64 ndarray or None
        The flat index of each element's voxel in the grid of the first ``dim`` axes of
        ``grid_shape`` (C order); None when the mesh is not such a voxel mesh or has no
        elements.
    """
    dim = mesh.dim
    cells = mesh.cells
    m = cells.shape[0]
    shape = np.asarray(mesh.grid_shape, np.int64)[:dim]
    lattice = np.asarray(mesh.lattice)[:, :dim]
    if m == 0 or lattice.shape[0] == 0 or shape.min() < 1 or lattice.min() < 0 or np.any(lattice.max(axis=0) > shape):
        return None
    nstrides = np.array([int(np.prod(shape[i + 1:] + 1)) for i in range(dim)], np.int64)
    strides = np.array([int(np.prod(shape[i + 1:])) for i in range(dim)], np.int64)
    node_lin = linear_index(lattice, nstrides)
    # one node per lattice point: two nodes at one point would let voxels that touch
    # hold different nodes on their common face, which is then no shared face
    if not _distinct(node_lin, int(np.prod(shape + 1))):
        return None
    corner_step = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim] @ nstrides
    voxel = np.empty(m, np.int64)
    for part in pieces(m):
        at = node_lin[cells[part]]  # (p, corners) lattice points of the corners
        lo = lattice[cells[part, 0]]
        # corner 0 below the far lattice plane: else corner 0 + 1 would wrap into the next row
        if np.any(lo >= shape) or not np.array_equal(at - at[:, :1], np.broadcast_to(corner_step, at.shape)):
            return None
        voxel[part] = linear_index(lo, strides)
    if not _distinct(voxel, int(np.prod(shape))):  # two elements in one voxel
        return None
    return voxel


def voxel_face_neighbours(mesh: Mesh) -> np.ndarray | None:
    """The element across each face of a voxel mesh, from its voxel grid.

    The same array as :func:`face_neighbours` for a mesh :func:`voxel_elements` accepts,
    in gathers of the neighbouring voxels rather than a sort of all faces.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    (M, F) int64 ndarray or None
        Element index across faces S1..S6 (2D: edges S1..S4), -1 for none; None when
        the mesh is not a voxel mesh of its lattice.
    """
    voxel = voxel_elements(mesh)
    if voxel is None:
        return None
    shape = [int(n) for n in np.asarray(mesh.grid_shape)[:mesh.dim]]
    m = voxel.size
    kind = np.int32 if m < 2**31 else np.int64
    index = np.full(int(np.prod(shape)), -1, kind)  # the element in each voxel
    index[voxel] = np.arange(m, dtype=kind)
    strides = [int(np.prod(shape[i + 1:])) for i in range(len(shape))]
    axes = HEX_FACE_PLANES if mesh.dim == 3 else QUAD_SIDE_PLANES
    nb = np.empty((m, len(axes)), np.int64)
    for part in pieces(m):
        v = voxel[part]
        for f, (axis, side) in enumerate(axes):
            pos = (v // strides[axis]) % shape[axis]  # the voxel's index along the face's axis
            inside = pos > 0 if side == 0 else pos < shape[axis] - 1
            step = -strides[axis] if side == 0 else strides[axis]
            got = index[np.where(inside, v + step, 0)].astype(np.int64)
            got[~inside] = -1
            nb[part, f] = got
    return nb


def face_neighbours(cells: np.ndarray, dim: int, n_points: int) -> np.ndarray:
    """The element across each face, from a sort of face keys (any conforming mesh).

    A quad face is keyed by its smallest node and the node diagonally opposite it, an
    edge by its two nodes. Faces that share that diagonal only (two chamfers of a merged
    mesh may) are told apart by their other diagonal.

    Parameters
    ----------
    cells : (M, 8) or (M, 4) int ndarray
        Hexahedra or quads, VTK corner order.
    dim : int
        3 for hexahedra, 2 for quads.
    n_points : int
        Number of nodes.

    Returns
    -------
    (M, F) int64 ndarray
        Element index across faces S1..S6 (2D: edges S1..S4), -1 for none.
    """
    table = HEX_FACES if dim == 3 else QUAD_EDGES
    m, nf = cells.shape[0], table.shape[0]
    n64 = np.int64(n_points)
    keys = np.empty((m, nf), np.int64)
    other = np.empty((m, nf), np.int64) if dim == 3 else None  # the other diagonal
    # piece by piece: the temporaries of a piece stay small and are reused, where whole-mesh
    # temporaries would each take fresh memory (slow to fault in on a virtual machine)
    for part in pieces(m):
        block = cells[part]
        for f, face in enumerate(table):
            if dim == 3:  # the diagonal holding the smallest node, by elementwise minima
                a, b, c, d = (block[:, i] for i in face)
                ac, bd = np.minimum(a, c), np.minimum(b, d)
                first = ac < bd
                lo = np.where(first, ac, bd)
                hi = np.where(first, np.maximum(a, c), np.maximum(b, d))
                other[part, f] = np.where(first, bd, ac) * n64 + np.where(first, np.maximum(b, d), np.maximum(a, c))
            else:
                lo, hi = np.minimum(block[:, face[0]], block[:, face[1]]), np.maximum(block[:, face[0]], block[:, face[1]])
            keys[part, f] = lo * n64 + hi
    flat = keys.ravel()
    order = np.argsort(flat, kind="stable")
    same = np.empty(max(flat.size - 1, 0), bool)  # sorted key i + 1 equals key i
    shared_only = []  # diagonals shared by faces that differ
    for part in pieces(same.size):
        i = order[part.start:part.stop + 1]
        sk = flat[i]
        np.equal(sk[1:], sk[:-1], out=same[part])
        if other is not None:
            so = other.reshape(-1)[i]
            differ = same[part] & (so[1:] != so[:-1])
            if differ.any():
                shared_only.append(sk[1:][differ])
    hard = None
    if shared_only:  # those diagonals' faces are paired by both diagonals below
        hard = np.isin(flat, np.concatenate(shared_only))
        same &= ~hard[order[1:]]
        rows = np.flatnonzero(hard)
        k1, k2 = flat[rows], other.reshape(-1)[rows]
    del other
    # the keys' memory holds the answer: fresh pages cost more than the work on them
    nb = flat
    del keys, flat
    nb.fill(-1)
    a = np.compress(same, order[:-1])  # the first face of each pair, as sorted
    b = np.compress(same, order[1:])
    del order, same
    if hard is not None:
        by_both = np.lexsort((k2, k1))
        rows, k1, k2 = rows[by_both], k1[by_both], k2[by_both]
        pair = (k1[1:] == k1[:-1]) & (k2[1:] == k2[:-1])
        a, b = np.r_[a, rows[:-1][pair]], np.r_[b, rows[1:][pair]]
    nb[a] = b // nf
    nb[b] = a // nf
    return nb.reshape(m, nf)


def neighbour_materials(mesh: Mesh) -> np.ndarray:
    """The material label of the element across each face.

    Parameters
    ----------
    mesh : Mesh
        Any conforming mesh; a lattice grid serves when its elements are boxes of it.

    Returns
    -------
    (M, F) uint8, uint16 or int ndarray
        Label across faces S1..S6 (2D: edges S1..S4), 0 for none.
    """
    nb = _neighbour_materials_by_lattice(mesh)
    if nb is None:
        nb = materials_across(mesh.material, face_neighbours(np.asarray(mesh.cells, np.int64), mesh.dim,
                                                             mesh.n_points))
    return nb


def materials_across(material: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """The material label across each face, from the element across it.

    Parameters
    ----------
    material : (M,) int ndarray
        Label of every element.
    neighbours : (M, F) int ndarray
        Element across each face, -1 for none (:func:`face_neighbours`).

    Returns
    -------
    (M, F) ndarray of ``material``'s dtype
        Label across each face, 0 for none.
    """
    material = np.asarray(material)
    return np.where(neighbours >= 0, material[np.maximum(neighbours, 0)], 0).astype(material.dtype, copy=False)


def cavity_faces(points: np.ndarray, cells: np.ndarray, dim: int, elements: np.ndarray,
                 faces: np.ndarray) -> np.ndarray:
    """Which of the given free faces are walls of a cavity: a hole the material closes round.

    The free faces fall into surfaces joined at their edges (2D: sides joined at their nodes).
    A body's outer surface, its normals out of the material, encloses a positive volume; the
    wall of a cavity, its normals into the hole, a negative one. A body floating in a cavity
    faces the hole too: its surface counts with the walls when a ray from it crosses a wall an
    odd number of times. A surface that reaches a bounding plane of the image is closed by its
    faces on that plane, so a hole open to a cut plane counts as outside.

    Parameters
    ----------
    points : (N, 3) float ndarray
        Node coordinates (any frame, mm).
    cells : (M, c) int ndarray
        Hexahedra (c >= 8) or quads (c >= 4), corners first in VTK order, none inverted (the
        faces of :mod:`dicer.mesh.topology` then turn out of their element).
    dim : int
        3 or 2.
    elements, faces : (F,) int ndarray
        Element index and face number 0..5 (2D: 0..3) of each free face.

    Returns
    -------
    (F,) bool ndarray
        True for the faces of surfaces that enclose a negative volume (area in 2D), and of
        the surfaces inside those.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count = int(elements.size)
    if not count:
        return np.zeros(0, bool)
    table = HEX_FACES if dim == 3 else QUAD_EDGES
    nodes = np.asarray(cells)[elements[:, None], table[faces]].astype(np.int64)
    if dim == 3:  # faces that share an edge
        turn = np.roll(nodes, -1, axis=1)
        keys = (np.minimum(nodes, turn) * np.int64(points.shape[0]) + np.maximum(nodes, turn)).ravel()
    else:  # sides that share a node
        keys = nodes.ravel()
    owner = np.repeat(np.arange(count), nodes.shape[1])
    order = np.argsort(keys)  # equal keys side by side: any order among them links them
    keys, owner = keys[order], owner[order]
    linked = keys[1:] == keys[:-1]
    graph = coo_matrix((np.ones(int(linked.sum()), np.int8), (owner[:-1][linked], owner[1:][linked])),
                       shape=(count, count))
    surfaces, surface = connected_components(graph, directed=False)
    # each surface about its own first node, so a small cavity's volume is not lost to rounding
    _, first = np.unique(surface, return_index=True)
    xyz = np.asarray(points, float)[nodes]
    p = xyz - xyz[first[surface], :1]
    if dim == 3:  # the divergence theorem over the faces' two triangles
        measure = (np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2]))
                   + np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 2], p[:, 3]))) / 6.0
    else:
        measure = (p[:, 0, 0] * p[:, 1, 1] - p[:, 1, 0] * p[:, 0, 1]) / 2.0
    enclosed = np.bincount(surface, weights=measure, minlength=surfaces)
    mirrored = enclosed.sum() < 0  # the material's volume: corners in the mirrored order throughout
    wall = enclosed > 0 if mirrored else enclosed < 0
    bodies = np.flatnonzero(~wall)
    if wall.any() and bodies.size > 1:  # a body may float in a cavity: its surface faces the hole too
        # a point of each body's face that turns most to x, off its edges and diagonals: the
        # rays along x from it leave its plane and miss the lattice lines of the walls
        if dim == 3:
            facing = np.cross(xyz[:, 2] - xyz[:, 0], xyz[:, 3] - xyz[:, 1])
            facing = np.abs(facing[:, 0]) / np.maximum(norm(facing, axis=1), 1e-300)
        else:
            step = xyz[:, 1, :2] - xyz[:, 0, :2]
            facing = np.abs(step[:, 1]) / np.maximum(norm(step, axis=1), 1e-300)
        by = np.lexsort((-facing, surface))
        chosen = by[np.searchsorted(surface[by], bodies)]
        # (in a lattice face's two axes: fractions 0.68 / 0.46 / 0.32 / 0.54, neither equal
        # nor adding to 1, so off the lines between lattice points of small slope too)
        weights = np.array([0.41, 0.27, 0.19, 0.13] if dim == 3 else [0.37, 0.63])
        probes = np.einsum("bki,k->bi", xyz[chosen], weights)
        wall[bodies[_inside_walls(probes, xyz, surface, wall)]] = True
    return wall[surface]


def _inside_walls(probes: np.ndarray, corners: np.ndarray, surface: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """Whether each probe point lies inside any of the closed surfaces marked ``wall``.

    A ray from each probe along +x crosses a surface an odd number of times when the probe
    is inside it. The faces (3D: each quad's two triangles) are binned by their extent in
    y and z, so each probe meets only the faces its ray passes: the work follows the faces
    and the probes, not their product.

    probes : (B, 3); corners : (F, k, 3) every free face's corners (2D: a side's two, in x
    and y); surface : (F,) each face's surface; wall : (S,) bool, the surfaces to test.
    """
    faces = np.flatnonzero(wall[surface])
    quads = corners[faces]
    if dim3 := corners.shape[1] == 4:
        tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        owner = np.concatenate([surface[faces], surface[faces]])
        plane = (1, 2)
    else:
        tri, owner, plane = quads[:, :, :2], surface[faces], (1,)
    low, high = tri[:, :, plane].min(axis=1), tri[:, :, plane].max(axis=1)
    cell = max(float(np.mean(high - low)), 1e-300) * 2.0
    origin = low.min(axis=0)
    first_cell = np.floor((low - origin) / cell).astype(np.int64)
    span = np.floor((high - origin) / cell).astype(np.int64) - first_cell + 1
    width = int((first_cell[:, -1] + span[:, -1]).max()) + 1  # cells along z (2D: along y)
    # every (cell, face) the faces cover, sorted by cell
    count = span.prod(axis=1)
    face = np.repeat(np.arange(tri.shape[0]), count)
    step = np.arange(face.size) - np.repeat(np.cumsum(count) - count, count)
    if dim3:
        row, col = np.divmod(step, span[face, 1])
        key = (first_cell[face, 0] + row) * width + first_cell[face, 1] + col
    else:
        key = first_cell[face, 0] + step
    order = np.argsort(key, kind="stable")
    key, face = key[order], face[order]
    at = np.floor((probes[:, plane] - origin) / cell).astype(np.int64)
    inside_grid = np.all(at >= 0, axis=1) & (at[:, -1] < width)
    probe_key = at[:, 0] * width + at[:, 1] if dim3 else at[:, 0]
    lo, hi = np.searchsorted(key, probe_key, "left"), np.searchsorted(key, probe_key, "right")
    hi = np.where(inside_grid, hi, lo)
    found = hi - lo  # the faces in each probe's cell: face[lo:hi]
    probe = np.repeat(np.arange(probes.shape[0]), found)
    pair = face[np.arange(probe.size) - np.repeat(np.cumsum(found) - found, found) + np.repeat(lo, found)]
    p, t = probes[probe], tri[pair]
    if dim3:  # the probe's (y, z) in the triangle's projection, and the crossing ahead of it
        a, b, c = t[:, 0], t[:, 1], t[:, 2]

        def side(u, v):  # twice the signed area of (u, v, probe) in the y-z plane
            return (v[:, 1] - u[:, 1]) * (p[:, 2] - u[:, 2]) - (v[:, 2] - u[:, 2]) * (p[:, 1] - u[:, 1])

        w = np.column_stack([side(b, c), side(c, a), side(a, b)])
        area = w.sum(axis=1)
        hit = (area != 0) & (np.all(w > 0, axis=1) | np.all(w < 0, axis=1))
        x = (w[:, 0] * a[:, 0] + w[:, 1] * b[:, 0] + w[:, 2] * c[:, 0]) / np.where(area == 0, 1.0, area)
    else:  # the side spans the probe's y (half-open) and crosses ahead of it
        a, b = t[:, 0], t[:, 1]
        hit = (a[:, 1] > p[:, 1]) != (b[:, 1] > p[:, 1])
        dy = np.where(hit, b[:, 1] - a[:, 1], 1.0)
        x = a[:, 0] + (p[:, 1] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
    hit &= x > p[:, 0]
    crossings = probe[hit] * np.int64(wall.size) + owner[pair[hit]]
    keys, times = np.unique(crossings, return_counts=True)
    inside = np.zeros(probes.shape[0], bool)
    inside[keys[times % 2 == 1] // wall.size] = True
    return inside
