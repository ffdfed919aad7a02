"""Per-element quality metrics as CSV, in the columns of automesh's ``metrics`` command.

One header line, then one line per element in mesh order (line i + 1 is element i + 1,
the element numbers of every export)::

    maximum edge ratio,minimum scaled jacobian,maximum skew,element volume
    1.000000e+00,1.000000e+00,0.000000e+00,8.000000e+00

Columns (verdict definitions, :mod:`dicer.mesh.metrics`): longest over shortest edge;
the minimum corner scaled Jacobian; skew, the largest |cos| between the principal axes;
the element's volume in mm^3 (a quad's area in mm^2). Numbers carry 7 significant digits
(``%.6e``, as automesh writes them). Lines are formatted in bulk by
:mod:`dicer.export.textfmt`, and the file is parsed back at array speed and compared
with the values before it is renamed into place.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.textfmt import Float, Sci, write_chunks
from dicer.io.atomic import atomic_path
from dicer.mesh import metrics as _metrics
from dicer.mesh.model import Mesh
from dicer.parallel import ordered_map

HEADER = b"maximum edge ratio,minimum scaled jacobian,maximum skew,element volume\n"
"""automesh's header line, byte for byte."""

_FMT = Sci(7, b"e")  # d.dddddde+XX: 7 significant digits
_DIGITS = 7


COLUMNS = ("edge_ratio", "scaled_jacobian", "skew", "volume")
"""The CSV's columns as :func:`dicer.mesh.metrics.element_metrics` names them."""


def element_metrics(mesh: Mesh, metrics: dict | None = None) -> np.ndarray:
    """(M, 4) float64: the CSV's columns for every element, in mesh order; ``metrics``
    holds those already computed (by :func:`dicer.mesh.metrics.element_metrics`)."""
    have = metrics or {}
    missing = [k for k in COLUMNS if k not in have]
    if missing:
        have = {**have, **_metrics.element_metrics(mesh.points, mesh.cells, missing)}
    return np.column_stack([have[k] for k in COLUMNS])


def _fields_of(values: np.ndarray):
    """The fields of rows ``start .. stop - 1`` of ``values`` (M, 4), as write_chunks takes them."""
    return lambda start, stop: ([Float(values[start:stop, 0], _FMT)]
                                + [Float(values[start:stop, j], _FMT, b",") for j in (1, 2, 3)] + [b"\n"])


_CHUNK = 1 << 20
"""Bytes of whole lines parsed at a time: the parse's temporaries (a dozen bytes of index
per character) stay a few MB and are reused, instead of several GB for a large mesh."""


def parse_metrics_csv(data: bytes, name: str = "metrics CSV") -> np.ndarray:
    """(M, 4) float64 from the bytes of a file :func:`write_metrics_csv` wrote (vectorised,
    in blocks of whole lines of about ``_CHUNK`` bytes).

    Every field must be ``[-]d.dddddde[+-]XX``; anything else is a DicerError naming the line.
    """
    if not data.startswith(HEADER):
        raise DicerError(f"{name}: the first line is not the metrics header {HEADER.decode().strip()!r}")
    start, end = len(HEADER), len(data)
    if start == end:
        return np.empty((0, 4))
    if data[-1] != 10:
        raise DicerError(f"{name}: the last line is cut short")
    blocks = []  # (start, stop): whole lines
    while start < end:
        stop = data.rfind(b"\n", start, min(start + _CHUNK, end)) + 1
        if stop <= start:  # one line longer than a block
            stop = data.find(b"\n", start) + 1
        blocks.append((start, stop))
        start = stop

    def parse(block: tuple[int, int]) -> np.ndarray:  # lines before it counted only for a message
        a, b = block
        return _parse_lines(np.frombuffer(data, np.uint8, b - a, a), name,
                            lambda: data.count(b"\n", len(HEADER), a))

    # blocks side by side; in order, so the first bad line is the one named
    return np.concatenate(list(ordered_map(parse, blocks)))


_FIELD = _DIGITS + 6
"""Bytes of a non-negative field and the separator after it: d.dddddde+XX and , or newline."""


def _value(mantissa: np.ndarray, exponent: np.ndarray) -> np.ndarray:
    """``mantissa`` x 10^(``exponent`` - 6) in one correctly rounded operation, as a decimal
    parser gives it: 2.400000e+01 is 24.0 exactly."""
    k = exponent - (_DIGITS - 1)
    return np.where(k >= 0, mantissa * _POW10[np.maximum(k, 0)], mantissa / _POW10[np.maximum(-k, 0)])


_POW10 = 10.0 ** np.arange(100 + _DIGITS)
"""10^0 .. 10^106 (the exponents two digits hold, and the mantissa's shift), computed once."""


def _parse_non_negative(body: np.ndarray) -> np.ndarray | None:
    """(m, 4) float64 from lines of four non-negative values, the common case: every line is
    then 52 bytes, so the fields are columns of a (m, 4, 13) view and need no search for
    separators. None when ``body`` is not such lines (a negative value, a damaged line):
    the general parse judges it."""
    if body.size % (4 * _FIELD):
        return None
    f = body.reshape(-1, 4, _FIELD)
    digit_columns = [0, *range(2, _DIGITS + 1), _DIGITS + 3, _DIGITS + 4]
    digits = f[:, :, digit_columns] - np.uint8(48)  # wraps below "0": caught by the range test
    if not (np.all(f[:, :3, _FIELD - 1] == 44) and np.all(f[:, 3, _FIELD - 1] == 10) and np.all(f[:, :, 1] == 46)
            and np.all(f[:, :, _DIGITS + 1] == 101) and np.all((f[:, :, _DIGITS + 2] == 43) | (f[:, :, _DIGITS + 2] == 45))
            and np.all(digits <= 9)):
        return None
    mantissa = digits[:, :, :_DIGITS].astype(np.int64) @ (10 ** np.arange(_DIGITS - 1, -1, -1, dtype=np.int64))
    exponent = ((digits[:, :, _DIGITS].astype(np.int64) * 10 + digits[:, :, _DIGITS + 1])
                * np.where(f[:, :, _DIGITS + 2] == 45, -1, 1))
    return _value(mantissa, exponent)


def _parse_lines(body: np.ndarray, name: str, first) -> np.ndarray:
    """(m, 4) float64 from whole lines ``body`` (bytes ending in a newline); ``first()`` is
    the number of value lines before them (for messages)."""
    fast = _parse_non_negative(body)
    if fast is not None:
        return fast
    sep = np.flatnonzero((body == 44) | (body == 10))
    if sep.size % 4 or np.any(body[sep[3::4]] != 10) or np.any(body[sep[np.arange(sep.size) % 4 != 3]] != 44):
        raise DicerError(f"{name}: a line does not hold 4 comma-separated values")
    start = np.r_[0, sep[:-1] + 1]
    neg = body[start] == 45
    s = start + neg
    width = 5 + _DIGITS  # d . 6 digits e sign 2 digits
    ok = (sep - s) == width
    s = np.where(ok, s, 0)
    mask = np.array([0, 1] + [0] * (_DIGITS - 1) + [1, 1, 0, 0], bool)  # fixed characters
    offsets = np.arange(width)
    chars = body[s[:, None] + offsets]
    digits = chars[:, ~mask].astype(np.int64) - 48
    ok &= np.all((digits >= 0) & (digits <= 9), axis=1)
    ok &= (chars[:, 1] == 46) & (chars[:, _DIGITS + 1] == 101) & np.isin(chars[:, _DIGITS + 2], (43, 45))
    if not ok.all():
        bad = int(np.flatnonzero(~ok)[0])
        raise DicerError(f"{name}: line {first() + bad // 4 + 2} holds a value that is not [-]d.dddddde[+-]XX")
    mantissa = digits[:, :_DIGITS] @ (10 ** np.arange(_DIGITS - 1, -1, -1, dtype=np.int64))
    exponent = (digits[:, _DIGITS] * 10 + digits[:, _DIGITS + 1]) * np.where(chars[:, _DIGITS + 2] == 45, -1, 1)
    value = _value(mantissa, exponent)
    return np.where(neg, -value, value).reshape(-1, 4)


def read_metrics_csv(path: str | os.PathLike) -> np.ndarray:
    """(M, 4) float64 from a metrics CSV written by :func:`write_metrics_csv`."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise DicerError(f"{path}: cannot read the metrics CSV ({exc.strerror})") from None
    return parse_metrics_csv(data, str(path))


def write_metrics_csv(mesh: Mesh, path: str | os.PathLike, metrics: dict | None = None) -> np.ndarray:
    """Write the per-element metrics of ``mesh`` to ``path`` atomically; returns them (M, 4).
    ``metrics``: those already computed, by name (:data:`COLUMNS`), reused.

    The file is read back and every value compared with what was meant (within half a
    unit of the 7th significant digit) before it is renamed into place.
    """
    values = element_metrics(mesh, metrics)
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(values), axis=1))[0])
        raise DicerError(f"{path}: element {bad + 1} has a zero-length edge (non-finite edge ratio); "
                         "remesh from the labels with 'dicer mesh'")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(HEADER)
            write_chunks(f, values.shape[0], _fields_of(values), compact=True)
        back = read_metrics_csv(tmp)
        # a printed value is within half a unit of its 7th digit; the parse adds a rounding or two
        same = back.shape == values.shape
        for i in range(0, values.shape[0] if same else 0, _CHUNK // 16):  # blocks: small temporaries
            v = values[i:i + _CHUNK // 16]
            same = not np.any(np.abs(back[i:i + _CHUNK // 16] - v) > np.abs(v) * (0.5 * 10.0 ** (1 - _DIGITS) + 1e-15))
            if not same:
                break
        if not same:
            raise DicerError(f"{path}: read-back check failed: the file does not hold the metrics written; "
                             "check the disk and write again")
    return values
