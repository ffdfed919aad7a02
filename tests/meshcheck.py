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
