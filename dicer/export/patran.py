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
packets are formatted in bulk by :mod:`dicer.export.textfmt`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dicer.export.format import Format
from dicer.export.textfmt import Float, Int, Sci, int_lines, row_ids, write_chunks
from dicer.mesh.topology import HEX20_EXODUS

E16 = Sci(9, b"E", fortran=True, width=16)
SHAPES = {(3, 1): (8, 8), (3, 2): (8, 20), (2, 1): (4, 4), (2, 2): (4, 8)}  # -> (IV shape code, nodes)


def header(it: int, ident: int, iv: int, kc: int, *n: int) -> bytes:
    """One ``(I2,8I8)`` header card."""
    n = tuple(n) + (0,) * (5 - len(n))
    return (f"{it:2d}{ident:8d}{iv:8d}{kc:8d}" + "".join(f"{v:8d}" for v in n) + "\n").encode()


COMPONENT_TYPES = {(3, 1): 12, (3, 2): 112, (2, 1): 8, (2, 2): 108}
"""Named-component entity type of the model's elements, by (dimension, order)."""


def component_names(model) -> dict[int, str]:
    """Label -> packet 21 name of each material present: its name cut to the 12 columns of the
    card, ended by ``_<label>`` where two cut names would be the same."""
    cut = {k: model.names[k][:12] for k in model.labels()}
    seen = [v for v in cut.values()]
    return {k: v if seen.count(v) == 1 else f"{model.names[k][:11 - len(str(k))]}_{k}" for k, v in cut.items()}


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
    """The model's cells in PATRAN node order."""
    if model.dim == 3 and model.order == 2:
        return model.cells[:, HEX20_EXODUS]  # PATRAN's 20-node order is Exodus's
    return model.cells


def write_patran(model, path: str | Path) -> None:
    """Write the SolverModel ``model`` as a PATRAN 2 neutral file."""
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


def check_patran(path: str | Path, model) -> None:
    """Read the file back with dicer's strict PATRAN reader and compare it with ``model``."""
    from dicer.export import readers

    readers.check_patran(path, model)


FORMAT = Format("patran", (".out", ".neu"), write_patran, check_patran)
