"""Checks of meshes that several test modules share."""

import numpy as np

from dicer.export.stl import material_triangles, open_edges
from dicer.mesh.faces import neighbour_materials
from dicer.mesh.topology import QUAD_EDGES


def pinches(mesh):
    """Places where two elements of one material touch along an edge only (2D: at a node
    only): 3D, the edges of the materials' triangulated surfaces that do not close up
    (what ``dicer surface`` refuses); 2D, the nodes with more than two boundary edges of
    one material."""
    nb = neighbour_materials(mesh)
    kinds = np.unique(mesh.material)
    if mesh.dim == 3:
        return sum(open_edges(material_triangles(mesh, k, nb)) for k in kinds)
    count = 0
    for k in kinds:
        e, s = np.nonzero((mesh.material[:, None] == k) & (nb != k))
        ends = mesh.cells[e[:, None], QUAD_EDGES[s]]
        count += int(np.count_nonzero(np.bincount(ends.ravel()) > 2))
    return count


def exterior_pinches(mesh):
    """Edges (3D) or nodes (2D) of the whole mesh's exterior, all materials together, on
    more than two exterior faces: where the exterior surface touches itself."""
    from dicer.mesh.faces import face_neighbours
    from dicer.mesh.topology import HEX_FACES

    cells = np.asarray(mesh.cells, np.int64)
    e, s = np.nonzero(face_neighbours(cells, mesh.dim, mesh.n_points) < 0)
    if mesh.dim == 2:
        return int(np.count_nonzero(np.bincount(cells[e[:, None], QUAD_EDGES[s]].ravel()) > 2))
    f = cells[e[:, None], HEX_FACES[s]]
    edges = np.sort(np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2), axis=1)
    return int(np.count_nonzero(np.unique(edges, axis=0, return_counts=True)[1] > 2))


def node_pinches(mesh):
    """Nodes where a material's surface (3D) is pinched: its faces around the node form two
    fans or more, which meet at the node only (the paper's type B). Each fan is followed by
    hand, face to face across the edges at the node."""
    from dicer.mesh.topology import HEX_FACES

    cells, material = np.asarray(mesh.cells), np.asarray(mesh.material)
    count = 0
    for k in np.unique(material):
        faces = cells[material == k][:, HEX_FACES].reshape(-1, 4)
        key, seen = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
        boundary = [tuple(f) for f in faces if seen[np.searchsorted(
            key.view([("", key.dtype)] * 4).ravel(), np.sort(f).view([("", key.dtype)] * 4))][0] == 1]
        around = {}
        for f in boundary:
            for i, v in enumerate(f):
                around.setdefault(v, []).append({f[i - 1], f[(i + 1) % 4]})
        for v, ends in around.items():
            fans, left = 0, list(range(len(ends)))
            while left:
                fans += 1
                reach = set(ends[left.pop()])
                grew = True
                while grew:
                    grew = False
                    for j in list(left):
                        if ends[j] & reach:
                            reach |= ends[j]
                            left.remove(j)
                            grew = True
            count += fans > 1
    return count


def meshio_vtu_with_grid(mesh, path, meshio_mesh=None):
    """``mesh`` written by meshio's VTU writer (zlib), as dicer wrote VTU files until its own
    writer, with the grid's field data put in after <UnstructuredGrid> (meshio's writer drops
    field data; its reader keeps it): the files of earlier dicer versions. ``meshio_mesh``: the
    meshio mesh to write instead of ``to_meshio(mesh)`` (changed data)."""
    import shutil

    import meshio

    from dicer.io.meshes import _field_data_xml, to_meshio

    raw = path.with_suffix(".raw.vtu")
    meshio.write(raw, to_meshio(mesh) if meshio_mesh is None else meshio_mesh, binary=True, compression="zlib")
    with open(raw, "rb") as src, open(path, "wb") as dst:
        head = src.read(4096)
        tag = b"<UnstructuredGrid>\n"
        at = head.index(tag) + len(tag)
        dst.write(head[:at] + _field_data_xml(mesh).encode() + head[at:])
        shutil.copyfileobj(src, dst, 1 << 22)
    return raw
