"""Abaqus / CalculiX input deck (``.inp``): the model part, ready to ``*INCLUDE`` from a deck with a step.

Layout::

    *HEADING                 provenance (dicer version, input name + SHA-256, config hash)
    *NODE                    numbered from 1, coordinates in mm
    *ELEMENT, TYPE=C3D8, ELSET=<material>    one block per material
    *NSET, NSET=X0 ... Z1    bounding-box planes; <material>_BOUNDARY; <a>_<b> interfaces; EXTERIOR
    *ELSET, ELSET=EXTERIOR_S1 ...  + *SURFACE, NAME=EXTERIOR, TYPE=ELEMENT
    *MATERIAL, *ELASTIC, *DENSITY, *SOLID SECTION per material (2D: thickness on the data line)

There is no *STEP. Numbers fit CalculiX 2.20's reader, which takes at most 10
characters for an integer and 20 for a float after it drops blanks, and 16
entries per line: integers are right-aligned in 7 (or 11) columns, coordinates
printed with 9 (or 13) significant digits in 15 (or 19) columns; a 20-node
element continues on a second line after a trailing comma (16 entries first).
Blank padding keeps every field a fixed width, so each block is formatted in
bulk by :mod:`dicer.export.textfmt`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dicer.export.format import Format
from dicer.export.textfmt import Float, Int, Sci, aligned_width, int_lines, int_width, row_ids, write_chunks

PER_LINE = 16  # CalculiX and Abaqus: at most 16 entries on a data line


def _num(v: float) -> str:
    """A material constant, at most 20 characters (CalculiX's float field)."""
    return f"{float(v):.12g}"


def node_block(stream, points: np.ndarray, width: int, digits: int, lead_nl: bool = True) -> None:
    """Rows ``\\n<id>, x, y, z`` for ids 1..N (each row starts with the newline that ends the previous line)."""
    fmt = Sci(digits)

    def fields(start, stop):
        p = points[start:stop]
        lead = b"\n" if lead_nl else b""
        return [Int(row_ids(start, stop), width, lead)] + [Float(p[:, j], fmt, b",") for j in range(3)]

    write_chunks(stream, points.shape[0], fields)


def element_block(stream, cells: np.ndarray, elements: np.ndarray, width: int, width_cont: int) -> None:
    """Rows ``\\n<element id>, n1, ..., nk`` (1-based), continued after 16 entries with ``,\\n``."""

    def fields(start, stop):
        e = elements[start:stop]
        c = cells[e] + 1
        # the 16th entry ends the first line
        return [Int(e + 1, width, b"\n")] + [Int(c[:, j], width_cont, b",\n") if j + 1 == PER_LINE
                                             else Int(c[:, j], width, b",") for j in range(c.shape[1])]

    write_chunks(stream, elements.size, fields)


def write_abaqus(model, path: str | Path) -> None:
    """Write the SolverModel ``model`` as an Abaqus/CalculiX deck at ``path``."""
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
        for name, ids in model.node_sets.items():
            w(f"*NSET, NSET={name}\n".encode())
            w(int_lines(ids + 1, PER_LINE, wid))
        if model.exterior is not None and model.exterior.size:
            faces = model.exterior
            present = []
            for s in range(1, (6 if model.dim == 3 else 4) + 1):
                ids = faces[faces[:, 1] == s, 0]
                if ids.size:
                    present.append(s)
                    w(f"*ELSET, ELSET=EXTERIOR_S{s}\n".encode())
                    w(int_lines(np.sort(ids) + 1, PER_LINE, wid))
            w(b"*SURFACE, NAME=EXTERIOR, TYPE=ELEMENT\n")
            for s in present:
                w(f"EXTERIOR_S{s}, S{s}\n".encode())
        for k in model.labels():
            name, p = model.names[k], model.props[k]
            w(f"*MATERIAL, NAME={name}\n*ELASTIC\n{_num(p['youngs_modulus'])}, {_num(p['poissons_ratio'])}\n"
              f"*DENSITY\n{_num(p['density'])}\n".encode())
            w(f"*SOLID SECTION, ELSET={name}, MATERIAL={name}\n".encode())
            if model.dim == 2:
                w(f"{_num(model.thickness)}\n".encode())


def check_deck(path: str | Path, model, verify: str = "strict") -> None:
    """Read the deck back and compare it with ``model``: with dicer's strict reader, or with
    meshio's when ``verify`` is ``meshio`` (``export.verify``)."""
    from dicer.export import readers

    if verify == "meshio":
        readers.check_abaqus_meshio(path, model)
    else:
        readers.check_abaqus(path, model)


FORMAT = Format("abaqus", (".inp",), write_abaqus, check_deck, check_options={"verify": ("verify", "strict")})
