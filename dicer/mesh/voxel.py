"""Voxel hexahedral meshing (VHM): one element per non-background voxel."""

from __future__ import annotations

import numpy as np

from dicer.arrays import nonzero
from dicer.config import takes_settings
from dicer.errors import DicerError
from dicer.mesh.frame import check_direction
from dicer.mesh.model import Mesh
from dicer.mesh.topology import HEX_CORNERS, QUAD_CORNERS
from dicer.pages import ordinary_pages

_BLOCK = 1 << 16
"""Grid points per slab of x planes: a slab's temporaries stay in cache."""


def voxel_mesh(labels: np.ndarray, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), direction=None) -> Mesh:
    """Mesh every non-zero voxel of ``labels`` as one hexahedron (a quad in 2D).

    Nodes are shared between neighbouring elements and numbered in C order of their
    lattice index; elements are in C order of their voxel.

    Parameters
    ----------
    labels : (nx, ny, nz) or (nx, ny) int ndarray
        0 background, 1..K material.
    spacing, origin : sequence of float, optional
        Voxel size and image origin (``Volume.origin``), mm (2 or 3 values).
    direction : sequence of 9 float, optional
        Direction cosines (ITK order, row-major) of a 3D image; kept in the mesh for the
        exports (scanner coordinates), the nodes stay in the lattice frame.

    Returns
    -------
    Mesh
        Its ``cells`` int32 while the node numbers fit (below 2**31 - 1 nodes), else int64.
    """
    labels = np.asarray(labels)
    if labels.ndim not in (2, 3):
        raise DicerError(f"labels have {labels.ndim} dimensions; a 2D or 3D label image is needed")
    if not np.issubdtype(labels.dtype, np.integer):
        raise DicerError(f"labels have dtype {labels.dtype}; an integer label image is needed")
    dim = labels.ndim
    direction = check_direction(direction, dim)
    spacing3 = np.ones(3)
    origin3 = np.zeros(3)
    spacing3[:dim] = np.asarray(spacing, dtype=float)[:dim]
    origin3[:dim] = np.asarray(origin, dtype=float)[:dim]
    vol = labels if dim == 3 else labels[:, :, None]
    corners = HEX_CORNERS if dim == 3 else QUAD_CORNERS
    grid_shape = np.array(vol.shape, dtype=np.int64)

    solid = vol != 0
    if not solid.any():
        raise DicerError("the label image has no non-background voxel; nothing to mesh")
    with ordinary_pages():  # fresh huge pages are slow to come by on virtual machines (dicer.pages)
        points, cells, lattice = _hexahedra(solid, corners, spacing3, origin3)
        material = vol[solid].astype(np.int32)
    return Mesh(points, cells, material, lattice, spacing3, origin3, grid_shape, direction=direction)


def _hexahedra(solid: np.ndarray, corners: np.ndarray, spacing3: np.ndarray, origin3: np.ndarray):
    """Points, cells and lattice of the voxel mesh of the (nx, ny, nz) mask ``solid``.

    Works slab by slab of x planes (no loop over voxels): every output array is written
    once, in order, and the temporaries are a slab's size.
    """
    nx, ny, nz = solid.shape
    flat = bool(corners[:, 2].max() == 0)  # quads: the node grid has a single z layer
    node_shape = (nx + 1, ny + 1, 1 if flat else nz + 1)

    # voxel (i, j, k) is anchored at grid point (i, j, k), its corner 0; a grid point is a
    # node when a solid voxel has it as a corner: the anchors dilated by one along +x, +y, +z
    anchor = np.zeros(node_shape, dtype=bool)
    anchor[:nx, :ny, :nz] = solid
    used = anchor.copy()
    used[1:] |= anchor[:-1]
    used[:, 1:] |= used[:, :-1].copy()
    if not flat:
        used[:, :, 1:] |= used[:, :, :-1].copy()

    # nodes are numbered in C order of the grid: x plane p starts after all nodes of planes < p
    plane_start = np.zeros(node_shape[0] + 1, dtype=np.int64)
    np.cumsum(np.count_nonzero(used.reshape(node_shape[0], -1), axis=1), out=plane_start[1:])
    n_nodes = int(plane_start[-1])

    # corner c of the voxel anchored at flat grid index f is the node at flat index f + offset[c]
    plane = node_shape[1] * node_shape[2]
    offset = corners @ np.array([plane, node_shape[2], 1], dtype=np.int64)
    step = max(1, _BLOCK // plane)  # x planes per slab
    # Int32 node numbers while they fit: half the fresh memory of Int64 (the files hold Int32)
    index = np.int32 if n_nodes < 2**31 - 1 else np.int64
    cells = np.empty((int(np.count_nonzero(solid)), len(corners)), dtype=index)
    node_id = np.empty((step + 1) * plane, dtype=index)  # node number of each grid point of a slab
    row = 0
    for x0 in range(0, nx, step):
        x1 = min(nx, x0 + step)
        window = used[x0 : x1 + 1].reshape(-1)  # the slab's node planes and the next one
        node_id[: window.size][window] = np.arange(plane_start[x0], plane_start[x1 + 1], dtype=index)
        first = np.flatnonzero(anchor[x0:x1])
        np.take(node_id, first[:, None] + offset, out=cells[row : row + first.size], mode="clip")
        row += first.size
    del node_id, anchor

    lattice = np.empty((n_nodes, 3), dtype=np.int64)
    points = np.empty((n_nodes, 3), dtype=np.float64)
    coordinate = [origin3[axis] + spacing3[axis] * np.arange(node_shape[axis]) for axis in range(3)]
    for x0 in range(0, node_shape[0], step):
        x1 = min(node_shape[0], x0 + step)
        index = nonzero(used[x0:x1])
        rows = slice(plane_start[x0], plane_start[x1])
        for axis in range(3):
            np.add(index[axis], x0 if axis == 0 else 0, out=lattice[rows, axis])
            np.take(coordinate[axis], lattice[rows, axis], out=points[rows, axis], mode="clip")
    return points, cells, lattice


@takes_settings("mesh")
def mesh_labels(labels, *, names: list[str], coordinates: str) -> Mesh:
    """The mesh stage: :func:`voxel_mesh` of a label volume, with the material names.

    The settings are keyword-only with no defaults here: the command line passes
    ``dicer.config.stage_kwargs(config, "mesh")``; a library call may give a
    configuration as the second argument instead, or leave settings out (the schema's
    defaults fill them, :func:`dicer.config.takes_settings`).

    Parameters
    ----------
    labels : dicer.image.Volume
        Label volume, 0 background, 1..K materials.
    names : list of str
        The material names (the ``materials`` section); label i is ``names[i - 1]``.
    coordinates : {"scanner", "index"}
        ``mesh.coordinates``: scanner keeps the image's direction cosines for the
        exports, index drops them.

    Returns
    -------
    Mesh
    """
    direction = labels.direction if coordinates == "scanner" else None
    mesh = voxel_mesh(labels.array, labels.spacing, labels.origin, direction)
    mesh.names = list(names)
    return mesh
