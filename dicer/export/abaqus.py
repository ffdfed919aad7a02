"""Abaqus / CalculiX input deck (``.inp``): the model part, ready to ``*INCLUDE`` from a deck with a step.

Layout::

    *HEADING                 provenance (dicer version, input name + SHA-256, config hash)
    *NODE                    numbered from 1, coordinates in mm
    *ELEMENT, TYPE=C3D8, ELSET=<material>    one block per material
    *NSET, NSET=X0 ... Z1    bounding-box planes; EXTERIOR; CAVITIES; <material>_BOUNDARY; <a>_<b> interfaces
    *ELSET, ELSET=EXTERIOR_S1 ...  + *SURFACE, NAME=EXTERIOR, TYPE=ELEMENT (the outer surface)
    *ELSET, ELSET=CAVITIES_S1 ...  + *SURFACE, NAME=CAVITIES, TYPE=ELEMENT (walls of enclosed voids, if any)
    *MATERIAL, *ELASTIC, *DENSITY, *SOLID SECTION per material (2D: thickness on the data line)

There is no *STEP. Numbers fit CalculiX 2.20's reader, which takes at most 10
characters for an integer and 20 for a float after it drops blanks, and 16
entries per line: integers are right-aligned in 7 (or 11) columns, coordinates
printed with 9 (or 13) significant digits in 15 (or 19) columns; a 20-node
element continues on a second line after a trailing comma (16 entries first).
Blank padding keeps every field a fixed width, so each block is formatted in
bulk by :mod:`dicer.export.textfmt`.

Read-back: :func:`read_abaqus` parses decks exactly as they are written here, whole
blocks at a time (:mod:`dicer.export.textparse`), and :func:`check_abaqus` compares all of
a deck with the model; :func:`check_abaqus_meshio` re-reads it with meshio instead.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.readers import compare, named, tolerance
from dicer.export.textfmt import (Float, Int, Sci, aligned_width, int_lines, int_width, row_ids, write_chunks,
                                  write_int_blocks)
from dicer.export.textparse import FormatError, layout_of, parse_int_list, parse_records, record_length
from dicer.mesh.topology import MESHIO_TYPES

PER_LINE = 16  # CalculiX and Abaqus: at most 16 entries on a data line


def _num(v: float) -> str:
    """A material constant, at most 20 characters (CalculiX's float field)."""
    return f"{float(v):.12g}"


def node_block(stream, points: np.ndarray, width: int, digits: int, lead_nl: bool = True) -> None:
    """Write node rows ``\\n<id>, x, y, z`` for ids 1..N.

    Each row starts with the newline that ends the previous line.

    Parameters
    ----------
    stream : binary file
    points : (N, 3) float64 ndarray
    width : int
        Columns of the id field.
    digits : int
        Significant digits of the coordinates.
    lead_nl : bool, optional
        Start the first row with a newline too.
    """
    fmt = Sci(digits)

    def fields(start, stop):
        p = points[start:stop]
        lead = b"\n" if lead_nl else b""
        return [Int(row_ids(start, stop), width, lead)] + [Float(p[:, j], fmt, b",") for j in range(3)]

    write_chunks(stream, points.shape[0], fields)


def element_block(stream, cells: np.ndarray, elements: np.ndarray, width: int, width_cont: int) -> None:
    """Write element rows ``\\n<element id>, n1, ..., nk`` (1-based), continued after 16 entries with ``,\\n``.

    Parameters
    ----------
    stream : binary file
    cells : (M, k) int ndarray
        0-based node indices.
    elements : (m,) int ndarray
        The elements written, 0-based.
    width, width_cont : int
        Columns of the id fields on the first and on continuation lines.
    """

    def fields(start, stop):
        e = elements[start:stop]
        c = np.take(cells, e, axis=0)  # rows by take: about twice as fast as indexing
        c += 1
        # the 16th entry ends the first line
        return [Int(e + 1, width, b"\n")] + [Int(c[:, j], width_cont, b",\n") if j + 1 == PER_LINE
                                             else Int(c[:, j], width, b",") for j in range(c.shape[1])]

    write_chunks(stream, elements.size, fields)


def write_abaqus(model, path: str | Path) -> None:
    """Write a SolverModel as an Abaqus/CalculiX deck.

    Parameters
    ----------
    model : SolverModel
        Any dimension and order; 2D sections take ``thickness``.
    path : str or Path
        The ``.inp`` file.

    Raises
    ------
    ValueError
        A number no field of the deck holds.
    """
    digits = 13 if model.digits > 9 else 9
    wid = aligned_width(int_width(max(model.n_points, model.n_cells)), b",")
    wid_cont = aligned_width(int_width(model.n_points), b",\n")
    with open(path, "wb", buffering=1 << 20) as f:
        w = f.write
        if model.use_heading:
            w(b"*HEADING\n" + model.heading[0].encode() + b"\n")
        for line in model.heading[0 if not model.use_heading else 1 :]:
            w(b"** " + line.encode() + b"\n")
        w(f"** {model.n_points} nodes, {model.n_cells} {model.element_type} elements\n".encode())
        w(b"*NODE")
        node_block(f, model.points, wid, digits)
        w(b"\n")
        for k, elements in model.blocks():
            w(f"*ELEMENT, TYPE={model.element_type}, ELSET={model.names[k]}".encode())
            element_block(f, model.cells, elements, wid, wid_cont)
            w(b"\n")
        # many sets at once (an atlas has thousands)
        write_int_blocks(w, ((f"*NSET, NSET={name}\n".encode(), ids + 1) for name, ids in model.node_sets.items()),
                         PER_LINE, wid)
        for surface, faces in model.free_face_sets().items():
            present = np.unique(faces[:, 1]).tolist()
            for s in present:
                w(f"*ELSET, ELSET={surface}_S{s}\n".encode())
                w(int_lines(np.sort(faces[faces[:, 1] == s, 0]) + 1, PER_LINE, wid))
            w(f"*SURFACE, NAME={surface}, TYPE=ELEMENT\n".encode())
            for s in present:
                w(f"{surface}_S{s}, S{s}\n".encode())
        for k in model.labels():
            name, p = model.names[k], model.props[k]
            w(f"*MATERIAL, NAME={name}\n*ELASTIC\n{_num(p['youngs_modulus'])}, {_num(p['poissons_ratio'])}\n"
              f"*DENSITY\n{_num(p['density'])}\n".encode())
            w(f"*SOLID SECTION, ELSET={name}, MATERIAL={name}\n".encode())
            if model.dim == 2:
                w(f"{_num(model.thickness)}\n".encode())


# --- read-back: meshio's reader, or dicer's strict one ----------------------------------------

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



def check_abaqus_meshio(path: str | Path, model) -> None:
    """Re-read an Abaqus deck with meshio and compare it with the model (``export.verify: meshio``).

    Parameters
    ----------
    path : str or Path
        The deck.
    model : SolverModel
        What it should hold.

    Raises
    ------
    DicerError
        A difference.
    """
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
        # in windows that double: a deck of many short blocks (an atlas's sets) must not
        # scan the rest of the file for each of them
        window, lo = 4096, 0
        count = (arr.size - a + stride - 1) // stride  # records to the file's end
        hit = -1
        while lo < count:
            hi = min(count, lo + window)
            starts = arr[a + lo * stride : a + hi * stride : stride]
            found = np.flatnonzero(starts == ord("*"))
            if found.size:
                hit = lo + int(found[0])
                break
            lo, window = hi, 2 * window
        if hit < 0:
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
        self.tolerance = tolerance(model, model.digits)
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
            if not err.max() <= tol:  # NaN fails too; the row only then (a maximum along rows of 3 is slow)
                worst = err.max(axis=1)
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
            want = np.take(cells, e, axis=0)
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
    block_names: set[str] = set()
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
            if name in block_names:  # a set: an atlas's thousands of blocks
                raise FormatError(s, f"a second element block for ELSET={name}")
            block_names.add(name)
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

    Nodes must be numbered 1..N in order and elements 1..M once each; fields must be
    fixed-width as dicer writes them.

    Parameters
    ----------
    path : str or Path
        A deck written by :func:`write_abaqus`.

    Returns
    -------
    dict
        ``points`` (N, 3) float64 (bit for bit what ``float`` gives for each number),
        ``cells`` (M, k) 0-based in element number order (int32 up to 9-digit numbers,
        else int64), ``element_type``, ``blocks`` [(ELSET name, 0-based element indices)]
        in file order, ``node_sets`` and ``element_sets`` {name: 0-based ids},
        ``surfaces`` {name: [(element set, face)]}, ``materials`` {name: {"elastic": (E,
        nu), "density": (rho,)}}, ``sections`` {ELSET: (material, [data])} and
        ``heading`` (the *HEADING lines).

    Raises
    ------
    DicerError
        Anything else, naming the file, the line and the column.
    """
    return named(_read_abaqus, path)


def check_abaqus(path: str | Path, model) -> None:
    """Re-read an Abaqus deck with dicer's strict reader and compare all of it with the model.

    Heading, nodes, elements and their material blocks, node and element sets, the
    exterior surface, materials and sections.

    Parameters
    ----------
    path : str or Path
    model : SolverModel

    Raises
    ------
    DicerError
        The first difference.
    """
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
    element_sets, surfaces = {}, {}
    for surface, faces in model.free_face_sets().items():
        present = np.unique(faces[:, 1]).tolist()
        element_sets.update({f"{surface}_S{s}": np.sort(faces[faces[:, 1] == s, 0]) for s in present})
        surfaces[surface] = [(f"{surface}_S{s}", f"S{s}") for s in present]
    _same_sets("element set", got["element_sets"], element_sets)
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


def check_deck(path: str | Path, model, *, verify: str) -> None:
    """Read the deck back and compare it with the model.

    Parameters
    ----------
    path : str or Path
    model : SolverModel
    verify : {"strict", "meshio"}
        dicer's strict reader, or meshio's (``export.verify``).

    Raises
    ------
    DicerError
        A difference.
    """
    if verify == "meshio":
        check_abaqus_meshio(path, model)
    else:
        check_abaqus(path, model)


FORMAT = Format("abaqus", (".inp",), write_abaqus, check_deck, check_options={"verify": "verify"}, digits=(9, 13))
