"""Voxel hexahedral meshing (VHM): one element per non-background voxel."""

from __future__ import annotations

import numpy as np

from dicer.errors import DicerError
from dicer.mesh.model import HEX_CORNERS, QUAD_CORNERS, Mesh


def voxel_mesh(labels: np.ndarray, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)) -> Mesh:
    """Mesh every non-zero voxel of ``labels`` as one hexahedron (a quad in 2D).

    labels : (nx, ny, nz) or (nx, ny) integer array, 0 = background, 1..K = material.
    spacing, origin : voxel size and image origin in mm (2 or 3 values).
    Returns a Mesh whose nodes are shared between neighbouring elements, numbered
    in C order of their lattice index; elements are in C order of their voxel.
    """
    labels = np.asarray(labels)
    if labels.ndim not in (2, 3):
        raise DicerError(f"labels have {labels.ndim} dimensions; a 2D or 3D label image is needed")
    if not np.issubdtype(labels.dtype, np.integer):
        raise DicerError(f"labels have dtype {labels.dtype}; an integer label image is needed")
    dim = labels.ndim
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
    nx, ny, nz = vol.shape
    node_shape = (nx + 1, ny + 1, nz + 1) if dim == 3 else (nx + 1, ny + 1, 1)
    used = np.zeros(node_shape, dtype=bool)
    for dx, dy, dz in corners:
        used[dx : dx + nx, dy : dy + ny, dz : dz + nz] |= solid

    n_nodes = int(np.count_nonzero(used))
    node_id = np.cumsum(used.ravel(), dtype=np.int64).reshape(node_shape)
    node_id -= 1  # node_id at a used grid point is its node number (C order)

    # corner c of every element: the node grid shifted by c, read where a voxel is solid
    cells = np.empty((int(np.count_nonzero(solid)), len(corners)), dtype=np.int64)
    for c, (dx, dy, dz) in enumerate(corners):
        cells[:, c] = node_id[dx : dx + nx, dy : dy + ny, dz : dz + nz][solid]
    del node_id

    index = np.nonzero(used)
    lattice = np.empty((n_nodes, 3), dtype=np.int64)
    points = np.empty((n_nodes, 3), dtype=np.float64)
    for axis in range(3):
        lattice[:, axis] = index[axis]
        coordinate = origin3[axis] + spacing3[axis] * np.arange(node_shape[axis])
        points[:, axis] = coordinate[index[axis]]
    material = vol[solid].astype(np.int32)
    return Mesh(points, cells, material, lattice, spacing3, origin3, grid_shape)
