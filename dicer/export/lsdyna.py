"""LS-DYNA keyword file (``.k``): fixed-width cards as the keyword manual lays them out.

::

    *KEYWORD
    *TITLE                    provenance (80 columns)
    *NODE                     NID (I8), X Y Z (E16), 8-node hexahedra only
    *PART                     per material: title card (its name), PID SECID MID (I10)
    *SECTION_SOLID            SECID ELFORM (I10): 1 (one-point, C3D8R), 2 (selectively reduced, C3D8),
                              -2 (accurate fully integrated, C3D8I)
    *MAT_ELASTIC              MID RO E PR (I10, E10)
    *ELEMENT_SOLID            EID PID N1..N8 (10 x I8)
    *SET_NODE_LIST_TITLE      the node sets of the Abaqus deck: title, SID (I10), node ids (8 x I10)
    *SET_SEGMENT_TITLE        the face sets (EXTERIOR, CAVITIES, the interfaces): title, SID (I10),
                              a card per face, N1..N4 (4 x I10) wound outward (counter-clockwise
                              seen from outside its element: positive pressure presses inward)
    *END

Units are dicer's: mm, N, MPa (N/mm^2), t/mm^3, so times come out in seconds.
Part, section and material ids are the material label. Only 8-node
hexahedra are written (``export.order: 1``, 3D meshes). :func:`read_lsdyna` reads such
files back strictly and :func:`check_lsdyna` compares one with the model.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.readers import Lines, compare, named
from dicer.export.textfmt import Float, Int, Sci, row_ids, write_chunks, write_int_blocks
from dicer.export.textparse import CHUNK_ROWS, FormatError, layout_of_columns, parse_records
from dicer.pages import map_readonly

log = logging.getLogger("dicer")

E16 = Sci(9, b"e", width=16)
ELFORM = {"C3D8": 2, "C3D8R": 1, "C3D8I": -2}


def _e10(v: float) -> str:
    """A real in a 10-column field with as many digits as fit (an exponent without its
    sign or leading zeros where that fits one more: 1.98765e-9, not 1.9877e-09)."""
    for p in range(9, 0, -1):
        short = re.sub(r"e([+-])0*(\d)", lambda m: "e" + m[1].replace("+", "") + m[2], f"{float(v):.{p - 1}e}")
        for text in (f"{float(v):.{p}g}", short):
            if len(text) <= 10 and np.isfinite(float(text)):  # 1.7977e308 would read back as inf
                return f"{text:>10s}"
    raise ValueError(f"{v} does not fit a 10-column field")


ROUNDED_CONSTANT = 1e-7
"""Relative change of a material constant by its 10-column field above which the export warns."""


def _warn_of_rounded_constants(model, path) -> None:
    """Warn when *MAT_ELASTIC's 10-column fields round a material constant by more than
    ROUNDED_CONSTANT (the other decks print them in full)."""
    rounded = []
    for k in model.labels():
        for key in ("density", "youngs_modulus", "poissons_ratio"):
            value = float(model.props[k][key])
            printed = float(_e10(value))
            if value and abs(printed - value) > ROUNDED_CONSTANT * abs(value):
                rounded.append(f"{model.names[k]} {key} {value!r} as {printed!r}")
    if rounded:
        log.warning("export: %s: LS-DYNA's 10-column *MAT_ELASTIC fields round %s; give the constants with fewer "
                    "digits, or export to .inp, .feb or .exo, which print them in full", Path(path).name,
                    ", ".join(rounded[:6]) + (f" and {len(rounded) - 6} more" if len(rounded) > 6 else ""))


def write_lsdyna(model, path: str | Path) -> None:
    """Write a SolverModel (8-node hexahedra) as an LS-DYNA keyword file.

    Parameters
    ----------
    model : SolverModel
        3D, order 1.
    path : str or Path
        The ``.k`` file.
    """
    if model.dim != 3 or model.order != 1:
        raise ValueError("LS-DYNA export writes 8-node hexahedra only (3D meshes, export.order 1)")
    if max(model.n_points, model.n_cells) >= 10**8:
        raise ValueError("more than 99999999 nodes or elements do not fit LS-DYNA's 8-column fields")
    with open(path, "wb", buffering=1 << 20) as f:
        w = f.write
        w(b"*KEYWORD\n*TITLE\n" + model.heading[0][:80].encode() + b"\n")
        for line in model.heading[1:]:
            w(b"$ " + line.encode() + b"\n")
        w(b"*NODE\n$#   nid               x               y               z\n")
        write_chunks(f, model.n_points, lambda a, b: [Int(row_ids(a, b), 8)]
                     + [Float(model.points[a:b, j], E16) for j in range(3)] + [b"\n"])
        for k in model.labels():
            pr = model.props[k]
            w(f"*PART\n{model.names[k]}\n$#     pid     secid       mid\n{k:10d}{k:10d}{k:10d}\n".encode())
            w(f"*SECTION_SOLID\n$#   secid    elform\n{k:10d}{ELFORM[model.element_type]:10d}\n".encode())
            w(f"*MAT_ELASTIC\n$#     mid        ro         e        pr\n{k:10d}{_e10(pr['density'])}"
              f"{_e10(pr['youngs_modulus'])}{_e10(pr['poissons_ratio'])}\n".encode())
        w(b"*ELEMENT_SOLID\n$#   eid     pid      n1      n2      n3      n4      n5      n6      n7      n8\n")
        write_chunks(f, model.n_cells, lambda a, b: [Int(row_ids(a, b), 8), Int(model.material[a:b], 8)]
                     + [Int(model.cells[a:b, j] + 1, 8) for j in range(8)] + [b"\n"])
        write_int_blocks(w, ((f"*SET_NODE_LIST_TITLE\n{name}\n$#     sid\n{sid:10d}\n".encode(), ids + 1)
                             for sid, (name, ids) in enumerate(model.node_sets.items(), start=1)),
                         8, 10, sep=b"")  # 8 x I10
        write_int_blocks(w, ((f"*SET_SEGMENT_TITLE\n{name}\n$#     sid\n{sid:10d}\n".encode(),
                              (model.facets(faces) + 1).ravel())
                             for sid, (name, faces) in enumerate(model.face_sets().items(), start=1)),
                         4, 10, sep=b"")  # a card per face: N1..N4, 4 x I10
        w(b"*END\n")


# --- strict reader ----------------------------------------------------------------------------


def read_lsdyna(path: str | Path) -> dict:
    """Read an LS-DYNA keyword file as dicer writes it, strictly (fixed-width cards).

    Parameters
    ----------
    path : str or Path
        A keyword file written by :func:`write_lsdyna`.

    Returns
    -------
    dict
        ``points``, ``cells`` (0-based), ``material`` (part ids), ``parts`` (pid ->
        title), ``materials`` (mid -> (ro, e, pr)), ``node_sets`` (title -> 0-based ids),
        ``segment_sets`` (title -> (F, 4) 0-based node ids) and ``title``.

    Raises
    ------
    DicerError
        Anything out of place, naming the file and line.
    """
    return named(_read_lsdyna, path)


# cards checked and converted many at once: columns per field, kinds, what each field is (messages)
_NODE_CARD = ((8, 16, 16, 16), "ifff", ("*NODE id",) + ("*NODE coordinate",) * 3)
_ELEMENT_CARD = ((8,) * 10, "i" * 10, ("*ELEMENT_SOLID id", "*ELEMENT_SOLID part") + ("*ELEMENT_SOLID node",) * 8)
_BIG = {"*NODE": _NODE_CARD, "*ELEMENT_SOLID": _ELEMENT_CARD}
_SET_FIELD = 10  # I10 node ids, 8 to a full card
_BATCHED = ("*PART", "*SECTION_SOLID", "*MAT_ELASTIC", "*SET_NODE_LIST_TITLE", "*SET_SEGMENT_TITLE")  # many small blocks


def _read_lsdyna(path: str | Path) -> dict:
    """:func:`read_lsdyna` with messages that start at the line.

    A file laid out as dicer writes it is read from a memory map: the *NODE and
    *ELEMENT_SOLID cards are checked and converted in place, a block at a time, and only
    the rest of the file (keywords, parts, node sets) is split into lines. Any deviation
    there, and every error, sends the whole file through the line-by-line reading, which
    names the line.
    """
    plain = _cut_large_blocks(Path(path))
    if plain is not None:
        text, parsed = plain
        try:
            return _parse(_TextLines(text), parsed)
        except DicerError:
            pass  # its line numbers count the shortened text: read the whole file to name the line
    return _parse(Lines(path), {})


class _TextLines(Lines):
    """:class:`Lines` of text in memory (a keyword file with its large blocks' cards cut out).

    Parameters
    ----------
    data : bytes
        Whole lines, the last one ended by a newline.
    """

    def __init__(self, data: bytes):
        self.data = data
        self.arr = np.frombuffer(data, np.uint8)
        self.ends = np.flatnonzero(self.arr == 10)
        self.starts = np.concatenate([[0], self.ends[:-1] + 1])
        self.lengths = self.ends - self.starts


def _cut_large_blocks(path: Path):
    """Parse the *NODE and *ELEMENT_SOLID cards of a keyword file in place, and cut them out of its text.

    A block qualifies when its data cards follow its keyword and comment lines as one run
    of whole cards of the first card's layout up to the next keyword (and element ids run
    1..M): that is, they are exactly the non-comment lines a line-by-line reading of the
    block finds, and they parse as they would there (:func:`_cards`).

    Parameters
    ----------
    path : Path

    Returns
    -------
    (bytes, dict) or None
        The file without those cards, and {index of the block's keyword among the
        file's keywords: arrays}: a *NODE block's (ints (N, 1) int32, points (N, 3)
        float64) as :func:`parse_records` gives them, an *ELEMENT_SOLID block's
        (material, cells) as :func:`_elements_in_place` does; None for a file of another
        layout, or a flaw in these cards (the caller reads it line by line).
    """
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                return None
            data = map_readonly(f.fileno())  # no copy of a file of GBs
    except (OSError, ValueError):
        return None
    try:
        return _cut(data)
    finally:
        with contextlib.suppress(BufferError):  # a view still alive (an error's traceback): the GC unmaps
            data.close()  # now, not when collected: the file may be renamed next (Windows)


def _cut(data) -> tuple[bytes, dict] | None:
    """:func:`_cut_large_blocks` on the file's memory map ``data``."""
    size = len(data)
    if data[size - 1 :] != b"\n":
        return None
    arr = np.frombuffer(data, np.uint8)

    def next_key(at: int) -> int:  # the first keyword line from the line start ``at`` on
        # a search for one byte runs at memory speed (for b"\n*", it stops at every line end);
        # a '*' that does not start a line (in a title) is passed over
        while True:
            hit = data.find(b"*", at)
            if hit < 0:
                return size
            if hit == 0 or data[hit - 1] == 10:
                return hit
            at = hit + 1

    pieces, parsed, kept, i = [], {}, 0, 0
    key = next_key(0)
    while key < size:  # one pass per keyword: dicer's files have a few, an atlas's some 10,000
        eol = data.find(b"\n", key)
        after = next_key(eol + 1)
        card = _BIG.get(data[key:eol].decode("ascii", "replace").strip().upper())
        if card is not None:
            body = eol + 1
            while data[body : body + 1] == b"$":  # the comment lines heading the cards
                body = data.find(b"\n", body) + 1
            length = sum(card[0]) + 1
            if after == body or (after - body) % length:
                return None
            buf = arr[body:after]
            try:
                layout = layout_of_columns(bytes(buf[:length]), card[0])
                if layout.kinds != card[1]:
                    return None
                parsed[i] = (_elements_in_place(buf, layout) if card is _ELEMENT_CARD
                             else parse_records(buf, layout))
            except FormatError:
                return None
            pieces.append(data[kept:body])
            kept = after
            _release(data, body, after)
        i += 1
        key = after
    pieces.append(data[kept:])
    return b"".join(pieces), parsed


def _elements_in_place(buf: np.ndarray, layout) -> tuple[np.ndarray, np.ndarray]:
    """Parse *ELEMENT_SOLID cards (EID PID N1..N8) straight into the arrays the reader returns.

    Parameters
    ----------
    buf : (m * 81,) uint8 ndarray
        Whole cards.
    layout : Layout
        Ten integer fields.

    Returns
    -------
    material : (m,) int32 ndarray
        The part ids.
    cells : (m, 8) int64 ndarray
        0-based node ids (range checked by the caller, who knows the node count).

    Raises
    ------
    FormatError
        A character out of place, or an element id that is not its card's place.
    """
    m = buf.size // layout.length
    material = np.empty(m, np.int32)
    cells = np.empty((m, 8), np.int64)

    def sink(start: int, ints: np.ndarray, reals: np.ndarray) -> None:
        # chunks arrive from worker threads: each writes its own rows only; no (m, 10) array of
        # the whole block, and no second pass over the cells
        r = ints.shape[0]
        wrong = ints[:, 0] != np.arange(start + 1, start + r + 1, dtype=ints.dtype)
        if wrong.any():
            raise FormatError(int(np.flatnonzero(wrong)[0]) * layout.length, "element ids do not run 1..M")
        material[start : start + r] = ints[:, 1]
        np.subtract(ints[:, 2:], 1, out=cells[start : start + r])

    parse_records(buf, layout, sink=sink)
    return material, cells


def _release(data, a: int, b: int) -> None:
    """Drop the mapped pages of data[a:b] once parsed (they stay in the page cache): a mapped
    page counts in the process's memory until the mapping ends."""
    import mmap

    if hasattr(mmap, "MADV_DONTNEED"):
        first = a // mmap.PAGESIZE * mmap.PAGESIZE
        if b > first:
            data.madvise(mmap.MADV_DONTNEED, first, b - first)


def _parse(lines: Lines, parsed: dict) -> dict:
    """The dict :func:`read_lsdyna` returns, from the lines of a keyword file.

    Parameters
    ----------
    lines : Lines
        The file, or the file with the cards of the blocks ``parsed`` cut out.
    parsed : dict
        {keyword index: arrays}: the cards of those blocks, parsed
        (:func:`_cut_large_blocks`).

    Returns
    -------
    dict

    Raises
    ------
    DicerError
        Naming the line (of ``lines``).
    """
    n = len(lines)
    nonempty = np.flatnonzero(lines.lengths > 0)
    lead = lines.arr[lines.starts[nonempty]]
    key_rows = nonempty[lead == ord("*")]
    comment = np.zeros(n, bool)
    comment[nonempty[lead == ord("$")]] = True
    keys = [lines.text(i).strip().upper() for i in key_rows]
    if not keys or keys[0] != "*KEYWORD" or keys[-1] != "*END":
        cut = f" (this one ends after line {n} without *END: truncated?)" if keys and keys[-1] != "*END" else ""
        raise DicerError(f"an LS-DYNA keyword file starts with *KEYWORD and ends with *END{cut}")
    bounds = np.append(key_rows, n)
    out = {"parts": {}, "materials": {}, "node_sets": {}, "segment_sets": {}, "title": ""}
    points = cells = pids = element_rows = None
    batched: dict[str, list[int]] = {key: [] for key in _BATCHED}
    for i, key in enumerate(keys):
        if key in batched:  # all blocks of the kind together, below
            batched[key].append(i)
            continue
        rows = np.arange(bounds[i] + 1, bounds[i + 1])
        rows = rows[~comment[rows]]
        if key == "*TITLE":
            out["title"] = lines.text(rows[0]) if rows.size else ""
        elif key == "*NODE":  # cut out of ``lines`` (its cards parsed in place) or read here
            (ints, points), rows = (parsed[i], None) if i in parsed else _cards(lines, rows, _NODE_CARD)
            _run_one_to_n(ints[:, 0], rows, "*NODE ids must run 1..N in order")
        elif key == "*ELEMENT_SOLID":
            if i in parsed:  # ids checked, parts and 0-based nodes filled in as parsed
                (pids, cells), element_rows = parsed[i], None
            else:
                (ints, _), element_rows = _cards(lines, rows, _ELEMENT_CARD)
                _run_one_to_n(ints[:, 0], element_rows, "*ELEMENT_SOLID ids must run 1..M in order")
                pids, cells = ints[:, 1].astype(np.int32), np.subtract(ints[:, 2:], 1, dtype=np.int64)
        elif key in ("*KEYWORD", "*END"):
            if rows.size:
                raise DicerError(f"line {rows[0] + 1}: {key} takes no data cards")
        else:
            raise DicerError(f"line {key_rows[i] + 1}: unexpected keyword {key}")
    blocks = {key: np.array(batched[key], np.intp) for key in _BATCHED}
    _parts(lines, key_rows, bounds, comment, blocks, out)
    for key, name, read in (("*SET_NODE_LIST_TITLE", "node_sets", _node_sets),
                            ("*SET_SEGMENT_TITLE", "segment_sets", _segment_sets)):
        if blocks[key].size:
            out[name] = read(lines, key_rows, bounds, blocks[key], comment)
    if points is None or cells is None:
        raise DicerError("no *NODE or *ELEMENT_SOLID block")
    if cells.size and (cells.min() < 0 or cells.max() >= points.shape[0]):
        bad = int(np.flatnonzero(((cells < 0) | (cells >= points.shape[0])).any(axis=1))[0])
        raise DicerError(f"{_line(element_rows, bad)}elements refer to nodes that do not exist (element {bad + 1}; "
                         f"the file has {points.shape[0]} nodes)")
    out.update(points=points, cells=cells, material=pids)
    return out


def _line(rows: np.ndarray | None, i: int) -> str:
    """``line L: `` of the i-th card of a block (nothing for cards cut out of the text)."""
    return "" if rows is None else f"line {rows[i] + 1}: "


def _run_one_to_n(ids: np.ndarray, rows: np.ndarray | None, message: str) -> None:
    """Raise DicerError naming the first card whose id is not its place (1, 2, ...)."""
    wrong = ids != np.arange(1, ids.size + 1, dtype=ids.dtype)
    if wrong.any():
        i = int(np.flatnonzero(wrong)[0])
        raise DicerError(f"{_line(rows, i)}{message} (id {ids[i]} on card {i + 1})")


def _cards(lines: Lines, rows: np.ndarray, card: tuple):
    """The data cards of a *NODE or *ELEMENT_SOLID block, from its lines.

    Parameters
    ----------
    lines : Lines
    rows : (n,) int ndarray
        The block's non-comment lines.
    card : tuple
        ``(widths, kinds, names)``: columns, ``i``/``f`` and the name of each field.

    Returns
    -------
    (ints, reals)
        (n, fields) arrays: integers int32 when parsed at once, int64 when read column by
        column (comment lines among the cards), reals float64.
    rows : (n,) int ndarray
        The cards' lines.

    Raises
    ------
    DicerError
        Naming the line.
    """
    widths, kinds, names = card
    lines.lengths_are(rows, sum(widths), names[0].split()[0])
    if rows.size and int(rows[-1]) - int(rows[0]) + 1 == rows.size:  # one run of lines: at once
        buf = lines.arr[int(lines.starts[rows[0]]) : int(lines.ends[rows[-1]]) + 1]
        return _parse_cards(lines, rows, buf, card), rows
    # comment lines between the cards: column by column, as the lines come
    edges = np.cumsum((0,) + tuple(widths))
    cols = {k: [(lines.ints if k == "i" else lines.floats)(rows, int(edges[j]), widths[j], names[j])
                for j in range(len(widths)) if kinds[j] == k] for k in "if"}
    return tuple(np.column_stack(cols[k]) if cols[k] else np.zeros((rows.size, 0)) for k in "if"), rows


def _card_error(lines: Lines, row: int, col: int, card: tuple, reason: str) -> DicerError:
    """The error for a bad character at column ``col`` (0-based) of line ``row``, a card of ``card``'s fields."""
    widths, kinds, names = card
    edges = np.cumsum((0,) + tuple(widths))
    j = int(np.searchsorted(edges, col, side="right")) - 1
    if j >= len(widths):
        return DicerError(f"line {row + 1}: {reason} in column {col + 1}")
    a, b = int(edges[j]), int(edges[j + 1])
    text = lines.text(row)[a:b]
    return DicerError(f"line {row + 1}: {names[j]}: {text!r} in columns {a + 1}-{b} is not "
                      f"{'an integer' if kinds[j] == 'i' else 'a number'} as dicer writes it ({reason} in "
                      f"column {col + 1})")


def _parse_cards(lines: Lines, rows: np.ndarray, buf: np.ndarray, card: tuple):
    """Check and convert cards of one layout at once (:func:`parse_records`).

    Parameters
    ----------
    lines : Lines
    rows : (n,) int ndarray
        The cards' lines, each ``sum(widths)`` columns long (checked by the caller).
    buf : (n * (sum(widths) + 1),) uint8 ndarray
        Those lines back to back, newlines included.
    card : tuple
        ``(widths, kinds, names)``.

    Returns
    -------
    ints : (n, kinds.count("i")) ndarray
        int32 for fields of up to 9 columns, else int64.
    reals : (n, kinds.count("f")) float64 ndarray

    Raises
    ------
    DicerError
        At the first character that does not fit the first card's layout, naming its line
        and column.
    """
    widths, kinds, _ = card
    length = sum(widths) + 1
    try:
        layout = layout_of_columns(bytes(buf[:length]), widths)
        if layout.kinds != kinds:  # a real where an integer belongs, or the other way round
            j = next(j for j in range(len(kinds)) if layout.kinds[j] != kinds[j])
            raise FormatError(sum(widths[:j]), f"{'a real' if layout.kinds[j] == 'f' else 'an integer'} field")
        return parse_records(buf, layout)
    except FormatError as exc:
        i, col = divmod(exc.offset, length)  # whole cards: the offset gives the card and column
        raise _card_error(lines, int(rows[min(i, rows.size - 1)]), col, card, exc.message) from None


def _block_rows(key_rows: np.ndarray, bounds: np.ndarray, blocks: np.ndarray, comment: np.ndarray):
    """The non-comment lines of many blocks.

    Parameters
    ----------
    key_rows : (K,) int ndarray
        The keyword lines.
    bounds : (K + 1,) int ndarray
        ``key_rows``, then the line count.
    blocks : (S,) int ndarray
        Indices into ``key_rows``, increasing.
    comment : (n,) bool ndarray

    Returns
    -------
    rows : (r,) int64 ndarray
        The lines, in file order.
    owner : (r,) int ndarray
        The index into ``blocks`` of each line's block.
    first, count : (S,) int ndarray
        Where each block's lines start in ``rows``, and how many there are.
    """
    lo, hi = key_rows[blocks] + 1, bounds[blocks + 1]
    size = hi - lo
    rows = np.arange(int(size.sum()), dtype=np.int64) + np.repeat(lo - (np.cumsum(size) - size), size)
    owner = np.repeat(np.arange(blocks.size), size)
    keep = ~comment[rows]
    rows, owner = rows[keep], owner[keep]
    count = np.bincount(owner, minlength=blocks.size)
    return rows, owner, np.cumsum(count) - count, count


def _cards_per_block(lines: Lines, key_rows, bounds, comment, blocks, want: int, message: str, columns: int):
    """``(rows, first)`` (see :func:`_block_rows`) of blocks that must hold ``want`` non-comment lines
    each, the last one (the data card) at least ``columns`` long; DicerError naming the line."""
    rows, _, first, count = _block_rows(key_rows, bounds, blocks, comment)
    if np.any(count != want):
        raise DicerError(f"line {key_rows[blocks[int(np.flatnonzero(count != want)[0])]] + 1}: {message}")
    data = rows[first + want - 1]
    short = lines.lengths[data] < columns
    if short.any():
        row = int(data[np.flatnonzero(short)[0]])
        raise DicerError(f"line {row + 1}: {message.split()[0]} card has {lines.lengths[row]} columns, "
                         f"expected at least {columns}")
    return rows, first


def _parts(lines: Lines, key_rows, bounds, comment, blocks: dict, out: dict) -> None:
    """The *PART, *SECTION_SOLID and *MAT_ELASTIC blocks (one per material: thousands for an atlas),
    each field converted for all blocks of a kind at once, into ``out``."""
    if blocks["*PART"].size:
        rows, first = _cards_per_block(lines, key_rows, bounds, comment, blocks["*PART"], 2,
                                       "*PART needs a title card and one data card", 30)
        pid, secid, mid = (lines.ints(rows[first + 1], 10 * k, 10, "*PART") for k in range(3))
        for t, p, s, m in zip(rows[first], pid.tolist(), secid.tolist(), mid.tolist()):
            out["parts"][p] = {"title": lines.text(t).strip(), "secid": s, "mid": m}
    if blocks["*SECTION_SOLID"].size:
        rows, first = _cards_per_block(lines, key_rows, bounds, comment, blocks["*SECTION_SOLID"], 1,
                                       "*SECTION_SOLID needs one data card", 20)
        secid = lines.ints(rows, 0, 10, "*SECTION_SOLID")
        elform = lines.ints(rows, 10, 10, "*SECTION_SOLID ELFORM")
        out["sections"] = sections = {}
        for s, e in zip(secid.tolist(), elform.tolist()):
            sections[s] = e
    if blocks["*MAT_ELASTIC"].size:
        rows, first = _cards_per_block(lines, key_rows, bounds, comment, blocks["*MAT_ELASTIC"], 1,
                                       "*MAT_ELASTIC needs one data card", 40)
        mid = lines.ints(rows, 0, 10, "*MAT_ELASTIC")
        ro, e, pr = (lines.floats(rows, 10 * k, 10, "*MAT_ELASTIC") for k in (1, 2, 3))
        for m, values in zip(mid.tolist(), zip(ro.tolist(), e.tolist(), pr.tolist())):
            out["materials"][m] = values


def _gather(lines: Lines, rows: np.ndarray, length: int) -> np.ndarray:
    """(len(rows) * length,) uint8: the first ``length`` bytes of each line ``rows``, back to back."""
    out = np.empty((rows.size, length), np.uint8)
    for a in range(0, rows.size, CHUNK_ROWS):  # a chunk at a time: the index array stays a few MB
        r = rows[a : a + CHUNK_ROWS]
        out[a : a + r.size] = lines.arr[lines.starts[r][:, None] + np.arange(length)]
    return out.ravel()


def _titled_sets(lines: Lines, key_rows: np.ndarray, bounds: np.ndarray, blocks: np.ndarray, comment: np.ndarray,
                 least: int, message: str) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The titles of set blocks (a title card, a SID card, data cards), and their data cards' lines
    with the index of the block each belongs to; DicerError ``message`` naming the first block
    of fewer than ``least`` cards."""
    rows, sid, first, count = _block_rows(key_rows, bounds, blocks, comment)
    if np.any(count < least):
        raise DicerError(f"line {key_rows[blocks[int(np.flatnonzero(count < least)[0])]] + 1}: {message}")
    names = [lines.text(r).strip() for r in rows[first]]
    data = np.arange(rows.size) - np.repeat(first, count) >= 2  # after the title and SID cards
    return names, rows[data], sid[data]


def _node_sets(lines: Lines, key_rows: np.ndarray, bounds: np.ndarray, blocks: np.ndarray,
               comment: np.ndarray) -> dict:
    """The *SET_NODE_LIST_TITLE blocks, all sets' cards checked and converted together.

    Each block holds a title card, a SID card and data cards of 8 x I10 node ids, all
    full but the last.

    Parameters
    ----------
    lines : Lines
    key_rows : (K,) int ndarray
        The keyword lines.
    bounds : (K + 1,) int ndarray
        ``key_rows``, then the line count.
    blocks : (S,) int ndarray
        The indices (into ``key_rows``) of the node set blocks, in file order (at least one).
    comment : (n,) bool ndarray
        Comment lines (``$``), left out.

    Returns
    -------
    dict
        title -> (m,) int64 0-based node ids, in file order (a later set of a title
        replaces an earlier one).

    Raises
    ------
    DicerError
        Naming the line.
    """
    names, rows, sid = _titled_sets(lines, key_rows, bounds, blocks, comment, 2,
                                    "*SET_NODE_LIST_TITLE needs a title and a data card")
    length = lines.lengths[rows]
    last = np.ones(rows.size, bool)  # the last card of its set
    last[:-1] = sid[1:] != sid[:-1]
    full = _SET_FIELD * 8
    for bad, why in ((length % _SET_FIELD != 0, "cards must be whole 10-column fields"),
                     (length > full, f"a card of more than {full} columns"),
                     ((length < full) & ~last, "only the last card may be short")):
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DicerError(f"line {rows[i] + 1}: node set {names[sid[i]]}: {why}")
    per = length // _SET_FIELD  # ids per card
    at = np.cumsum(per) - per  # where each card's ids go
    flat = np.empty(int(per.sum()), np.int64)
    # the full cards together, then the short last cards a length at a time (at most 7 lengths)
    for k in np.unique(per[per > 0]).tolist():
        pick = np.flatnonzero(per == k)
        card = ((_SET_FIELD,) * k, "i" * k, ("node set",) * k)
        ints, _ = _parse_cards(lines, rows[pick], _gather(lines, rows[pick], _SET_FIELD * k + 1), card)
        flat[at[pick][:, None] + np.arange(k)] = ints
    flat -= 1
    ends = np.cumsum(np.bincount(sid, weights=per, minlength=blocks.size).astype(np.int64))
    out: dict = {}
    for name, ids in zip(names, np.split(flat, ends[:-1])):
        out[name] = ids
    return out


def _segment_sets(lines: Lines, key_rows: np.ndarray, bounds: np.ndarray, blocks: np.ndarray,
                  comment: np.ndarray) -> dict:
    """The *SET_SEGMENT_TITLE blocks: a title card, a SID card and a card of 4 x I10 node ids per
    face, all sets' cards checked and converted together (arguments as :func:`_node_sets`).

    Returns
    -------
    dict
        title -> (F, 4) int64 0-based node ids, in file order.

    Raises
    ------
    DicerError
        Naming the line.
    """
    names, rows, sid = _titled_sets(lines, key_rows, bounds, blocks, comment, 3,
                                    "*SET_SEGMENT_TITLE needs a title, a SID card and a segment card")
    width = 4 * _SET_FIELD
    wrong = lines.lengths[rows] != width
    if wrong.any():
        i = int(np.flatnonzero(wrong)[0])
        raise DicerError(f"line {rows[i] + 1}: segment set {names[sid[i]]}: a segment card is four 10-column node "
                         f"ids ({width} columns), this one {lines.lengths[rows[i]]}")
    card = ((_SET_FIELD,) * 4, "iiii", ("segment node",) * 4)
    ints, _ = _parse_cards(lines, rows, _gather(lines, rows, width + 1), card)
    ends = np.cumsum(np.bincount(sid, minlength=blocks.size))
    return {name: faces.astype(np.int64) - 1 for name, faces in zip(names, np.split(ints, ends[:-1]))}


def check_lsdyna(path: str | Path, model) -> None:
    """Re-read an LS-DYNA keyword file with :func:`read_lsdyna` and compare it with the model.

    Parameters
    ----------
    path : str or Path
        The keyword file.
    model : SolverModel
        Linear hexahedra.

    Raises
    ------
    DicerError
        The first difference.
    """
    got = _read_lsdyna(path)
    compare(model, got["points"], got["cells"], got["material"], "the keyword file", digits=9)
    for name, ids in model.node_sets.items():
        if not np.array_equal(got["node_sets"].get(name, np.zeros(0)), ids):
            raise DicerError(f"node set {name} differs")
    faces = model.face_sets()
    if set(got["segment_sets"]) != set(faces):
        raise DicerError(f"segment sets {sorted(got['segment_sets'])} where the model has {sorted(faces)}")
    for name, rows in faces.items():
        if not np.array_equal(got["segment_sets"][name], model.facets(rows)):
            raise DicerError(f"segment set {name} differs")
    for k in model.labels():
        if got["parts"].get(k, {}).get("title") != model.names[k] or k not in got["materials"]:
            raise DicerError(f"part or material {model.names[k]} missing")



FORMAT = Format("lsdyna", (".k", ".key", ".dyn"), write_lsdyna, check_lsdyna, dims=(3,), orders=(1,),
                limits="LS-DYNA export writes 8-node hexahedra only (3D meshes, export.order 1); export a 3D "
                       "mesh at export.order 1, or this one to .inp (a 2D one as CPS4/CPE4) or another format",
                digits=(9,), warn=_warn_of_rounded_constants)  # E16 columns
