"""PATRAN 2 neutral file (``.out`` / ``.neu``): packets 25, 26, 01, 02 and 99, fixed-width cards.

Every packet opens with a header card ``(I2,8I8)`` -- IT, ID, IV, KC, N1..N5 --
followed by KC data cards:

* 25 title: one card, the provenance line (80 columns).
* 26 summary: N1 nodes, N2 elements, N3 materials, N4 properties; one card with
  the date, time and version fields left blank (reruns are byte-identical).
* 01 node (ID = node number): card 1 the coordinates ``(3E16.9)``, card 2
  ``(I1,A1,3I8,2X,6I1)`` = ``1G       6       0       0  000000``.
* 02 element (ID = element number, IV = shape: 4 quad, 8 hex): card 1
  ``(4I8,3E16.9)`` = node count, configuration 0, property id = material
  label, 0, three zero orientation angles; then the node numbers ``(10I8)``.
  20-node hexahedra list their mid-edge nodes as PATRAN does: the bottom edges,
  the vertical edges, then the top edges (VTK and Abaqus put the top edges
  before the vertical ones).
* 21 named component, one per material present (ID = material label): IV = twice the
  material's element count, KC = 1 + IV/10 rounded up; card 1 the material's name
  ``(A12)``, then (type, element number) pairs ``(10I8)``, the last card holding what is
  left. Type 12 is an 8-node hexahedron, 112 a 20-node one, 8 and 108 quads. PATRAN
  lists these groups by name; the property id of packet 02 is the label as before.
* 99 end of file.

Each kind of packet is a fixed number of fixed-width lines, so whole blocks of
packets are formatted in bulk by :mod:`dicer.export.textfmt`. :func:`read_patran` reads
such files back strictly and :func:`check_patran` compares one with the model.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.readers import Lines, compare, named
from dicer.export.textfmt import Float, Int, Sci, int_lines, row_ids, write_chunks
from dicer.mesh.topology import HEX20_EXODUS

E16 = Sci(9, b"E", fortran=True, width=16)
SHAPES = {(3, 1): (8, 8), (3, 2): (8, 20), (2, 1): (4, 4), (2, 2): (4, 8)}  # -> (IV shape code, nodes)


def header(it: int, ident: int, iv: int, kc: int, *n: int) -> bytes:
    """One ``(I2,8I8)`` header card.

    Parameters
    ----------
    it, ident, iv, kc : int
        Packet type, id, additional id and card count.
    *n : int
        Up to five further fields (0 for those left out).

    Returns
    -------
    bytes
        The card with its newline.
    """
    n = tuple(n) + (0,) * (5 - len(n))
    return (f"{it:2d}{ident:8d}{iv:8d}{kc:8d}" + "".join(f"{v:8d}" for v in n) + "\n").encode()


COMPONENT_TYPES = {(3, 1): 12, (3, 2): 112, (2, 1): 8, (2, 2): 108}
"""Named-component entity type of the model's elements, by (dimension, order)."""


def _cut(name: str, width: int = 12) -> str:
    """``name`` in ``width`` characters: a name ending in a number keeps the number whole and
    loses letters before it (``label_69705095`` -> ``lab_69705095``, not ``label_697050``, which
    reads as another label)."""
    if len(name) <= width:
        return name
    import re

    number = re.search(r"_?([0-9]+)$", name)
    if number and len(number.group(1)) + 2 <= width:
        head = name[:number.start()][:width - len(number.group(1)) - 1].rstrip("_")
        if head:
            return f"{head}_{number.group(1)}"
    return name[:width]


def component_names(model) -> dict[int, str]:
    """Packet 21 name of each material present.

    Its name when it fits the 12 columns of the card and no other name cut to 12 (a trailing
    number kept whole, :func:`_cut`) is the same in upper case; else the name cut and ended by
    ``_<label>``, cut shorter where that would be
    another material's name (so the names are unique and a name that fits stays the
    user's own).

    Parameters
    ----------
    model : SolverModel

    Returns
    -------
    dict of int to str
        Label -> name.
    """
    labels = list(model.labels())
    cut = {k: _cut(model.names[k]) for k in labels}
    # compared in upper case: solvers read names so (Left_Hippoca and LEFT_HIPPOCA are one)
    count = Counter(v.upper() for v in cut.values())
    out = {k: v for k, v in cut.items() if count[v.upper()] == 1}
    taken = {v.upper() for v in out.values()}
    for k in labels:
        if k in out:
            continue
        # names start with a letter, so "_<label>" alone is never another material's name
        for width in range(11 - len(str(k)), -1, -1):
            name = f"{model.names[k][:width]}_{k}"
            if name.upper() not in taken:
                break
        out[k] = name
        taken.add(name.upper())
    return {k: out[k] for k in labels}


def _components(f, model) -> None:
    """Packet 21 per material present: its name and (type, element number) pairs."""
    kind = COMPONENT_TYPES[(model.dim, model.order)]
    names = component_names(model)
    for label, elements in model.blocks():
        pairs = np.empty((elements.size, 2), np.int64)
        pairs[:, 0] = kind
        pairs[:, 1] = elements + 1
        iv = 2 * elements.size
        f.write(header(21, label, iv, 1 + -(-iv // 10)))
        f.write(names[label].encode() + b"\n")
        f.write(int_lines(pairs.ravel(), 10, 8, sep=b""))


def patran_order(model) -> np.ndarray:
    """The model's cells in PATRAN node order.

    Parameters
    ----------
    model : SolverModel

    Returns
    -------
    (M, k) int ndarray
    """
    if model.dim == 3 and model.order == 2:
        return model.cells[:, HEX20_EXODUS]  # PATRAN's 20-node order is Exodus's
    return model.cells


def write_patran(model, path: str | Path) -> None:
    """Write a SolverModel as a PATRAN 2 neutral file.

    Parameters
    ----------
    model : SolverModel
    path : str or Path
        The ``.out`` or ``.neu`` file.
    """
    iv, nn = SHAPES[(model.dim, model.order)]
    if max(model.n_points, model.n_cells) >= 10**8:
        raise ValueError("more than 99999999 nodes or elements do not fit PATRAN's 8-column fields")
    cells = patran_order(model)
    node_cards = -(-nn // 10)
    labels = model.labels()
    zeros5 = b"       0" * 5
    with open(path, "wb", buffering=1 << 20) as f:
        title = model.heading[0][:80]
        f.write(header(25, 0, 0, 1) + title.encode() + b"\n")
        f.write(header(26, 0, 0, 1, model.n_points, model.n_cells, len(labels), len(labels), 0))
        f.write(b" " * 32 + b"\n")
        node_head, node_tail = b"       0       2" + zeros5 + b"\n", b"\n1G       6       0       0  000000\n"
        write_chunks(f, model.n_points, lambda a, b: [b" 1", Int(row_ids(a, b), 8), node_head]
                     + [Float(model.points[a:b, j], E16) for j in range(3)] + [node_tail])
        head_tail = f"{1 + node_cards:8d}".encode() + zeros5 + b"\n" + f"{nn:8d}{0:8d}".encode()
        angles = b" 0.000000000E+00" * 3

        def element_fields(a, b):
            fields = [b" 2", Int(row_ids(a, b), 8), f"{iv:8d}".encode() + head_tail, Int(model.material[a:b], 8),
                      f"{0:8d}".encode() + angles]
            for j in range(nn):  # ten node numbers a card
                fields += [b"\n"] * (j % 10 == 0) + [Int(cells[a:b, j] + 1, 8)]
            return fields + [b"\n"]

        write_chunks(f, model.n_cells, element_fields)
        _components(f, model)
        f.write(header(99, 0, 0, 1))


# --- strict reader ----------------------------------------------------------------------------


def _patran_headers(lines: Lines, rows: np.ndarray, it: int, what: str) -> np.ndarray:
    """(n, 9) header fields IT ID IV KC N1..N5 of ``(I2,8I8)`` cards, IT checked."""
    lines.lengths_are(rows, 66, what)
    out = np.column_stack([lines.ints(rows, 0, 2, what)] + [lines.ints(rows, 2 + 8 * k, 8, what) for k in range(8)])
    if np.any(out[:, 0] != it):
        raise DicerError(f"line {int(rows[np.flatnonzero(out[:, 0] != it)[0]]) + 1}: expected a packet {it:02d} header")
    return out


def _patran_packets(lines: Lines, rows: np.ndarray, it: int, what: str) -> tuple[np.ndarray, np.ndarray]:
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

    Nodes and elements must be numbered 1..N and 1..M in order.

    Parameters
    ----------
    path : str or Path
        From :func:`write_patran`.

    Returns
    -------
    dict
        ``points`` (N, 3), ``cells`` (M, k) 0-based in VTK/Abaqus node order,
        ``material`` (M,) property ids, ``title``, ``dim`` and ``order``.

    Raises
    ------
    DicerError
        Any other layout, naming the file and line.
    """
    return named(_read_patran, path)


def _patran_component(lines: Lines, row: int) -> tuple[int, int, str, np.ndarray]:
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

    lines = Lines(path)
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


def check_patran(path: str | Path, model) -> None:
    """Re-read a PATRAN neutral file with :func:`read_patran` and compare it with the model.

    Parameters
    ----------
    path : str or Path
    model : SolverModel
        Any dimension and order, as written to the neutral file ``path``.

    Raises
    ------
    DicerError
        The first difference.
    """
    got = _read_patran(path)
    if (got["dim"], got["order"]) != (model.dim, model.order):
        raise DicerError("element shape or order differs")
    compare(model, got["points"], got["cells"], got["material"], "the neutral file", digits=9)
    names = component_names(model)
    if sorted(got["components"]) != sorted(names):
        raise DicerError(f"named components {sorted(got['components'])} read back, materials {sorted(names)} written")
    for label, elements in model.blocks():
        name, pairs = got["components"][label]
        if (name != names[label] or not np.all(pairs[:, 0] == COMPONENT_TYPES[(model.dim, model.order)])
                or not np.array_equal(pairs[:, 1], elements + 1)):
            raise DicerError(f"named component {label} ({names[label]}) differs")



FORMAT = Format("patran", (".out", ".neu"), write_patran, check_patran, digits=(9,), holds_sets=False)  # E16.9; no sets
