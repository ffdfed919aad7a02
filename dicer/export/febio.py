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
                                             interfaces, EXTERIOR), comma-separated node numbers
        <Surface name="EXTERIOR">, <Surface name="<a>_<b>">   <quad4 id> (order 2: <quad8>) facets
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
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dicer.errors import DicerError
from dicer.export.format import Format
from dicer.export.textfmt import Float, Int, Sci, int_lines, int_width, write_chunks
from dicer.mesh.topology import HEX20_FACES, HEX_FACES

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


def facets(model, faces: np.ndarray) -> np.ndarray:
    """Node indices of the outward facets of element faces.

    Parameters
    ----------
    model : SolverModel
    faces : (F, 2) int ndarray
        Rows of element index and Abaqus face number 1..6.

    Returns
    -------
    (F, 4) or (F, 8) int ndarray
        0-based.
    """
    table = HEX20_FACES if model.order == 2 else HEX_FACES  # wound outward, as FEBio wants them
    return model.cells[faces[:, 0][:, None], table[faces[:, 1] - 1]]


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
            _rows(f, ftype, np.arange(1, faces.shape[0] + 1), facets(model, faces) + 1, width)
            w(b"\t\t</Surface>\n")
        w(b"\t</Mesh>\n\t<MeshDomains>\n")
        for k in labels:
            w(f'\t\t<SolidDomain name="{model.names[k]}" mat="{model.names[k]}"/>\n'.encode())
        w(b"\t</MeshDomains>\n</febio_spec>\n")


# --- reader ---------------------------------------------------------------------------------


def _numbers(texts: list[str], per_row: int, dtype, what: str) -> np.ndarray:
    """(len(texts), per_row) array of the comma-separated numbers in each text, strictly."""
    if not texts:
        return np.zeros((0, per_row), dtype)
    counts = np.char.count(np.array(texts), ",") + 1
    if np.any(counts != per_row):
        bad = int(np.flatnonzero(counts != per_row)[0])
        raise DicerError(f"{what} {bad + 1} has {counts[bad]} values, expected {per_row}")
    flat = _parse(",".join(texts), dtype, what)
    if flat.size != len(texts) * per_row:
        raise DicerError(f"{what}: not a number among the values")
    return flat.reshape(-1, per_row)


def _parse(text: str, dtype, what: str) -> np.ndarray:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns, and stops, at text that is not a number
        try:
            return np.fromstring(text, dtype=dtype, sep=",")
        except (ValueError, DeprecationWarning):
            raise DicerError(f"{what}: not a number among the values") from None


def _ids(values: list[str], what: str) -> np.ndarray:
    try:
        return np.array(values, dtype=np.int64) if values else np.zeros(0, np.int64)
    except ValueError:
        raise DicerError(f"{what}: an id that is not an integer") from None


def read_febio(path: str | Path) -> dict:
    """Read an FEBio 4.0 file as dicer writes it, strictly, with ElementTree.

    Node ids must run 1..N in order, facet ids 1..F.

    Parameters
    ----------
    path : str or Path
        An XML file, from :func:`write_febio`; FEBio 4.0 only.

    Returns
    -------
    dict
        ``version``, ``module``, ``materials`` (list of dicts: id, name, type, E, v,
        density), ``points`` (N, 3), ``blocks`` (list of (type, name, element ids (m,),
        (m, k) 0-based connectivity)), ``node_sets`` (name -> 0-based node indices),
        ``surfaces`` (name -> (facet type, (F, k) 0-based nodes)) and ``domains`` (list of
        (name, mat)).

    Raises
    ------
    DicerError
        Anything out of place.
    """
    import xml.etree.ElementTree as ET

    out = {"materials": [], "blocks": [], "node_sets": {}, "surfaces": {}, "domains": []}
    # ids and texts of the nodes, and of the elements or facets of the current block
    got = {"node_ids": [], "node_text": [], "ids": [], "text": []}
    stack: list[str] = []
    parents: list = []
    sections = []
    try:
        for event, el in ET.iterparse(str(path), events=("start", "end")):
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
                    got["ids"], got["text"] = [], []
                continue
            path_ = "/".join(stack)
            stack.pop()
            parents.pop()
            _end_element(path_, el, stack, parents, out, got)
    except ET.ParseError as exc:
        raise DicerError(f"not well-formed XML ({exc})") from None
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


def _end_element(path_: str, el, stack: list[str], parents: list, out: dict, got: dict) -> None:
    """Take in the XML element ``el`` at its end tag (``path_`` its path, ``stack`` its parents' tags)."""
    if path_ == "febio_spec/Module":
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
    elif path_ == "febio_spec/Mesh/Nodes/node":
        got["node_ids"].append(el.get("id"))
        got["node_text"].append(el.text or "")
        parents[-1].remove(el)  # the only child left: keeps memory flat on large files
    elif path_ in ("febio_spec/Mesh/Elements/elem",) or (
            len(stack) == 3 and stack[1] == "Mesh" and stack[2] == "Surface"):
        got["ids"].append(el.get("id"))
        got["text"].append(el.text or "")
        if stack[2] == "Surface":
            if el.tag not in FACET_TYPES.values():
                raise DicerError(f"facet <{el.tag}> in a surface")
            out.setdefault("_facet_types", set()).add(el.tag)
        parents[-1].remove(el)
    elif path_ == "febio_spec/Mesh/Nodes":
        ids = _ids(got["node_ids"], "node")
        if not np.array_equal(ids, np.arange(1, ids.size + 1)):
            raise DicerError("node ids must run 1..N in order")
        out["points"] = _numbers(got["node_text"], 3, np.float64, "node")
        got["node_ids"], got["node_text"] = [], []
        el.clear()
    elif path_ == "febio_spec/Mesh/Elements":
        etype = el.get("type")
        if etype not in FEBIO_TYPES.values():
            raise DicerError(f"element type {etype!r}, expected hex8 or hex20")
        k = 8 if etype == "hex8" else 20
        conn = _numbers(got["text"], k, np.int64, f"element of {el.get('name')}")
        out["blocks"].append((etype, el.get("name"), _ids(got["ids"], "element"), conn - 1))
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
        types = out.pop("_facet_types", set())
        if len(types) > 1:
            raise DicerError(f"surface {name} mixes facet types {sorted(types)}")
        ftype = types.pop() if types else "quad4"
        ids = _ids(got["ids"], "facet")
        if not np.array_equal(ids, np.arange(1, ids.size + 1)):
            raise DicerError(f"surface {name}: facet ids must run 1..F in order")
        conn = _numbers(got["text"], 4 if ftype == "quad4" else 8, np.int64, f"facet of {name}")
        out["surfaces"][name] = (ftype, conn - 1)
        el.clear()
    elif path_ == "febio_spec/MeshDomains/SolidDomain":
        out["domains"].append((el.get("name"), el.get("mat")))
    elif len(stack) == 2 and stack[1] == "Mesh" and el.tag not in ("Nodes", "Elements", "NodeSet", "Surface"):
        raise DicerError(f"unexpected <{el.tag}> in <Mesh>")


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
    from dicer.export.readers import compare
    from dicer.export.textfmt import sci_digits

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
    cells = np.full(model.cells.shape, -1, np.int64)
    material = np.zeros(model.n_cells, np.int32)
    for (k, elements), (etype, name, ids, conn) in zip(blocks, got["blocks"]):
        if etype != FEBIO_TYPES[model.order] or name != model.names[k]:
            raise DicerError(f"element block {name} ({etype}) read back, expected {model.names[k]}")
        if not np.array_equal(ids, elements + 1):
            raise DicerError(f"element numbers of {name} differ")
        cells[elements] = conn
        material[elements] = k
    fmt = Sci(13 if model.digits > 9 else 9)
    printed = sci_digits(model.points.ravel(), fmt)
    want = printed.view(f"S{printed.shape[1]}").ravel().astype(np.float64).reshape(-1, 3)
    if got["points"].shape != want.shape or not np.array_equal(got["points"], want):
        raise DicerError("node coordinates differ from the printed values")
    compare(model, got["points"], cells, material, "the FEBio file", digits=fmt.digits)
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
        if ftype != FACET_TYPES[model.order] or not np.array_equal(conn, facets(model, faces)):
            raise DicerError(f"surface {name} differs")


FORMAT = Format("febio", (".feb",), write_febio, check_febio, dims=(3,),
                limits="FEBio has no plane (2D) elements; export this {dim}D mesh to .inp (CPS4/CPE4) or another "
                       "format, or mesh a 3D volume for .feb",
                write_options={"material_type": "febio_material"},
                check_options={"material_type": "febio_material"})
