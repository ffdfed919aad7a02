"""Element topology: the corner, edge and face tables of the hexahedron and the quad.

Every table indexes corners in VTK order, which is also the node order of Abaqus
(C3D8, CPS4, ...)::

        7-------6          3-------2
       /|      /|          |       |
      4-------5 |          |       |      y
      | 3-----|-2          0-------1      |  z
      |/      |/                          | /
      0-------1                           |/____ x

Corner c of an element sits at lattice offset ``HEX_CORNERS[c]`` (``QUAD_CORNERS[c]``)
from corner 0, so for an element of positive Jacobian:

* edges run from their lower-numbered end in the order of the mid-edge nodes of the
  quadratic elements (nodes 8..19 of the 20-node hexahedron, 4..7 of the 8-node quad);
* faces come in the Abaqus order S1..S6 and are wound outward by the right-hand rule
  (counter-clockwise seen from outside the element); Abaqus lists the same faces the
  other way round, ``HEX_FACES[:, [0, 3, 2, 1]]``. A quad's sides S1..S4 are its edges,
  which run counter-clockwise around it.

This module depends on numpy only, so every part of dicer can import it.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "HEX_CORNERS", "QUAD_CORNERS",
    "HEX_EDGES", "QUAD_EDGES", "HEX_EDGE_AXES", "QUAD_EDGE_AXES",
    "HEX_CORNER_NEIGHBOURS", "QUAD_CORNER_NEIGHBOURS", "HEX_AXIS_CORNERS", "QUAD_AXIS_CORNERS",
    "HEX_FACES", "HEX_FACE_EDGES", "QUAD_SIDE_EDGES", "HEX_FACE_PLANES", "QUAD_SIDE_PLANES",
    "HEX20_FACES", "QUAD8_SIDES", "HEX20_EXODUS",
    "HEX_MIRROR", "HEX20_MIRROR", "HEX_FACE_MIRROR", "HEX_REVERSED", "QUAD_REVERSED",
    "MESHIO_TYPES",
]

# --- corners -------------------------------------------------------------------------------

HEX_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.int64
)
"""(8, 3) int64: lattice offsets of the 8 corners of a hexahedron in VTK (and Abaqus C3D8) order."""

QUAD_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.int64)
"""(4, 3) int64: lattice offsets of the 4 corners of a quad in VTK (and Abaqus CPS4) order (z = 0)."""

# --- edges ---------------------------------------------------------------------------------

HEX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])
"""(12, 2): end corners of the 12 edges of a hexahedron: the bottom face's edges and the top
face's, each counter-clockwise seen from +z, then the vertical edges upward. Row e is the
edge of node 8 + e of a 20-node hexahedron (VTK and Abaqus C3D20)."""

QUAD_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
"""(4, 2): end corners of the 4 edges of a quad, counter-clockwise, so each edge runs with
the element on its left. Row e is the edge of node 4 + e of an 8-node quad, and the side
S(e + 1) of the Abaqus element."""

HEX_EDGE_AXES = np.array([0, 1, 0, 1, 0, 1, 0, 1, 2, 2, 2, 2])
"""(12,): lattice axis (0 x, 1 y, 2 z) each edge of ``HEX_EDGES`` runs along."""

QUAD_EDGE_AXES = np.array([0, 1, 0, 1])
"""(4,): lattice axis (0 x, 1 y) each edge of ``QUAD_EDGES`` runs along."""

HEX_CORNER_NEIGHBOURS = np.array(
    [[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]]
)
"""(8, 3): for each hexahedron corner, the three corners its edges run to, in right-handed
order, so the triple product of the three edge vectors is the Jacobian at the corner."""

QUAD_CORNER_NEIGHBOURS = np.array([[1, 3], [2, 0], [3, 1], [0, 2]])
"""(4, 2): for each quad corner, the two corners its edges run to, counter-clockwise, so the
cross product of the two edge vectors is the Jacobian at the corner."""

HEX_AXIS_CORNERS = {
    0: (np.array([0, 3, 4, 7]), np.array([1, 2, 5, 6])),
    1: (np.array([0, 1, 4, 5]), np.array([3, 2, 7, 6])),
    2: (np.array([0, 1, 2, 3]), np.array([4, 5, 6, 7])),
}
"""axis -> (low corners (4,), high corners (4,)) of a hexahedron: the corners at lattice
offset 0 and 1 along the axis, paired so that low[i] and high[i] are the two ends of one
edge parallel to the axis."""

QUAD_AXIS_CORNERS = {
    0: (np.array([0, 3]), np.array([1, 2])),
    1: (np.array([0, 1]), np.array([3, 2])),
}
"""axis -> (low corners (2,), high corners (2,)) of a quad, paired as in ``HEX_AXIS_CORNERS``."""

# --- faces ---------------------------------------------------------------------------------

HEX_FACES = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])
"""(6, 4): corners of the faces S1..S6 of a hexahedron (bottom, top, then the sides
y = 0, x = 1, y = 1, x = 0), wound outward by the right-hand rule. Each starts at the first
corner of the Abaqus face; the Abaqus winding (inward) is ``HEX_FACES[:, [0, 3, 2, 1]]``."""

HEX_FACE_EDGES = np.array([[3, 2, 1, 0], [4, 5, 6, 7], [0, 9, 4, 8], [1, 10, 5, 9], [2, 11, 6, 10], [3, 8, 7, 11]])
"""(6, 4): rows of ``HEX_EDGES`` around each face of ``HEX_FACES``; edge j of face f joins
corners j and j + 1 (mod 4) of ``HEX_FACES[f]``."""

QUAD_SIDE_EDGES = np.array([[0], [1], [2], [3]])
"""(4, 1): rows of ``QUAD_EDGES`` along each side S1..S4 of a quad (a side is one edge)."""

HEX_FACE_PLANES = [(2, 0), (2, 1), (1, 0), (0, 1), (1, 1), (0, 0)]
"""(axis, side) of the lattice plane each face S1..S6 of a box-shaped hexahedron lies in:
normal to ``axis``, on the element's low (0) or high (1) end along it."""

QUAD_SIDE_PLANES = [(1, 0), (0, 1), (1, 1), (0, 0)]
"""(axis, side) of the lattice line each side S1..S4 of a box-shaped quad lies on: normal to
``axis``, on the element's low (0) or high (1) end along it."""

HEX20_FACES = np.column_stack([HEX_FACES, 8 + HEX_FACE_EDGES])
"""(6, 8): nodes of the faces S1..S6 of a 20-node hexahedron, the 4 corners of ``HEX_FACES``
then the mid-edge nodes of its edges in the same (outward) order: an outward 8-node quad."""

QUAD8_SIDES = np.column_stack([QUAD_EDGES, 4 + QUAD_SIDE_EDGES])
"""(4, 3): nodes of the sides S1..S4 of an 8-node quad: the two ends, then the mid-edge node."""

HEX20_EXODUS = np.r_[0:8, 8:12, 16:20, 12:16]
"""(20,): position in the VTK (Abaqus) 20-node order of each node of the 20-node hexahedron
of Exodus II and PATRAN, which put the vertical edges' nodes before the top face's."""

# --- corner permutations -------------------------------------------------------------------

HEX_MIRROR = np.array([4, 5, 6, 7, 0, 1, 2, 3])
"""(8,): corner order of a mirrored 8-node hexahedron: bottom and top face swap, so an
element turned inside out by a reflection has a positive Jacobian again."""

HEX20_MIRROR = np.r_[HEX_MIRROR, [12, 13, 14, 15, 8, 9, 10, 11, 16, 17, 18, 19]]
"""(20,): the same for the 20-node hexahedron: the mid-edge nodes of the two faces swap too."""

HEX_FACE_MIRROR = np.array([0, 2, 1, 3, 4, 5, 6])
"""(7,): face number S1..S6 of a hexahedron -> its number after ``HEX_MIRROR`` (index 0
unused): S1 and S2 (bottom and top) swap, the side faces keep their numbers."""

HEX_REVERSED = np.array([0, 3, 2, 1, 4, 7, 6, 5])
"""(8,): corner order that turns an inside-out hexahedron right side out: corners 1 and 3,
5 and 7 swap (a reflection through the diagonal plane of corners 0, 2, 4, 6)."""

QUAD_REVERSED = np.array([0, 3, 2, 1])
"""(4,): corner order that turns an inside-out quad right side out (corners 1 and 3 swap)."""

# --- names ---------------------------------------------------------------------------------

MESHIO_TYPES = {(3, 1): "hexahedron", (3, 2): "hexahedron20", (2, 1): "quad", (2, 2): "quad8"}
"""(dimension, order) -> meshio cell type name; the node order of each is VTK's."""
