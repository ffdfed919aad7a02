"""Intermediate meshes as VTU files with raw appended binary data, read back and checked
exactly before every rename.

The files are VTK XML UnstructuredGrid (ParaView and meshio open them): the XML header
lists the arrays, then one ``<AppendedData encoding="raw">`` block holds each array as
an 8-byte size (header_type UInt64) followed by its little-endian bytes. Integer arrays
are as narrow as their values allow: connectivity and offsets Int32, the lattice Int16
(images under 32767 voxels a side), the material UInt8 (up to 255 materials); the quality
arrays are Float32 (:data:`STAGE_QUALITY_TYPE`). At 6.4 M elements that is 0.49 GB, where
Int64 indices and Float64 quality took 0.91 GB; readers widen the arrays to the Mesh's
types again. Writing is one file write per array (a piece at a time for the narrowed
ones) and reading one ``np.fromfile`` per array, so both run at disk speed; meshio's VTU writer and reader (base64 or zlib) took 5-20 s each on a 6.4 M
element mesh (see docs/benchmark.md). meshio reads these files too, and checks the
small ones after writing (MESHIO_CHECK_CELLS). Other VTU files (older dicer files,
ParaView's) are read with meshio. The read-back check maps the file and compares its
arrays in place, and a reader maps rather than copies the arrays it only checks
(offsets, cell types) or drops (the quality data): fresh memory for a second copy of a
mesh costs more than the comparison.
"""

from __future__ import annotations

import contextlib
import io
import os
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from html import escape
from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np

from dicer.errors import DicerError
from dicer.io import SPACING_RANGE_MM
from dicer.io.atomic import atomic_path
from dicer.mesh.frame import check_direction, mirrored, to_lattice
from dicer.mesh.metrics import QUALITY_DATA, lattice_box_quality, quality_arrays, scaled_jacobian
from dicer.mesh.model import GRID_FIELDS, LEVEL_DATA, Mesh
from dicer.mesh.topology import HEX_MIRROR
from dicer.pages import map_readonly
from dicer.parallel import ordered_map


_VTK_TYPES = {
    np.dtype(t): n
    for t, n in [
        (np.float32, "Float32"), (np.float64, "Float64"),
        (np.int8, "Int8"), (np.int16, "Int16"), (np.int32, "Int32"), (np.int64, "Int64"),
        (np.uint8, "UInt8"), (np.uint16, "UInt16"), (np.uint32, "UInt32"), (np.uint64, "UInt64"),
    ]
}
_NUMPY_TYPES = {n: t.newbyteorder("<") for t, n in _VTK_TYPES.items()}
_VTK_CELL_TYPES = {"hexahedron": 12, "quad": 9, "hexahedron20": 25, "quad8": 23}
"""meshio's cell type names -> VTK's (the node order of each is VTK's in both)."""
_CELL_TYPE_NAMES = {(8, 12): "hexahedron", (4, 9): "quad", (20, 25): "hexahedron20", (8, 23): "quad8"}
"""(nodes per element, VTK cell type) -> meshio's name."""

_ROOT = b'<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">'
_ZLIB_ROOT = _ROOT[:-1] + b' compressor="vtkZLibDataCompressor">'
_ZLIB_BLOCK = 1 << 18
"""Bytes of an array per zlib block (VTK's layout: a header of UInt64 words, the block
count, the block size, the last block's size and each block's compressed size, then the
blocks); blocks are compressed and read on both cores."""
_APPENDED = b'<AppendedData encoding="raw">\n_'
# the newline before </AppendedData> is needed: meshio's raw-data reader cuts the
# data at the last newline before that tag
_TAIL = b"\n</AppendedData>\n</VTKFile>\n"
_HEAD_MAX = 1 << 20  # the XML before the data: a few dozen array tags, and a material's name each
_HEAD_LIMIT = 1 << 26
"""A dicer VTU's XML is read on past _HEAD_MAX up to this: its field data names each material
(about 100 bytes each; 65,535 materials of 32-character names take under 10 MB). Until it was,
a mesh of more than about 11,000 materials failed its own read-back check."""

MESHIO_CHECK_CELLS = 20_000
"""Meshes up to this many elements are also read back with meshio (the reference VTU
reader) after writing, which keeps dicer's files in step with it; larger ones only with
numpy: meshio's reader of raw appended data takes 20-50 times as long as the write
(under 0.1 s at this size, 48 s for 6.4 M elements; see docs/benchmark.md)."""


def to_meshio(mesh: Mesh) -> meshio.Mesh:
    """The Mesh as a meshio.Mesh: cell data ``material``, point data ``lattice``, field data geometry."""
    import meshio  # imported where used: most processes never need it (0.07 s)

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
        if name not in GRID_FIELDS and value.size == 2 and value.dtype.kind in "iu":
            found[int(value[0])] = name
    return [found[k] for k in range(1, len(found) + 1)] if set(found) == set(range(1, len(found) + 1)) else []


def _field_data_xml(mesh: Mesh) -> str:
    # ascii with repr() so that every float reads back bit for bit
    arrays = [
        ("spacing", "Float64", " ".join(repr(float(v)) for v in mesh.spacing)),
        ("origin", "Float64", " ".join(repr(float(v)) for v in mesh.origin)),
        ("grid_shape", "Int64", " ".join(str(int(v)) for v in mesh.grid_shape)),
    ]
    if mesh.direction is not None:
        # only when set: meshes of axis-aligned images keep the bytes they always had
        arrays.append(("direction", "Float64", " ".join(repr(float(v)) for v in np.ravel(mesh.direction))))
    if mesh.scanner:
        arrays.append(("scanner_coordinates", "Int64", "1"))
    rows = "".join(
        f'<DataArray type="{t}" Name="{n}" NumberOfTuples="{len(v.split())}" format="ascii">{v}</DataArray>\n'
        for n, t, v in arrays
    )
    return f"<FieldData>\n{rows}{names_xml(mesh.names, mesh.dim)}</FieldData>\n"


class _Later:
    """An array the writer reaches last, computed meanwhile: its type and shape are known
    up front (the file's header gives them), ``get()`` returns it when the writer gets there."""

    def __init__(self, get, dtype, shape: tuple[int, ...]):
        self.get, self.dtype, self.shape = get, np.dtype(dtype).newbyteorder("<"), tuple(shape)
        self.ndim = len(self.shape)
        self.nbytes = self.dtype.itemsize * int(np.prod(self.shape))

    def data(self) -> memoryview:
        a = self.get()
        if a.dtype.newbyteorder("<") != self.dtype or a.shape != self.shape:
            raise ValueError(f"an array of {a.dtype} {a.shape} came where {self.dtype} {self.shape} was announced")
        return np.ascontiguousarray(a, self.dtype).reshape(-1).view(np.uint8).data


@contextlib.contextmanager
def quality_meanwhile(mesh: Mesh, corners: np.ndarray | None = None):
    """The :data:`~dicer.mesh.metrics.QUALITY_DATA` arrays of ``mesh``, computed in a second
    thread while a writer (:func:`write_raw_vtu`) writes the arrays before them.
    ``corners``: (M, 8) or (M, 4) corner indices to measure instead of ``mesh.cells`` (the
    corners of quadratic elements; ``mesh`` then needs only ``points``).

    Yields
    ------
    later : dict of str to array-like
        Cell data for the writer (the arrays it reaches when it gets there).
    result : callable
        ``result()`` -> dict of str to (M,) float64 ndarray, the computed arrays.
    """
    with ThreadPoolExecutor(1) as pool:
        cells = mesh.cells if corners is None else corners
        metrics = pool.submit(quality_arrays, mesh.points, cells)
        yield ({k: _Later(lambda k=k: metrics.result()[k], np.float64, (len(cells),)) for k in QUALITY_DATA},
               metrics.result)


class _Narrow:
    """An integer array written in a narrower type (its values known to fit), converted a
    piece at a time as the writer writes it: fewer bytes on disk and no second copy in memory."""

    def __init__(self, a: np.ndarray, dtype=np.int32):
        self.a = np.ascontiguousarray(a)
        self.dtype, self.shape, self.ndim = np.dtype(dtype).newbyteorder("<"), self.a.shape, self.a.ndim
        self.nbytes = self.dtype.itemsize * self.a.size

    def array(self) -> np.ndarray:
        return self.a.astype(self.dtype)

    def write(self, f) -> None:
        flat = self.a.reshape(-1)
        buf = np.empty(min(flat.size, 1 << 21), self.dtype)
        for start in range(0, flat.size, buf.size):
            n = min(buf.size, flat.size - start)
            buf[:n] = flat[start:start + n]
            f.write(buf[:n].data)


_INT32_MAX = np.iinfo(np.int32).max


def _narrowest(smallest: int, largest: int, wide: bool = False, types=(np.uint8, np.int16, np.int32)):
    """The first of ``types`` that holds every value from ``smallest`` to ``largest`` (not
    ``wide``), else int64."""
    for t in types if not wide else ():
        info = np.iinfo(t)
        if info.min <= smallest and largest <= info.max:
            return np.dtype(t)
    return np.dtype(np.int64)


def _index_array(a: np.ndarray, smallest: int, largest: int, wide: bool = False, types=(np.int32,)):
    """An integer array (connectivity, lattice, material) in the narrowest of ``types`` that
    holds ``smallest`` .. ``largest`` (bounds on its values), else Int64 (also with ``wide``):
    the indices of any mesh that fits in memory fit in Int32, a lattice index in Int16 for
    images under 32767 voxels a side, and fewer bytes make the files quicker to write and
    read. Readers widen them again."""
    dtype = _narrowest(smallest, largest, wide, types)
    return np.asarray(a, np.int64) if dtype == np.int64 else _Narrow(a, dtype)


_WIDENABLE = ("offsets", "lattice", "material", "connectivity")
_WIDENINGS = tuple(tuple(n for i, n in enumerate(_WIDENABLE) if mask >> i & 1) for mask in range(1 << len(_WIDENABLE)))
"""Arrays written as Int64 although they fit a narrower type, tried in this order until
meshio can read the file (see :func:`_meshio_walk_ok`)."""


def _meshio_walk_ok(sizes: list[int]) -> bool:
    """True if meshio's reader of raw appended data finds every array of these byte sizes.

    It walks the arrays in order, finds each one's tag by its offset in the file and
    rewrites that offset to where the array will sit in a base64 copy (a multiple of 4);
    when an array's offset equals such a rewritten offset of an earlier one, it takes that
    earlier tag again and drops or misreads arrays. Whether that happens depends only on
    the sizes, so the writer picks index types for which it does not."""
    rewritten, offset, base64_at = set(), 0, 0
    for size in sizes:
        if offset in rewritten:
            return False
        rewritten.add(base64_at)
        offset += 8 + size
        base64_at += 4 * -(-(8 + size) // 3)
    return True


def _extra_array(path: Path, kind: str, key: str, values, count: int) -> np.ndarray:
    if isinstance(values, _Later):
        return values
    a = np.asarray(values)
    if a.dtype.newbyteorder("=") not in _VTK_TYPES:
        raise DicerError(f"{path}: {kind} data {key!r} has type {a.dtype}, which VTU cannot hold; "
                         "convert it to an integer or float type")
    if a.ndim not in (1, 2) or a.shape[0] != count:
        raise DicerError(f"{path}: {kind} data {key!r} has shape {a.shape}; one value or one row of "
                         f"values per {'node' if kind == 'point' else 'element'} ({count}) is needed")
    return a


def _cell_arrays(cells: np.ndarray, n_points: int, cell_type: str, wide=()) -> list[tuple[str, np.ndarray]]:
    """The <Cells> arrays of one block of ``cell_type``: connectivity and offsets as Int32
    unless named in ``wide`` or too large, types as UInt8."""
    k, n = cells.shape[1], cells.shape[0]
    offsets_type = np.int32 if k * n <= _INT32_MAX and "offsets" not in wide else np.int64
    return [("connectivity", _index_array(cells, 0, n_points, "connectivity" in wide)),
            ("offsets", np.arange(k, k * n + 1, k, dtype=offsets_type)),
            ("types", np.full(n, _VTK_CELL_TYPES[cell_type], np.uint8))]


def _vtu_arrays(mesh: Mesh, path: Path, wide=(), stage: bool = True) -> dict[str, list[tuple[str, np.ndarray]]]:
    """The arrays of the file by XML section, each C-contiguous and little-endian; the
    integer arrays named in ``wide`` as Int64 (see :func:`_index_array`). ``stage``: a
    stage file, its lattice and material as narrow as they fit; else (model.vtu) Int32."""
    sections = {
        "Points": [("Points", np.asarray(mesh.points, np.float64))],
        "Cells": _cell_arrays(mesh.cells, mesh.n_points, mesh.cell_type, wide),
        # a lattice index lies between -1 (a node between lattice points) and the grid's size
        "PointData": [("lattice", _index_array(mesh.lattice, -1, int(np.max(mesh.grid_shape, initial=0)) + 1,
                                               "lattice" in wide, (np.int16, np.int32) if stage else (np.int32,)))]
        + [(key, _extra_array(path, "point", key, v, mesh.n_points)) for key, v in mesh.point_data.items()
           if key != "lattice"],
        # labels are 1..K: one byte for up to 255 materials (an atlas of more takes two)
        "CellData": [("material", _index_array(mesh.material, int(np.min(mesh.material, initial=0)),
                                               int(np.max(mesh.material, initial=0)), "material" in wide,
                                               (np.uint8, np.int16, np.int32) if stage else (np.int32,)))]
        + [(key, _extra_array(path, "cell", key, v, mesh.n_cells)) for key, v in mesh.cell_data.items()
           if key != "material"],
    }
    return {
        s: [(n, a if isinstance(a, (_Later, _Narrow)) else np.ascontiguousarray(a, a.dtype.newbyteorder("<")))
            for n, a in arrays]
        for s, arrays in sections.items()
    }


def _deflate(data, flushes: int = 0) -> bytes:
    """zlib level 1 of ``data``, with ``flushes`` empty sync-flush blocks before the end
    (each a few bytes that change the stream's length, not what it holds)."""
    c = zlib.compressobj(1)
    out = [c.compress(data)] + [c.flush(zlib.Z_SYNC_FLUSH) for _ in range(flushes)]
    return b"".join(out + [c.flush()])


def _zlib_blocks(a: np.ndarray, start: int) -> list:
    """The array in VTK's zlib layout, [header words (<u8), compressed blocks...], to be
    placed at byte ``start`` of the appended data.

    meshio's reader of raw appended data walks the arrays in order, finds each one's tag
    by its offset and rewrites that offset as it goes, always to a multiple of 4 (a base64
    length); a later array whose offset equals such a value would be taken for an earlier
    one. So every array is made to end (the next one to start) off the multiples of 4: the
    last block gets up to a few empty flush blocks."""
    raw = memoryview(a.reshape(-1).view(np.uint8))
    n = len(raw)
    starts = list(range(0, n, _ZLIB_BLOCK))
    blocks = list(ordered_map(lambda i: _deflate(raw[i:i + _ZLIB_BLOCK]), starts))  # zlib frees the GIL
    for flushes in range(1, 9):
        end = start + 8 * (3 + len(blocks)) + sum(map(len, blocks))
        if not blocks or end % 4:
            break
        blocks[-1] = _deflate(raw[starts[-1]:], flushes)
    last = n - (len(blocks) - 1) * _ZLIB_BLOCK if blocks else 0
    header = np.array([len(blocks), _ZLIB_BLOCK, last, *map(len, blocks)], "<u8").tobytes()
    return [header, *blocks]


def _write_vtu(mesh: Mesh, path: Path, compress: bool = False) -> None:
    """Write ``mesh`` at ``path``: raw appended data, zlib blocks with ``compress``."""
    for wide in _WIDENINGS if not compress else ((),):
        sections = _vtu_arrays(mesh, path, wide, stage=not compress)
        if _meshio_walk_ok([a.nbytes for arrays in sections.values() for _, a in arrays]):
            break
    _write_sections(path, sections, _field_data_xml(mesh), mesh.n_points, mesh.n_cells, compress)


def _write_sections(path: Path, sections: dict, field_xml: str, n_points: int, n_cells: int,
                    compress: bool) -> None:
    """Write the arrays of :func:`_vtu_arrays`'s form at ``path`` after the <FieldData> ``field_xml``."""
    offset, tags, blocks = 0, [], []
    for section, arrays in sections.items():
        tags.append(f"<{section}>\n")
        for name, a in arrays:
            ncomp = f' NumberOfComponents="{a.shape[1]}"' if a.ndim == 2 and name != "connectivity" else ""
            tags.append(f'<DataArray type="{_VTK_TYPES[a.dtype.newbyteorder("=")]}" Name="{escape(name)}"'
                        f'{ncomp} format="appended" offset="{offset}"/>\n')
            # the array's own memory, no copy (an array to come: when the writer gets there),
            # or its compressed blocks
            if compress and isinstance(a, _Later):
                a = np.frombuffer(a.data(), a.dtype).reshape(a.shape)
            elif compress and isinstance(a, _Narrow):
                a = a.array()
            parts = (_zlib_blocks(a, offset) if compress
                     else [np.uint64(a.nbytes).astype("<u8").tobytes(),
                           a if isinstance(a, (_Later, _Narrow)) else a.reshape(-1).view(np.uint8).data])
            blocks.extend(parts)
            offset += sum(len(p) if isinstance(p, bytes) else p.nbytes for p in parts)
        tags.append(f"</{section}>\n")
    head = (
        '<?xml version="1.0"?>\n' + (_ZLIB_ROOT if compress else _ROOT).decode() + "\n<UnstructuredGrid>\n"
        + field_xml + f'<Piece NumberOfPoints="{n_points}" NumberOfCells="{n_cells}">\n'
        + "".join(tags) + "</Piece>\n</UnstructuredGrid>\n"
    ).encode() + _APPENDED
    with open(path, "wb") as f:
        f.write(head)
        for part in blocks:
            if isinstance(part, _Narrow):
                part.write(f)
            else:
                f.write(part.data() if isinstance(part, _Later) else part)
        f.write(_TAIL)


def check_mesh(mesh: Mesh, source: str, allow_inverted: bool = False) -> np.ndarray | None:
    """Raise DicerError unless ``mesh`` is a sound linear hex/quad mesh; returns the
    elements' scaled Jacobians when it computed them (not with ``allow_inverted``)."""
    if mesh.n_cells == 0:
        raise DicerError(f"{source}: mesh has no elements")
    if not np.all(np.isfinite(mesh.points)):
        raise DicerError(f"{source}: mesh has non-finite node coordinates")
    if mesh.cells.min() < 0 or mesh.cells.max() >= mesh.n_points:
        raise DicerError(f"{source}: element connectivity refers to nodes that do not exist")
    if mesh.material.shape != (mesh.n_cells,) or mesh.lattice.shape != (mesh.n_points, 3):
        raise DicerError(f"{source}: material or lattice data do not match the element and node counts")
    if allow_inverted:
        return None
    sj = scaled_jacobian(mesh.points, mesh.cells)
    _refuse_inverted(sj, source)
    return sj


def refuse_inverted(mesh: Mesh, source: str) -> None:
    """Raise DicerError when an element of ``mesh`` is degenerate or inverted (scaled
    Jacobian <= 0), its blocks measured on the process's cores: for the stages that only
    read a mesh (export, surface), whose outputs a solver or CAD tool would refuse or
    turn inside out."""
    from dicer.mesh.metrics import hex_min_jacobian_t, point_columns
    from dicer.mesh.model import pieces

    if mesh.cells.shape[1] != 8:
        _refuse_inverted(scaled_jacobian(mesh.points, mesh.cells), source)
        return
    columns = point_columns(mesh.points)  # views, not copies
    cells_t = mesh.cells.T

    def block(part: slice) -> np.ndarray:
        # the failing elements of the block only: no (M,) array of values to fault in
        return np.flatnonzero(hex_min_jacobian_t(columns, cells_t[:, part]) <= 0) + part.start

    bad = np.concatenate([np.zeros(0, np.int64), *ordered_map(block, pieces(mesh.n_cells, 1 << 18))])
    if bad.size:  # the scaled Jacobians of the elements named
        sj = np.ones(mesh.n_cells)
        sj[bad] = scaled_jacobian(mesh.points, mesh.cells[bad])
        _refuse_inverted(sj, source)


def _refuse_inverted(sj: np.ndarray, source: str) -> None:
    bad = np.flatnonzero(sj <= 0)
    if bad.size:
        raise DicerError(
            f"{source}: {bad.size} degenerate or inverted element(s), e.g. element {bad[0] + 1} "
            f"(scaled Jacobian {sj[bad[0]]:.3f})"
        )


def _bitwise_equal(a: np.ndarray, b: np.ndarray) -> bool:
    # bytes, not values: NaN in free data compares equal to itself, -0.0 differs from 0.0
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8))


def _same_mesh(a: Mesh, b: Mesh) -> bool:
    """True if ``b`` (read back) holds exactly ``a`` (written)."""
    return (
        a.n_points == b.n_points and a.n_cells == b.n_cells
        and np.array_equal(a.cells, b.cells) and np.array_equal(a.points, b.points)
        and np.array_equal(a.material, b.material) and np.array_equal(a.lattice, b.lattice)
        and np.array_equal(np.asarray(a.spacing, float), b.spacing)
        and np.array_equal(np.asarray(a.origin, float), b.origin)
        and np.array_equal(np.asarray(a.grid_shape, np.int64), b.grid_shape)
        and list(a.point_data) == list(b.point_data) and list(a.cell_data) == list(b.cell_data)
        and all(_bitwise_equal(np.asarray(v), b.point_data[k]) for k, v in a.point_data.items())
        and all(_bitwise_equal(np.asarray(v), b.cell_data[k]) for k, v in a.cell_data.items())
        and list(a.names) == list(b.names)
        and (a.direction is None) == (b.direction is None)
        and (a.direction is None or np.array_equal(np.asarray(a.direction, float), b.direction))
    )


def write_mesh(mesh: Mesh, path: str | os.PathLike, allow_inverted: bool = False) -> None:
    """Write ``mesh`` as VTU atomically, read it back and check it before keeping it.

    Every file is read back with dicer's reader and compared array for array (exact);
    meshes of up to ``MESHIO_CHECK_CELLS`` elements are also read with meshio. The file
    also holds the elements' quality (:data:`~dicer.mesh.metrics.QUALITY_DATA` cell data)
    for viewing; :func:`read_mesh` leaves it out again.
    """
    path = Path(path)
    if path.suffix.lower() != ".vtu":
        raise DicerError(f"{path}: intermediate meshes are VTU files; name the output *.vtu")
    check_mesh(mesh, str(path), allow_inverted=True)
    # the metrics (one pass: the check of inverted elements and the file's quality data, the
    # last arrays of the file) are computed in a second thread while the first arrays are
    # written; an inverted element still stops the write before the rename
    with ThreadPoolExecutor(1) as pool:
        metrics = pool.submit(_stage_quality, mesh, str(path), allow_inverted)
        later = {k: _Later(lambda k=k: metrics.result()[k], STAGE_QUALITY_TYPE, (mesh.n_cells,)) for k in QUALITY_DATA}
        with atomic_path(path) as tmp:
            _write_vtu(with_quality(mesh, later), tmp)
            mesh = with_quality(mesh, metrics.result())
            _check_written(mesh, tmp, path)


STAGE_QUALITY_TYPE = np.dtype(np.float32)
"""The type of the quality arrays in stage files: they are there to be looked at (ParaView
colours elements by them), every stage computes its own, and Float32 holds them to seven
digits in half the bytes."""


def _stage_quality(mesh: Mesh, name: str, allow_inverted: bool) -> dict[str, np.ndarray]:
    """The quality arrays of a stage file (:data:`STAGE_QUALITY_TYPE`); raises DicerError on
    an inverted element unless ``allow_inverted`` (before the writer reaches them, so before
    the rename). The lattice boxes of a mesh whose nodes sit on the lattice (all of a voxel
    mesh, most of a plane-merged one) get them in closed form
    (:func:`~dicer.mesh.metrics.lattice_box_quality`: a third of the element loop's time
    for those), the same values in Float32 to the last digit."""
    arrays = (lattice_box_quality(mesh.points, mesh.cells, mesh.lattice, mesh.spacing, mesh.origin)
              or quality_arrays(mesh.points, mesh.cells))
    if not allow_inverted:
        _refuse_inverted(arrays["scaled_jacobian"], name)
    return {k: v.astype(STAGE_QUALITY_TYPE) for k, v in arrays.items()}


def _check_written(mesh: Mesh, tmp: Path, path: Path) -> None:
    """Read the file ``tmp`` back (to become ``path``) and compare it with ``mesh``, array
    for array: dicer's reader maps the file and compares in place (no second copy of the
    mesh); small meshes are also read with meshio."""
    readers = [_read_mapped_vtu] + ([_read_meshio] if mesh.n_cells <= MESHIO_CHECK_CELLS else [])
    for reader in readers:
        back = _assemble(str(path), *(reader(tmp, str(path)) or _unreadable(str(path))), widen=False)
        if not _same_mesh(mesh, back):
            raise DicerError(f"{path}: read-back check failed: the file does not hold the mesh written; "
                             "check the disk and write again")


def with_quality(mesh: Mesh, arrays: dict[str, np.ndarray] | None = None) -> Mesh:
    """``mesh`` (not copied) with the quality cell data of its nodes as they are, after
    ``material``: ``arrays`` when given, else computed."""
    cell_data = {k: v for k, v in mesh.cell_data.items() if k not in QUALITY_DATA}
    arrays = quality_arrays(mesh.points, mesh.cells) if arrays is None else arrays
    return replace(mesh, cell_data=arrays | cell_data)


def _unreadable(name: str):
    raise DicerError(f"{name}: cannot read mesh (the VTU header is not dicer's); is the file complete?")


def _damaged(name: str, what: str) -> DicerError:
    return DicerError(f"{name}: cannot read mesh ({what}); is the file complete?")


_INDICES = ("connectivity", "lattice")
"""Index arrays a reader widens to int64 (the Mesh's type) as it reads them."""

_CHECKED = {("Cells", "offsets"), ("Cells", "types")} | {("CellData", k) for k in QUALITY_DATA}
"""Arrays a reader only checks or drops (the quality data describe the nodes as written):
compared in the mapped file, never copied into memory."""


def _read_mapped_vtu(path: Path, name: str):
    """:func:`_read_raw_vtu` with every array a read-only view of the file mapped into memory
    (no copy; the arrays may be unaligned), for checks that only compare them."""
    return _read_raw_vtu(path, name, mapped=True)


def _read_raw_vtu(path: Path, name: str, mapped: bool = False):
    """The parts of a dicer VTU with raw appended data, or None for any other file.

    Returns (cell_type, points, cells, point_data, cell_data, field_data) as _assemble takes them.
    ``mapped``: the arrays are views of the file mapped read-only (see _read_mapped_vtu).
    """
    file_size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(_HEAD_MAX)
        at = head.find(_APPENDED)
        while at < 0 and len(head) < min(file_size, _HEAD_LIMIT) and (_ROOT in head[:1024] or _ZLIB_ROOT in head[:1024]):
            head += f.read(_HEAD_MAX)
            at = head.find(_APPENDED, max(0, len(head) - 2 * _HEAD_MAX))
        compressed = at >= 0 and _ZLIB_ROOT in head[:at]
        if at < 0 or not (compressed or _ROOT in head[:at]):
            return None
        maps: list[np.ndarray] = []

        def fetch(start: int, dtype: np.dtype, count: int, view: bool) -> np.ndarray:
            """Up to ``count`` items of ``dtype`` at byte ``start`` of the file (fewer at its end):
            read into memory, or with ``view`` a view of the file mapped read-only."""
            if not view:
                f.seek(start)
                return np.fromfile(f, dtype, count)
            if not maps:
                maps.append(np.frombuffer(map_readonly(f.fileno()), np.uint8))
            whole = maps[0]
            stop = min(start + count * dtype.itemsize, whole.size) if start >= 0 else 0
            stop -= (stop - start) % dtype.itemsize if stop > start else 0
            return whole[start:stop].view(dtype) if stop > start else np.empty(0, dtype)
        def widened(start: int, dtype: np.dtype, count: int) -> np.ndarray:
            """Up to ``count`` integers of ``dtype`` at byte ``start``, read a piece at a time
            into int64 (the Mesh's index type): no narrow copy of the whole array."""
            out = np.empty(count, np.int64)
            f.seek(start)
            for at_item in range(0, count, 1 << 21):
                want = min(1 << 21, count - at_item)
                got = np.fromfile(f, dtype, want)
                out[at_item:at_item + got.size] = got
                if got.size < want:
                    return out[:at_item + got.size]
            return out

        try:
            root = ET.fromstring(head[:at] + b"</VTKFile>")
        except ET.ParseError as exc:
            raise _damaged(name, f"XML header: {exc}") from None
        data_start = at + len(_APPENDED)
        pieces = root.findall("UnstructuredGrid/Piece")
        if len(pieces) != 1:
            raise _damaged(name, f"{len(pieces)} pieces in the file, dicer writes one")
        piece = pieces[0]
        try:
            n_points, n_cells = int(piece.get("NumberOfPoints")), int(piece.get("NumberOfCells"))
            fields = {
                da.get("Name"): np.array(da.text.split(), _NUMPY_TYPES[da.get("type")])
                for da in root.iterfind("UnstructuredGrid/FieldData/DataArray")
            }
        except (TypeError, ValueError, KeyError, AttributeError) as exc:
            raise _damaged(name, f"XML header: {type(exc).__name__}: {exc}") from None

        def read(da: ET.Element, rows: int | None, view: bool) -> np.ndarray:
            label = f"array {da.get('Name')!r}"
            if da.get("format") != "appended" or da.get("type") not in _NUMPY_TYPES:
                raise _damaged(name, f"{label} has format {da.get('format')!r} and type {da.get('type')!r}; "
                                     "dicer writes appended data of VTK's numeric types")
            dtype = _NUMPY_TYPES[da.get("type")]
            try:
                ncomp = int(da.get("NumberOfComponents", "1"))
                offset = int(da.get("offset"))
            except (TypeError, ValueError) as exc:
                raise _damaged(name, f"{label}: bad NumberOfComponents or offset ({exc})") from None
            if compressed:
                a, end = _inflate(fetch, data_start + offset, file_size, name, label)
                if a.size % dtype.itemsize or (rows is not None and a.size // dtype.itemsize != rows * ncomp):
                    raise _damaged(name, f"{label} has {a.size} bytes, which does not match the header")
                ends.append(end - data_start)
                a = a.view(dtype)
                return a.astype(dtype.newbyteorder("="), copy=False) if ncomp == 1 else a.reshape(-1, ncomp)
            size = fetch(data_start + offset, np.dtype("<u8"), 1, view)
            if size.size != 1:
                raise _damaged(name, f"{label} is missing: the file is cut short")
            count, rest = divmod(int(size[0]), dtype.itemsize)
            # a damaged size word must not make numpy allocate more than the file holds
            if int(size[0]) > file_size - (data_start + offset + 8):
                raise _damaged(name, f"{label} claims {int(size[0])} bytes, more than the file holds: it is cut "
                                     "short or damaged")
            if rest or (rows is not None and count != rows * ncomp) or offset < 0:
                raise _damaged(name, f"{label} has {int(size[0])} bytes, which does not match the header")
            if not view and dtype.kind == "i" and dtype.itemsize < 8 and da.get("Name") in _INDICES:
                a = widened(data_start + offset + 8, dtype, count)
            else:
                a = fetch(data_start + offset + 8, dtype, count, view).astype(dtype.newbyteorder("="), copy=False)
            if a.size != count:
                raise _damaged(name, f"{label} is cut short")
            ends.append(offset + 8 + count * dtype.itemsize)
            return a if ncomp == 1 else a.reshape(-1, ncomp)

        def section(tag: str, rows: int | None) -> dict[str, np.ndarray]:
            node = piece.find(tag)
            return {} if node is None else {da.get("Name"): read(da, rows, mapped or (tag, da.get("Name")) in _CHECKED)
                                            for da in node.iterfind("DataArray")}

        ends: list[int] = []
        points = section("Points", n_points)
        cells = section("Cells", None)
        point_data = section("PointData", n_points)
        cell_data = section("CellData", n_cells)
        # nothing may be missing or added after the last array: ParaView checks the closing tags
        f.seek(data_start + max(ends, default=0))
        if f.read(len(_TAIL) + 1) != _TAIL:
            raise _damaged(name, "the end of the file is missing or damaged")
    if len(points) != 1 or set(cells) != {"connectivity", "offsets", "types"}:
        raise _damaged(name, "points or cells are missing from the XML header")
    block = _one_block(cells, n_cells)
    if block is None:
        return None  # not one hex or quad block: meshio reads it and says what it holds
    return block[0], next(iter(points.values())).reshape(n_points, -1), block[1], point_data, cell_data, fields


def _one_block(cells: dict, n_cells: int):
    """(cell type, (M, k) connectivity) when the cells are one block of one of dicer's cell
    types (:data:`_VTK_CELL_TYPES`: hexahedra or quads, linear or quadratic)."""
    conn, offsets, types = cells["connectivity"], cells["offsets"], cells["types"]
    k = conn.size // n_cells if n_cells else 0
    name = _CELL_TYPE_NAMES.get((k, int(types[0]))) if types.size else None
    if (name is None or conn.size != k * n_cells
            or not np.array_equal(offsets, np.arange(k, k * n_cells + 1, k))
            or not np.all(types == _VTK_CELL_TYPES[name])):
        return None
    return name, conn.reshape(n_cells, k)


def _inflate(fetch, start: int, file_size: int, name: str, label: str) -> tuple[np.ndarray, int]:
    """One array in VTK's zlib layout at byte ``start``: its bytes (uint8) and where it ends."""
    words = fetch(start, np.dtype("<u8"), 3, False)
    if words.size != 3:
        raise _damaged(name, f"{label} is missing: the file is cut short")
    n, size, last = (int(w) for w in words)
    if n > (file_size - start) // 8 or (n and not 0 < last <= size):
        raise _damaged(name, f"{label} has a damaged block header")
    lengths = fetch(start + 24, np.dtype("<u8"), n, False).astype(np.int64)
    data_at = start + 24 + 8 * n
    if lengths.size != n or int(lengths.sum()) > file_size - data_at:
        raise _damaged(name, f"{label} is cut short")
    packed = fetch(data_at, np.dtype(np.uint8), int(lengths.sum()), False)
    bounds = np.concatenate([[0], np.cumsum(lengths)])
    out = np.empty((n - 1) * size + last if n else 0, np.uint8)

    def unpack(i: int) -> bool:
        want = last if i == n - 1 else size
        try:
            got = zlib.decompress(packed[bounds[i]:bounds[i + 1]], bufsize=want)
        except zlib.error:
            return False
        out[i * size:i * size + want] = np.frombuffer(got, np.uint8) if len(got) == want else 0
        return len(got) == want

    if not all(ordered_map(unpack, range(n))):
        raise _damaged(name, f"{label} has a damaged compressed block")
    return out, data_at + int(bounds[-1])


def write_raw_vtu(mesh: Mesh, path: str | os.PathLike, compress: bool = False) -> None:
    """Write ``mesh`` as dicer's VTU (raw appended arrays) with no checks: the caller checks.

    Parameters
    ----------
    mesh : Mesh
    path : str or os.PathLike
    compress : bool, optional
        Each array in zlib blocks (level 1, VTK's layout), about a sixth of the size, the
        lattice and material as Int32 (the exported model.vtu); without it, a stage file
        with every integer array as narrow as it fits.
    """
    _write_vtu(mesh, Path(path), compress)


def write_cells_vtu(path: str | os.PathLike, points: np.ndarray, cells: np.ndarray, cell_type: str,
                    cell_data: dict, field_xml: str = "") -> None:
    """Write elements of any of dicer's cell types (linear or quadratic) as a VTU in zlib
    blocks, with no checks (the caller checks): the layout of :func:`write_raw_vtu` with
    ``compress``, but no lattice and no grid, for exported models of order 2.

    Parameters
    ----------
    path : str or os.PathLike
    points : (N, 3) float64 ndarray
    cells : (M, k) int ndarray
        Node indices in VTK's order.
    cell_type : str
        meshio's name: ``hexahedron``, ``quad``, ``hexahedron20`` or ``quad8``.
    cell_data : dict of str to (M,) or (M, c) ndarray or later array
        ``material`` first (written as Int32), then the rest in their own types.
    field_xml : str, optional
        <DataArray> elements for the <FieldData> (e.g. :func:`names_xml`).
    """
    path = Path(path)
    n_points, n_cells = len(points), len(cells)
    arrays = [(key, _extra_array(path, "cell", key, v, n_cells)) for key, v in cell_data.items()]
    sections = {
        "Points": [("Points", np.ascontiguousarray(points, "<f8"))],
        "Cells": _cell_arrays(cells, n_points, cell_type),
        "CellData": [(key, a if isinstance(a, _Later) else np.ascontiguousarray(
            a, "<i4" if key == "material" else a.dtype.newbyteorder("<"))) for key, a in arrays],
    }
    _write_sections(path, sections, f"<FieldData>\n{field_xml}</FieldData>\n", n_points, n_cells, compress=True)


def read_raw_vtu(path: str | os.PathLike, name: str):
    """The arrays of a VTU file dicer wrote (raw or zlib blocks), or None for any other VTU.

    Parameters
    ----------
    path : str or os.PathLike
    name : str
        The file as named in error messages.

    Returns
    -------
    tuple or None
        (cell type, points (N, 3), cells (M, k), point data, cell data, field data).
    """
    return _read_raw_vtu(Path(path), name)


_QUADRATIC = {"hexahedron20", "hexahedron27", "quad8", "quad9"}  # meshio's names of quadratic hexahedra and quads


def _refuse_quadratic(name: str, types: set[str]) -> None:
    if types & _QUADRATIC:  # an export with export.order 2 (model.vtu): its stage mesh is linear
        raise DicerError(f"{name}: holds quadratic elements ({', '.join(sorted(types))}), as an export with "
                         "export.order 2 writes them, and dicer reads meshes of linear hexahedra or quads; give "
                         "the stage mesh it was exported from (smoothed.vtu), or a model.vtu exported with "
                         "export.order 1")


def _read_meshio(path: Path, name: str):
    """The parts of any mesh file meshio reads, as _read_raw_vtu returns them."""
    import meshio

    from dicer.io import LABEL_SUFFIXES

    if path.name.lower().endswith(LABEL_SUFFIXES + (".dcm",)):  # meshio would call it a damaged mesh
        raise DicerError(f"{name}: is an image, not a mesh; give a mesh a dicer stage wrote (mesh.vtu, merged.vtu, "
                         "smoothed.vtu)")
    try:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            fmt = "vtu" if path.suffix.lower() == ".vtu" else None
            m = meshio.read(path, file_format=fmt)
    except (Exception, SystemExit) as exc:  # meshio raises many types (and may exit) on damaged files
        raise DicerError(f"{name}: cannot read mesh ({type(exc).__name__}: {str(exc)[:120]}); is the file complete?") from None
    blocks = [(b.type, b.data) for b in m.cells]
    types = {t for t, _ in blocks}
    _refuse_quadratic(name, types)
    if types - {"hexahedron", "quad"} or len(types) != 1:
        raise DicerError(f"{name}: expected only hexahedron or only quad elements, found {sorted(types)}; give a "
                         "mesh a dicer stage wrote (mesh.vtu, merged.vtu, smoothed.vtu)")
    cells = np.concatenate([d for _, d in blocks])
    cell_data = {k: np.concatenate(v) for k, v in m.cell_data.items()}
    return types.pop(), m.points, cells, dict(m.point_data), cell_data, m.field_data


_EDITED = "the file is damaged or was edited: write it again with the dicer stage that made it"


def _check_arrays(name, points, cells, material, lattice, level=None) -> None:
    """Refuse a mesh file whose arrays no stage can work on (a damaged or hand-edited file):
    the stages would index past the nodes, carry NaN into every output, or misplace nodes."""
    fix = _EDITED
    if cells.size and (cells.min() < 0 or cells.max() >= len(points)):
        bad = int(np.count_nonzero((cells < 0) | (cells >= len(points))))
        raise DicerError(f"{name}: {bad} element corner(s) refer to nodes that do not exist (valid node "
                         f"numbers 0..{len(points) - 1}); {fix}")
    if cells.size:
        unused = np.flatnonzero(np.bincount(cells.ravel(), minlength=len(points)) == 0)
        if unused.size:  # such a node alone made the X0, Y0 and Z0 node sets of a model on none of them
            raise DicerError(f"{name}: {unused.size} node(s) belong to no element (e.g. node {int(unused[0])}), and "
                             f"would enter the node sets of the planes they lie on; {fix}")
    finite = np.isfinite(points)
    if not finite.all():
        raise DicerError(f"{name}: {int(np.count_nonzero(~finite.all(axis=1)))} node(s) have NaN or infinite "
                         f"coordinates; {fix}")
    if material.shape != (len(cells),):
        raise DicerError(f"{name}: the material data hold {material.size} values for {len(cells)} elements; {fix}")
    if lattice.size and lattice.min() < 0:
        # -1 marks a node between lattice points: (-1, -1, -1), or (-1, -1, 0) in 2D, and only
        # in a graded mesh, on nodes of its transition templates (no voxel element holds one);
        # any other negative index is damage
        between = (lattice[:, 0] == -1) & (lattice[:, 1] == -1) & ((lattice[:, 2] == -1) | (lattice[:, 2] == 0))
        if level is None or np.asarray(level).shape != (len(cells),):
            between[:] = False
        elif between.any():
            in_voxel = np.zeros(len(lattice), bool)
            in_voxel[cells[np.asarray(level) == 0].ravel()] = True
            between &= ~in_voxel
        bad = (lattice < 0).any(axis=1) & ~between
        if bad.any():
            raise DicerError(f"{name}: {int(np.count_nonzero(bad))} node(s) have a negative lattice index; {fix}")


def _grid_fields(name, fd: dict, dim: int, lattice: np.ndarray, fix: str) -> tuple[np.ndarray, ...]:
    """The field data ``spacing``, ``origin`` and ``grid_shape`` (3 values each; a 2D mesh's
    third padded), checked: the plane sets and the smoothing read the image's border from
    them (grid_shape [4, 4, 4] put 80 interior nodes into the X1 set, a spacing of -1 moved
    smoothed nodes by 0.86 mm, and 2 or 4 values ended in tracebacks)."""
    values = {}
    for key, pad in (("spacing", 1.0), ("origin", 0.0), ("grid_shape", 1)):
        v = np.asarray(fd[key], np.float64).ravel()
        if v.size == 2 and dim == 2:
            v = np.r_[v, pad]
        if v.size != 3 or not np.isfinite(v).all():
            raise DicerError(f"{name}: field data {key!r} holds {v.size} value(s) ({', '.join(f'{x:g}' for x in v)}) "
                             f"where a {dim}D mesh has 3 finite numbers; {fix}")
        values[key] = v
    spacing, origin, shape = values["spacing"], values["origin"], values["grid_shape"]
    low, high = SPACING_RANGE_MM
    if not ((spacing >= low) & (spacing <= high)).all():
        raise DicerError(f"{name}: field data 'spacing' is {', '.join(f'{x:g}' for x in spacing)} mm, outside "
                         f"{low:g} to {high:g} mm; {fix}")
    if not ((shape >= 1) & (shape == np.round(shape)) & (shape < 2**53)).all():
        raise DicerError(f"{name}: field data 'grid_shape' is {', '.join(f'{x:g}' for x in shape)}, not whole "
                         f"numbers of voxels from 1; {fix}")
    shape = shape.astype(np.int64)
    reach = lattice.max(axis=0, initial=0)[:dim] if lattice.size else np.zeros(dim, np.int64)
    if (reach > shape[:dim]).any():
        raise DicerError(f"{name}: the nodes' lattice indices reach {', '.join(map(str, reach))}, past the field "
                         f"data's grid_shape {', '.join(map(str, shape[:dim]))}; {fix}")
    return spacing, origin, shape


def _assemble(name, cell_type, points, cells, point_data, cell_data, field_data, widen: bool | str = True) -> Mesh:
    """A Mesh from the arrays of a file, with dicer's checks of its data. ``widen=False``
    keeps the file's integer types (a read-back compared with the mesh written: no copy);
    ``"lattice"`` widens the lattice and leaves an Int32 connectivity as it is."""
    cells, lattice = np.asarray(cells), np.asarray(point_data.get("lattice", ()))
    fix = _EDITED
    if lattice.dtype.kind == "f" and not (np.isfinite(lattice).all() and (lattice == np.round(lattice)).all()):
        raise DicerError(f"{name}: the 'lattice' point data hold values that are not whole numbers; {fix}")
    if widen:
        if widen != "lattice" or cells.dtype not in (np.int32, np.int64):
            cells = cells.astype(np.int64, copy=False)
        lattice = lattice.astype(np.int64, copy=False)
    if "material" not in cell_data:
        raise DicerError(f"{name}: mesh has no 'material' cell data; make it with 'dicer mesh'")
    if "lattice" not in point_data:
        raise DicerError(f"{name}: mesh has no 'lattice' point data (not made by 'dicer mesh'); remesh from labels with 'dicer mesh'")
    material = np.asarray(cell_data["material"]).reshape(-1)
    if material.dtype.kind not in "iu":
        if material.dtype.kind != "f" or not np.all(np.isfinite(material)) or np.any(material != np.round(material)):
            raise DicerError(f"{name}: the 'material' cell data hold values that are not whole numbers; material "
                             "numbers are labels 1..K: write the mesh again with the dicer stage that made it")
    if material.size and material.min() < 1:
        raise DicerError(f"{name}: {int(np.count_nonzero(material < 1))} element(s) have material {int(material.min())}"
                         "; material numbers are labels 1..K (0 is background, which has no elements): write the "
                         "mesh again with the dicer stage that made it")
    if material.size and material.max() > np.iinfo(np.int32).max:  # cast below: 2**32 + 2 became 2
        raise DicerError(f"{name}: {int(np.count_nonzero(material > np.iinfo(np.int32).max))} element(s) have "
                         f"material {material.max():.0f}, past the largest material number dicer keeps "
                         f"({np.iinfo(np.int32).max}); {fix}")
    material = material.astype(np.int32, copy=False)
    dim = 3 if cells.ndim == 2 and cells.shape[1] == 8 else 2
    if lattice.size != len(points) * dim and lattice.size != len(points) * 3:
        raise DicerError(f"{name}: the 'lattice' point data hold {lattice.size} values for {len(points)} nodes of "
                         f"a {dim}D mesh ({dim} per node); {fix}")
    lattice = lattice.reshape(len(points), -1)
    if lattice.shape[1] == 2:
        lattice = np.column_stack([lattice, np.zeros(len(lattice), np.int64)])
    points = np.asarray(points).astype(np.float64, copy=False)
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
    elif dim == 2 and points.size and np.any(points[:, 2] != 0):  # exported as CPS4 off their plane
        raise DicerError(f"{name}: {int(np.count_nonzero(points[:, 2]))} node(s) of the 2D mesh lie off its plane "
                         f"(z up to {float(np.abs(points[:, 2]).max()):g} mm, where dicer's 2D meshes have z = 0); "
                         f"{fix}")
    _check_arrays(name, points, cells, material, lattice, cell_data.get(LEVEL_DATA))
    fd = field_data
    missing = [k for k in ("spacing", "origin", "grid_shape") if k not in fd]
    if missing:
        # without them the image border (plane sets, mirror planes) would be guessed from the
        # mesh's own extent: a free surface taken for a cut plane
        raise DicerError(f"{name}: the mesh file has no grid data ({', '.join(missing)} field data, which dicer's "
                         "stages write and tools such as meshio drop when they save a mesh again); use the "
                         "file the dicer stage wrote")
    spacing, origin, grid_shape = _grid_fields(name, fd, dim, lattice, fix)
    point_data = {k: np.asarray(v) for k, v in point_data.items() if k != "lattice"}
    if "node_class" in point_data:  # codes 0..7 (interior, A-F, X): others ended quality in a traceback
        codes = point_data["node_class"]
        if codes.shape != (len(points),) or codes.dtype.kind not in "iu" or codes.min(initial=0) < 0 or \
                codes.max(initial=0) > 7:
            raise DicerError(f"{name}: the 'node_class' point data are not one code 0..7 per node (shape "
                             f"{codes.shape}, type {codes.dtype}); {fix}")
    cell_data = {k: np.asarray(v) for k, v in cell_data.items() if k != "material"}
    names = names_from_field_data(fd)
    direction = None
    if "direction" in fd:
        direction = np.asarray(fd["direction"], np.float64).ravel()
        if direction.size != 9 or cells.shape[1] != 8:
            raise DicerError(f"{name}: field data 'direction' has {direction.size} values for a "
                             f"{'3D' if cells.shape[1] == 8 else '2D'} mesh; 3D meshes hold 9 (row-major 3x3): "
                             "remesh from the labels with 'dicer mesh'")
        direction = check_direction(direction, 3, name)
    if direction is not None and int(np.asarray(fd.get("scanner_coordinates", [0])).ravel()[0]) == 1:
        # an exported model: back from scanner coordinates into the lattice frame the stages work in
        points = to_lattice(points, spacing, origin, direction)
        if mirrored(direction):
            cells = cells[:, HEX_MIRROR]
    mesh = Mesh(points, cells, material, lattice, spacing, origin, grid_shape, point_data, cell_data, names,
                direction)
    if (cell_type == "quad") != (mesh.dim == 2):
        raise DicerError(f"{name}: inconsistent element type")
    return mesh


_DECK_SUFFIXES = (".inp", ".k", ".key", ".dyn", ".out", ".neu", ".msh", ".exo", ".e", ".feb")


def read_mesh(path: str | os.PathLike, source: str | None = None, mapped: bool = False) -> Mesh:
    """Read a dicer VTU (or any meshio format holding one hex or quad block with dicer's data).

    dicer's own VTU files (raw appended data) are read with numpy at disk speed; any
    other file with meshio. ``mapped``: a dicer VTU's arrays are read-only views of the
    file mapped into memory (pages from the page cache, no copy), for stages that only
    read the mesh and index with its connectivity (export, quality, merge, smooth): the
    connectivity keeps the file's Int32 (an int64 copy is 0.4 GB at 6.4 M hexahedra);
    other arrays of another dtype than a Mesh holds are still converted.
    """
    path = Path(path)
    name = source or str(path)
    if not path.exists():
        raise DicerError(f"{name}: mesh file not found; check the path")
    suffix = "".join(path.suffixes[-1:]).lower()
    if suffix in _DECK_SUFFIXES:  # "no 'material' cell data; make it with 'dicer mesh'" misled
        raise DicerError(f"{name}: a solver deck (what dicer export writes) holds no mesh for dicer's stages; give "
                         "the mesh a stage wrote (smoothed.vtu of dicer run) or an exported model.vtu")
    parts = _read_raw_vtu(path, name, mapped) if suffix == ".vtu" and path.is_file() else None
    if parts:
        _refuse_quadratic(name, {parts[0]})
    mesh = _assemble(name, *(parts or _read_meshio(path, name)), widen="lattice" if mapped else True)
    if mapped and parts:
        # the index arrays widened from the file's Int32 are copies: read-only too, as the
        # mapped arrays are, so that no stage writes into its input
        mesh.cells.flags.writeable = mesh.lattice.flags.writeable = False
    # the quality arrays describe the nodes as they were written: a stage that moves them
    # would carry stale values on, so every writer computes them afresh
    for key in QUALITY_DATA:
        mesh.cell_data.pop(key, None)
    return mesh
