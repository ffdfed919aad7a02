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
hexahedra are written (``export.order: 1``, 3D meshes). :func:`read_lsdyna` reads such
files back strictly and :func:`check_lsdyna` compares one with the model.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.readers import Lines, compare, named
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
        for sid, (name, ids) in enumerate(model.node_sets.items(), start=1):
            w(f"*SET_NODE_LIST_TITLE\n{name}\n$#     sid\n{sid:10d}\n".encode())
            w(int_lines(ids + 1, 8, 10, sep=b""))  # 8 x I10
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
        title), ``materials`` (mid -> (ro, e, pr)), ``node_sets`` (title -> 0-based ids)
        and ``title``.

    Raises
    ------
    DicerError
        Anything out of place, naming the file and line.
    """
    return named(_read_lsdyna, path)


def _read_lsdyna(path: str | Path) -> dict:
    """:func:`read_lsdyna` with messages that start at the line."""
    lines = Lines(path)
    n = len(lines)
    is_key = lines.arr[lines.starts[lines.lengths > 0]] == ord("*")
    key_rows = np.flatnonzero(lines.lengths > 0)[is_key]
    comment = np.zeros(n, bool)
    nonempty = np.flatnonzero(lines.lengths > 0)
    comment[nonempty[lines.arr[lines.starts[nonempty]] == ord("$")]] = True
    keys = [lines.text(i).strip().upper() for i in key_rows]
    if not keys or keys[0] != "*KEYWORD" or keys[-1] != "*END":
        raise DicerError("an LS-DYNA keyword file starts with *KEYWORD and ends with *END")
    bounds = list(key_rows) + [n]
    out = {"parts": {}, "materials": {}, "node_sets": {}, "title": ""}
    points = cells = pids = None
    for i, key in enumerate(keys):
        rows = np.arange(bounds[i] + 1, bounds[i + 1])
        rows = rows[~comment[rows]]
        if key == "*TITLE":
            out["title"] = lines.text(rows[0]) if rows.size else ""
        elif key == "*NODE":
            lines.lengths_are(rows, 56, "*NODE")
            ids = lines.ints(rows, 0, 8, "*NODE id")
            if not np.array_equal(ids, np.arange(1, rows.size + 1)):
                raise DicerError("*NODE ids must run 1..N in order")
            points = np.column_stack([lines.floats(rows, 8 + 16 * j, 16, "*NODE coordinate") for j in range(3)])
        elif key == "*PART":
            if rows.size != 2:
                raise DicerError("*PART needs a title card and one data card")
            vals = [lines.ints(rows[1:], 10 * k, 10, "*PART")[0] for k in range(3)]
            pid, secid, mid = (int(v) for v in vals)
            out["parts"][pid] = {"title": lines.text(rows[0]).strip(), "secid": secid, "mid": mid}
        elif key == "*SECTION_SOLID":
            if rows.size != 1:
                raise DicerError("*SECTION_SOLID needs one data card")
            out.setdefault("sections", {})[int(lines.ints(rows, 0, 10, "*SECTION_SOLID")[0])] = int(
                lines.ints(rows, 10, 10, "*SECTION_SOLID ELFORM")[0])
        elif key == "*MAT_ELASTIC":
            if rows.size != 1:
                raise DicerError("*MAT_ELASTIC needs one data card")
            mid = int(lines.ints(rows, 0, 10, "*MAT_ELASTIC")[0])
            out["materials"][mid] = tuple(float(lines.floats(rows, 10 * k, 10, "*MAT_ELASTIC")[0]) for k in (1, 2, 3))
        elif key == "*ELEMENT_SOLID":
            lines.lengths_are(rows, 80, "*ELEMENT_SOLID")
            ids = lines.ints(rows, 0, 8, "*ELEMENT_SOLID id")
            if not np.array_equal(ids, np.arange(1, rows.size + 1)):
                raise DicerError("*ELEMENT_SOLID ids must run 1..M in order")
            pids = lines.ints(rows, 8, 8, "*ELEMENT_SOLID part").astype(np.int32)
            cells = np.column_stack([lines.ints(rows, 16 + 8 * j, 8, "*ELEMENT_SOLID node") for j in range(8)])
        elif key == "*SET_NODE_LIST_TITLE":
            if rows.size < 2:
                raise DicerError("*SET_NODE_LIST_TITLE needs a title and a data card")
            name = lines.text(rows[0]).strip()
            data = rows[2:]
            if data.size and np.any(lines.lengths[data] % 10):
                raise DicerError(f"node set {name}: cards must be whole 10-column fields")
            full = data[lines.lengths[data] == 80]
            ids = [lines.ints(full, 10 * k, 10, "node set")[:, None] for k in range(8)]
            ids = np.concatenate(ids, axis=1).ravel() if full.size else np.zeros(0, np.int64)
            tail = data[lines.lengths[data] < 80]
            if tail.size > 1 or (tail.size == 1 and tail[0] != data[-1]):
                raise DicerError(f"node set {name}: only the last card may be short")
            if tail.size:
                k = int(lines.lengths[tail[0]]) // 10
                ids = np.concatenate([ids] + [lines.ints(tail, 10 * j, 10, "node set") for j in range(k)])
            out["node_sets"][name] = ids - 1
        elif key in ("*KEYWORD", "*END"):
            if rows.size:
                raise DicerError(f"{key} takes no data cards")
        else:
            raise DicerError(f"unexpected keyword {key}")
    if points is None or cells is None:
        raise DicerError("no *NODE or *ELEMENT_SOLID block")
    if cells.min() < 1 or cells.max() > points.shape[0]:
        raise DicerError("elements refer to nodes that do not exist")
    out.update(points=points, cells=cells - 1, material=pids)
    return out


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
    for k in model.labels():
        if got["parts"].get(k, {}).get("title") != model.names[k] or k not in got["materials"]:
            raise DicerError(f"part or material {model.names[k]} missing")



FORMAT = Format("lsdyna", (".k", ".key", ".dyn"), write_lsdyna, check_lsdyna, dims=(3,), orders=(1,),
                limits="LS-DYNA export writes 8-node hexahedra only (3D meshes, export.order 1); "
                       "set export.order 1 or choose another format")
