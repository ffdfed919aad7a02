"""A pillow layer: one layer of new elements over a mesh's exterior surface.

On a voxel staircase the elements at convex corners have two or three faces on the
surface. Placed on a smooth surface such an element goes flat at its corner, so the
smoothing keeps a kink there (the quality guard, the sub-voxel pull's ``lift``). With one
new element on every exterior face, every element at the surface has exactly one face on
it: the surface nodes can lie on the smooth surface while the elements under the layer
keep the shape the smoothing gave them. The layer is the pillowing of hexahedral meshing
(docs/smoothing.md §3b).

Faces in a bounding plane of the image (a cut or symmetry plane) get no element: the layer
meets such a plane at right angles, its nodes there stay in the plane.
"""

from __future__ import annotations

import numpy as np

from dicer.arrays import all_per_row, nonzero, norm
from dicer.mesh.faces import face_neighbours
from dicer.mesh.topology import HEX_FACES, QUAD_EDGES

__all__ = ["surface_faces", "outward_normals", "pillow_cells", "one_fan_per_node"]


def surface_faces(cells: np.ndarray, dim: int, n_points: int, planes: np.ndarray,
                  boundary: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The exterior faces that lie in no bounding plane, wound outward.

    Parameters
    ----------
    cells : (M, 8) or (M, 4) int ndarray
        Hexahedra or quads, VTK corner order.
    dim : int
        3 or 2.
    n_points : int
        Number of nodes.
    planes : (N,) uint8 ndarray
        Bounding planes of every node (:func:`dicer.mesh.boundary.plane_bits`).
    boundary : ((B,) int ndarray, (E,) int ndarray), optional
        Nodes among which every exterior node is, and the sorted elements holding one of
        them: the faces whose nodes are all such nodes are found among those elements alone,
        as every element at such a face holds it (None: all elements).

    Returns
    -------
    faces : (F, 4) or (F, 2) int64 ndarray
        Node ids of each face (2D: edge), counter-clockwise seen from outside (2D: the
        element on the left), in element order, then face order.
    owner : (F,) int64 ndarray
        The element each face belongs to.
    """
    table = HEX_FACES if dim == 3 else QUAD_EDGES
    if boundary is None:
        cells = np.asarray(cells, np.int64)
        owner, slot = nonzero(face_neighbours(cells, dim, n_points) < 0)
    else:
        nodes, elements = boundary
        cells = np.asarray(cells[elements], np.int64)
        owner, slot = nonzero(face_neighbours(cells, dim, n_points) < 0)
        mark = np.zeros(n_points, bool)
        mark[nodes] = True
        whole = all_per_row(mark[cells[owner[:, None], table[slot]]])
        owner, slot = owner[whole], slot[whole]
    faces = cells[owner[:, None], table[slot]]
    in_plane = np.bitwise_and.reduce(planes[faces], axis=1) != 0
    if boundary is not None:
        owner = np.asarray(boundary[1], np.int64)[owner]
    return faces[~in_plane], owner[~in_plane]


_SEEN_FROM = 0.5  # cosine of the angle a direction keeps from every face normal at its node, where it can
_DIRECTION_ROUNDS = 10


def outward_normals(points: np.ndarray, faces: np.ndarray, nodes: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Unit outward directions at surface nodes, along which the layer grows.

    The faces' area vectors summed at their nodes, then turned towards the unit normal of
    every face at the node that the direction makes an angle of more than 60 degrees with
    (a few rounds): at a sharp or folded part of the surface the plain sum can point
    almost along a face, and an element grown from that face along it is flat.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Node positions, mm.
    faces : (F, 4) or (F, 2) int ndarray
        From :func:`surface_faces`.
    nodes : (P,) int64 ndarray
        The faces' nodes, ascending.
    held : (P, 3) bool ndarray
        Coordinates a node keeps (its bounding planes' axes, z in 2D): the normal has no
        component along them, so a node on a plane moves in the plane.

    Returns
    -------
    (P, 3) float64 ndarray
        Rows of length 1 (0 where the faces' vectors cancel).
    """
    p = points
    if faces.shape[1] == 4:  # the cross product of the diagonals: twice the area vector
        a, b, c, d = (p[faces[:, i]] for i in range(4))
        area = np.cross(c - a, d - b)
    else:  # an edge with the element on its left: outward is to its right
        e = p[faces[:, 1]] - p[faces[:, 0]]
        area = np.column_stack([e[:, 1], -e[:, 0], np.zeros(len(e))])
    at = np.searchsorted(nodes, faces)

    def at_nodes(weights):  # (F, k) weights of the faces' unit vectors, summed at their nodes
        return np.stack([np.bincount(at.ravel(), weights=(weights * unit[:, None, k]).ravel(), minlength=nodes.size)
                         for k in range(3)], axis=1).astype(float)  # (bincount of nothing is integer)

    def normalised(v):
        v[held] = 0.0
        length = norm(v, axis=1, keepdims=True)
        return np.divide(v, length, out=np.zeros_like(v), where=length > 0)

    size = norm(area, axis=1)
    unit = area / np.maximum(size, 1e-300)[:, None]
    normal = normalised(at_nodes(np.repeat(size[:, None], faces.shape[1], axis=1)))
    for _ in range(_DIRECTION_ROUNDS):
        shortfall = np.maximum(_SEEN_FROM - np.einsum("fk,fjk->fj", unit, normal[at]), 0.0)
        if not shortfall.any():
            break
        normal = normalised(normal + at_nodes(shortfall))
    return normal


def pillow_cells(faces: np.ndarray, new_id: np.ndarray) -> np.ndarray:
    """The layer's elements: each face joined to its nodes' copies.

    Parameters
    ----------
    faces : (F, 4) or (F, 2) int64 ndarray
        From :func:`surface_faces`.
    new_id : (N,) int64 ndarray
        The copy of every surface node (the new surface node), -1 for others.

    Returns
    -------
    (F, 8) or (F, 4) int64 ndarray
        Hexahedra (the face as the bottom, wound towards its copy above) or quads
        (edge a-b: b, a, a', b'), VTK order, positive when the copies lie outside.
    """
    if faces.shape[1] == 4:
        return np.concatenate([faces, new_id[faces]], axis=1)
    a, b = faces[:, 0], faces[:, 1]
    return np.column_stack([b, a, new_id[a], new_id[b]])


def one_fan_per_node(faces: np.ndarray, kept: np.ndarray, material: np.ndarray) -> np.ndarray:
    """The faces of the layer with, at every node, one fan of faces, and of each material's.

    All new elements at a node share the edge from the node to its copy. Two that no chain
    of faces (joined by their edges) links share only that edge: the exterior would be
    pinched along it, four faces at one edge (a gap in the layer around the node, or a
    surface that touches itself there). Two of one material that no chain of that
    material's faces links would leave the material's surface open (another material's
    face between them). At such a node the faces of all but the largest fan lose their
    element (ties: the fan of the lowest face), first of the fans of all materials
    together, then of each material's; repeated until every node has one fan. An edge of
    more than two faces joins none of them. 2D (edges): unchanged.

    Parameters
    ----------
    faces : (F, 4) or (F, 2) int64 ndarray
        From :func:`surface_faces`.
    kept : (F,) bool ndarray
        Faces with an element of the layer.
    material : (F,) int ndarray
        The material of each face's element.

    Returns
    -------
    (F,) bool ndarray
        ``kept`` with the faces of the other fans dropped.
    """
    kept = kept.copy()
    if faces.shape[1] != 4:
        return kept
    n = np.int64(faces.max(initial=0)) + 1
    nxt = np.array([1, 2, 3, 0])
    while True:
        idx = np.flatnonzero(kept)
        if idx.size == 0:
            return kept
        f = faces[idx].astype(np.int64)
        mat = np.asarray(material)[idx].astype(np.int64)
        k = f.shape[0] * 4
        key = (np.minimum(f, f[:, nxt]) * n + np.maximum(f, f[:, nxt])).ravel()  # edge j: corners j, j + 1
        order = np.argsort(key, kind="stable")
        sk = key[order]
        start = np.r_[True, sk[1:] != sk[:-1]]
        group = np.cumsum(start) - 1
        pair = np.flatnonzero(~start[1:] & (np.bincount(group)[group[1:]] == 2))  # sorted i, i + 1: the two
        p, q = order[pair], order[pair + 1]  # edge slots: face * 4 + corner
        p_next, q_next = p - p % 4 + nxt[p % 4], q - q % 4 + nxt[q % 4]
        same = f.ravel()[p] == f.ravel()[q]  # both faces run the edge the same way
        a = np.r_[p, p_next]
        b = np.r_[np.where(same, q, q_next), np.where(same, q_next, q)]
        one_kind = np.tile(mat[p // 4] == mat[q // 4], 2)
        node, kind, face = f.ravel(), np.repeat(mat, 4), np.arange(k) // 4
        drop = _smaller_fans(node, np.zeros(k, np.int64), face, _fans(a, b, k))
        if drop.size == 0:
            drop = _smaller_fans(node, kind, face, _fans(a[one_kind], b[one_kind], k))
        if drop.size == 0:
            return kept
        kept[idx[drop]] = False


def _fans(a: np.ndarray, b: np.ndarray, k: int) -> np.ndarray:
    """(k,) the fan of every face corner, corners ``a`` and ``b`` joined."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(k, k))
    return connected_components(graph, directed=True, connection="weak")[1]


def _smaller_fans(node: np.ndarray, kind: np.ndarray, face: np.ndarray, fan: np.ndarray) -> np.ndarray:
    """The faces of every fan but the largest of its (node, kind) (ties: the lowest face's)."""
    by = np.lexsort((face, fan, kind, node))
    node, kind, fan, face = node[by], kind[by], fan[by], face[by]
    head = np.r_[True, (node[1:] != node[:-1]) | (kind[1:] != kind[:-1]) | (fan[1:] != fan[:-1])]
    lead = np.flatnonzero(head)
    size = np.diff(np.r_[lead, node.size])
    g_node, g_kind, g_face = node[lead], kind[lead], face[lead]  # g_face: the fan's lowest face
    pick = np.lexsort((g_face, -size, g_kind, g_node))
    best = np.r_[True, (g_node[pick][1:] != g_node[pick][:-1]) | (g_kind[pick][1:] != g_kind[pick][:-1])]
    loses = np.zeros(lead.size, bool)
    loses[pick[~best]] = True
    return np.unique(face[loses[np.cumsum(head) - 1]])
