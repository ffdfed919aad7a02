"""FEBio input file (``.feb``, FEBio XML format 4.0): the model part, ready for a
boundary condition, a load and a ``<Control>`` section.

::

    <febio_spec version="4.0">
      <Module type="solid"/>
      <Material>        per material: <material id name type="isotropic elastic"> E, v, density
      <Mesh>
        <Nodes name="model">                 <node id="1">x,y,z</node>, numbered from 1
        <Elements type="hex8" name=<material>>   one per material, <elem id> = Abaqus element number
        <NodeSet name=...>                   the Abaqus deck's node sets (planes, boundaries,
                                             interfaces, EXTERIOR, CAVITIES), comma-separated node numbers
        <Surface name="EXTERIOR">, <Surface name="CAVITIES">, <Surface name="<a>_<b>">
                                             <quad4 id> (order 2: <quad8>) facets
      <MeshDomains>     <SolidDomain name=<material> mat=<material>/> per material

Hexahedra only (``hex8``, ``hex20``): FEBio has no plane-stress or plane-strain
elements. Node order within an element is VTK's, which is FEBio's for hex8 and, for
hex20, Abaqus C3D20's (bottom, top, then vertical mid-edge nodes), so dicer's order is
written as it is. Surface facets are listed counter-clockwise seen from outside the
element they belong to (outward normal, as FEBio's pressure loads expect); an
interface facet ``<a>_<b>`` belongs to material a and points into material b.

Lines are formatted in bulk by :mod:`dicer.export.textfmt` and written without the
blank padding of fixed-width fields. Coordinates carry ``export.digits`` significant
digits; the provenance goes into XML comments; nothing depends on the date.

The read-back check (:func:`check_febio`) reads the file with :func:`read_febio`: the row
lines (``<node>``, ``<elem>``, ``<quad4>``, ``<quad8>``), which must be one to a line as
written, are checked and converted in bulk with numpy, the rest of the file goes through
ElementTree; what was read is compared with the model chunk by chunk.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.textfmt import Float, Int, Sci, int_lines, int_width, write_chunks

SPEC_VERSION = "4.0"
FEBIO_TYPES = {1: "hex8", 2: "hex20"}
FACET_TYPES = {1: "quad4", 2: "quad8"}
MATERIAL_TYPES = ("isotropic elastic", "neo-Hookean")
PER_LINE = 16  # node numbers per line of a node set


def _num(v: float) -> str:
    return f"{float(v):.12g}"


def _comment(text: str) -> str:
    # "--" may not appear inside an XML comment (a file name could hold one)
    return "<!-- " + text.replace("--", "- -") + " -->\n"


def _rows(stream, tag: bytes, ids: np.ndarray, values: np.ndarray, width: int, fmt: Sci | None = None) -> None:
    """Lines ``<tag id="ID">v1,v2,...</tag>`` for every row of ``values`` (ints, or floats with ``fmt``)."""
    indent = b"\t\t\t<" + tag + b' id="'
    close = b"</" + tag + b">\n"

    def fields(a, b):
        v = values[a:b]
        row = [indent, Int(ids[a:b], width), b'">']
        for j in range(v.shape[1]):
            lead = b"," if j else b""
            row.append(Float(v[:, j], fmt, lead) if fmt else Int(v[:, j], width, lead))
        return row + [close]

    write_chunks(stream, ids.size, fields, compact=True)


def write_febio(model, path: str | Path, *, material_type: str) -> None:
    """Write a SolverModel (3D) as an FEBio 4.0 input file.

    Parameters
    ----------
    model : SolverModel
    path : str or Path
        The ``.feb`` file.
    material_type : {"isotropic elastic", "neo-Hookean"}
        FEBio material of every domain (both take E, v and density from the config's
        materials).
    """
    if model.dim != 3:
        raise ValueError("FEBio has no plane elements; export 3D meshes to .feb")
    if material_type not in MATERIAL_TYPES:
        raise ValueError(f"FEBio material type {material_type!r}: choose one of {', '.join(MATERIAL_TYPES)}")
    width = int_width(max(model.n_points, model.n_cells, 1))
    fmt = Sci(13 if model.digits > 9 else 9)
    labels = model.labels()
    with open(path, "wb", buffering=1 << 20) as f:
        w = f.write
        w(b'<?xml version="1.0" encoding="ISO-8859-1"?>\n')
        for line in model.heading:
            w(_comment(line).encode())
        w(_comment(f"{model.n_points} nodes, {model.n_cells} {FEBIO_TYPES[model.order]} elements").encode())
        w(f'<febio_spec version="{SPEC_VERSION}">\n\t<Module type="solid"/>\n\t<Material>\n'.encode())
        for i, k in enumerate(labels, start=1):  # FEBio wants material ids 1, 2, ... in order
            p = model.props[k]
            w(f'\t\t<material id="{i}" name="{model.names[k]}" type="{material_type}">\n'
              f"\t\t\t<density>{_num(p['density'])}</density>\n\t\t\t<E>{_num(p['youngs_modulus'])}</E>\n"
              f"\t\t\t<v>{_num(p['poissons_ratio'])}</v>\n\t\t</material>\n".encode())
        w(b'\t</Material>\n\t<Mesh>\n\t\t<Nodes name="model">\n')
        _rows(f, b"node", np.arange(1, model.n_points + 1), model.points, width, fmt)
        w(b"\t\t</Nodes>\n")
        for k, elements in model.blocks():
            w(f'\t\t<Elements type="{FEBIO_TYPES[model.order]}" name="{model.names[k]}">\n'.encode())
            _rows(f, b"elem", elements + 1, model.cells[elements] + 1, width)
            w(b"\t\t</Elements>\n")
        for name, ids in model.node_sets.items():
            w(f'\t\t<NodeSet name="{name}">\n'.encode())
            # lines of 16 numbers; the comma that joins two lines goes at the end of the first
            text = int_lines(ids + 1, PER_LINE, width).replace(b" ", b"")
            w(text[:-1].replace(b"\n", b",\n") + b"\n")
            w(b"\t\t</NodeSet>\n")
        ftype = FACET_TYPES[model.order].encode()
        for name, faces in model.face_sets().items():
            w(f'\t\t<Surface name="{name}">\n'.encode())
            _rows(f, ftype, np.arange(1, faces.shape[0] + 1), model.facets(faces) + 1, width)
            w(b"\t\t</Surface>\n")
        w(b"\t</Mesh>\n\t<MeshDomains>\n")
        for k in labels:
            w(f'\t\t<SolidDomain name="{model.names[k]}" mat="{model.names[k]}"/>\n'.encode())
        w(b"\t</MeshDomains>\n</febio_spec>\n")


# --- reader ---------------------------------------------------------------------------------
#
# Nearly all of a large file is row lines, one to a line as the writer puts them:
#
#     \t\t\t<node id="7">1.30000000e+01,-1.15000000e+02,1.26000000e+02</node>\n
#     \t\t\t<elem id="7">1,712,744,9,2,713,745,10</elem>\n           (also <quad4>, <quad8>)
#
# One XML event per row costs a minute on a mesh of millions of elements, so the reader
# finds the runs of consecutive row lines with numpy, checks and converts them with
# whole-array operations, a chunk of lines at a time, and hands the rest of the file --
# the skeleton, each run replaced by a placeholder element -- to ElementTree, which checks
# its XML and every section as before and says in which block each run sits.
#
# Every byte of a row line is checked: the prefix and the suffix as words, the '">' after
# the id, the commas by position (k - 1 to a line, between the '">' and the suffix, no
# value empty), the id and the values by content where they are converted.

_ROWS = {"node": "Nodes", "elem": "Elements", "quad4": "Surface", "quad8": "Surface"}  # row tag -> its block
_TAGS = tuple(_ROWS)
_PLACEHOLDER = "_rows"
_SCAN = 1 << 22  # bytes per newline search
_CHUNK = 1 << 14  # row lines checked and converted at a time: temporaries stay cache-sized
_NL, _QUOTE, _PLUS, _COMMA, _MINUS, _ZERO, _GT, _E = 10, 34, 43, 44, 45, 48, 62, 101
_POW10 = 10.0 ** np.arange(23)  # exact powers of ten (10**22 is the largest exact double)
# 10**k as (multiplier, divisor) at k + 22 for |k| <= 22, one of them 1: M * mul / div rounds once
_SCALE = np.concatenate([np.ones(22), _POW10]), np.concatenate([_POW10[:0:-1], np.ones(23)])
_U = np.uint64
_ZEROS8 = np.frombuffer(b"00000000", "<u8")[0]
_HIGH = _U(0x8080808080808080)
_NINES = _U(0x7676767676767676)  # + a byte 0..9 stays below 0x80, + 10 or more reaches it
_LANES = _U(0x0001020304050607)  # (the lowest set byte's 0x01) * this >> 56: that byte's index
_ID_END = np.frombuffer(b'">\0\0\0\0\0\0', "<u8")[0]
# _KEEP[n]: the n highest bytes of a little-endian word, the last n of its 8 in the file
_KEEP = np.array([(0xFFFFFFFFFFFFFFFF << (8 * (8 - n))) & 0xFFFFFFFFFFFFFFFF for n in range(9)], np.uint64)


def _prefix(tag: str) -> bytes:
    return b"\t\t\t<" + tag.encode() + b' id="'


def _suffix(tag: str) -> bytes:
    return b"</" + tag.encode() + b">\n"


def _word(text: bytes) -> np.uint64:
    """8 bytes as the little-endian word a gather from :func:`_words` gives."""
    return np.frombuffer(text, "<u8")[0]


def _words(buf: np.ndarray, width: int = 8) -> np.ndarray:
    """(size - width + 1,) view of ``buf`` whose item i is bytes i .. i + width - 1 (a
    little-endian uint64 for width 8, else ``V<width>``): one gather fetches them from any offset."""
    return np.ndarray((max(buf.size - width + 1, 0),), "<u8" if width == 8 else f"V{width}", buf, 0, (1,))


def _eight_digits(d: np.ndarray) -> np.ndarray:
    """(m,) uint64 words of 8 digit values (0..9, the first byte the most significant) -> the
    numbers, in place (SWAR: pairs, quads, then all eight)."""
    d *= _U(2561)
    d >>= _U(8)
    d &= _U(0x00FF00FF00FF00FF)
    d *= _U(6553601)
    d >>= _U(16)
    d &= _U(0x0000FFFF0000FFFF)
    d *= _U(42949672960001)
    d >>= _U(32)
    return d


class _Run(NamedTuple):
    """Consecutive row lines of one tag.

    tag : str
    line : int
        1-based line number of the first.
    start : int
        Offset of the first line's first byte (a line starts after its predecessor's newline).
    ends : (n,) int64 ndarray
        Offset of each line's newline.
    """

    tag: str
    line: int
    start: int
    ends: np.ndarray

    def lines(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """First bytes and newlines, (m,) int64 each, of lines a .. b - 1."""
        e = self.ends[a:b]
        s = np.empty_like(e)
        s[:1] = self.start if a == 0 else self.ends[a - 1] + 1
        np.add(e[:-1], 1, out=s[1:])
        return s, e


def _lines(run: _Run) -> str:
    """The file lines of a run, for messages."""
    last = run.line + run.ends.size - 1
    return f"line {run.line}" if last == run.line else f"lines {run.line}-{last}"


def _codes(buf: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(n,) int8: 1 + the index in ``_TAGS`` of the row prefix the lines at ``starts`` begin with, else 0.

    A word gathered per line compares its first 8 bytes with the prefixes' (``\t\t\t<node``,
    ``\t\t\t<elem``, ``\t\t\t<quad``); only on those candidates the prefix's last 8 bytes
    are gathered and compared.
    """
    code = np.zeros(starts.size, np.int8)
    if buf.size < 16:
        return code
    words = _words(buf)
    room = starts + 16 <= buf.size  # a prefix (at most 14 bytes) and its words lie inside
    head = words[np.where(room, starts, 0)]
    for c, tag in enumerate(_TAGS, start=1):
        pre = _prefix(tag)
        cand = np.flatnonzero((head == _word(pre[:8])) & room)
        code[cand[words[starts[cand] + len(pre) - 8] == _word(pre[-8:])]] = c
    return code


def _row_runs(buf: np.ndarray) -> list[_Run]:
    """The runs of row lines: lines that begin exactly with a row prefix (``\\t\\t\\t<node id="``, ...)
    and end with a newline.

    The newlines are searched, and the lines after them classified, a cache-sized chunk
    of bytes at a time, chunks side by side in threads.

    Parameters
    ----------
    buf : (size,) uint8 ndarray

    Returns
    -------
    list of _Run
        In file order.
    """
    from dicer.parallel import ordered_map

    def scan(a: int):
        ends = np.flatnonzero(buf[a : a + _SCAN] == _NL) + a
        return ends, _codes(buf, ends + 1)  # the line after each newline

    parts = list(ordered_map(scan, range(0, buf.size, _SCAN)))
    if not parts:
        return []
    ends = np.concatenate([p[0] for p in parts]).astype(np.int64, copy=False)
    # line i ends at ends[i]; the line after the last newline has none and is no row
    code = np.concatenate([_codes(buf, np.zeros(1, np.int64))] + [p[1] for p in parts])[: ends.size]
    del parts
    edges = np.flatnonzero(code[1:] != code[:-1]) + 1  # where a run of one code starts or ends
    edges = np.concatenate([[0], edges, [code.size]]).tolist()
    return [_Run(_TAGS[code[a] - 1], a + 1, int(ends[a - 1]) + 1 if a else 0, ends[a:b])
            for a, b in zip(edges[:-1], edges[1:]) if code[a]]


def _skeleton(buf: np.ndarray, runs: list[_Run]) -> tuple[bytes, np.ndarray, np.ndarray]:
    """The file with run j replaced by the one line ``<_rows k="j"/>``.

    Returns
    -------
    bytes
    at, removed : (J,) int64 ndarray
        The skeleton line of each placeholder, and the file lines taken out up to and
        including it (to give ElementTree's errors the file's line numbers).
    """
    parts, at = [], 0
    for j, run in enumerate(runs):
        a, b = run.start, int(run.ends[-1]) + 1
        parts += [buf[at:a].tobytes(), b'<%s k="%d"/>\n' % (_PLACEHOLDER.encode(), j)]
        at = b
    parts.append(buf[at:].tobytes())
    taken = np.array([run.ends.size - 1 for run in runs], np.int64)
    removed = np.cumsum(taken)
    return b"".join(parts), np.array([run.line for run in runs], np.int64) - removed + taken, removed


def _digit_run(d: np.ndarray) -> np.ndarray:
    """(m,) int64: how many of the 8 bytes of each word ``d`` (uint64, bytes XOR '0') are digits
    before the first byte that is not one (8: all are)."""
    other = (d + _NINES) | d
    other &= _HIGH  # 0x80 in the bytes that are not digits
    none = other == 0
    other &= ~other + _U(1)  # the first of them
    other >>= _U(7)
    other *= _LANES
    other >>= _U(56)
    other[none] = 8
    return other.view(np.int64)


def _ids(buf: np.ndarray, at: np.ndarray):
    """Ids of 1 to 15 digits that start at ``at`` and end with ``">``, from a word or two each.

    Returns
    -------
    q, ids : (r,) int64 ndarray
        The ``"`` after each id, and the ids; None if an id is empty, of 16 digits or
        more, or not followed by ``">``.
    """
    words = _words(buf)
    d = words[at] ^ _ZEROS8  # digits -> 0..9
    width = _digit_run(d)
    long = np.flatnonzero(width == 8)  # ids of 8 digits or more (meshes of 10 M nodes)
    if long.size:
        width[long] += _digit_run(words[at[long] + 8] ^ _ZEROS8)
    q = at + width
    if width.min() < 1 or width.max() > 15 or not np.all((words[q] & _U(0xFFFF)) == _ID_END):
        return None
    d <<= (_U(8) - np.minimum(width, 8).view(np.uint64)) * _U(8)  # the id's digits to the top (_eight_digits)
    ids = _eight_digits(d).view(np.int64)
    if long.size:
        ids[long] = _uints(buf, q[long], width[long])
    return q, ids


def _layout(buf: np.ndarray, s: np.ndarray, e: np.ndarray, tag: str, k: int):
    """Ids, and where the values of row lines end, if every line is PREFIX ID ``">`` v1,...,vk SUFFIX.

    The prefix was compared when the line was taken for a row. Ids must be integers of
    1 to 18 digits, values non-empty; the values' bytes are checked by the caller.

    Parameters
    ----------
    buf : uint8 ndarray
    s, e : (r,) int64 ndarray
        Consecutive lines: first byte, newline.
    tag : str
    k : int
        Values per row.

    Returns
    -------
    ids : (r,) int64 ndarray
    stop, width : (r, k) int64 ndarray
        End (exclusive) and length of each value. None instead of the three when a line
        is out of shape.
    """
    pre, suf = _prefix(tag), _suffix(tag)
    r = s.size
    lo = int(s[0])
    text = buf[lo : int(e[-1]) + 1]
    words = _words(buf)
    mid_end = e + 1 - len(suf)  # where the suffix starts
    if not (words[mid_end] == _word(suf[:8])).all() or (len(suf) > 8 and not (words[e - 7] == _word(suf[-8:])).all()):
        return None
    got = _ids(buf, s + len(pre))
    if got is None:  # ids of 16 digits or more (or a line out of shape): the quotes tell where they end
        quotes = np.flatnonzero(text == _QUOTE)
        if quotes.size != 2 * r:
            return None
        quotes = quotes.reshape(r, 2) + lo
        q = quotes[:, 1]
        if not (np.array_equal(quotes[:, 0], s + (len(pre) - 1)) and np.all(q > s + len(pre))
                and np.all(buf[q + 1] == _GT)):
            return None
        ids = _uints(buf, q, q - s - len(pre))
        if ids is None:
            return None
    else:
        q, ids = got
    # the k - 1 commas of a line lie between its '">' and its suffix, none next to another:
    # in sorted order they make the rows of an (r, k - 1) table only if every line holds
    # its count, and the order of the table's bounds (every width >= 1) shows that it does
    commas = np.flatnonzero(text == _COMMA)
    if commas.size != r * (k - 1):
        return None
    stop = np.empty((r, k), np.int64)
    stop[:, : k - 1] = commas.reshape(r, k - 1)
    stop[:, : k - 1] += lo
    stop[:, k - 1] = mid_end
    width = np.empty((r, k), np.int64)
    np.subtract(stop[:, 1:], stop[:, :-1], out=width[:, 1:])
    width[:, 1:] -= 1
    np.subtract(stop[:, 0], q + 2, out=width[:, 0])
    if width.min() < 1:
        return None
    return ids, stop, width


def _uints(buf: np.ndarray, stop: np.ndarray, width: np.ndarray, out: np.ndarray | None = None) -> np.ndarray | None:
    """Values of the decimal digit strings ``buf[stop_i - width_i : stop_i]`` (1 to 18 digits).

    Eight digits a step: the 8 bytes that end a string's next group are gathered as one
    word, the bytes before the string cleared, every byte checked to be a digit and the
    8 digits converted at once (SWAR).

    Parameters
    ----------
    buf : uint8 ndarray
    stop, width : (m,) int64 ndarray
    out : (m,) int64 ndarray, optional

    Returns
    -------
    (m,) int64 ndarray
        ``out`` if given; None if a byte is not a digit or a string is longer than 18 digits.
    """
    top = int(width.max()) if width.size else 0
    out = np.zeros(stop.size, np.int64) if out is None else out
    if top > 18:
        return None
    words = _words(buf)
    for g in range((top + 7) // 8):
        d = words[np.maximum(stop - 8 * (g + 1), 0)]
        d ^= _ZEROS8  # a digit byte becomes its value
        d &= _KEEP[np.clip(width - 8 * g, 0, 8) if top > 8 else width]
        bad = d + _NINES
        bad |= d
        bad &= _HIGH
        if bad.any():
            return None
        if g:
            out += _eight_digits(d).view(np.int64) * 10 ** (8 * g)
        else:
            np.copyto(out, _eight_digits(d).view(np.int64))
    return out


def _float_layout(token: bytes):
    """(length, digits after the point) of a number printed ``d.ddd[eE][+-]XX`` (dicer's, unsigned),
    or None: the layout the numbers of a chunk are read in."""
    import re

    m = re.fullmatch(rb"-?[0-9]\.([0-9]+)[eE][+-][0-9][0-9]", token)
    if m is None or len(m.group(1)) > 14:  # at most 15 digits: exact in a double
        return None
    return len(m.group(1)) + 6, len(m.group(1))


def _floats(buf: np.ndarray, stop: np.ndarray, width: np.ndarray, layout, out: np.ndarray) -> np.ndarray:
    """The numbers ``buf[stop_i - width_i : stop_i]`` that are in ``layout``, correctly rounded.

    ``[-]d.ddd[eE][+-]XX``: a window that ends where the number ends is gathered for
    each and compared with the layout's template word by word, the digits give the
    integer mantissa M (at most 15 digits, exact) and the exponent k, and
    ``M * 10**k`` (``M / 10**-k``) is one correctly rounded operation on exact operands
    while ``|k| <= 22``: bit for bit what strtod gives.

    Parameters
    ----------
    buf : uint8 ndarray
    stop, width : (m,) int64 ndarray
    layout : (int, int) or None
        From :func:`_float_layout`.
    out : (m,) float64 ndarray
        Takes the numbers.

    Returns
    -------
    (p,) int64 ndarray
        The numbers not read (their ``out`` undefined): another notation, or |k| > 22.
    """
    if layout is None or not stop.size:
        return np.arange(stop.size)
    n, f = layout
    size = -(-(n + 1) // 8) * 8  # whole words; the last n + 1 bytes: the sign's column and the number
    o = size - n - 1  # the sign's column
    win = _words(buf, size)[np.maximum(stop - size, 0)].view(np.uint8).reshape(-1, size)
    d = win - np.uint8(_ZERO)  # digit values; any other byte wraps above 9
    d *= d < 10
    canon = win - d  # digits -> '0'
    # the template: '0' where a digit belongs, the point; 0 where the bytes are checked apart
    # (before the number, its sign, the exponent's letter and sign)
    template = np.zeros(size, np.uint8)
    template[o + 1 :] = np.frombuffer(b"0." + b"0" * f + b"\0\x0000", np.uint8)
    mask = np.full(size, 0xFF, np.uint8)
    mask[[*range(o + 1), o + 3 + f, o + 4 + f]] = 0
    canon = canon.view("<u8")
    canon &= mask.view("<u8")
    fast = np.ones(stop.size, bool)
    for j, word in enumerate(template.view("<u8")):
        fast &= canon[:, j] == word
    exp = win[:, o + 4 + f]
    neg = (width == n + 1) & (win[:, o] == _MINUS)
    fast &= ((width == n) | neg) & (stop >= size)
    fast &= ((win[:, o + 3 + f] | np.uint8(0x20)) == _E) & ((exp == _PLUS) | (exp == _MINUS))  # e or E; + or -
    mant = d[:, o + 1].astype(np.float64)
    for c in range(o + 3, o + 3 + f):
        mant *= 10
        mant += d[:, c]
    k = d[:, o + 5 + f].astype(np.int64) * 10 + d[:, o + 6 + f]
    np.negative(k, out=k, where=exp == _MINUS)
    k -= f
    fast &= np.abs(k) <= 22
    np.clip(k, -22, 22, out=k)
    k += 22
    mant *= _SCALE[0][k]
    np.divide(mant, _SCALE[1][k], out=out)
    np.negative(out, out=out, where=neg)
    return np.flatnonzero(~fast)


def _slow_floats(buf: np.ndarray, stop: np.ndarray, width: np.ndarray, what: str) -> np.ndarray:
    """(m,) float64: numbers of other notations, by ``np.fromstring`` (strictly: ``[0-9+-.eE]`` only)."""
    n = width + 1  # each with a separator
    off = np.cumsum(n) - n
    text = buf[np.arange(int(n.sum())) - np.repeat(off - (stop - width), n)]
    text[off + n - 1] = _COMMA
    allowed = np.zeros(256, bool)
    allowed[list(b"0123456789+-.eE,")] = True
    got = _parse(text[:-1].tobytes(), np.float64, what) if allowed[text].all() else np.zeros(0)
    if got.size != stop.size:
        raise DicerError(f"{what}: not a number among the values")
    return got


def _chunk(buf: np.ndarray, s: np.ndarray, e: np.ndarray, tag: str, k: int, floats: bool, ids: np.ndarray,
           values: np.ndarray):
    """Check and convert row lines into ``ids`` (r,) and ``values`` (r, k).

    Returns
    -------
    False if a line is out of shape, else the floats left to :func:`_slow_floats`
    (stop, width, flat positions in ``values``) or None: that reader is not safe in a
    worker thread.
    """
    got = _layout(buf, s, e, tag, k)
    if got is None:
        return False
    ids[:], stop, width = got
    stop, width, flat = stop.reshape(-1), width.reshape(-1), values.reshape(-1)
    if not floats:
        return None if _uints(buf, stop, width, out=flat) is not None else False
    slow = _floats(buf, stop, width, _float_layout(buf[stop[0] - width[0] : stop[0]].tobytes()), flat)
    return (stop[slow], width[slow], slow) if slow.size else None


def _explain(buf: np.ndarray, s: np.ndarray, e: np.ndarray, tag: str, k: int, floats: bool, what: str,
             row0: int, line0: int) -> None:
    """Raise DicerError naming the first line of a chunk that :func:`_chunk` refused.

    The line is found by bisection with :func:`_chunk`, then read as text for the message.
    """
    def fits(a: int, b: int) -> bool:
        ids, values = np.empty(b - a, np.int64), np.empty((b - a, k), np.float64 if floats else np.int64)
        got = _chunk(buf, s[a:b], e[a:b], tag, k, floats, ids, values)
        if got is False:
            return False
        try:
            if got is not None:
                _slow_floats(buf, got[0], got[1], what)
        except DicerError:
            return False
        return True

    lo, hi = 0, s.size  # the first bad line is in [lo, hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if not fits(lo, mid) else (mid, hi)
    line = buf[s[lo] : e[lo] + 1].tobytes()
    row, where = row0 + lo + 1, f"line {line0 + lo}"
    pre, suf = _prefix(tag), _suffix(tag)
    ident, sep, values = line[len(pre) : len(line) - len(suf)].partition(b'">')
    if not line.endswith(suf):
        raise DicerError(f"{what} {row} ({where}): the line does not end with </{tag}>")
    if not sep or not ident.isdigit():
        raise DicerError(f'{what} {row} ({where}): not <{tag} id="ID">values</{tag}> with an integer ID')
    if len(ident) > 18:
        raise DicerError(f"{what} {row} ({where}): an id of more than 18 digits")
    if b"<" in values:
        raise DicerError(f"{what} {row} ({where}): more than one element on the line")
    if values.count(b",") + 1 != k:
        raise DicerError(f"{what} {row} has {values.count(b',') + 1} values, expected {k} ({where})")
    if not floats and max(len(v) for v in values.split(b",")) > 18:
        raise DicerError(f"{what} {row} ({where}): a number of more than 18 digits")
    odd = values.translate(None, b"0123456789," + (b"+-.eE" if floats else b""))
    raise DicerError(f"{what} {row} ({where}): not a number among the values"
                     + (f" ({odd[:1].decode('latin-1')!r})" if odd else ""))


def _read_run(buf: np.ndarray, run: _Run, k: int, floats: bool, what: str, row0: int):
    """Check and convert a run of row lines, chunks side by side in threads.

    Parameters
    ----------
    buf : uint8 ndarray
    run : _Run
    k : int
        Values per row.
    floats : bool
        float64 values (nodes), else int64.
    what : str
        Names a row in errors ("node", "element of bone").
    row0 : int
        Rows of the block before this run (errors count rows from the block's first).

    Returns
    -------
    ids : (n,) int64 ndarray
    values : (n, k) int64 or float64 ndarray
    """
    from dicer.parallel import ordered_map

    n = run.ends.size
    ids = np.empty(n, np.int64)
    values = np.empty((n, k), np.float64 if floats else np.int64)

    def one(a: int):
        b = a + _CHUNK
        return _chunk(buf, *run.lines(a, b), run.tag, k, floats, ids[a:b], values[a:b])

    for a, got in zip(range(0, n, _CHUNK), ordered_map(one, range(0, n, _CHUNK))):
        try:
            if got is not None and got is not False:  # here, where numpy's warnings are safe to catch
                values[a : a + _CHUNK].reshape(-1)[got[2]] = _slow_floats(buf, got[0], got[1], what)
        except DicerError:
            got = False
        if got is False:
            _explain(buf, *run.lines(a, a + _CHUNK), run.tag, k, floats, what, row0 + a, run.line + a)
    return ids, values


def _block_rows(got: dict, k: int, floats: bool, what: str):
    """Ids (n,) and values (n, k) of the runs placed in the block that ends (none: empty)."""
    buf, runs = got["buf"], got["block"]
    got["block"] = []
    parts, row0 = [], 0
    for run in runs:
        parts.append(_read_run(buf, run, k, floats, what, row0))
        row0 += run.ends.size
    if len(parts) == 1:
        return parts[0]
    if not parts:
        return np.zeros(0, np.int64), np.zeros((0, k), np.float64 if floats else np.int64)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _parse(text: bytes | str, dtype, what: str) -> np.ndarray:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns, and stops, at text that is not a number
        try:
            return np.fromstring(text, dtype=dtype, sep=",")
        except (ValueError, DeprecationWarning):
            raise DicerError(f"{what}: not a number among the values") from None


def read_febio(path: str | Path) -> dict:
    """Read an FEBio 4.0 file as dicer writes it, strictly.

    Row lines (``<node>``, ``<elem>``, ``<quad4>``, ``<quad8>``) are checked and converted
    in bulk with numpy and must be as the writer puts them, one to a line; the rest of
    the file goes through ElementTree. Node ids must run 1..N in order, facet ids 1..F.

    Parameters
    ----------
    path : str or Path
        An XML file, from :func:`write_febio`; FEBio 4.0 only.

    Returns
    -------
    dict
        ``version``, ``module``, ``materials`` (list of dicts: id, name, type, E, v,
        density), ``points`` (N, 3) float64, ``blocks`` (list of (type, name, element
        ids (m,) int64, (m, k) int64 0-based connectivity)), ``node_sets`` (name -> 0-based
        node indices, int64), ``surfaces`` (name -> (facet type, (F, k) int64 0-based
        nodes)) and ``domains`` (list of (name, mat)).

    Raises
    ------
    DicerError
        Anything out of place.
    """
    import mmap

    with open(path, "rb") as f:
        # the page cache's pages, mapped: no copy of a file of a GB
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if os.fstat(f.fileno()).st_size else None
    try:
        return _read(np.frombuffer(mapped, np.uint8) if mapped is not None else np.zeros(0, np.uint8))
    except DicerError as exc:
        message = str(exc)  # raised again below, without the frames that hold views of the map
    finally:
        if mapped is not None:
            try:
                mapped.close()
            except BufferError:  # views still held by an error on its way up: unmapped with them
                pass
    raise DicerError(message)


def _read(buf: np.ndarray) -> dict:
    """:func:`read_febio` of the bytes ``buf`` (uint8)."""
    import io
    import xml.etree.ElementTree as ET

    runs = _row_runs(buf)
    skeleton, at, removed = _skeleton(buf, runs)
    out = {"materials": [], "blocks": [], "node_sets": {}, "surfaces": {}, "domains": []}
    # the bytes, the runs, those placed so far, and those of the Mesh block being read
    got = {"buf": buf, "runs": runs, "placed": set(), "block": []}
    stack: list[str] = []
    parents: list = []
    sections = []
    try:
        for event, el in ET.iterparse(io.BytesIO(skeleton), events=("start", "end")):
            if event == "start":
                stack.append(el.tag)
                parents.append(el)
                if len(stack) == 1:
                    if el.tag != "febio_spec":
                        raise DicerError(f"root element <{el.tag}>, expected <febio_spec>")
                    out["version"] = el.get("version")
                elif len(stack) == 2:
                    sections.append(el.tag)
                elif len(stack) == 3 and stack[1] == "Mesh":
                    got["block"] = []
                continue
            path_ = "/".join(stack)
            stack.pop()
            parents.pop()
            _end_element(path_, el, stack, parents, out, got)
    except ET.ParseError as exc:
        line, column = exc.position
        j = int(np.searchsorted(at, line))  # placeholders above the line: add their runs' lines
        line += int(removed[j - 1]) if j else 0
        raise DicerError(f"not well-formed XML ({str(exc).rsplit(': line', 1)[0]}: line {line}, "
                         f"column {column})") from None
    lost = sorted(set(range(len(runs))) - got["placed"])
    if lost:  # in a comment, a CDATA section or an attribute value of the skeleton
        run = runs[lost[0]]
        raise DicerError(f"<{run.tag}> rows at {_lines(run)} are not elements of the file")
    _complete(out, sections)
    return out


def _complete(out: dict, sections: list[str]) -> None:
    """Raise DicerError unless the file read into ``out`` has every section and valid node references."""
    if out.get("version") != SPEC_VERSION:
        raise DicerError(f"febio_spec version {out.get('version')!r}, expected {SPEC_VERSION!r}")
    for need in ("Module", "Material", "Mesh", "MeshDomains"):
        if need not in sections:
            raise DicerError(f"no <{need}> section")
    if "points" not in out or not out["blocks"]:
        raise DicerError("no <Nodes> or <Elements> in <Mesh>")
    n = out["points"].shape[0]
    for etype, name, _, conn in out["blocks"]:
        if conn.size and (conn.min() < 0 or conn.max() >= n):
            raise DicerError(f"elements of {name} refer to nodes that do not exist")


def _place(el, stack: list[str], got: dict) -> None:
    """Take the placeholder ``el`` of a run into the Mesh block it sits in, if the run belongs there."""
    j = el.get("k", "")
    if not (j.isdigit() and int(j) < len(got["runs"]) and int(j) not in got["placed"]):
        raise DicerError(f"unexpected <{el.tag}> element")
    run = got["runs"][int(j)]
    got["placed"].add(int(j))
    block = _ROWS[run.tag]
    if stack[1:] != ["Mesh", block]:
        raise DicerError(f"<{run.tag}> rows at {_lines(run)} sit in <{stack[-1]}>, not in <Mesh><{block}>")
    got["block"].append(run)


def _end_element(path_: str, el, stack: list[str], parents: list, out: dict, got: dict) -> None:
    """Take in the XML element ``el`` of the skeleton at its end tag (``path_`` its path, ``stack``
    its parents' tags)."""
    if el.tag == _PLACEHOLDER:
        _place(el, stack, got)
        parents[-1].remove(el)
    elif path_ == "febio_spec/Module":
        out["module"] = el.get("type")
    elif path_ == "febio_spec/Material/material":
        mat = {"id": el.get("id"), "name": el.get("name"), "type": el.get("type")}
        for key in ("E", "v", "density"):
            child = el.find(key)
            try:
                mat[key] = float(child.text)
            except (AttributeError, TypeError, ValueError):
                raise DicerError(f"material {mat['name']}: no number in <{key}>") from None
        out["materials"].append(mat)
        el.clear()
    elif len(stack) == 3 and stack[1] == "Mesh" and stack[2] in ("Nodes", "Elements", "Surface"):
        # the rows were taken out as runs: whatever is left here is out of place
        if el.tag in _ROWS:
            raise DicerError(f'a <{el.tag}> row in <{stack[2]}> not on a line of its own as '
                             f'\\t\\t\\t<{el.tag} id="ID">values</{el.tag}>')
        if stack[2] == "Surface":
            raise DicerError(f"facet <{el.tag}> in a surface")
        raise DicerError(f"unexpected <{el.tag}> in <{stack[2]}>")
    elif path_ == "febio_spec/Mesh/Nodes":
        ids, points = _block_rows(got, 3, True, "node")
        if not np.array_equal(ids, np.arange(1, ids.size + 1)):
            raise DicerError("node ids must run 1..N in order")
        out["points"] = points
        el.clear()
    elif path_ == "febio_spec/Mesh/Elements":
        etype = el.get("type")
        if etype not in FEBIO_TYPES.values():
            raise DicerError(f"element type {etype!r}, expected hex8 or hex20")
        k = 8 if etype == "hex8" else 20
        ids, conn = _block_rows(got, k, False, f"element of {el.get('name')}")
        conn -= 1
        out["blocks"].append((etype, el.get("name"), ids, conn))
        el.clear()
    elif path_ == "febio_spec/Mesh/NodeSet":
        name = el.get("name")
        text = (el.text or "").strip()
        ids = _parse(text, np.int64, f"node set {name}") if text else np.zeros(0, np.int64)
        if text and ids.size != text.count(",") + 1:
            raise DicerError(f"node set {name}: not a number among the values")
        if name in out["node_sets"]:
            raise DicerError(f"node set {name} appears twice")
        out["node_sets"][name] = ids - 1
        el.clear()
    elif path_ == "febio_spec/Mesh/Surface":
        name = el.get("name")
        types = {run.tag for run in got["block"]}
        if len(types) > 1:
            raise DicerError(f"surface {name} mixes facet types {sorted(types)}")
        ftype = types.pop() if types else "quad4"
        ids, conn = _block_rows(got, 4 if ftype == "quad4" else 8, False, f"facet of {name}")
        if not np.array_equal(ids, np.arange(1, ids.size + 1)):
            raise DicerError(f"surface {name}: facet ids must run 1..F in order")
        conn -= 1
        out["surfaces"][name] = (ftype, conn)
        el.clear()
    elif path_ == "febio_spec/MeshDomains/SolidDomain":
        out["domains"].append((el.get("name"), el.get("mat")))
    elif len(stack) == 2 and stack[1] == "Mesh" and el.tag not in ("Nodes", "Elements", "NodeSet", "Surface"):
        raise DicerError(f"unexpected <{el.tag}> in <Mesh>")


def _printed_values(points: np.ndarray, fmt: Sci) -> np.ndarray:
    """The floats the writer's text of ``points`` reads back as, found without the text.

    The writer prints ``M * 10**k`` with M the ``fmt.digits``-digit mantissa; like
    :func:`_floats`, one multiplication (or division) of exact operands rounds it as strtod
    does while ``|k| <= 22``; the few others are printed and parsed.

    Parameters
    ----------
    points : (...) float ndarray
    fmt : Sci

    Returns
    -------
    float64 ndarray
        Of the shape of ``points``.
    """
    from dicer.export.textfmt import _mantissa, sci_digits

    x = np.ascontiguousarray(points, np.float64).reshape(-1)
    m, e = _mantissa(x, fmt.digits, False)  # Sci(9) or Sci(13): not the Fortran form
    k = e - (fmt.digits - 1)
    far = np.flatnonzero(np.abs(k) > 22)
    np.clip(k, -22, 22, out=k)
    k += 22
    out = m.astype(np.float64)  # exact: at most 15 digits
    out *= _SCALE[0][k]
    out /= _SCALE[1][k]
    np.negative(out, out=out, where=(x < 0) & (m > 0))  # as printed: no sign on a zero
    if far.size:
        printed = sci_digits(x[far], fmt)
        out[far] = printed.view(f"S{printed.shape[1]}").ravel().astype(np.float64)
    return out.reshape(np.shape(points))


def _compare_points(model, points: np.ndarray, fmt: Sci) -> None:
    """Raise DicerError unless the nodes read are the printed coordinates exactly, within the
    print precision of the model's (:func:`dicer.export.readers.tolerance`).

    Chunks side by side in threads: no array of the size of the mesh is made.

    Parameters
    ----------
    model : SolverModel
    points : (N, 3) float64 ndarray
        Read.
    fmt : Sci
        As written.
    """
    from dicer.export.readers import tolerance
    from dicer.parallel import ordered_map

    if points.shape != model.points.shape:
        raise DicerError(f"the FEBio file has {points.shape[0]} nodes, expected {model.n_points}")
    x, got = np.ascontiguousarray(model.points, np.float64).reshape(-1), points.reshape(-1)
    step = 3 * _CHUNK

    def one(a: int) -> tuple[bool, float]:
        v, g = x[a : a + step], got[a : a + step]
        return np.array_equal(g, _printed_values(v, fmt)), float(np.abs(g - v).max())

    tol = tolerance(model, fmt.digits)
    for exact, err in ordered_map(one, range(0, x.size, step)):
        if not exact:
            raise DicerError("node coordinates differ from the printed values")
        if not err <= tol:
            raise DicerError(f"the FEBio file: node coordinates differ by {err:.3g} mm")


def _compare_cells(model, elements: np.ndarray, conn: np.ndarray) -> None:
    """Raise DicerError unless ``conn`` (m, k), read, is the model's connectivity of ``elements`` (m,)."""
    from dicer.parallel import ordered_map

    if conn.shape != (elements.size, model.cells.shape[1]):
        raise DicerError(f"the FEBio file has elements of {conn.shape[1]} nodes, expected {model.cells.shape[1]}")

    def one(a: int) -> bool:
        return np.array_equal(conn[a : a + _CHUNK], model.cells[elements[a : a + _CHUNK]])

    for a, same in zip(range(0, elements.size, _CHUNK), ordered_map(one, range(0, elements.size, _CHUNK))):
        if not same:
            part = elements[a : a + _CHUNK]
            bad = part[np.flatnonzero((conn[a : a + _CHUNK] != model.cells[part]).any(axis=1))[0]]
            raise DicerError(f"the FEBio file: connectivity of element {bad + 1} differs")


def check_febio(path: str | Path, model, *, material_type: str) -> None:
    """Re-read an FEBio file with :func:`read_febio` and compare it with the model.

    The node coordinates equal the printed values exactly, element numbers and
    connectivity exactly, every material, domain, node set and surface is present and
    equal.

    Parameters
    ----------
    path : str or Path
    model : SolverModel
    material_type : str
        As written (:func:`write_febio`).

    Raises
    ------
    DicerError
        The first difference.
    """
    got = read_febio(path)
    if got.get("module") != "solid":
        raise DicerError(f"module {got.get('module')!r}, expected 'solid'")
    labels = model.labels()
    want_mats = [(str(i), model.names[k], material_type) for i, k in enumerate(labels, start=1)]
    if [(m["id"], m["name"], m["type"]) for m in got["materials"]] != want_mats:
        raise DicerError("materials differ")
    for m, k in zip(got["materials"], labels):
        p = model.props[k]
        if (m["E"], m["v"], m["density"]) != tuple(float(_num(p[key])) for key in
                                                   ("youngs_modulus", "poissons_ratio", "density")):
            raise DicerError(f"constants of material {m['name']} differ")
    if got["domains"] != [(model.names[k], model.names[k]) for k in labels]:
        raise DicerError("mesh domains differ")
    blocks = model.blocks()
    if len(got["blocks"]) != len(blocks):
        raise DicerError(f"{len(got['blocks'])} element blocks read back, expected {len(blocks)}")
    # the blocks hold every element once, in their material's block (model.blocks()), so
    # element numbers, connectivity and materials are compared block by block
    for (k, elements), (etype, name, ids, conn) in zip(blocks, got["blocks"]):
        if etype != FEBIO_TYPES[model.order] or name != model.names[k]:
            raise DicerError(f"element block {name} ({etype}) read back, expected {model.names[k]}")
        if not np.array_equal(ids, elements + 1):
            raise DicerError(f"element numbers of {name} differ")
        _compare_cells(model, elements, conn)
    _compare_points(model, got["points"], Sci(13 if model.digits > 9 else 9))
    if list(got["node_sets"]) != list(model.node_sets):
        raise DicerError(f"node sets {list(got['node_sets'])} read back, expected {list(model.node_sets)}")
    for name, ids in model.node_sets.items():
        if not np.array_equal(got["node_sets"][name], ids):
            raise DicerError(f"node set {name} differs")
    want_s = model.face_sets()
    if list(got["surfaces"]) != list(want_s):
        raise DicerError(f"surfaces {list(got['surfaces'])} read back, expected {list(want_s)}")
    for name, faces in want_s.items():
        ftype, conn = got["surfaces"][name]
        if ftype != FACET_TYPES[model.order] or not np.array_equal(conn, model.facets(faces)):
            raise DicerError(f"surface {name} differs")


FORMAT = Format("febio", (".feb",), write_febio, check_febio, dims=(3,),
                limits="FEBio has no plane (2D) elements; export this {dim}D mesh to .inp (CPS4/CPE4) or another "
                       "format, or mesh a 3D volume for .feb",
                write_options={"material_type": "febio_material"},
                check_options={"material_type": "febio_material"}, digits=(9, 13))
