"""Gmsh mesh file (``.msh``, format 2.2, ASCII) through meshio.

Each element carries its material label as physical and geometrical tag, and
``$PhysicalNames`` names every material present, so Gmsh lists the parts by name.
2D meshes are written with two coordinates per node.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dicer.export.format import Format
from dicer.mesh.topology import MESHIO_TYPES


def write_gmsh(model, path: str | Path) -> None:
    """Write a SolverModel as a Gmsh 2.2 ASCII file.

    Parameters
    ----------
    model : SolverModel
        Written through meshio, with the material names as physical names.
    path : str or Path
        The ``.msh`` file.
    """
    import meshio  # imported where used: the other formats' processes skip it (0.07 s)

    points = model.points if model.dim == 3 else model.points[:, :2]
    tag = model.material.astype(np.int32)
    # $PhysicalNames: each material's name for its physical tag (its label), of the elements' dimension
    names = {model.names[k]: np.array([k, model.dim]) for k in model.labels()}
    m = meshio.Mesh(points, [(MESHIO_TYPES[(model.dim, model.order)], model.cells)],
                    cell_data={"gmsh:physical": [tag], "gmsh:geometrical": [tag]}, field_data=names)
    meshio.write(path, m, file_format="gmsh22", binary=False)


def check_gmsh(path: str | Path, model) -> None:
    """Read a Gmsh file back with meshio and compare it with the model (materials and their names).

    Parameters
    ----------
    path : str or Path
        The ``.msh`` file.
    model : SolverModel

    Raises
    ------
    DicerError
        A node, element or material name that differs.
    """
    from dicer.export.readers import check_meshio

    check_meshio(path, model, "gmsh")


FORMAT = Format("gmsh", (".msh",), write_gmsh, check_gmsh, holds_sets=False)  # materials as physical groups only
