"""Vectorised fixed-width ASCII formatting shared by the text exporters.

A text writer describes one kind of line as a list of fields -- literal bytes,
right-aligned integers of a fixed width, floats in scientific notation of a
fixed width, each optionally preceded by a short ``lead`` (a separator such as
``b","`` or the newline that ends the previous line) -- and :func:`format_rows`
turns whole arrays into a ``(rows, line_length)`` uint8 buffer, a chunk of rows
at a time, with numpy alone:

* integers are split into 4-digit groups, each looked up as one 32-bit word in
  a digit table (zero-padded, or blank-padded while the higher groups are zero);
* floats are split into a decimal exponent and an integer mantissa, which is
  then printed like an integer; the exponent is looked up in a table.

When every field's length is a multiple of 4 bytes the row buffer is filled
32-bit word by word, otherwise byte by byte (slower, same result). There is no
per-line Python string formatting, and the output depends only on the numbers,
so reruns are byte-identical.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import BinaryIO, Iterator

import numpy as np

from dicer.parallel import ordered_map

CHUNK_ROWS = 1 << 16
"""Rows formatted per chunk: bounds the temporary memory of a writer."""

_SPACE, _ZERO, _MINUS, _PLUS, _DOT = 32, 48, 45, 43, 46
_LAST, _INNER = 10000, 20000  # offsets of the blank-padded 4-digit tables (zero-padded at 0)


def _digit_table() -> np.ndarray:
    """(30000,) uint32: 4-digit groups as words -- zero-padded | blank-padded last group | blank inner group."""
    v = np.arange(10000)
    digits = ((v[:, None] // np.array([1000, 100, 10, 1])) % 10 + _ZERO).astype(np.uint8)
    ndig = 1 + (v >= 10).astype(int) + (v >= 100) + (v >= 1000)  # by comparison: log10 is not exact on every CPU
    last = digits.copy()
    last[np.arange(4)[None, :] < (4 - ndig)[:, None]] = _SPACE  # "   7", "   0"
    inner = last.copy()
    inner[0] = _SPACE  # "    ": an inner group of a number whose higher groups are all zero
    return np.ascontiguousarray(np.concatenate([digits, last, inner])).view("<u4").ravel()


_TABLE = _digit_table()
_POW10 = 10 ** np.arange(19, dtype=np.int64)
_POW10F = 10.0 ** np.arange(0, 309)  # exact up to 1e22, correctly rounded beyond


def int_width(max_value: int) -> int:
    """Digits needed to print a non-negative integer.

    Parameters
    ----------
    max_value : int

    Returns
    -------
    int
    """
    return len(str(int(max(max_value, 0))))


def aligned_width(digits: int, lead: bytes = b"") -> int:
    """The smallest field width >= ``digits`` for which ``lead`` + field fills whole 32-bit words.

    Parameters
    ----------
    digits : int
    lead : bytes, optional
        What precedes the field.

    Returns
    -------
    int
    """
    w = max(digits, 1)
    while (len(lead) + w) % 4:
        w += 1
    return w


def _int_words(v: np.ndarray, groups: int, zero_pad: bool) -> np.ndarray:
    """(n, groups) uint32: the values right-aligned in 4*groups characters."""
    n = v.shape[0]
    out = np.empty((n, groups), "<u4")
    small = groups <= 2 and (v.size == 0 or int(v.max()) < 2**32)
    rest = v.astype(np.uint32) if small else v.astype(np.int64)
    higher = np.full(n, zero_pad)
    for g in range(groups):
        last = g == groups - 1
        if last:
            part = rest
        else:
            scale = 10 ** (4 * (groups - 1 - g))
            part = rest // scale
            rest = rest - part * scale
        if zero_pad:
            index = part
        else:
            index = part + (~higher).astype(part.dtype) * part.dtype.type(_LAST if last else _INNER)
            if not last:
                higher = higher | (part != 0)
        out[:, g] = _TABLE[index]
    return out


def int_digits(values: np.ndarray, width: int, zero_pad: bool = False, lead: bytes = b"") -> np.ndarray:
    """Non-negative integers right-aligned in a field, as bytes.

    Parameters
    ----------
    values : (n,) int ndarray
    width : int
        Columns of the field.
    zero_pad : bool, optional
        Leading zeros instead of blanks.
    lead : bytes, optional
        Put before every field.

    Returns
    -------
    (n, len(lead) + width) uint8 ndarray
    """
    v = np.asarray(values).ravel()
    if v.size and (int(v.min()) < 0 or int(v.max()) >= 10**width):
        raise ValueError(f"integers out of range for a field of {width} digits")
    total = len(lead) + width
    n = v.shape[0]
    if total % 4 == 0 and not zero_pad:
        words = _int_words(v, total // 4, zero_pad=False)
        if lead:
            keep = np.uint32((0xFFFFFFFF << (8 * len(lead))) & 0xFFFFFFFF)
            words[:, 0] = (words[:, 0] & keep) | np.uint32(int.from_bytes(lead, "little"))
        return words.view(np.uint8).reshape(n, total)
    groups = -(-width // 4)
    body = _int_words(v, groups, zero_pad).view(np.uint8).reshape(n, 4 * groups)[:, 4 * groups - width :]
    if not lead:
        return body
    out = np.empty((n, total), np.uint8)
    out[:, : len(lead)] = np.frombuffer(lead, np.uint8)
    out[:, len(lead) :] = body
    return out


@dataclass(frozen=True)
class Sci:
    """Scientific notation with ``digits`` significant digits: ``[-]d.ddde[+-]XX``.

    Parameters
    ----------
    digits : int, optional
    exp_char : bytes, optional
        The exponent letter.
    fortran : bool, optional
        Fortran's E-edit form ``[-]0.dddE[+-]XX`` (mantissa in [0.1, 1)).
    width : int, optional
        Right-align in this many columns (at least the printed length, which has one
        column for the sign, blank for plus).
    """

    digits: int = 9
    exp_char: bytes = b"e"
    fortran: bool = False
    width: int | None = None

    @property
    def body(self) -> int:
        # sign, lead digit ('0' in Fortran form), '.', digits after the point, e, sign, 2 exponent digits
        """Printed length of a number, sign column included."""
        return 3 + (self.digits - (0 if self.fortran else 1)) + 4

    @property
    def length(self) -> int:
        """Columns of the field: ``body``, or ``width`` when larger."""
        return max(self.body, self.width or 0)


def _exp_words(exp_char: bytes) -> np.ndarray:
    e = np.arange(-99, 100)
    sign = np.where(e < 0, _MINUS, _PLUS).astype(np.uint32)
    a = np.abs(e)
    return (np.uint32(exp_char[0]) | (sign << 8) | ((a // 10 + _ZERO).astype(np.uint32) << 16)
            | ((a % 10 + _ZERO).astype(np.uint32) << 24)).astype("<u4")


_EXP_WORDS = {b"e": _exp_words(b"e"), b"E": _exp_words(b"E")}


def _mantissa(x: np.ndarray, p: int, fortran: bool):
    """Integer mantissa m (p digits) and decimal exponent e of x: |x| ~ m * 10**(e - p + 1)."""
    a = np.abs(x)
    zero = a < 1e-99
    a[zero] = 1.0
    e = np.floor(np.log10(a)).astype(np.int64)
    for _ in range(3):
        k = p - 1 - e  # m = a * 10**k, one correctly rounded operation
        m = a * _POW10F[np.clip(k, 0, 308)]
        below = np.flatnonzero(k < 0)  # numbers of more than p digits before the point: few
        if below.size:
            m[below] = a[below] / _POW10F[-k[below]]
        m = np.rint(m, out=m).astype(np.int64)
        hi = m >= _POW10[p]
        lo = m < _POW10[p - 1]
        if not (hi.any() or lo.any()):
            break
        e = e + hi - lo
    m[zero] = 0
    e[zero] = -1 if fortran else 0
    if fortran:
        e = e + 1
    if np.any(np.abs(e) > 99):
        raise ValueError("number too large to print with a two-digit exponent")
    return m, e


def printed_values(values: np.ndarray, digits: int) -> np.ndarray:
    """The numbers ``values`` print as with ``digits`` significant digits (:func:`sci_digits`).

    Parameters
    ----------
    values : float ndarray
    digits : int

    Returns
    -------
    float64 ndarray
        The same shape.

    Raises
    ------
    ValueError
        As :func:`sci_digits`.
    """
    x = np.asarray(values, dtype=np.float64)
    m, e = _mantissa(x.ravel(), digits, False)
    k = e - digits + 1  # |x| printed: m * 10**k
    mag = np.where(k >= 0, m * 10.0 ** np.maximum(k, 0), m / 10.0 ** np.maximum(-k, 0))
    return np.copysign(mag, x.ravel()).reshape(x.shape)


def sci_digits(values: np.ndarray, fmt: Sci, lead: bytes = b"") -> np.ndarray:
    """Floats in scientific notation, as bytes.

    Magnitudes below 1e-99 print as zero.

    Parameters
    ----------
    values : (n,) float ndarray
    fmt : Sci
    lead : bytes, optional
        Put before every field.

    Returns
    -------
    (n, len(lead) + fmt.length) uint8 ndarray

    Raises
    ------
    ValueError
        Non-finite values or magnitudes of 1e99 and above (no two-digit exponent holds
        them).
    """
    x = np.asarray(values, dtype=np.float64).ravel()
    n = x.shape[0]
    p = fmt.digits
    total = len(lead) + fmt.length
    if n and not np.all(np.isfinite(x)):
        raise ValueError("cannot print non-finite numbers")
    m, e = _mantissa(x, p, fmt.fortran)
    neg = (x < 0) & (m > 0)
    expw = _EXP_WORDS[fmt.exp_char][e + 99]
    pad = fmt.length - fmt.body
    if pad == 0 and len(lead) == (0 if fmt.fortran else 1) and (p - 1) % 4 == 0:
        # word-aligned: [lead sign d .] or [sign 0 . d], then [4 digits]..., then [e s x x]
        groups = (p - 1) // 4
        words = np.empty((n, groups + 2), "<u4")
        first, rest = np.divmod(m, _POW10[p - 1])
        first = first.astype(np.uint32) + np.uint32(_ZERO)
        sign = np.where(neg, _MINUS, _SPACE).astype(np.uint32)
        if fmt.fortran:
            words[:, 0] = sign | np.uint32(_ZERO << 8 | _DOT << 16) | (first << 24)
        else:
            words[:, 0] = np.uint32(lead[0] | _DOT << 24) | (sign << 8) | (first << 16)
        words[:, 1 : groups + 1] = _int_words(rest, groups, zero_pad=True)
        words[:, groups + 1] = expw
        return words.view(np.uint8).reshape(n, total)
    out = np.full((n, total), _SPACE, np.uint8)
    if lead:
        out[:, : len(lead)] = np.frombuffer(lead, np.uint8)
    c = len(lead) + pad  # column of the sign
    out[:, c] = np.where(neg, _MINUS, _SPACE)
    digits = int_digits(m, p, zero_pad=True)
    if fmt.fortran:
        out[:, c + 1] = _ZERO
        out[:, c + 2] = _DOT
        out[:, c + 3 : c + 3 + p] = digits
        t = c + 3 + p
    else:
        out[:, c + 1] = digits[:, 0]
        out[:, c + 2] = _DOT
        out[:, c + 3 : c + 2 + p] = digits[:, 1:]
        t = c + 2 + p
    out[:, t : t + 4] = expw.view(np.uint8).reshape(n, 4)
    return out


@dataclass(frozen=True)
class Int:
    """A right-aligned integer field.

    Parameters
    ----------
    values : (n,) int ndarray
    width : int
        Columns.
    lead : bytes, optional
        Put before the field.
    zero_pad : bool, optional
        Leading zeros instead of blanks.
    """

    values: np.ndarray
    width: int
    lead: bytes = b""
    zero_pad: bool = False

    @property
    def length(self) -> int:
        """Bytes of the field with its lead."""
        return len(self.lead) + self.width

    def render(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, length) uint8: rows ``start .. stop - 1`` of the field."""
        return int_digits(self.values[start:stop], self.width, self.zero_pad, self.lead)


@dataclass(frozen=True)
class Float:
    """A float field printed in scientific notation.

    Parameters
    ----------
    values, fmt
        The numbers and their notation, as in :func:`sci_digits`.
    lead : bytes, optional
        Put before the field.
    """

    values: np.ndarray
    fmt: Sci
    lead: bytes = b""

    @property
    def length(self) -> int:
        """Bytes of the field with its lead."""
        return len(self.lead) + self.fmt.length

    def render(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, length) uint8: rows ``start .. stop - 1`` of the field."""
        return sci_digits(self.values[start:stop], self.fmt, self.lead)


Field = bytes | Int | Float


def line_length(fields: list[Field]) -> int:
    """Bytes per row of some fields.

    Parameters
    ----------
    fields : list of bytes, Int or Float

    Returns
    -------
    int
    """
    return sum(len(f) if isinstance(f, bytes) else f.length for f in fields)


def format_rows(fields: list[Field], n: int, chunk: int = CHUNK_ROWS) -> Iterator[np.ndarray]:
    """Rows of fields as byte buffers, a chunk at a time.

    Array fields hold ``n`` values; literals repeat on every row. Rows carry no
    implicit newline: put ``b"\\n"`` in a field's lead or a literal.

    Parameters
    ----------
    fields : list of bytes, Int or Float
    n : int
        Rows.
    chunk : int, optional
        Rows per buffer.

    Yields
    ------
    (rows, line_length) uint8 ndarray
    """
    lengths = [len(f) if isinstance(f, bytes) else f.length for f in fields]
    length = sum(lengths)
    aligned = all(w % 4 == 0 for w in lengths)
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        rows = stop - start
        if aligned:
            words = np.empty((rows, length // 4), "<u4")
            col = 0
            for f, w in zip(fields, lengths):
                k = w // 4
                if isinstance(f, bytes):
                    words[:, col : col + k] = np.frombuffer(f, "<u4")
                else:
                    words[:, col : col + k] = f.render(start, stop).view("<u4")
                col += k
            yield words.view(np.uint8).reshape(rows, length)
        else:
            buf = np.empty((rows, length), np.uint8)
            col = 0
            for f, w in zip(fields, lengths):
                if isinstance(f, bytes):
                    buf[:, col : col + w] = np.frombuffer(f, np.uint8)
                else:
                    buf[:, col : col + w] = f.render(start, stop)
                col += w
            yield buf


def write_rows(stream: BinaryIO, fields: list[Field], n: int, chunk: int = CHUNK_ROWS) -> int:
    """Write rows of fields to a binary stream.

    Parameters
    ----------
    stream : binary file
    fields : list of bytes, Int or Float
    n : int
        Rows.
    chunk : int, optional
        Rows per buffer.

    Returns
    -------
    int
        Bytes written.
    """
    total = 0
    for buf in format_rows(fields, n, chunk):
        stream.write(memoryview(buf).cast("B"))
        total += buf.size
    return total


def write_chunks(stream: BinaryIO, n: int, fields_of, compact: bool = False, chunk: int = CHUNK_ROWS) -> None:
    """Write ``n`` rows, a chunk at a time, whose fields ``fields_of(start, stop)`` gives.

    Parameters
    ----------
    stream : binary file
    n : int
        Rows to write.
    fields_of : callable
        ``fields_of(start, stop)`` -> the fields of rows ``start .. stop - 1`` (arrays of
        ``stop - start`` values): temporaries such as 1-based ids stay one chunk large.
        Called from worker threads (:func:`dicer.parallel.ordered_map`): it only reads.
    compact : bool, optional
        Drop the blank padding of number fields (:func:`compact_rows`).
    chunk : int, optional
        Rows per chunk.
    """

    def render(start: int) -> list:
        stop = min(n, start + chunk)
        fields = fields_of(start, stop)
        if compact:
            return list(compact_rows(fields, stop - start, chunk))
        return [memoryview(buf).cast("B") for buf in format_rows(fields, stop - start, chunk)]

    # chunks are formatted side by side (numpy leaves the interpreter lock), written in order
    for parts in ordered_map(render, range(0, n, chunk)):
        for part in parts:
            stream.write(part)


def row_ids(start: int, stop: int) -> np.ndarray:
    """The 1-based numbers of rows ``start .. stop - 1``.

    Parameters
    ----------
    start, stop : int

    Returns
    -------
    (stop - start,) int64 ndarray
    """
    return np.arange(start + 1, stop + 1, dtype=np.int64)


def int_lines(values: np.ndarray, per_line: int, width: int, sep: bytes = b",") -> bytes:
    """Integers as newline-terminated lines of up to ``per_line`` right-aligned fields.

    For set lists (node and element sets): full lines are formatted in bulk, the
    last, shorter line separately.

    Parameters
    ----------
    values : (n,) int ndarray
    per_line : int
    width : int
        Columns per field.
    sep : bytes, optional
        Between fields.

    Returns
    -------
    bytes
    """
    v = np.asarray(values, dtype=np.int64).ravel()
    full = v.size // per_line
    parts = []
    if full:
        block = v[: full * per_line].reshape(full, per_line)
        fields: list[Field] = [Int(block[:, j], width, sep if j else b"") for j in range(per_line)]
        fields.append(b"\n")
        parts.extend(buf.tobytes() for buf in format_rows(fields, full))
    tail = v[full * per_line :]
    if tail.size:
        fields = [Int(tail[j : j + 1], width, sep if j else b"") for j in range(tail.size)]
        parts.append(next(format_rows(fields + [b"\n"], 1)).tobytes())
    return b"".join(parts)


def int_line_blocks(headers: list[bytes], blocks: list[np.ndarray], per_line: int, width: int,
                    sep: bytes = b",") -> bytes:
    """``b"".join(h + int_lines(v, per_line, width, sep) for h, v in zip(headers, blocks))``
    in one pass: for the thousands of node sets of an atlas, where a call per set costs
    more than its numbers.

    Every field has ``width`` columns, so each number's place in the output follows from
    its set and its position in the set; the numbers are formatted together and the
    headers, separators and newlines put around them.

    Parameters
    ----------
    headers : list of bytes
        The line(s) before each block (its keyword line).
    blocks : list of (n_i,) int ndarray
    per_line, width, sep
        As :func:`int_lines`.

    Returns
    -------
    bytes
    """
    if not blocks:
        return b""
    sizes = np.array([b.size for b in blocks], np.int64)
    head_len = np.array([len(h) for h in headers], np.int64)
    values = np.concatenate([np.asarray(b, np.int64).ravel() for b in blocks]) if sizes.sum() else np.zeros(0, np.int64)
    step = width + len(sep)  # a field after the first of its line
    lines = -(-sizes // per_line)
    body = sizes * width + (sizes - lines) * len(sep) + lines  # fields, separators, newlines
    start = np.cumsum(np.r_[0, head_len + body])  # where each block's header starts
    out = np.full(int(start[-1]), ord(" "), np.uint8)
    # the headers
    heads = np.frombuffer(b"".join(headers), np.uint8)
    out[np.repeat(start[:-1] - np.r_[0, np.cumsum(head_len)[:-1]], head_len) + np.arange(heads.size)] = heads
    if values.size:
        # the numbers, right-aligned in their fields: formatted as one column
        digits = np.frombuffer(int_lines(values, 1, width), np.uint8).reshape(values.size, width + 1)[:, :width]
        block = np.repeat(np.arange(len(blocks)), sizes)
        pos = np.arange(values.size) - np.repeat(np.cumsum(sizes) - sizes, sizes)  # place in its block
        line, col = np.divmod(pos, per_line)
        line_len = per_line * step - len(sep) + 1
        at = start[:-1][block] + head_len[block] + line * line_len + col * step  # first column of the field
        out[at[:, None] + np.arange(width)] = digits
        if sep:
            later = col > 0
            out[(at[later] - len(sep))[:, None] + np.arange(len(sep))] = np.frombuffer(sep, np.uint8)
        last = (col == per_line - 1) | (pos == np.repeat(sizes, sizes) - 1)  # a line's last field
        out[at[last] + width] = ord("\n")
    return out.tobytes()


SET_GROUP = 1 << 21
"""Set entries formatted together by :func:`write_int_blocks` (an atlas has thousands of small sets)."""


def write_int_blocks(write, blocks, per_line: int, width: int, sep: bytes = b",", group: int = SET_GROUP) -> None:
    """``write(header + int_lines(values, ...))`` for every ``(header, values)`` of ``blocks``,
    formatted by :func:`int_line_blocks` in groups of at most ``group`` values (a bounded
    buffer; one call per set costs more than its numbers).

    Parameters
    ----------
    write : callable
        Takes bytes.
    blocks : iterable of (bytes, (n_i,) int ndarray)
    per_line, width, sep
        As :func:`int_lines`.
    group : int, optional
    """
    batch: list = []
    held = 0
    for header, values in blocks:
        if batch and held + values.size > group:
            write(int_line_blocks([h for h, _ in batch], [v for _, v in batch], per_line, width, sep))
            batch, held = [], 0
        batch.append((header, values))
        held += values.size
    if batch:
        write(int_line_blocks([h for h, _ in batch], [v for _, v in batch], per_line, width, sep))


def compact_rows(fields: list[Field], n: int, chunk: int = CHUNK_ROWS) -> Iterator[bytes]:
    """Like :func:`format_rows`, but numbers take only the characters they need.

    The rows are formatted at fixed widths, then the blank padding inside the number
    fields (not their leads, not literals) is dropped with one boolean mask per chunk:
    for formats such as XML, where ``id="     7"`` would be legal but odd. Floats lose
    the blank that stands for a plus sign.

    Parameters
    ----------
    fields, n, chunk
        As in :func:`format_rows`.

    Yields
    ------
    bytes
        One chunk of rows.
    """
    lengths = [len(f) if isinstance(f, bytes) else f.length for f in fields]
    number = np.zeros(sum(lengths), bool)
    col = 0
    for f, w in zip(fields, lengths):
        if not isinstance(f, bytes):
            number[col + len(f.lead) : col + w] = True
        col += w
    for buf in format_rows(fields, n, chunk):
        yield buf[~((buf == _SPACE) & number)].tobytes()
