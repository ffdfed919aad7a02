"""VTU export for ParaView (cell data ``material``, ``scaled_jacobian`` and ``edge_ratio``) through meshio.

Order 1 is written with meshio (zlib level 1) plus dicer's grid field data, so the
file is also a valid dicer mesh (``lattice`` point data, grid field data) that every
stage can read; unlike the intermediate meshes (raw data, :mod:`dicer.io.meshes`) the
delivered file stays compressed, about a sixth of the raw size, and meshio's check of
it reads zlib data several times faster than raw appended data. Order 2 is written with meshio as ``hexahedron20`` /
``quad8`` cells; the quality arrays are then those of the element's corners.
"""

from __future__ import annotations

import contextlib
import functools
import sys
import zlib
from pathlib import Path

import meshio
import meshio.vtu._vtu  # noqa: F401  (its zlib is swapped while writing, see _fast_vtu_compression)
import numpy as np

from dicer.export.format import Format
from dicer.export.model import scanner_mesh
from dicer.io.meshes import _field_data_xml, names_xml, splice_field_data, to_meshio
from dicer.mesh.metrics import quality_arrays
from dicer.mesh.model import Mesh
from dicer.mesh.topology import MESHIO_TYPES


def _corner_quality(model) -> dict[str, np.ndarray]:
    k = 8 if model.dim == 3 else 4
    return quality_arrays(model.points, model.cells[:, :k])


class _FastZlib:
    """zlib at level 1 for meshio's VTU writer: its default level 6 took over half of the
    writing time of a large mesh, for files only slightly smaller."""

    compress = staticmethod(functools.partial(zlib.compress, level=1))
    decompress = staticmethod(zlib.decompress)


@contextlib.contextmanager
def _fast_vtu_compression():
    module = sys.modules["meshio.vtu._vtu"]
    saved = module.zlib
    module.zlib = _FastZlib
    try:
        yield
    finally:
        module.zlib = saved


def _write_vtu(mesh: Mesh, path: Path) -> None:
    # meshio's VTU writer drops field data (its reader keeps it): write with meshio,
    # then splice a <FieldData> block in after <UnstructuredGrid>.
    raw = path.with_name(path.name + ".raw.vtu")
    try:
        with _fast_vtu_compression():
            meshio.write(raw, to_meshio(mesh), file_format="vtu", binary=True, compression="zlib")
        splice_field_data(raw, path, _field_data_xml(mesh).encode())
    finally:
        raw.unlink(missing_ok=True)


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
        out = mesh.copy()
        out.names = model.name_list()  # the config's names, whatever the mesh carried
        out.cell_data = quality_arrays(mesh.points, mesh.cells) | out.cell_data
        _write_vtu(out, Path(path))
        return
    m = meshio.Mesh(model.points, [(MESHIO_TYPES[(model.dim, model.order)], model.cells)],
                    cell_data={"material": [model.material],
                               **{k: [v] for k, v in _corner_quality(model).items()}})
    raw = Path(path).with_name(Path(path).name + ".raw.vtu")
    try:
        meshio.write(raw, m, file_format="vtu", binary=True, compression="zlib")
        block = f"<FieldData>\n{names_xml(model.name_list(), model.dim)}</FieldData>\n".encode()
        splice_field_data(raw, Path(path), block)
    finally:
        raw.unlink(missing_ok=True)


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

    check_meshio(path, model, "vtu")


FORMAT = Format("vtu", (".vtu",), write_vtu, check_vtu)
