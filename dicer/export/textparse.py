"""Vectorised strict parsing of fixed-width text records: the inverse of :mod:`dicer.export.textfmt`.

dicer's text decks are runs of records (one line, or two for a continued element)
of a fixed length: blank-padded integers, numbers in scientific notation of a fixed
width, separators in fixed columns. :func:`layout_of` reads the layout off the first
record of a run; :func:`parse_records` then checks and converts every record of the
run with whole-array numpy operations, a chunk of rows at a time:

* every byte is checked against the layout with elementwise operations only (digits
  are mapped to ``'0'``, one OR mask folds ``' '`` into ``'0'`` where an integer may be
  blank-padded, and the result must equal a template row); integers must be
  right-aligned, signs are checked column by column;
* digits become numbers column by column (``v = 10 v + digit``), each step over every
  field of a run of equally spaced fields at once (strided views);
* a number ``[ -]d.ddd[eE][+-]XX`` becomes its integer mantissa ``M`` and exponent
  ``k``; ``M * 10**k`` (or ``M / 10**-k``) is one correctly rounded operation on exact
  operands while ``|k| <= 22``, so the result is bit for bit what ``float(text)``
  gives (beyond that, those few fields go through ``float``).

Anything out of place raises :class:`FormatError` with the byte offset of the first
bad character, which the reader of the file turns into a line and column.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import as_strided

from dicer.parallel import ordered_map

CHUNK_ROWS = 1 << 15
"""Records checked and converted per pass: temporaries stay a few MB (cache-sized)."""

_ZERO, _SPACE, _MINUS, _PLUS = 48, 32, 45, 43
_POW10 = 10.0 ** np.arange(23)  # exact powers of ten (10**22 is the largest exact double)
_INT = re.compile(rb" *[0-9]+")
_REAL = re.compile(rb" *[ -][0-9]\.[0-9]+[eE][+-][0-9]{2}")  # right-aligned: blank padding first

# column classes, for messages
_C_SEP, _C_INT, _C_DIGIT, _C_SIGN, _C_ESIGN, _C_LETTER = range(6)
_EXPECTED = {_C_SEP: "{sep}", _C_INT: "a digit or a blank", _C_DIGIT: "a digit", _C_SIGN: "a blank or '-'",
             _C_ESIGN: "'+' or '-'", _C_LETTER: "{sep}"}


class FormatError(Exception):
    """A record that does not fit its layout.

    Parameters
    ----------
    offset : int
        Bytes into the parsed buffer of the first bad character.
    message : str
    """

    def __init__(self, offset: int, message: str):
        super().__init__(message)
        self.offset = int(offset)
        self.message = message


@dataclass(frozen=True)
class Run:
    """``count`` fields of one shape, ``stride`` bytes apart from column ``start`` on.

    Parameters
    ----------
    kind : {"i", "f"}
    start, stride, count : int
    width : int
        Columns per field.
    digits : tuple of int
        Offsets (from the field's first column) of the integer's or mantissa's digit
        columns, most significant first.
    exp : tuple of int, optional
        Reals only: the two exponent digit offsets.
    sign, esign : int, optional
        Reals only: the offsets of the mantissa's and exponent's signs.
    after : int, optional
        Reals only: the digits after the point.
    """

    kind: str
    start: int
    stride: int
    count: int
    width: int
    digits: tuple
    exp: tuple = ()
    sign: int = 0
    esign: int = 0
    after: int = 0

    def shape(self) -> tuple:
        """What two runs must share to be one run: all but place and count."""
        return (self.kind, self.width, self.digits, self.exp, self.sign, self.esign, self.after)


@dataclass(frozen=True)
class Layout:
    """The fixed layout of one kind of record.

    Parameters
    ----------
    length : int
        Bytes per record (newlines included).
    kinds : str
        ``"i"`` or ``"f"`` per field.
    template, ormask : (length,) uint8 ndarray
        A record is valid where ``canon(u) | ormask == template`` (``canon`` maps digits
        to ``'0'``), and in its sign columns.
    klass : (length,) ndarray
        Column class (messages).
    pairs : (length - 1,) bool ndarray
        True where columns j and j + 1 lie in one integer field (right alignment).
    signs, esigns : ndarray
        Columns of mantissa and exponent signs.
    runs : tuple of Run
        The fields as runs of equally spaced fields of one shape, in order.
    """

    length: int
    kinds: str
    template: np.ndarray
    ormask: np.ndarray
    klass: np.ndarray
    pairs: np.ndarray
    signs: np.ndarray
    esigns: np.ndarray
    runs: tuple


def _runs(fields: list[Run]) -> tuple:
    """Merge consecutive one-field runs of one shape and a constant spacing."""
    out: list[Run] = []
    for f in fields:
        last = out[-1] if out else None
        if last is not None and last.shape() == f.shape() and (
                last.count == 1 or f.start - (last.start + (last.count - 1) * last.stride) == last.stride):
            out[-1] = dataclasses.replace(last, count=last.count + 1, stride=f.start - last.start
                                          if last.count == 1 else last.stride)
        else:
            out.append(f)
    return tuple(out)


def layout_of(record: bytes, terminated: bool = True) -> Layout:
    """The layout of a record.

    Fields are separated by ``,`` or a newline (``,\\n`` continues a record on the next
    line), each a blank-padded integer or a blank-padded real ``[ -]d.ddd[eE][+-]XX``.

    Parameters
    ----------
    record : bytes
    terminated : bool, optional
        The record ends with a newline.

    Returns
    -------
    Layout
    """
    n = len(record)
    template = np.frombuffer(record, np.uint8).copy()
    ormask = np.zeros(n, np.uint8)
    klass = np.full(n, _C_SEP, np.uint8)
    pairs = np.zeros(max(n - 1, 0), bool)
    signs, esigns, fields, kinds = [], [], [], []
    for m in re.finditer(rb"[^,\n]+", record):
        a, b, text = m.start(), m.end(), m.group()
        if _INT.fullmatch(text):
            if len(text.strip()) > 18:
                raise FormatError(a, "an integer of more than 18 digits")
            kinds.append("i")
            template[a:b] = _ZERO
            ormask[a : b - 1] = 0x10  # ' ' | 0x10 == '0': blanks allowed but in the last column
            klass[a:b] = _C_INT
            klass[b - 1] = _C_DIGIT
            pairs[a : b - 1] = True
            fields.append(Run("i", a, 0, 1, b - a, tuple(range(b - a))))
        elif _REAL.fullmatch(text):
            kinds.append("f")
            f0, a = a, a + re.search(rb"[0-9]", text).start() - 1  # a: the sign's column (blanks before it)
            e = f0 + text.upper().index(b"E")
            template[a] = ormask[a] = 0xFF  # sign: checked by column
            klass[a] = _C_SIGN
            signs.append(a)
            digits = [a + 1] + list(range(a + 3, e))
            if len(digits) > 15:
                raise FormatError(a, "a number of more than 15 significant digits")
            template[digits] = _ZERO
            klass[digits] = _C_DIGIT
            klass[[a + 2, e]] = _C_LETTER
            template[e + 1] = ormask[e + 1] = 0xFF
            klass[e + 1] = _C_ESIGN
            esigns.append(e + 1)
            template[e + 2 : e + 4] = _ZERO
            klass[e + 2 : e + 4] = _C_DIGIT
            fields.append(Run("f", f0, 0, 1, b - f0, tuple(c - f0 for c in digits), (e + 2 - f0, e + 3 - f0),
                              a - f0, e + 1 - f0, e - a - 3))
        else:
            raise FormatError(a, f"{text.decode('ascii', 'replace').strip()!r} is neither an integer nor a "
                                 "number in scientific notation")
    if terminated and not record.endswith(b"\n"):
        raise FormatError(n, "the record does not end with a newline")
    return Layout(length=n, kinds="".join(kinds), template=template, ormask=ormask, klass=klass, pairs=pairs,
                  signs=np.array(signs, np.intp), esigns=np.array(esigns, np.intp), runs=_runs(fields))


def layout_of_columns(record: bytes, widths, terminated: bool = True) -> Layout:
    """The layout of a record of fixed columns without separators (LS-DYNA cards).

    Each field fills its columns: a blank-padded integer or a blank-padded real
    ``[ -]d.ddd[eE][+-]XX``, read off the field as :func:`layout_of` reads one.

    Parameters
    ----------
    record : bytes
        ``sum(widths)`` columns, then a newline when ``terminated``.
    widths : sequence of int
        Columns per field, in order from column 0.
    terminated : bool, optional
        The record ends with a newline.

    Returns
    -------
    Layout

    Raises
    ------
    FormatError
        A field that is not one number filling its columns (offset of its first column or
        its bad character), or a record of another length.
    """
    n = sum(widths) + bool(terminated)
    if len(record) != n or (terminated and record[-1:] != b"\n"):
        raise FormatError(min(len(record), n - 1), f"a record of {len(record)} bytes where {n} belong")
    parts, fields, kinds, a = [], [], [], 0
    for w in widths:
        try:
            one = layout_of(record[a : a + w], terminated=False)
        except FormatError as exc:
            raise FormatError(a + exc.offset, exc.message) from None
        if len(one.kinds) != 1 or one.runs[0].start != 0 or one.runs[0].width != w:
            raise FormatError(a, f"{record[a : a + w].decode('ascii', 'replace')!r} is not one number "
                                 f"filling columns {a + 1}-{a + w}")
        parts.append(one)
        fields.append(dataclasses.replace(one.runs[0], start=a))
        kinds.append(one.kinds)
        a += w
    # the fields' layouts side by side, then the newline (a separator column)
    tail = (np.array([10], np.uint8),) if terminated else ()
    template = np.concatenate([p.template for p in parts] + list(tail))
    ormask = np.concatenate([p.ormask for p in parts] + [np.zeros(len(tail), np.uint8)])
    klass = np.concatenate([p.klass for p in parts] + [np.full(len(tail), _C_SEP, np.uint8)])
    pairs = np.zeros(max(n - 1, 0), bool)  # never across fields: each is right-aligned in its own
    starts = np.cumsum([0] + list(widths))
    for p, s in zip(parts, starts):
        pairs[s : s + p.pairs.size] = p.pairs
    signs = np.concatenate([p.signs + s for p, s in zip(parts, starts)] + [np.zeros(0, np.intp)]).astype(np.intp)
    esigns = np.concatenate([p.esigns + s for p, s in zip(parts, starts)] + [np.zeros(0, np.intp)]).astype(np.intp)
    return Layout(length=n, kinds="".join(kinds), template=template, ormask=ormask, klass=klass, pairs=pairs,
                  signs=signs, esigns=esigns, runs=_runs(fields))


def _describe(layout: Layout, col: int, byte: int) -> str:
    sep = "a line end" if layout.template[col] == 10 else repr(chr(layout.template[col]))
    want = _EXPECTED[int(layout.klass[col])].format(sep=sep)
    got = "a line end" if byte == 10 else repr(chr(byte))
    return f"{got} where {want} belongs"


def _check(u: np.ndarray, layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """Raise FormatError (offset into ``u``'s rows) at the first bad byte; return (digit values, 0
    elsewhere; digit mask)."""
    d = u - np.uint8(_ZERO)  # digits 0..9, every other byte wraps above 9
    dig = d < 10
    d *= dig  # digit values, 0 elsewhere
    canon = u - d  # digits -> '0'
    canon |= layout.ormask
    bad = canon != layout.template
    for cols, allowed in ((layout.signs, (_SPACE, _MINUS)), (layout.esigns, (_PLUS, _MINUS))):
        if cols.size:
            s = u[:, cols]
            bad[:, cols] = (s != allowed[0]) & (s != allowed[1])
    # a digit followed by a blank inside an integer: not right-aligned (column c: c and c + 1)
    step = dig[:, :-1] > dig[:, 1:]
    step &= layout.pairs
    if bad.any() or step.any():
        shifted = np.zeros_like(bad)
        shifted[:, :-1] = step
        row = int(np.argmax((bad | shifted).any(axis=1)))
        if bad[row].any():  # a wrong character says more than the alignment it upsets
            col = int(np.argmax(bad[row]))
            raise FormatError(row * layout.length + col, _describe(layout, col, int(u[row, col])))
        col = int(np.argmax(shifted[row]))
        raise FormatError(row * layout.length + col, "an integer that is not right-aligned in its field")
    return d, dig


def _horner(view: np.ndarray, offsets: tuple, dtype) -> np.ndarray:
    """(r, k) values of the digit columns ``offsets`` (most significant first) of ``view`` (r, k, w)."""
    acc = view[:, :, offsets[0]].astype(dtype)
    for o in offsets[1:]:
        acc *= 10
        acc += view[:, :, o]
    return acc


def _values(layout: Layout, d: np.ndarray, u: np.ndarray, ints: np.ndarray, reals: np.ndarray) -> None:
    """Convert checked rows (``d``: digit values, 0 elsewhere; ``u``: the bytes) into ``ints`` / ``reals``.

    One pass per digit column of a run of fields, over all its fields at once (strided views).
    """
    r = d.shape[0]
    ni = nf = 0
    for run in layout.runs:
        shape = (r, run.count, run.width)
        view = as_strided(d[:, run.start :], shape, (d.strides[0], run.stride, 1))
        if run.kind == "i":
            ints[:, ni : ni + run.count] = _horner(view, run.digits, np.int32 if run.width <= 9 else np.int64)
            ni += run.count
            continue
        raw = as_strided(u[:, run.start :], shape, (u.strides[0], run.stride, 1))
        m = _horner(view, run.digits, np.float64)  # exact: at most 15 digits (layout_of)
        k = _horner(view, run.exp, np.int32)
        np.negative(k, out=k, where=raw[:, :, run.esign] == _MINUS)
        k -= run.after
        x = np.where(k >= 0, m * _POW10[np.clip(k, 0, 22)], m / _POW10[np.clip(-k, 0, 22)])
        far = np.argwhere(np.abs(k) > 22)
        for i, j in far:  # 10**|k| is not exact there: let Python round these (rare) fields
            x[i, j] = float(bytes(raw[i, j, run.sign + 1 :]))  # unsigned: the sign comes below
        np.negative(x, out=x, where=raw[:, :, run.sign] == _MINUS)
        reals[:, nf : nf + run.count] = x
        nf += run.count


def parse_records(buf: np.ndarray, layout: Layout, chunk: int = CHUNK_ROWS, sink=None):
    """Check and convert whole records of one layout.

    Parameters
    ----------
    buf : (n * layout.length,) uint8 ndarray
        n whole records.
    layout : Layout
    chunk : int, optional
        Records per pass.
    sink : callable, optional
        ``sink(start, ints, reals)`` takes the values of records ``start, start + 1, ...``
        chunk by chunk ((r, ·) arrays): a caller that compares the values with what it
        expects holds no array of the whole block. Chunks are parsed in worker threads
        (:func:`dicer.parallel.ordered_map`), so the sink may be called from several at
        once and out of order: it should only read. A FormatError the sink raises (offset
        into its chunk's rows) is moved to the offset in ``buf``; of several, the first in
        the buffer is raised.

    Returns
    -------
    ints : (n, number of integer fields) ndarray
        int32 if every integer field is at most 9 columns wide, else int64.
    reals : (n, number of real fields) float64 ndarray
    n : int
        Instead of both when ``sink`` is given: the record count.

    Raises
    ------
    FormatError
        At the first byte that does not fit, or when ``buf`` does not hold whole records
        (offset of the incomplete last record).
    """
    n, rest = divmod(buf.size, layout.length)
    rows = buf[: n * layout.length].reshape(n, layout.length)
    wide = any(run.kind == "i" and run.width > 9 for run in layout.runs)
    size = n if sink is None else 0
    ints = np.empty((size, layout.kinds.count("i")), np.int64 if wide else np.int32)  # 9 digits fit int32
    reals = np.empty((size, layout.kinds.count("f")), np.float64)

    def one(start: int) -> None:
        u = rows[start : start + chunk]
        try:
            d, _ = _check(u, layout)
            if sink is None:
                _values(layout, d, u, ints[start : start + chunk], reals[start : start + chunk])
            else:  # each thread its own buffers
                r = u.shape[0]
                i, f = np.empty((r, ints.shape[1]), ints.dtype), np.empty((r, reals.shape[1]), np.float64)
                _values(layout, d, u, i, f)
                sink(start, i, f)
        except FormatError as exc:
            raise FormatError(start * layout.length + exc.offset, exc.message) from None

    # chunks are checked side by side; in order, so the first bad record is the one reported
    for _ in ordered_map(one, range(0, n, chunk)):
        pass
    if rest:
        raise FormatError(n * layout.length, f"a record of {rest} bytes where {layout.length} belong "
                                             "(a line cut short or run on)")
    return (ints, reals) if sink is None else n


def record_length(buf: np.ndarray | bytes, continued: bool = False) -> int:
    """Bytes up to and including the first newline of a buffer.

    Parameters
    ----------
    buf : uint8 ndarray or bytes
    continued : bool, optional
        Look for the first newline not preceded by a comma.

    Returns
    -------
    int
        0 if there is none.
    """
    data = bytes(buf[:4096])
    at = 0
    while True:
        i = data.find(b"\n", at)
        if i < 0:
            return 0
        if not (continued and i > 0 and data[i - 1 : i] == b","):
            return i + 1
        at = i + 1


def parse_int_list(buf: np.ndarray, per_line: int) -> np.ndarray:
    """The integers of a set list.

    Lines of ``per_line`` right-aligned fields of one width joined by ``,`` (the last line
    may be shorter), every line ending in a newline.

    Parameters
    ----------
    buf : uint8 ndarray
    per_line : int

    Returns
    -------
    (n,) int32 ndarray
        int64 for fields wider than 9 columns.

    Raises
    ------
    FormatError
    """
    first = bytes(buf[:4096])
    cut = re.search(rb"[,\n]", first)
    if cut is None:
        raise FormatError(0, "a set line without a comma or line end")
    width = cut.start() + 1  # one field and its separator
    layout = layout_of(first[: width - 1] + b"\n")
    # the separator column (',' or a line end by position) is checked here, not by the layout
    template, ormask = layout.template.copy(), layout.ormask.copy()
    template[-1] = ormask[-1] = 0xFF
    layout = dataclasses.replace(layout, template=template, ormask=ormask)
    n, rest = divmod(buf.size, width)
    if rest:
        raise FormatError(n * width, "a set line cut short or run on")
    cells = buf.reshape(n, width)
    seps = cells[:, -1]
    want = np.full(n, ord(","), np.uint8)
    want[per_line - 1 :: per_line] = 10
    want[-1] = 10
    bad = np.flatnonzero(seps != want)
    if bad.size:
        i = int(bad[0])
        got = "a line end" if seps[i] == 10 else repr(chr(seps[i]))
        raise FormatError(i * width + width - 1, f"{got} where {'a line end' if want[i] == 10 else repr(',')} belongs")
    ints, _ = parse_records(buf, layout)
    return ints[:, 0]


def parse_column(cols: np.ndarray) -> np.ndarray:
    """The values of a fixed-width column.

    All right-aligned non-negative integers, or all blank-padded reals
    ``[ -]d.ddd[eE][+-]XX`` of one shape.

    Parameters
    ----------
    cols : (n, width) uint8 ndarray
        Rows may be strided, columns contiguous.

    Returns
    -------
    (n,) int64 or float64 ndarray

    Raises
    ------
    FormatError
        At the first field that does not fit the first one's shape (offset
        ``row * width + column``).
    """
    n, width = cols.shape
    if n == 0:
        return np.zeros(0)
    layout = layout_of(cols[0].tobytes(), terminated=False)
    if len(layout.kinds) != 1 or layout.runs[0].start != 0 or layout.runs[0].width != width:
        raise FormatError(0, "not one right-aligned number filling the column")
    out = np.empty((n, 1), np.int64 if layout.kinds == "i" else np.float64)
    none = np.empty((n, 0), out.dtype)
    for start in range(0, n, CHUNK_ROWS):
        u = cols[start : start + CHUNK_ROWS]
        try:
            d, _ = _check(u, layout)
        except FormatError as exc:
            raise FormatError(start * width + exc.offset, exc.message) from None
        part = out[start : start + CHUNK_ROWS]
        _values(layout, d, u, *((part, none[: u.shape[0]]) if layout.kinds == "i" else (none[: u.shape[0]], part)))
    return out[:, 0]
