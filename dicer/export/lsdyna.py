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
    *END

Units are dicer's: mm, N, MPa (N/mm^2), t/mm^3, so times come out in seconds.
Part, section and material ids are the material label. Only 8-node
hexahedra are written (``export.order: 1``, 3D meshes).
"""

from __future__ import annotations

from pathlib import Path

from dicer.export.format import Format
from dicer.export.textfmt import Float, Int, Sci, int_lines, row_ids, write_chunks

E16 = Sci(9, b"e", width=16)
ELFORM = {"C3D8": 2, "C3D8R": 1, "C3D8I": -2}


def _e10(v: float) -> str:
    """A real in a 10-column field with as many digits as fit."""
    for p in range(9, 0, -1):
        text = f"{float(v):.{p}g}"
        if len(text) <= 10:
            return f"{text:>10s}"
    raise ValueError(f"{v} does not fit a 10-column field")


def write_lsdyna(model, path: str | Path) -> None:
    """Write the SolverModel ``model`` (8-node hexahedra) as an LS-DYNA keyword file."""
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
        for sid, (name, ids) in enumerate(model.node_sets.items(), start=1):
            w(f"*SET_NODE_LIST_TITLE\n{name}\n$#     sid\n{sid:10d}\n".encode())
            w(int_lines(ids + 1, 8, 10, sep=b""))  # 8 x I10
        w(b"*END\n")


def check_lsdyna(path: str | Path, model) -> None:
    """Read the file back with dicer's strict LS-DYNA reader and compare it with ``model``."""
    from dicer.export import readers

    readers.check_lsdyna(path, model)


FORMAT = Format("lsdyna", (".k", ".key", ".dyn"), write_lsdyna, check_lsdyna, dims=(3,), orders=(1,),
                limits="LS-DYNA export writes 8-node hexahedra only (3D meshes, export.order 1); "
                       "set export.order 1 or choose another format")
