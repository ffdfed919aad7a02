"""Intermediate meshes as VTU files (meshio), with a read-back check after every write."""

from __future__ import annotations

import contextlib
import functools
import io
import os
import shutil
import sys
import zlib
from pathlib import Path

import meshio
import meshio.vtu._vtu  # noqa: F401  (its zlib is swapped while writing, see _fast_vtu_compression)
import numpy as np

from dicer.errors import DicerError
from dicer.io.atomic import atomic_path
from dicer.mesh.metrics import scaled_jacobian
from dicer.mesh.model import Mesh

_FIELDS = ("spacing", "origin", "grid_shape")


def to_meshio(mesh: Mesh) -> meshio.Mesh:
    """The Mesh as a meshio.Mesh: cell data ``material``, point data ``lattice``, field data geometry."""
    point_data = {"lattice": mesh.lattice, **mesh.point_data}
    cell_data = {"material": [mesh.material], **{k: [v] for k, v in mesh.cell_data.items()}}
    return meshio.Mesh(mesh.points, [(mesh.cell_type, mesh.cells)], point_data=point_data, cell_data=cell_data)


def names_xml(names, dim: int) -> str:
    """One field data array per material, named after it and holding ``[label, dim]``.

    This is meshio's own form of named parts (what it reads from and writes to Gmsh's
    $PhysicalNames), so ``meshio convert`` carries the names on; ParaView lists the
    arrays, names and labels, under Data Arrays. A VTK string array would name them
    too, but meshio cannot read string arrays, and many readers of these files use it.
    """
    return "".join(f'<DataArray type="Int64" Name="{name}" NumberOfTuples="2" format="ascii">{label} {dim}</DataArray>\n'
                   for label, name in enumerate(names, start=1))


def names_from_field_data(field_data: dict) -> list[str]:
    """Material names by label from field data written by :func:`names_xml` (empty if none)."""
    found = {}
    for name, value in field_data.items():
        value = np.asarray(value).ravel()
        if name not in _FIELDS and value.size == 2 and value.dtype.kind in "iu":
            found[int(value[0])] = name
    return [found[k] for k in range(1, len(found) + 1)] if set(found) == set(range(1, len(found) + 1)) else []


def _field_data_xml(mesh: Mesh) -> bytes:
    arrays = [
        ("spacing", "Float64", " ".join(repr(float(v)) for v in mesh.spacing)),
        ("origin", "Float64", " ".join(repr(float(v)) for v in mesh.origin)),
        ("grid_shape", "Int64", " ".join(str(int(v)) for v in mesh.grid_shape)),
    ]
    rows = "".join(
        f'<DataArray type="{t}" Name="{n}" NumberOfTuples="3" format="ascii">{v}</DataArray>\n' for n, t, v in arrays
    )
    return f"<FieldData>\n{rows}{names_xml(mesh.names, mesh.dim)}</FieldData>\n".encode()


def splice_field_data(raw: Path, path: Path, block: bytes) -> None:
    """Copy the VTU ``raw`` to ``path`` with ``block`` (a <FieldData> element) put in after
    <UnstructuredGrid>: meshio's VTU writer drops field data (its reader keeps it)."""
    with open(raw, "rb") as src, open(path, "wb") as dst:
        head = src.read(4096)
        tag = b"<UnstructuredGrid>\n"
        at = head.index(tag) + len(tag)
        dst.write(head[:at] + block + head[at:])
        shutil.copyfileobj(src, dst, 1 << 22)


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
        splice_field_data(raw, path, _field_data_xml(mesh))
    finally:
        raw.unlink(missing_ok=True)


def check_mesh(mesh: Mesh, source: str, allow_inverted: bool = False) -> None:
    """Raise DicerError unless ``mesh`` is a sound linear hex/quad mesh."""
    if mesh.n_cells == 0:
        raise DicerError(f"{source}: mesh has no elements")
    if not np.all(np.isfinite(mesh.points)):
        raise DicerError(f"{source}: mesh has non-finite node coordinates")
    if mesh.cells.min() < 0 or mesh.cells.max() >= mesh.n_points:
        raise DicerError(f"{source}: element connectivity refers to nodes that do not exist")
    if mesh.material.shape != (mesh.n_cells,) or mesh.lattice.shape != (mesh.n_points, 3):
        raise DicerError(f"{source}: material or lattice data do not match the element and node counts")
    if not allow_inverted:
        sj = scaled_jacobian(mesh.points, mesh.cells)
        bad = np.flatnonzero(sj <= 0)
        if bad.size:
            raise DicerError(
                f"{source}: {bad.size} degenerate or inverted element(s), e.g. element {bad[0] + 1} "
                f"(scaled Jacobian {sj[bad[0]]:.3f})"
            )


def write_mesh(mesh: Mesh, path: str | os.PathLike, allow_inverted: bool = False) -> None:
    """Write ``mesh`` as VTU atomically, read it back with meshio and check it before keeping it."""
    path = Path(path)
    if path.suffix.lower() != ".vtu":
        raise DicerError(f"{path}: intermediate meshes are VTU files; name the output *.vtu")
    check_mesh(mesh, str(path), allow_inverted)
    with atomic_path(path) as tmp:
        _write_vtu(mesh, tmp)
        back = read_mesh(tmp, source=str(path))
        # the file must hold exactly the mesh that passed check_mesh above (so the
        # element metrics need not be computed a second time)
        same = (back.n_points == mesh.n_points and back.n_cells == mesh.n_cells
                and np.array_equal(back.cells, mesh.cells) and np.array_equal(back.points, mesh.points)
                and np.array_equal(back.material, mesh.material) and np.array_equal(back.lattice, mesh.lattice)
                and back.names == list(mesh.names))
        if not same:
            raise DicerError(f"{path}: read-back check failed: the file does not hold the mesh written; "
                             "check the disk and write again")


def read_mesh(path: str | os.PathLike, source: str | None = None) -> Mesh:
    """Read a dicer VTU (or any meshio format holding one hex or quad block with dicer's data)."""
    path = Path(path)
    name = source or str(path)
    if not path.exists():
        raise DicerError(f"{name}: mesh file not found; check the path")
    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            fmt = "vtu" if path.suffix.lower() == ".vtu" else None
            m = meshio.read(path, file_format=fmt)
    except (Exception, SystemExit) as exc:  # meshio raises many types (and may exit) on damaged files
        raise DicerError(f"{name}: cannot read mesh ({type(exc).__name__}: {str(exc)[:120]}); is the file complete?") from None
    blocks = [(b.type, b.data) for b in m.cells]
    types = {t for t, _ in blocks}
    if types - {"hexahedron", "quad"} or len(types) != 1:
        raise DicerError(f"{name}: expected only hexahedron or only quad elements, found {sorted(types)}")
    cell_type = types.pop()
    cells = np.concatenate([d for _, d in blocks]).astype(np.int64)
    if "material" not in m.cell_data:
        raise DicerError(f"{name}: mesh has no 'material' cell data; make it with 'dicer mesh'")
    if "lattice" not in m.point_data:
        raise DicerError(f"{name}: mesh has no 'lattice' point data (not made by 'dicer mesh'); remesh from labels with 'dicer mesh'")
    material = np.concatenate(m.cell_data["material"]).astype(np.int32)
    lattice = np.asarray(m.point_data["lattice"], dtype=np.int64).reshape(len(m.points), -1)
    if lattice.shape[1] == 2:
        lattice = np.column_stack([lattice, np.zeros(len(lattice), np.int64)])
    points = np.asarray(m.points, dtype=np.float64)
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
    fd = m.field_data
    spacing = np.asarray(fd.get("spacing", np.ones(3)), float).ravel()
    origin = np.asarray(fd.get("origin", np.zeros(3)), float).ravel()
    if "grid_shape" in fd:
        grid_shape = np.asarray(fd["grid_shape"], np.int64).ravel()
    else:
        grid_shape = lattice.max(axis=0) if len(lattice) else np.zeros(3, np.int64)
    point_data = {k: np.asarray(v) for k, v in m.point_data.items() if k != "lattice"}
    cell_data = {k: np.concatenate(v) for k, v in m.cell_data.items() if k != "material"}
    names = names_from_field_data(fd)
    mesh = Mesh(points, cells, material, lattice, spacing, origin, grid_shape, point_data, cell_data, names)
    if (cell_type == "quad") != (mesh.dim == 2):
        raise DicerError(f"{name}: inconsistent element type")
    return mesh
