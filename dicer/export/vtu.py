"""VTU export for ParaView (cell data ``material``, ``scaled_jacobian`` and ``edge_ratio``).

Order 1 is written as the intermediate meshes are (:mod:`dicer.io.meshes`: raw appended
arrays, dicer's grid field data, so the file is also a valid dicer mesh every stage can
read), but each array in zlib blocks (level 1, VTK's ``vtkZLibDataCompressor`` layout),
about a sixth of the raw size; it is read back with dicer's reader and compared exactly,
and small files also with meshio. Order 2 is written the same way as ``hexahedron20`` /
``quad8`` cells (VTK's types 25 and 23), without the lattice and the grid; the quality
arrays are then those of the element's corners. (meshio's writer, zlib level 6 on one core,
took 22 s of a 46 s export of the head CT's 2.27 M C3D20 elements.)
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from dicer.export.format import Format
from dicer.export.model import scanner_mesh
from dicer.errors import DicerError
from dicer.io.meshes import (MESHIO_CHECK_CELLS, names_from_field_data, names_xml, quality_meanwhile, read_raw_vtu,
                             write_cells_vtu, write_raw_vtu)
from dicer.mesh.model import Mesh
from dicer.mesh.topology import MESHIO_TYPES


def _write_vtu(mesh: Mesh, path: Path) -> None:
    write_raw_vtu(mesh, path, compress=True)


def write_vtu(model, path: str | Path, mesh: Mesh | None = None) -> None:
    """Write a SolverModel as VTU with material and quality cell data.

    The older call ``write_vtu(model, mesh, path)`` works too.

    Parameters
    ----------
    model : SolverModel
    path : str or Path
        The ``.vtu`` file.
    mesh : Mesh, optional
        The linear mesh as exported (order 1); default the model's own mesh, in the
        model's frame.
    """
    if isinstance(path, Mesh):  # write_vtu(model, mesh, path)
        mesh, path = path, mesh
    if model.order == 1:
        if mesh is None:
            if model.mesh is None:
                raise ValueError("a linear model is written to VTU with its mesh; pass mesh=")
            mesh = scanner_mesh(model.mesh, model)
        # the config's names, whatever the mesh carried; arrays shared, not copied; the quality
        # data (the last arrays) computed while the first are compressed, kept for the check
        with quality_meanwhile(mesh) as (later, result):
            _write_vtu(replace(mesh, names=model.name_list(), cell_data=later | mesh.cell_data), Path(path))
            model.cell_data.update(result())
        return
    # the corners' quality computed while the nodes and cells are compressed, kept for the check
    corners = model.cells[:, :8 if model.dim == 3 else 4]
    with quality_meanwhile(model, corners) as (later, result):
        write_cells_vtu(path, model.points, model.cells, MESHIO_TYPES[(model.dim, model.order)],
                        {"material": model.material} | later, names_xml(model.name_list(), model.dim))
        model.cell_data.update(result())


def check_vtu(path: str | Path, model) -> None:
    """Read a VTU file back with meshio and compare it with the model (materials, quality data, names).

    Parameters
    ----------
    path : str or Path
    model : SolverModel
        With its material names.

    Raises
    ------
    DicerError
        The first difference (coordinates, cells, cell data or names).
    """
    from dicer.export.readers import check_meshio

    path = Path(path)
    parts = read_raw_vtu(path, str(path))
    if parts is None or model.n_cells <= MESHIO_CHECK_CELLS:
        check_meshio(path, model, "vtu")
    if parts is not None:
        _check_raw(parts, model)


def _check_raw(parts, model) -> None:
    """The arrays dicer's reader got from the file (order 1 or 2) against the model, exactly."""
    from dicer.mesh.metrics import QUALITY_DATA

    cell_type, points, cells, point_data, cell_data, fields = parts
    if cell_type != MESHIO_TYPES[(model.dim, model.order)]:
        raise DicerError(f"{cell_type} elements read back, {MESHIO_TYPES[(model.dim, model.order)]} written")
    if points.shape[0] != model.n_points or not np.array_equal(points[:, :model.dim], model.points[:, :model.dim]):
        raise DicerError("the node coordinates read back differ from those written")
    if not np.array_equal(cells, model.cells):
        raise DicerError("the connectivity read back differs from that written")
    if not np.array_equal(cell_data.get("material"), model.material):
        raise DicerError("the element materials read back differ from those written")
    for name in QUALITY_DATA:
        got = cell_data.get(name)
        if np.shape(got) != (model.n_cells,):
            raise DicerError(f"cell data {name} read back with the wrong length")
        if name in model.cell_data and not np.array_equal(got, model.cell_data[name], equal_nan=True):
            raise DicerError(f"cell data {name} read back differs from that written")
    if model.order == 1 and model.mesh is not None and not np.array_equal(point_data.get("lattice"),
                                                                           model.mesh.lattice):
        raise DicerError("the lattice indices read back differ from those written")
    names = names_from_field_data(fields)
    if names != model.name_list():
        raise DicerError(f"material names {names} read back, expected {model.name_list()}")


FORMAT = Format("vtu", (".vtu",), write_vtu, check_vtu, holds_sets=False)
