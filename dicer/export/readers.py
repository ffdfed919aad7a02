"""Read-back checks of every export, and strict readers of the text decks dicer writes.

``read_abaqus``, ``read_patran`` and ``read_lsdyna`` parse dicer's own Abaqus/CalculiX,
PATRAN neutral and LS-DYNA keyword files as their writers lay them out (fixed-width
fields, whole blocks at a time with numpy) and raise DicerError, naming the line, on
anything out of place. ``check_abaqus`` (the default read-back of ``.inp`` decks) and
``check_abaqus_meshio`` (``export.verify: meshio``) re-read a deck with dicer's reader or
meshio's; ``check_meshio`` re-reads VTU and Gmsh files with meshio. Every ``check_*``
compares node count, coordinates (to print precision), connectivity and materials
with the model that was written, and the sets the file holds, and raises DicerError
on the first difference.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.textparse import (
    FormatError,
    layout_of,
    parse_column,
    parse_int_list,
    parse_records,
    record_length,
)
from dicer.mesh.topology import HEX20_EXODUS, MESHIO_TYPES


# element types CalculiX reads that meshio's Abaqus reader lacks (same node order as their cousins)
_EXTRA_ABAQUS_TYPES = {"CPE4": "quad", "CPE4R": "quad", "CPS8": "quad8", "CPS8R": "quad8",
                       "CPE8": "quad8", "CPE8R": "quad8"}


@contextlib.contextmanager
def _meshio_abaqus_types():
    """Teach meshio's Abaqus reader the plane element types it does not list, for the duration only."""
    from meshio.abaqus import _abaqus

    table = _abaqus.abaqus_to_meshio_type
    added = [k for k in _EXTRA_ABAQUS_TYPES if k not in table]
    table.update({k: _EXTRA_ABAQUS_TYPES[k] for k in added})
    try:
        yield
    finally:
        for k in added:
            table.pop(k, None)


def _tolerance(model, digits: int) -> float:
    scale = float(np.abs(model.points).max()) if model.n_points else 1.0
    return max(scale, 1e-30) * 10.0 ** (1 - digits)


def compare(model, points: np.ndarray, cells: np.ndarray, material: np.ndarray, what: str,
            digits: int | None = None) -> None:
    """Raise DicerError unless nodes (to ``digits`` significant digits, default the model's),
    connectivity (0-based, file order = element number order) and materials equal the model's."""
    if points.shape[0] != model.n_points:
        raise DicerError(f"{what} has {points.shape[0]} nodes, expected {model.n_points}")
    if cells.shape != model.cells.shape:
        raise DicerError(f"{what} has elements of shape {cells.shape}, expected {model.cells.shape}")
    dim = model.dim
    err = np.abs(points[:, :dim] - model.points[:, :dim]).max() if model.n_points else 0.0
    if not err <= _tolerance(model, digits or model.digits):
        raise DicerError(f"{what}: node coordinates differ by {err:.3g} mm")
    if not np.array_equal(cells, model.cells):
        bad = int(np.flatnonzero((cells != model.cells).any(axis=1))[0])
        raise DicerError(f"{what}: connectivity of element {bad + 1} differs")
    if not np.array_equal(material, model.material):
        raise DicerError(f"{what}: element materials differ")


def check_abaqus_meshio(path: str | Path, model) -> None:
    """Re-read an Abaqus deck with meshio and compare it with ``model`` (``export.verify: meshio``)."""
    import meshio

    try:
        with _meshio_abaqus_types():
            m = meshio.read(path, file_format="abaqus")
    except Exception as exc:  # meshio raises many types
        raise DicerError(f"meshio cannot read the deck ({type(exc).__name__}: {str(exc)[:100]})") from None
    want = MESHIO_TYPES[(model.dim, model.order)]
    types = {b.type for b in m.cells}
    if types != {want}:
        raise DicerError(f"element types {sorted(types)} read back, expected {want}")
    blocks = model.blocks()
    if len(m.cells) != len(blocks):
        raise DicerError(f"{len(m.cells)} element blocks read back, expected {len(blocks)} (one per material)")
    cells = np.empty_like(model.cells)
    material = np.zeros(model.n_cells, np.int32)
    for (k, elements), block in zip(blocks, m.cells):
        name = model.names[k]
        sets = m.cell_sets.get(name)
        if sets is None or sum(len(s) for s in sets) != elements.size or len(block.data) != elements.size:
            raise DicerError(f"material set {name} does not hold its {elements.size} elements")
        cells[elements] = block.data
        material[elements] = k
    for name, ids in model.node_sets.items():
        got = m.point_sets.get(name)
        if got is None or not np.array_equal(np.sort(np.asarray(got)), ids):
            raise DicerError(f"node set {name} differs")
    compare(model, np.asarray(m.points, float), cells, material, "the deck")


def check_meshio(path: str | Path, model, file_format: str) -> None:
    """Re-read a VTU or Gmsh file with meshio and compare it with ``model`` (cell data ``material``)."""
    import meshio

    try:
        m = meshio.read(path, file_format=file_format)
    except Exception as exc:
        raise DicerError(f"meshio cannot read the file ({type(exc).__name__}: {str(exc)[:100]})") from None
    want = MESHIO_TYPES[(model.dim, model.order)]
    types = {b.type for b in m.cells}
    if types != {want}:
        raise DicerError(f"element types {sorted(types)} read back, expected {want}")
    cells = np.concatenate([b.data for b in m.cells]).astype(np.int64)
    key = "material" if "material" in m.cell_data else "gmsh:physical"
    if key not in m.cell_data:
        raise DicerError("no material cell data read back")
    material = np.concatenate(m.cell_data[key]).astype(np.int32)
    compare(model, np.asarray(m.points, float), cells, material, "the file")
    if file_format == "vtu":
        from dicer.mesh.metrics import QUALITY_DATA

        for name in QUALITY_DATA:
            got = np.concatenate(m.cell_data.get(name, [np.empty(0)]))
            if got.shape != (model.n_cells,):
                raise DicerError(f"cell data {name} read back with {got.size} values for {model.n_cells} elements")
    # the material names (VTU field data, Gmsh $PhysicalNames) are part of the file too
    names = {name: int(np.asarray(v).ravel()[0]) for name, v in m.field_data.items()
             if np.asarray(v).size == 2 and name not in ("spacing", "origin", "grid_shape")}
    want = {model.names[k]: k for k in (model.labels() if file_format == "gmsh" else model.names)}
    if names != want:
        raise DicerError(f"material names {names} read back, expected {want}")


# --- strict fixed-width readers -------------------------------------------------------------


class _Lines:
    """A text file as byte lines, with vectorised access to fixed columns of many lines."""

    def __init__(self, path: str | Path):
        self.data = Path(path).read_bytes()
        if not self.data.endswith(b"\n"):
            raise DicerError("the file ends in the middle of a line (truncated?)")
        self.arr = np.frombuffer(self.data, np.uint8)
        self.ends = np.flatnonzero(self.arr == 10)
        self.starts = np.concatenate([[0], self.ends[:-1] + 1])
        self.lengths = self.ends - self.starts

    def __len__(self) -> int:
        return int(self.ends.size)

    def text(self, i: int) -> str:
        return self.data[self.starts[i] : self.ends[i]].decode("ascii", "replace")

    def columns(self, rows: np.ndarray, first: int, width: int) -> np.ndarray:
        """(n, width) uint8: columns first..first+width-1 (0-based) of the given lines."""
        if rows.size == 0:
            return np.zeros((0, width), np.uint8)
        if rows.max() >= len(self) or np.any(self.lengths[rows] < first + width):
            raise DicerError(f"lines too short for columns {first + 1}-{first + width}")
        at = self.starts[rows] + first
        step = int(at[1] - at[0]) if at.size > 1 else 1
        if step > 0 and np.all(np.diff(at) == step):  # evenly spaced lines (fixed-length packets): a view
            view = np.lib.stride_tricks.as_strided(self.arr[at[0] :], shape=(at.size, width), strides=(step, 1))
            return view
        return self.arr[at[:, None] + np.arange(width)]

    def _convert(self, rows: np.ndarray, first: int, width: int, dtype, what: str, kind: str) -> np.ndarray:
        view = self.columns(rows, first, width)
        if rows.size > 64:  # the fields as dicer writes them, at array speed (dicer.export.textparse)
            try:
                values = parse_column(view)
                if values.dtype.kind == np.dtype(dtype).kind:
                    return values.astype(dtype, copy=False)
            except FormatError:
                pass  # a negative integer or a bad field: numpy's conversion takes or names it
        cols = np.ascontiguousarray(view).view(f"S{width}").ravel()
        try:
            return cols.astype(dtype)
        except ValueError:
            pass
        # name the first line that does not convert: find its chunk, then the line (error path only)
        for start in range(0, cols.size, 1 << 12):
            try:
                cols[start : start + (1 << 12)].astype(dtype)
            except ValueError:
                for i in range(start, min(start + (1 << 12), cols.size)):
                    try:
                        cols[i : i + 1].astype(dtype)
                    except ValueError:
                        text = cols[i].decode("ascii", "replace")
                        raise DicerError(f"line {int(rows[i]) + 1}: {what}: {text!r} in columns "
                                         f"{first + 1}-{first + width} is not {kind}") from None
        raise DicerError(f"{what}: not {kind} in columns {first + 1}-{first + width}")

    def ints(self, rows: np.ndarray, first: int, width: int, what: str) -> np.ndarray:
        return self._convert(rows, first, width, np.int64, what, "an integer")

    def floats(self, rows: np.ndarray, first: int, width: int, what: str) -> np.ndarray:
        return self._convert(rows, first, width, np.float64, what, "a number")

    def expect(self, rows: np.ndarray, first: int, text: bytes, what: str) -> None:
        got = self.columns(rows, first, len(text))
        if not np.all(got == np.frombuffer(text, np.uint8)):
            bad = int(rows[np.flatnonzero((got != np.frombuffer(text, np.uint8)).any(axis=1))[0]])
            raise DicerError(f"line {bad + 1}: expected {text.decode()!r} for {what}")

    def lengths_are(self, rows: np.ndarray, n: int, what: str) -> None:
        if rows.size and rows.max() >= len(self):
            raise DicerError(f"the file ends after {len(self)} lines, before its {what} cards (truncated?)")
        if rows.size and np.any(self.lengths[rows] != n):
            bad = int(rows[np.flatnonzero(self.lengths[rows] != n)[0]])
            raise DicerError(f"line {bad + 1}: {what} card has {self.lengths[bad]} columns, expected {n}")


def _patran_headers(lines: _Lines, rows: np.ndarray, it: int, what: str) -> np.ndarray:
    """(n, 9) header fields IT ID IV KC N1..N5 of ``(I2,8I8)`` cards, IT checked."""
    lines.lengths_are(rows, 66, what)
    out = np.column_stack([lines.ints(rows, 0, 2, what)] + [lines.ints(rows, 2 + 8 * k, 8, what) for k in range(8)])
    if np.any(out[:, 0] != it):
        raise DicerError(f"line {int(rows[np.flatnonzero(out[:, 0] != it)[0]]) + 1}: expected a packet {it:02d} header")
    return out


def _patran_packets(lines: _Lines, rows: np.ndarray, it: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """IDs and the shared IV, KC, N1..N5 fields of a run of packets of type ``it`` whose
    headers differ only in the ID (checked byte for byte)."""
    lines.lengths_are(rows, 66, what)
    lines.expect(rows, 0, f"{it:2d}".encode(), f"{what} (packet type)")
    first = _patran_headers(lines, rows[:1], it, what)[0]
    lines.expect(rows, 10, lines.data[lines.starts[rows[0]] + 10 : lines.starts[rows[0]] + 66], f"{what} fields")
    return lines.ints(rows, 2, 8, what), first


PATRAN_SHAPES = {8: {8: (3, 1), 20: (3, 2)}, 4: {4: (2, 1), 8: (2, 2)}}


def read_patran(path: str | Path) -> dict:
    """Read a PATRAN 2 neutral file of one element shape (as dicer writes them), strictly.

    Returns points (N, 3), cells (M, k) 0-based in VTK/Abaqus node order, material
    (M,) property ids, title, dim and order. Nodes and elements must be numbered
    1..N and 1..M in order; any other layout raises DicerError naming the file and line.
    """
    return _named(_read_patran, path)


def _named(reader, path: str | Path) -> dict:
    """``reader(path)`` with the file's name at the head of its error message."""
    try:
        return reader(path)
    except DicerError as exc:
        raise DicerError(f"{path}: {exc}; dicer's strict readers read files exactly as dicer writes them: "
                         "export the mesh again") from None


def _patran_component(lines: _Lines, row: int) -> tuple[int, int, str, np.ndarray]:
    """The packet 21 at line ``row``: (line after it, ID, name, (n, 2) type and element pairs)."""
    h = _patran_headers(lines, np.array([row]), 21, "named component header")[0]
    iv, kc = int(h[2]), int(h[3])
    if iv % 2 or kc != 1 + -(-iv // 10):
        raise DicerError(f"line {row + 1}: named component with {iv} values in {kc} cards")
    name = lines.text(row + 1)
    if not 0 < len(name) <= 12:
        raise DicerError(f"line {row + 2}: a component name of 1 to 12 characters is expected")
    full, rest = divmod(iv, 10)
    rows = row + 2 + np.arange(full)
    lines.lengths_are(rows, 80, "named component")
    values = [np.column_stack([lines.ints(rows, 8 * j, 8, "named component") for j in range(10)]).ravel()]
    if rest:
        last = np.array([row + 2 + full])
        lines.lengths_are(last, 8 * rest, "named component")
        values.append(np.array([lines.ints(last, 8 * j, 8, "named component")[0] for j in range(rest)]))
    return row + 1 + kc, int(h[1]), name, np.concatenate(values).reshape(-1, 2)


def _read_patran(path: str | Path) -> dict:
    """:func:`read_patran` with messages that start at the line."""

    lines = _Lines(path)
    h = _patran_headers(lines, np.array([0]), 25, "title header")[0]
    title = lines.text(1)
    s = _patran_headers(lines, np.array([2]), 26, "summary header")[0]
    n_nodes, n_elems = int(s[4]), int(s[5])
    if h[3] != 1 or s[3] != 1:
        raise DicerError("packets 25 and 26 must have one data card each")
    rows = 4 + 3 * np.arange(n_nodes)
    ids, nh = _patran_packets(lines, rows, 1, "node header")
    if not np.array_equal(ids, np.arange(1, n_nodes + 1)) or nh[3] != 2:
        raise DicerError("node packets must be numbered 1..N with two cards each")
    lines.lengths_are(rows + 1, 48, "node coordinate")
    points = np.column_stack([lines.floats(rows + 1, 16 * j, 16, "node coordinate") for j in range(3)])
    lines.lengths_are(rows + 2, 34, "node constraint")
    lines.expect(rows + 2, 0, b"1G", "node card 2")
    e0 = 4 + 3 * n_nodes
    first = _patran_headers(lines, np.array([e0]), 2, "element header")[0]
    kc = int(first[3])
    rows = e0 + (1 + kc) * np.arange(n_elems)
    ids, eh = _patran_packets(lines, rows, 2, "element header")
    if not np.array_equal(ids, np.arange(1, n_elems + 1)):
        raise DicerError("element packets must be numbered 1..M")
    shape = int(first[2])
    if shape not in PATRAN_SHAPES:
        raise DicerError("element packets must all be hexahedra (8) or all quads (4)")
    card1 = lines.data[lines.starts[rows[0] + 1] : lines.ends[rows[0] + 1]]
    lines.lengths_are(rows + 1, 80, "element card 1")
    lines.expect(rows + 1, 0, card1[:16], "element node count and configuration")
    lines.expect(rows + 1, 24, card1[24:80], "element CEID and orientation angles")
    nn = int(lines.ints(rows[:1] + 1, 0, 8, "element node count")[0])
    if nn not in PATRAN_SHAPES[shape] or kc != 1 + -(-nn // 10):
        raise DicerError("element packets must all have a valid node count for their shape")
    material = lines.ints(rows + 1, 16, 8, "element property id").astype(np.int32)
    cells = np.empty((n_elems, nn), np.int64)
    for j in range(nn):
        cells[:, j] = lines.ints(rows + 2 + j // 10, 8 * (j % 10), 8, "element node")
    end = e0 + (1 + kc) * n_elems
    components = {}
    while end < len(lines) and lines.ints(np.array([end]), 0, 2, "packet type")[0] == 21:
        end, label, name, pairs = _patran_component(lines, end)
        components[label] = (name, pairs)
    _patran_headers(lines, np.array([end]), 99, "end of file")
    if len(lines) != end + 1:
        raise DicerError("data after the end-of-file packet 99")
    dim, order = PATRAN_SHAPES[shape][nn]
    if dim == 3 and order == 2:
        back = np.empty_like(cells)
        back[:, HEX20_EXODUS] = cells
        cells = back
    if cells.min() < 1 or cells.max() > n_nodes:
        raise DicerError("elements refer to nodes that do not exist")
    return {"points": points, "cells": cells - 1, "material": material, "title": title, "dim": dim, "order": order,
            "components": components}


def read_lsdyna(path: str | Path) -> dict:
    """Read an LS-DYNA keyword file as dicer writes it, strictly (fixed-width cards).

    Returns points, cells (0-based), material (part ids), parts (pid -> title),
    materials (mid -> (ro, e, pr)), node_sets (title -> 0-based ids) and title; anything
    out of place raises DicerError naming the file and line.
    """
    return _named(_read_lsdyna, path)


def _read_lsdyna(path: str | Path) -> dict:
    """:func:`read_lsdyna` with messages that start at the line."""
    lines = _Lines(path)
    n = len(lines)
    is_key = lines.arr[lines.starts[lines.lengths > 0]] == ord("*")
    key_rows = np.flatnonzero(lines.lengths > 0)[is_key]
    comment = np.zeros(n, bool)
    nonempty = np.flatnonzero(lines.lengths > 0)
    comment[nonempty[lines.arr[lines.starts[nonempty]] == ord("$")]] = True
    keys = [lines.text(i).strip().upper() for i in key_rows]
    if not keys or keys[0] != "*KEYWORD" or keys[-1] != "*END":
        raise DicerError("an LS-DYNA keyword file starts with *KEYWORD and ends with *END")
    bounds = list(key_rows) + [n]
    out = {"parts": {}, "materials": {}, "node_sets": {}, "title": ""}
    points = cells = pids = None
    for i, key in enumerate(keys):
        rows = np.arange(bounds[i] + 1, bounds[i + 1])
        rows = rows[~comment[rows]]
        if key == "*TITLE":
            out["title"] = lines.text(rows[0]) if rows.size else ""
        elif key == "*NODE":
            lines.lengths_are(rows, 56, "*NODE")
            ids = lines.ints(rows, 0, 8, "*NODE id")
            if not np.array_equal(ids, np.arange(1, rows.size + 1)):
                raise DicerError("*NODE ids must run 1..N in order")
            points = np.column_stack([lines.floats(rows, 8 + 16 * j, 16, "*NODE coordinate") for j in range(3)])
        elif key == "*PART":
            if rows.size != 2:
                raise DicerError("*PART needs a title card and one data card")
            vals = [lines.ints(rows[1:], 10 * k, 10, "*PART")[0] for k in range(3)]
            pid, secid, mid = (int(v) for v in vals)
            out["parts"][pid] = {"title": lines.text(rows[0]).strip(), "secid": secid, "mid": mid}
        elif key == "*SECTION_SOLID":
            if rows.size != 1:
                raise DicerError("*SECTION_SOLID needs one data card")
            out.setdefault("sections", {})[int(lines.ints(rows, 0, 10, "*SECTION_SOLID")[0])] = int(
                lines.ints(rows, 10, 10, "*SECTION_SOLID ELFORM")[0])
        elif key == "*MAT_ELASTIC":
            if rows.size != 1:
                raise DicerError("*MAT_ELASTIC needs one data card")
            mid = int(lines.ints(rows, 0, 10, "*MAT_ELASTIC")[0])
            out["materials"][mid] = tuple(float(lines.floats(rows, 10 * k, 10, "*MAT_ELASTIC")[0]) for k in (1, 2, 3))
        elif key == "*ELEMENT_SOLID":
            lines.lengths_are(rows, 80, "*ELEMENT_SOLID")
            ids = lines.ints(rows, 0, 8, "*ELEMENT_SOLID id")
            if not np.array_equal(ids, np.arange(1, rows.size + 1)):
                raise DicerError("*ELEMENT_SOLID ids must run 1..M in order")
            pids = lines.ints(rows, 8, 8, "*ELEMENT_SOLID part").astype(np.int32)
            cells = np.column_stack([lines.ints(rows, 16 + 8 * j, 8, "*ELEMENT_SOLID node") for j in range(8)])
        elif key == "*SET_NODE_LIST_TITLE":
            if rows.size < 2:
                raise DicerError("*SET_NODE_LIST_TITLE needs a title and a data card")
            name = lines.text(rows[0]).strip()
            data = rows[2:]
            if data.size and np.any(lines.lengths[data] % 10):
                raise DicerError(f"node set {name}: cards must be whole 10-column fields")
            full = data[lines.lengths[data] == 80]
            ids = [lines.ints(full, 10 * k, 10, "node set")[:, None] for k in range(8)]
            ids = np.concatenate(ids, axis=1).ravel() if full.size else np.zeros(0, np.int64)
            tail = data[lines.lengths[data] < 80]
            if tail.size > 1 or (tail.size == 1 and tail[0] != data[-1]):
                raise DicerError(f"node set {name}: only the last card may be short")
            if tail.size:
                k = int(lines.lengths[tail[0]]) // 10
                ids = np.concatenate([ids] + [lines.ints(tail, 10 * j, 10, "node set") for j in range(k)])
            out["node_sets"][name] = ids - 1
        elif key in ("*KEYWORD", "*END"):
            if rows.size:
                raise DicerError(f"{key} takes no data cards")
        else:
            raise DicerError(f"unexpected keyword {key}")
    if points is None or cells is None:
        raise DicerError("no *NODE or *ELEMENT_SOLID block")
    if cells.min() < 1 or cells.max() > points.shape[0]:
        raise DicerError("elements refer to nodes that do not exist")
    out.update(points=points, cells=cells - 1, material=pids)
    return out


def check_patran(path: str | Path, model) -> None:
    """Re-read a PATRAN neutral file with :func:`read_patran` and compare it with ``model``."""
    got = _read_patran(path)
    if (got["dim"], got["order"]) != (model.dim, model.order):
        raise DicerError("element shape or order differs")
    compare(model, got["points"], got["cells"], got["material"], "the neutral file", digits=9)
    from dicer.export.patran import COMPONENT_TYPES, component_names

    names = component_names(model)
    if sorted(got["components"]) != sorted(names):
        raise DicerError(f"named components {sorted(got['components'])} read back, materials {sorted(names)} written")
    for label, elements in model.blocks():
        name, pairs = got["components"][label]
        if (name != names[label] or not np.all(pairs[:, 0] == COMPONENT_TYPES[(model.dim, model.order)])
                or not np.array_equal(pairs[:, 1], elements + 1)):
            raise DicerError(f"named component {label} ({names[label]}) differs")


def check_lsdyna(path: str | Path, model) -> None:
    """Re-read an LS-DYNA keyword file with :func:`read_lsdyna` and compare it with ``model``."""
    got = _read_lsdyna(path)
    compare(model, got["points"], got["cells"], got["material"], "the keyword file", digits=9)
    for name, ids in model.node_sets.items():
        if not np.array_equal(got["node_sets"].get(name, np.zeros(0)), ids):
            raise DicerError(f"node set {name} differs")
    for k in model.labels():
        if got["parts"].get(k, {}).get("title") != model.names[k] or k not in got["materials"]:
            raise DicerError(f"part or material {model.names[k]} missing")


# --- strict Abaqus / CalculiX reader --------------------------------------------------------

NODES_PER_ELEMENT = {(3, 1): 8, (3, 2): 20, (2, 1): 4, (2, 2): 8}
_PER_LINE = 16  # entries per data line (Abaqus, CalculiX); a longer element record continues
_SMALL_BLOCK = 1 << 16  # bytes: heading, surface and material blocks are a few lines


def _map_file(path: Path):
    """The file memory-mapped read-only (no copy of a deck of GBs; pages come from the page cache).

    Nothing a reader returns views the mapping, so it is unmapped when the reader returns.
    """
    import mmap

    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size == 0:
            raise FormatError(0, "the file is empty")
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)


def _release(data, a: int, b: int) -> None:
    """Unmap the pages of data[a:b] once parsed: the deck is read once, and a mapped page counts
    in the process's memory until the mapping ends (they stay in the page cache)."""
    import mmap

    if isinstance(data, mmap.mmap) and hasattr(mmap, "MADV_DONTNEED"):
        first = a // mmap.PAGESIZE * mmap.PAGESIZE
        if b > first:
            data.madvise(mmap.MADV_DONTNEED, first, b - first)


def _where(arr: np.ndarray, offset: int) -> str:
    """``line L, column C`` of the byte ``offset`` (counted only when an error is reported), or
    ``at the end of the file``."""
    if offset >= arr.size:
        return "at the end of the file"
    head = arr[: max(offset, 0)]
    nl = np.flatnonzero(head == 10)
    line = nl.size + 1
    column = offset - (int(nl[-1]) + 1 if nl.size else 0) + 1
    return f"line {line}, column {column}"


def _keyword(text: str, at: int) -> tuple[str, dict[str, str]]:
    """``*KEY, A=b, ...`` -> ("KEY", {"A": "b"}); keyword and parameter names upper case."""
    parts = [p.strip() for p in text[1:].split(",")]
    params = {}
    for p in parts[1:]:
        name, eq, value = p.partition("=")
        if not eq or not name.strip() or not value.strip():
            raise FormatError(at, f"parameter {p!r} of *{parts[0]} is not NAME=value")
        params[name.strip().upper()] = value.strip()
    return parts[0].upper(), params


def _need(params: dict, key: str, keyword: str, at: int) -> str:
    if key not in params:
        raise FormatError(at, f"*{keyword} without its {key}= parameter")
    return params[key]


def _small_lines(arr: np.ndarray, a: int, b: int, keyword: str) -> list[str]:
    """The data lines of a short block as text."""
    if b - a > _SMALL_BLOCK:
        raise FormatError(a, f"*{keyword} has {b - a} bytes of data lines, far more than it takes")
    try:
        return arr[a:b].tobytes().decode("ascii").split("\n")[:-1]
    except UnicodeDecodeError:
        raise FormatError(a, f"a non-ASCII character in the data of *{keyword}") from None


def _numbers(lines: list[str], count: int, keyword: str, a: int) -> list[float]:
    if len(lines) != 1:
        raise FormatError(a, f"*{keyword} takes one data line, the deck has {len(lines)}")
    fields = [f.strip() for f in lines[0].split(",")]
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise FormatError(a, f"*{keyword} data {lines[0]!r} is not {count} number(s)") from None
    if len(values) != count or not all(np.isfinite(values)):
        raise FormatError(a, f"*{keyword} data {lines[0]!r} is not {count} finite number(s)")
    return values


def _records(arr: np.ndarray, a: int, b: int, kinds: str, what: str, entries_first_line: int = 0, sink=None):
    """Parse the fixed-width block arr[a:b] whose records hold fields ``kinds`` (``i``/``f``)
    (``sink``: handed the values chunk by chunk, see :func:`parse_records`)."""
    buf = arr[a:b]
    if buf.size == 0:
        raise FormatError(a, f"{what} without data lines")
    length = record_length(buf, continued=entries_first_line > 0)
    if length == 0:
        raise FormatError(a, f"{what}: no line end in the first record")
    try:
        first = bytes(buf[:length])
        layout = layout_of(first)
        if layout.kinds != kinds:
            raise FormatError(0, f"{what} lines hold {len(layout.kinds)} entries "
                                 f"({layout.kinds.count('f')} real), expected {len(kinds)} ({kinds.count('f')} real)")
        if entries_first_line and first.split(b"\n")[0].count(b",") != entries_first_line:
            raise FormatError(0, f"{what} lines continue after other than {entries_first_line} entries")
        return parse_records(buf, layout, sink=sink)
    except FormatError as exc:
        raise FormatError(a + exc.offset, f"{what}: {exc.message}") from None


def _int_list(arr: np.ndarray, a: int, b: int, what: str) -> np.ndarray:
    """(n,) ids of a set's data lines, 1-based as written, checked strictly increasing."""
    if b == a:
        raise FormatError(a, f"{what} without data lines")
    try:
        ids = parse_int_list(arr[a:b], _PER_LINE)
    except FormatError as exc:
        raise FormatError(a + exc.offset, f"{what}: {exc.message}") from None
    if ids.size > 1 and not np.all(ids[1:] > ids[:-1]):
        raise FormatError(a, f"{what}: ids not in increasing order")
    return ids


def _stride(arr: np.ndarray, a: int, key: str, params: dict) -> int:
    """Bytes per record of a large fixed-width block (nodes, elements, sets), 0 for other blocks."""
    from dicer.export.model import ELEMENT_TYPES

    head = arr[a : a + 4096]
    if key == "NODE":
        return record_length(head)
    if key == "ELEMENT":
        kind = ELEMENT_TYPES.get(params.get("TYPE", "").upper())
        return record_length(head, continued=kind is not None and NODES_PER_ELEMENT[kind] + 1 > _PER_LINE)
    if key in ("NSET", "ELSET"):
        cut = np.flatnonzero((head == ord(",")) | (head == 10))
        return int(cut[0]) + 1 if cut.size else 0
    return 0


def _block_end(data, arr: np.ndarray, a: int, stride: int = 0) -> int:
    """Where the data lines from ``a`` on end: the start of the next keyword line, or the file's end.

    stride : bytes per record of a fixed-width block, whose next keyword starts a record:
    one byte per record is looked at instead of every byte. When the records are broken
    (a line cut short), the first '*' at a record start may be missed or false; the block's
    parse then fails at the first broken record, which is the error to report anyway.
    """
    if stride > 0:
        starts = arr[a::stride]
        hit = int(np.argmax(starts == ord("*"))) if starts.size else 0
        if not starts.size or starts[hit] != ord("*"):
            return arr.size
        if arr[a + hit * stride - 1] == 10:
            return a + hit * stride
    at = data.find(b"\n*", a - 1)
    return arr.size if at < 0 else at + 1


class _Expected:
    """Compares the node and element blocks of a deck with the model written, chunk by chunk
    as they are parsed (the check holds no second copy of the mesh).

    Each ``nodes`` / ``elements`` call takes one chunk of parsed records (``start``: the
    index of its first record in the block) and raises FormatError (offset into the
    chunk's rows) at the first record that differs.
    """

    def __init__(self, model):
        self.model = model
        self.tolerance = _tolerance(model, model.digits)
        self.blocks = {model.names[k]: elements for k, elements in model.blocks()}

    def nodes(self, length: int):
        points, dim, tol = self.model.points, self.model.dim, self.tolerance

        def sink(start: int, ints: np.ndarray, reals: np.ndarray) -> None:
            r = ints.shape[0]
            if start + r > points.shape[0]:
                raise FormatError((points.shape[0] - start) * length, f"the deck has more than the model's "
                                                                     f"{points.shape[0]} nodes")
            ids = ints[:, 0] - np.arange(start + 1, start + 1 + r, dtype=ints.dtype)
            if ids.any():
                raise FormatError(int(np.flatnonzero(ids)[0]) * length, "node numbers do not run 1, 2, ... in order")
            err = np.abs(reals[:, :dim] - points[start : start + r, :dim])
            worst = err.max(axis=1)
            if not worst.max() <= tol:  # NaN fails too
                bad = int(np.flatnonzero(~(worst <= tol))[0])
                raise FormatError(bad * length, f"node coordinates differ by {float(worst.max()):.3g} mm")
        return sink

    def elements(self, name: str, length: int):
        """The sink of block ``name``: element numbers, then connectivity, as the model's block."""
        elements, cells = self.blocks.get(name), self.model.cells
        if elements is None:
            return None

        def sink(start: int, ints: np.ndarray, reals: np.ndarray) -> None:
            r = ints.shape[0]
            e = elements[start : start + r]
            if e.size != r:
                raise FormatError(e.size * length, f"ELSET={name} holds more than its {elements.size} elements")
            if not np.array_equal(ints[:, 0], e + 1):
                raise FormatError(int(np.flatnonzero(ints[:, 0] != e + 1)[0]) * length,
                                  f"material set {name} does not hold its {elements.size} elements")
            want = cells[e]
            want += 1
            same = ints[:, 1:] == want
            if not same.all():
                bad = int(np.flatnonzero(~same.all(axis=1))[0])
                raise FormatError(bad * length, f"connectivity of element {int(e[bad]) + 1} differs")
        return sink


def _parse_abaqus(data, arr: np.ndarray, model=None) -> dict:
    """The deck ``data`` (bytes or mmap; ``arr``: the same as uint8) as :func:`read_abaqus`
    returns it; FormatError on a flaw.

    model : compare the nodes and elements with this SolverModel while they are parsed
        (FormatError at the first record that differs) and return no arrays of them:
        ``points`` and ``cells`` are then None and each block's element indices are the
        model's (equal to those read).
    """
    from dicer.export.model import ELEMENT_TYPES

    expected = _Expected(model) if model is not None else None
    n_nodes = 0

    size = arr.size
    if arr[-1] != 10:
        raise FormatError(size - 1, "the file ends in the middle of this line (truncated?)")
    if arr[0] != ord("*"):
        raise FormatError(0, "a deck starts with a keyword line (*HEADING or *NODE)")
    out = {"heading": [], "points": None, "element_type": None, "blocks": [], "node_sets": {},
           "element_sets": {}, "surfaces": {}, "materials": {}, "sections": {}}
    conn, material, nxt, nodes_seen = [], None, 0, False
    while nxt < size:
        s = nxt  # a keyword line
        e = data.find(b"\n", s)
        a = e + 1  # its data lines run to the next keyword line
        try:
            line = bytes(data[s:e]).decode("ascii")
        except UnicodeDecodeError:
            raise FormatError(s, "a non-ASCII character in a keyword line") from None
        if line.startswith("**"):
            nxt = _block_end(data, arr, a)
            if nxt > a:
                raise FormatError(a, "data lines after a comment line")
            continue
        key, params = _keyword(line, s)
        stride = _stride(arr, a, key, params)
        b = nxt = _block_end(data, arr, a, stride)
        if stride:
            _release(data, a, b)  # the scan for the block's end touched one byte per record
        if key == "HEADING":
            if out["heading"] or nodes_seen:
                raise FormatError(s, "*HEADING after the start of the model or twice")
            out["heading"] = _small_lines(arr, a, b, key) or [""]
        elif key == "NODE":
            if nodes_seen:
                raise FormatError(s, "a second *NODE block (dicer writes one)")
            nodes_seen = True
            if expected is not None:
                n_nodes = _records(arr, a, b, "ifff", "a *NODE line", sink=expected.nodes(stride))
                _release(data, a, b)
                if n_nodes != model.n_points:
                    raise FormatError(b, f"the deck has {n_nodes} nodes, the model {model.n_points}")
                continue
            ints, reals = _records(arr, a, b, "ifff", "a *NODE line")
            _release(data, a, b)
            if not np.array_equal(ints[:, 0], np.arange(1, ints.shape[0] + 1)):
                bad = int(np.flatnonzero(ints[:, 0] != np.arange(1, ints.shape[0] + 1))[0])
                raise FormatError(a + bad * (b - a) // ints.shape[0], "node numbers do not run 1, 2, ... in order")
            out["points"] = reals
            n_nodes = reals.shape[0]
        elif key == "ELEMENT":
            etype = _need(params, "TYPE", key, s).upper()
            name = _need(params, "ELSET", key, s)
            if etype not in ELEMENT_TYPES:
                raise FormatError(s, f"unknown element type {etype}")
            if out["element_type"] not in (None, etype):
                raise FormatError(s, f"element type {etype} after {out['element_type']} (dicer writes one type)")
            if not nodes_seen:
                raise FormatError(s, "*ELEMENT before *NODE")
            if any(name == n for n, _ in out["blocks"]):
                raise FormatError(s, f"a second element block for ELSET={name}")
            out["element_type"] = etype
            k = NODES_PER_ELEMENT[ELEMENT_TYPES[etype]]
            sink = expected.elements(name, stride) if expected is not None else None
            if expected is not None and (sink is None or k != model.cells.shape[1]):
                raise FormatError(s, f"ELSET={name} of {etype} elements, which the model does not hold")
            if sink is not None:
                count = _records(arr, a, b, "i" * (k + 1), f"a *ELEMENT line of ELSET={name}",
                                 _PER_LINE if k + 1 > _PER_LINE else 0, sink=sink)
                _release(data, a, b)
                if count != expected.blocks[name].size:
                    raise FormatError(b, f"material set {name} does not hold its {expected.blocks[name].size} "
                                         "elements")
                out["blocks"].append((name, expected.blocks[name]))
                continue
            ints, _ = _records(arr, a, b, "i" * (k + 1), f"a *ELEMENT line of ELSET={name}",
                               _PER_LINE if k + 1 > _PER_LINE else 0)
            _release(data, a, b)
            out["blocks"].append((name, ints[:, 0] - 1))
            conn.append((a, ints[:, 1:]))
        else:
            material = _card(key, params, arr, a, b, s, out, material)
    if not nodes_seen or not out["blocks"]:
        raise FormatError(size, "no *NODE or no *ELEMENT block (truncated?)")
    return _finish_abaqus(out, size, n_nodes, conn, expected is not None)


def _card(key: str, params: dict, arr: np.ndarray, a: int, b: int, s: int, out: dict, material: str | None):
    """Read a set, surface, material or section card (keyword line at ``s``, data ``a:b``) into ``out``;
    returns the name of the material being described."""
    if key in ("NSET", "ELSET"):
        name = _need(params, key, key, s)
        sets = out["node_sets" if key == "NSET" else "element_sets"]
        if name in sets or len(params) != 1:
            raise FormatError(s, f"*{key}, {key}={name} twice or with other parameters")
        sets[name] = _int_list(arr, a, b, f"*{key}, {key}={name}") - 1
    elif key == "SURFACE":
        name = _need(params, "NAME", key, s)
        if params.get("TYPE", "").upper() != "ELEMENT" or name in out["surfaces"]:
            raise FormatError(s, f"*SURFACE, NAME={name} twice or not TYPE=ELEMENT")
        rows = [tuple(p.strip() for p in t.split(",")) for t in _small_lines(arr, a, b, key)]
        if not rows or any(len(r) != 2 for r in rows):
            raise FormatError(a, f"*SURFACE, NAME={name} data lines are not 'element set, face'")
        out["surfaces"][name] = rows
    elif key == "MATERIAL":
        material = _need(params, "NAME", key, s)
        if material in out["materials"]:
            raise FormatError(s, f"*MATERIAL, NAME={material} twice")
        out["materials"][material] = {}
    elif key in ("ELASTIC", "DENSITY"):
        if material is None or key.lower() in out["materials"][material] or params:
            raise FormatError(s, f"*{key} outside a *MATERIAL, twice in one, or with parameters")
        out["materials"][material][key.lower()] = tuple(
            _numbers(_small_lines(arr, a, b, key), 2 if key == "ELASTIC" else 1, key, a))
    elif key == "SOLID SECTION":
        name = _need(params, "ELSET", key, s)
        lines = _small_lines(arr, a, b, key)
        if name in out["sections"] or len(lines) > 1:
            raise FormatError(s, f"*SOLID SECTION, ELSET={name} twice or with more than one data line")
        out["sections"][name] = (_need(params, "MATERIAL", key, s),
                                 _numbers(lines, 1, key, a) if lines else [])
    else:
        raise FormatError(s, f"unexpected keyword *{key} (dicer's decks hold no such card)")
    return material


def _finish_abaqus(out: dict, size: int, n_nodes: int, conn: list, compared: bool) -> dict:
    """Check that the deck read into ``out`` is whole and its sets and numbers valid; add ``cells``
    (None when ``compared``: the records were compared with the model as they were parsed)."""
    # a deck cut at a line end is whole up to there: its last cards tell (every block has a
    # section, every section a material with its constants)
    for name, _ in out["blocks"]:
        section = out["sections"].get(name)
        if section is None:
            raise FormatError(size, f"ELSET={name} has no *SOLID SECTION (truncated?)")
        if set(out["materials"].get(section[0], {})) != {"elastic", "density"}:
            raise FormatError(size, f"material {section[0]} of ELSET={name} lacks *ELASTIC or *DENSITY (truncated?)")
    n_cells = sum(ids.size for _, ids in out["blocks"])
    for kind, limit in (("node_sets", n_nodes), ("element_sets", n_cells)):
        for name, ids in out[kind].items():
            if ids[0] < 0 or ids[-1] >= limit:
                raise FormatError(size, f"set {name} refers to {kind.split('_')[0]}s that do not exist")
    if compared:  # every record was compared with the model's as it was parsed
        out["cells"] = None
        return out
    seen = np.zeros(n_cells, bool)
    cells = np.empty((n_cells, conn[0][1].shape[1]), conn[0][1].dtype)
    for (name, ids), (a, c) in zip(out["blocks"], conn):
        # increasing within a block (as written) and unseen in the others: each number once
        if ids[0] < 0 or ids[-1] >= n_cells or np.any(ids[1:] <= ids[:-1]) or seen[ids].any():
            raise FormatError(a, f"element numbers of ELSET={name} are not increasing, repeat, or leave "
                                 f"gaps in 1..{n_cells}")
        if c.min() < 1 or c.max() > n_nodes:
            raise FormatError(a, f"elements of ELSET={name} refer to nodes that do not exist")
        seen[ids] = True
        cells[ids] = c
    cells -= 1
    out["cells"] = cells
    return out


def _read_abaqus(path: str | Path, model=None) -> dict:
    """:func:`read_abaqus` with messages that start at the line (the caller names the file);
    ``model``: nodes and elements compared with it as they are parsed (see _parse_abaqus)."""
    try:
        data = _map_file(Path(path))
    except OSError as exc:
        raise DicerError(f"cannot read the file ({exc.strerror or exc})") from None
    except FormatError as exc:
        raise DicerError(exc.message) from None
    arr = np.frombuffer(data, np.uint8)
    try:
        return _parse_abaqus(data, arr, model)
    except FormatError as exc:
        message = f"{_where(arr, exc.offset)}: {exc.message}"
    del arr, data  # the error below must not keep the file mapped through its traceback
    raise DicerError(message)


def read_abaqus(path: str | Path) -> dict:
    """Read an Abaqus/CalculiX deck as dicer writes it, strictly and at array speed.

    Returns points (N, 3) float64 (bit for bit what ``float`` gives for each number),
    cells (M, k) 0-based in element number order (int32 up to 9-digit numbers, else int64), element_type, blocks
    [(ELSET name, 0-based element indices)] in file order, node_sets and element_sets
    {name: 0-based ids}, surfaces {name: [(element set, face)]}, materials {name:
    {"elastic": (E, nu), "density": (rho,)}}, sections {ELSET: (material, [data])} and
    heading (the *HEADING lines). Nodes must be numbered 1..N in order and elements 1..M
    once each; fields must be fixed-width as dicer writes them. Anything else raises
    DicerError naming the file, the line and the column.
    """
    return _named(_read_abaqus, path)


def check_abaqus(path: str | Path, model) -> None:
    """Re-read an Abaqus deck with dicer's strict reader and compare all of it with ``model``:
    heading, nodes, elements and their material blocks, node and element sets, the
    exterior surface, materials and sections."""
    from dicer.export.abaqus import _num

    got = _read_abaqus(path, model)  # nodes and elements compared with the model's record by record
    if got["element_type"] != model.element_type:
        raise DicerError(f"element type {got['element_type']} read back, expected {model.element_type}")
    want_heading = [model.heading[0]] if model.use_heading else []
    if got["heading"] != want_heading:
        raise DicerError(f"*HEADING {got['heading']} read back, expected {want_heading}")
    blocks = model.blocks()
    names = [name for name, _ in got["blocks"]]
    if names != [model.names[k] for k, _ in blocks]:
        raise DicerError(f"element blocks {names} read back, expected {[model.names[k] for k, _ in blocks]}")
    _same_sets("node set", got["node_sets"], model.node_sets)
    faces = model.exterior if model.exterior is not None else np.zeros((0, 2), np.int64)
    present = np.unique(faces[:, 1]).tolist()
    _same_sets("element set", got["element_sets"],
               {f"EXTERIOR_S{s}": np.sort(faces[faces[:, 1] == s, 0]) for s in present})
    surfaces = {"EXTERIOR": [(f"EXTERIOR_S{s}", f"S{s}") for s in present]} if present else {}
    if got["surfaces"] != surfaces:
        raise DicerError(f"surfaces {got['surfaces']} read back, expected {surfaces}")
    labels = model.labels()
    materials = {model.names[k]: {"elastic": (float(_num(model.props[k]["youngs_modulus"])),
                                              float(_num(model.props[k]["poissons_ratio"]))),
                                  "density": (float(_num(model.props[k]["density"])),)} for k in labels}
    if got["materials"] != materials:
        raise DicerError(f"materials {got['materials']} read back, expected {materials}")
    thickness = [float(_num(model.thickness))] if model.dim == 2 else []
    sections = {model.names[k]: (model.names[k], thickness) for k in labels}
    if got["sections"] != sections:
        raise DicerError(f"sections {got['sections']} read back, expected {sections}")


def _same_sets(kind: str, got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    if set(got) != set(want):
        extra, missing = sorted(set(got) - set(want)), sorted(set(want) - set(got))
        raise DicerError(f"{kind}s differ: {extra or 'none'} read back but not written, {missing or 'none'} missing")
    for name, ids in want.items():
        if not np.array_equal(got[name], ids):
            raise DicerError(f"{kind} {name} differs")
