"""One mesh data model for every stage.

Index convention used throughout dicer: image arrays are indexed ``[x, y, z]``
(``[x, y]`` in 2D) and a node's ``lattice`` index ``(i, j, k)`` is the voxel corner
``origin + (i, j, k) * spacing`` before any smoothing moves it. Every stage works in
this axis-aligned *lattice frame*; ``direction`` (when set) says how the exports turn it
into scanner coordinates (:mod:`dicer.mesh.frame`, docs/coordinates.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from dicer.parallel import ordered_map
from dicer.mesh.topology import HEX_CORNERS, MESHIO_TYPES, QUAD_CORNERS  # noqa: F401  (corners re-exported)

LEVEL_DATA = "coarsening_level"
"""Cell data of graded meshes ('dicer merge' with merge.method=templates): 0 for an element
of one voxel, l for an element made at level l (a coarse cell or part of a transition
template: 2D cells of 3**l voxels a side; 3D cells grow by three along one axis per step,
3**l voxels a side once the level's three steps are done). Every node of an element with level > 0 is an interior node: such
elements lie inside one material, away from every boundary and interface."""

GRID_FIELDS = ("spacing", "origin", "grid_shape", "direction", "scanner_coordinates")
"""Field data of dicer's mesh files that hold the grid, not a material's name."""

CHUNK = 1 << 18
"""Rows (elements, nodes or index entries) per pass of the loops that work in pieces: the
pieces' temporaries stay small and are reused."""


def pieces(n: int, size: int = CHUNK) -> Iterator[slice]:
    """The slices ``[0:size]``, ``[size:2 size]``, ... that cover ``range(n)``.

    Parameters
    ----------
    n : int
        Number of rows.
    size : int, optional
        Rows per piece.

    Yields
    ------
    slice
        One piece of rows; the last may be shorter.
    """
    for start in range(0, n, size):
        yield slice(start, start + size)


class Sized:
    """``n_points`` and ``n_cells`` of a class with ``points`` and ``cells`` arrays."""

    points: np.ndarray
    cells: np.ndarray

    @property
    def n_points(self) -> int:
        """Number of nodes."""
        return int(self.points.shape[0])

    @property
    def n_cells(self) -> int:
        """Number of elements."""
        return int(self.cells.shape[0])


@dataclass
class Mesh(Sized):
    """A linear all-hexahedral (3D) or all-quad (2D) mesh.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Node coordinates, mm (z = 0 in 2D).
    cells : (M, 8) or (M, 4) int64 or int32 ndarray
        Hexahedra or quads, VTK corner order, 0-based: int32 from the voxel mesher and
        plane merging while the node numbers fit (:func:`dicer.mesh.voxel.voxel_mesh`,
        :func:`dicer.mesh.merge.merge_planes`) and, read-only, when read mapped from a
        dicer VTU (:func:`dicer.io.meshes.read_mesh`); int64 otherwise.
    material : (M,) int32 ndarray
        Class label 1..K of each element.
    lattice : (N, 3) int64 ndarray
        Integer voxel-corner index of each node (k = 0 in 2D).
    spacing, origin : (3,) float64 ndarray
        Voxel size and position of lattice (0, 0, 0), mm.
    grid_shape : (3,) int64 ndarray
        Voxels per axis of the source image (1 for z in 2D); its bounding planes are
        lattice 0 and grid_shape along each axis.
    point_data, cell_data : dict of str to ndarray, optional
        Further per-node / per-element arrays carried through.
    names : list of str, optional
        Material names by label (names[0] is label 1's), written to VTU files as one
        field data array per material so ParaView shows them; empty when unknown.
    direction : (3, 3) float64 ndarray, optional
        Direction cosines of the source image (column j: scanner direction of index
        axis j), or None (identity, 2D, or mesh.coordinates: index). ``points`` stay in
        the lattice frame; the exports apply it.
    scanner : bool, optional
        True when ``points`` and ``cells`` are already in the scanner frame (an exported
        model.vtu): reading such a file turns it back into the lattice frame.
    """

    points: np.ndarray
    cells: np.ndarray
    material: np.ndarray
    lattice: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    grid_shape: np.ndarray
    point_data: dict[str, np.ndarray] = field(default_factory=dict)
    cell_data: dict[str, np.ndarray] = field(default_factory=dict)
    names: list[str] = field(default_factory=list)
    direction: np.ndarray | None = None
    scanner: bool = False

    @property
    def dim(self) -> int:
        """2 for a quad mesh, 3 for a hexahedral mesh."""
        return 3 if self.cells.shape[1] == 8 else 2

    @property
    def cell_type(self) -> str:
        """meshio's name of the element type."""
        return MESHIO_TYPES[(self.dim, 1)]

    def copy(self) -> "Mesh":
        """A deep copy: every array and list copied."""
        return Mesh(
            self.points.copy(), self.cells.copy(), self.material.copy(), self.lattice.copy(),
            self.spacing.copy(), self.origin.copy(), self.grid_shape.copy(),
            {k: v.copy() for k, v in self.point_data.items()},
            {k: v.copy() for k, v in self.cell_data.items()}, list(self.names),
            None if self.direction is None else self.direction.copy(), self.scanner,
        )


def is_graded(mesh: "Mesh") -> bool:
    """Whether a mesh has coarse cells or transition templates (graded coarsening).

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    bool
        True where any element's :data:`LEVEL_DATA` is above 0.
    """
    level = mesh.cell_data.get(LEVEL_DATA)
    return level is not None and bool(np.any(np.asarray(level) > 0))


def nodes_off_lattice(mesh: "Mesh") -> int:
    """How many nodes lie away from their lattice point (``origin + spacing * lattice``):
    none in a voxel or plane-merged mesh, most boundary nodes of a smoothed one. Nodes
    between lattice points (index -1, transition templates) are not counted.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    int
    """
    lattice = np.asarray(mesh.lattice)
    spacing, origin = np.asarray(mesh.spacing, float), np.asarray(mesh.origin, float)
    reach = float(np.abs(origin).max(initial=0)) + float((spacing * np.asarray(mesh.grid_shape)).max(initial=0))
    tolerance = 1e-9 * max(1.0, reach)  # rounding of origin + spacing * index, not a move
    points = np.asarray(mesh.points)

    def count(part: slice) -> int:  # a column at a time: no (n, 3) temporaries
        away, placed = None, None
        for a in range(3):
            index = lattice[part, a]
            moved = np.abs(points[part, a] - (index * spacing[a] + origin[a])) > tolerance
            away = moved if away is None else away | moved
            placed = index >= 0 if placed is None else placed & (index >= 0)
        return int(np.count_nonzero(away & placed))

    return sum(ordered_map(count, pieces(mesh.n_points)))  # both cores: a pass over every node

