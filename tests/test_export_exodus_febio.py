"""Exodus II (netCDF4) and FEBio 4.0 exports: blocks, sets, node orders, read-back, bad input."""

from __future__ import annotations

import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import netCDF4
import numpy as np
import pytest

from dicer.config import load_config
from dicer.errors import DicerError
from dicer.export import export_mesh, prepare_model
from dicer.export.febio import FACET_TYPES, FEBIO_TYPES, SPEC_VERSION, _complete, read_febio
from dicer.mesh.voxel import voxel_mesh
from test_export_formats import labels, mesh  # noqa: F401  (the same two-material model)

# From the Exodus II element documentation (1-based): the corners of each side of a
# hexahedron, and the edges whose mid-edge node is HEX20 node 9..20 (PATRAN's order:
# bottom edges, vertical edges, top edges).
EXO_HEX_SIDES = [(1, 2, 6, 5), (2, 3, 7, 6), (3, 4, 8, 7), (1, 5, 8, 4), (1, 4, 3, 2), (5, 6, 7, 8)]
EXO_HEX20_EDGES = [(1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (2, 6), (3, 7), (4, 8),
                   (5, 6), (6, 7), (7, 8), (8, 5)]
EXO_QUAD_SIDES = [(1, 2), (2, 3), (3, 4), (4, 1)]
QUAD8_EDGES = [(1, 2), (2, 3), (3, 4), (4, 1)]
# FEBio's hex20 (its shape functions): mid-edge nodes 9..20 on the bottom, top, vertical edges.
FEBIO_HEX20_EDGES = [(1, 2), (2, 3), (3, 4), (4, 1), (5, 6), (6, 7), (7, 8), (8, 5),
                     (1, 5), (2, 6), (3, 7), (4, 8)]




@pytest.fixture
def mesh2d():
    lab = np.zeros((4, 5), np.uint8)
    lab[:, :2] = 1
    lab[1:3, 2:] = 2
    return voxel_mesh(lab, spacing=(0.5, 0.75), origin=(-1.0, 2.0))


def cfg(**export):
    return load_config(settings={"export": export})


def _text(var) -> list[str]:
    var.set_auto_mask(False)
    return [b"".join(r).rstrip(b"\0").decode() for r in np.asarray(var[:])]


def _side_nodes(conn: np.ndarray, elem: np.ndarray, side: np.ndarray, dim: int) -> set[int]:
    """1-based nodes of Exodus sides (element positions 1-based), from the documented tables."""
    corners = EXO_HEX_SIDES if dim == 3 else EXO_QUAD_SIDES
    edges = EXO_HEX20_EDGES if dim == 3 else QUAD8_EDGES
    nodes = set()
    for e, s in zip(elem.tolist(), side.tolist()):
        row = conn[e - 1]
        c = corners[s - 1]
        nodes.update(row[i - 1] for i in c)
        if row.size > 2 ** dim:  # quadratic: the mid-edge nodes of the side's edges
            ring = list(c) + [c[0]] if dim == 3 else list(c)
            for a, b in zip(ring[:-1], ring[1:]):
                k = next(i for i, ed in enumerate(edges) if set(ed) == {a, b})
                nodes.add(row[2 ** dim + k])
    return nodes


# --- Exodus II ------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [1, 2])
def test_exodus_blocks_sets_and_meshio(tmp_path, mesh, order):
    config = cfg(order=order)
    export_mesh(mesh, tmp_path / "m.inp", config, source=tmp_path / "patient_7.nii")
    info = export_mesh(mesh, tmp_path / "m.exo", config, source=tmp_path / "patient_7.nii")
    model = prepare_model(mesh, config)
    deck = meshio.read(tmp_path / "m.inp", file_format="abaqus")

    # meshio reads it: the points, and the cells block by block (meshio does not reorder
    # Exodus's HEX20, so those come in Exodus order)
    m = meshio.read(tmp_path / "m.exo")
    assert np.array_equal(m.points, model.points)
    blocks = model.blocks()
    order_cells = model.cells[np.concatenate([e for _, e in blocks])]
    if order == 2:
        exo = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 16, 17, 18, 19, 12, 13, 14, 15]
        order_cells = order_cells[:, exo]
    assert [b.type for b in m.cells] == ["hexahedron" if order == 1 else "hexahedron20"] * 2
    assert np.array_equal(np.concatenate([b.data for b in m.cells]), order_cells)
    assert {k: v.size for k, v in m.point_sets.items()} == {k: len(v) for k, v in deck.point_sets.items()}

    with netCDF4.Dataset(tmp_path / "m.exo") as nc:
        assert _text(nc["eb_names"]) == ["soft_tissue", "bone"]
        assert list(nc["eb_prop1"][:]) == [1, 2]
        assert [nc[f"connect{i}"].elem_type for i in (1, 2)] == ["HEX8" if order == 1 else "HEX20"] * 2
        counts = [len(nc.dimensions[f"num_el_in_blk{i}"]) for i in (1, 2)]
        assert counts == [int(np.count_nonzero(mesh.material == k)) for k in (1, 2)]
        assert _text(nc["coor_names"]) == ["X", "Y", "Z"]
        ns = _text(nc["ns_names"])
        assert ns == list(deck.point_sets)  # the Abaqus deck's node sets, in its order
        for i, name in enumerate(ns, start=1):
            assert np.array_equal(np.sort(nc[f"node_ns{i}"][:] - 1), np.sort(deck.point_sets[name]))
        assert _text(nc["ss_names"]) == ["EXTERIOR", "soft_tissue_bone"]
        assert len(nc.dimensions["num_side_ss1"]) == info["exterior_faces"]
        # element numbers of the Abaqus deck through the element number map
        assert np.array_equal(nc["elem_num_map"][:] - 1, np.concatenate([e for _, e in blocks]))
        # no path and no input name anywhere in the file's text
        assert "patient_7" not in nc.title and "/" not in nc.title
    raw = (tmp_path / "m.exo").read_bytes()
    assert b"patient_7" not in raw and str(tmp_path).encode() not in raw


@pytest.mark.parametrize("order", [1, 2])
def test_exodus_side_sets_are_the_faces_of_their_node_sets(tmp_path, mesh, order):
    # the (element, side) pairs, read with Exodus's documented side and node numbering,
    # cover exactly the nodes of the node set of the same name
    export_mesh(mesh, tmp_path / "m.exo", cfg(order=order))
    with netCDF4.Dataset(tmp_path / "m.exo") as nc:
        conn = np.concatenate([nc[f"connect{i}"][:] for i in (1, 2)])
        ns = dict(zip(_text(nc["ns_names"]), (nc[f"node_ns{i}"][:] for i in range(1, 100))))
        for i, name in enumerate(_text(nc["ss_names"]), start=1):
            got = _side_nodes(conn, nc[f"elem_ss{i}"][:], nc[f"side_ss{i}"][:], 3)
            assert got == set(ns[name].tolist()), name


@pytest.mark.parametrize("order", [1, 2])
def test_exodus_two_dimensional(tmp_path, mesh2d, order):
    export_mesh(mesh2d, tmp_path / "q.e", cfg(order=order))
    with netCDF4.Dataset(tmp_path / "q.e") as nc:
        assert len(nc.dimensions["num_dim"]) == 2 and "coordz" not in nc.variables
        assert _text(nc["coor_names"]) == ["X", "Y"]
        assert nc["connect1"].elem_type == ("QUAD4" if order == 1 else "QUAD8")
        conn = np.concatenate([nc[f"connect{i}"][:] for i in (1, 2)])
        ns = dict(zip(_text(nc["ns_names"]), (nc[f"node_ns{i}"][:] for i in range(1, 100))))
        for i, name in enumerate(_text(nc["ss_names"]), start=1):
            got = _side_nodes(conn, nc[f"elem_ss{i}"][:], nc[f"side_ss{i}"][:], 2)
            assert got == set(ns[name].tolist()), name
    m = meshio.read(tmp_path / "q.e")
    assert np.allclose(m.points[:, :2], prepare_model(mesh2d, cfg(order=order)).points[:, :2], rtol=0, atol=0)


def test_exodus_read_back_and_missing_netcdf4(tmp_path, mesh, monkeypatch):
    import dataclasses

    from dicer.export import exodus, registry

    def broken(path, model):
        raise DicerError("side set EXTERIOR differs")

    monkeypatch.setitem(registry.BY_SUFFIX, ".exo", dataclasses.replace(exodus.FORMAT, check=broken))
    with pytest.raises(DicerError, match="read-back check failed: side set EXTERIOR differs"):
        export_mesh(mesh, tmp_path / "m.exo", cfg())
    monkeypatch.undo()
    monkeypatch.setitem(sys.modules, "netCDF4", None)  # import netCDF4 now fails
    with pytest.raises(DicerError, match="netCDF4"):
        export_mesh(mesh, tmp_path / "m.exo", cfg())
    assert list(tmp_path.iterdir()) == []


# --- FEBio ----------------------------------------------------------------------------------


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.replace("\n", "").split(",")]


@pytest.mark.parametrize("order", [1, 2])
def test_febio_structure(tmp_path, mesh, order):
    config = cfg(order=order, midside_nodes="midpoint")
    export_mesh(mesh, tmp_path / "m.inp", config)
    export_mesh(mesh, tmp_path / "m.feb", config)
    model = prepare_model(mesh, config)
    deck = meshio.read(tmp_path / "m.inp", file_format="abaqus")
    root = ET.parse(tmp_path / "m.feb").getroot()  # well-formed XML
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    assert [c.tag for c in root] == ["Module", "Material", "Mesh", "MeshDomains"]
    assert root.find("Module").get("type") == "solid"
    mats = root.findall("Material/material")
    assert [(m.get("id"), m.get("name"), m.get("type")) for m in mats] == [
        ("1", "soft_tissue", "isotropic elastic"), ("2", "bone", "isotropic elastic")]
    for m, want in zip(mats, config["materials"]):
        assert float(m.find("E").text) == want["youngs_modulus"]
        assert float(m.find("v").text) == want["poissons_ratio"]
        assert float(m.find("density").text) == want["density"]
    assert [(d.get("name"), d.get("mat")) for d in root.findall("MeshDomains/SolidDomain")] == [
        ("soft_tissue", "soft_tissue"), ("bone", "bone")]

    nodes = root.findall("Mesh/Nodes/node")
    assert [int(n.get("id")) for n in nodes] == list(range(1, model.n_points + 1))  # 1-based, in order
    xyz = np.array([[float(v) for v in n.text.split(",")] for n in nodes])
    assert np.allclose(xyz, model.points, rtol=1e-8, atol=0)

    etype = "hex8" if order == 1 else "hex20"
    blocks = root.findall("Mesh/Elements")
    assert [(b.get("type"), b.get("name")) for b in blocks] == [(etype, "soft_tissue"), (etype, "bone")]
    ids, conn = [], []
    for b in blocks:
        for e in b:
            assert e.tag == "elem"
            ids.append(int(e.get("id")))
            conn.append(_ints(e.text))
    ids, conn = np.array(ids), np.array(conn) - 1
    assert sorted(ids) == list(range(1, model.n_cells + 1))
    assert np.array_equal(conn, model.cells[ids - 1])  # FEBio's node order is dicer's

    # FEBio's hex8: positive volume with its corner numbering; hex20: mid-edge nodes where
    # FEBio's shape functions put them (bottom, top, then vertical edges)
    p = xyz[conn]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 3] - p[:, 0]), p[:, 4] - p[:, 0])
    assert np.all(vol > 0)
    if order == 2:
        for k, (a, b) in enumerate(FEBIO_HEX20_EDGES):
            assert np.allclose(p[:, 8 + k], 0.5 * (p[:, a - 1] + p[:, b - 1]), atol=1e-7)

    sets = {s.get("name"): _ints(s.text) for s in root.findall("Mesh/NodeSet")}
    assert list(sets) == list(deck.point_sets)
    for name, got in sets.items():
        assert np.array_equal(np.array(got) - 1, np.sort(deck.point_sets[name]))

    surfaces = {s.get("name"): s for s in root.findall("Mesh/Surface")}
    assert list(surfaces) == ["EXTERIOR", "soft_tissue_bone"]
    ftype = "quad4" if order == 1 else "quad8"
    centre = model.points[model.cells[:, :8]].mean(axis=1)
    for name, surf in surfaces.items():
        assert all(f.tag == ftype for f in surf)
        assert [int(f.get("id")) for f in surf] == list(range(1, len(surf) + 1))
        facets = np.array([_ints(f.text) for f in surf]) - 1
        assert set(facets.ravel().tolist()) == set((np.array(sets[name]) - 1).tolist())
        # counter-clockwise seen from outside: the normal points away from the element
        q = xyz[facets[:, :4]]
        normal = np.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 0])
        owner = model.exterior[:, 0] if name == "EXTERIOR" else model.interfaces[name][:, 0]
        assert np.all(np.einsum("ij,ij->i", normal, q.mean(axis=1) - centre[owner]) > 0)
        if order == 2:
            for k in range(4):
                assert np.allclose(xyz[facets[:, 4 + k]], 0.5 * (q[:, k] + q[:, (k + 1) % 4]), atol=1e-7)
    assert len(surfaces["EXTERIOR"]) == model.exterior.shape[0]


def test_febio_reader_is_strict(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.feb", cfg())
    text = (tmp_path / "m.feb").read_text()
    got = read_febio(tmp_path / "m.feb")
    assert got["points"].shape == (mesh.n_points, 3) and len(got["blocks"]) == 2
    bad = {
        "not well-formed": text.replace("</Nodes>", "</Node>"),
        "node ids": text.replace('<node id="2">', '<node id="3">', 1),
        "values": re.sub(r'(<elem id="\d+">)(\d+),', r"\1", text, count=1),
        "version": text.replace('version="4.0"', 'version="2.5"'),
        "not a number": text.replace('<NodeSet name="X0">\n1,', '<NodeSet name="X0">\nx,', 1),
        "hex8 or hex20": text.replace('type="hex8"', 'type="tet4"', 1),
    }
    for message, content in bad.items():
        (tmp_path / "bad.feb").write_text(content)
        with pytest.raises(DicerError, match=message):
            read_febio(tmp_path / "bad.feb")


def test_febio_material_choice_and_plane_meshes(tmp_path, mesh, mesh2d, capsys):
    export_mesh(mesh, tmp_path / "n.feb", cfg(febio_material="neo-Hookean"))
    root = ET.parse(tmp_path / "n.feb").getroot()
    assert {m.get("type") for m in root.iter("material")} == {"neo-Hookean"}
    with pytest.raises(DicerError, match="FEBio has no plane"):
        export_mesh(mesh2d, tmp_path / "q.feb", cfg())
    assert not (tmp_path / "q.feb").exists()

    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    write_mesh(mesh2d, tmp_path / "plane.vtu")
    assert main(["export", str(tmp_path / "plane.vtu"), "-o", str(tmp_path / "p.feb")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "FEBio has no plane" in err[0]
    assert not (tmp_path / "p.feb").exists()
    write_mesh(mesh, tmp_path / "solid.vtu")
    for name in ("m.feb", "m.exo", "m.e"):
        assert main(["export", str(tmp_path / "solid.vtu"), "-o", str(tmp_path / name)]) == 0


def test_febio_example_of_the_docs(tmp_path):
    # docs/exports.md: the sections a user adds to a block's model file refer to its sets
    doc = (Path(__file__).parents[1] / "docs" / "exports.md").read_text()
    snippet = re.search(r"<!-- febio-example -->\s*```xml\n(.*?)```", doc, re.S).group(1)
    block = voxel_mesh(np.ones((2, 2, 4), np.uint8), spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0))
    config = load_config(settings={"materials": [{"name": "block", "youngs_modulus": 100.0,
                                                  "poissons_ratio": 0.3, "density": 1e-9}]})
    export_mesh(block, tmp_path / "block.feb", config)
    text = (tmp_path / "block.feb").read_text().replace("</febio_spec>", snippet + "</febio_spec>")
    root = ET.fromstring(text)
    node_sets = {s.get("name") for s in root.iter("NodeSet")}
    surfaces = {s.get("name") for s in root.iter("Surface")}
    for bc in root.iter("bc"):
        assert bc.get("node_set") in node_sets
    for load in root.iter("surface_load"):
        assert load.get("surface") in surfaces
    assert [c.tag for c in root][:2] == ["Module", "Material"] and root.find("Control") is not None


def test_an_exodus_file_of_too_many_blocks_and_sets_is_refused_before_any_work(tmp_path, mesh, monkeypatch):
    # an atlas of thousands of labels: more variables than netCDF's default build opens, and
    # defining them takes time growing with the square of their number, so the export stops
    # at once and says what to do
    import dicer.export.exodus as exodus

    model = prepare_model(mesh, cfg())
    arrays = len(model.blocks()) + len(model.node_sets) + 2 * len(model.face_sets())
    monkeypatch.setattr(exodus, "_MAX_ARRAYS", arrays - 1)
    with pytest.raises(DicerError, match=rf"make {arrays} netCDF variables.*export.sets=\[exterior\]"):
        export_mesh(mesh, tmp_path / "m.e", cfg())
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(exodus, "_MAX_ARRAYS", arrays)
    export_mesh(mesh, tmp_path / "m.e", cfg())
    assert (tmp_path / "m.e").stat().st_size > 0


# --- FEBio reader: bulk rows against ElementTree ----------------------------------------------
#
# read_febio reads the row lines (<node>, <elem>, <quad4>, <quad8>) with numpy and the rest
# with ElementTree. The former reader, ElementTree alone with one event per row, is kept
# here as the reference it must match exactly.

def _tree_numbers(texts: list[str], per_row: int, dtype, what: str) -> np.ndarray:
    """(len(texts), per_row) array of the comma-separated numbers in each text, strictly."""
    if not texts:
        return np.zeros((0, per_row), dtype)
    counts = np.char.count(np.array(texts), ",") + 1
    if np.any(counts != per_row):
        bad = int(np.flatnonzero(counts != per_row)[0])
        raise DicerError(f"{what} {bad + 1} has {counts[bad]} values, expected {per_row}")
    flat = _tree_parse(",".join(texts), dtype, what)
    if flat.size != len(texts) * per_row:
        raise DicerError(f"{what}: not a number among the values")
    return flat.reshape(-1, per_row)


def _tree_parse(text: str, dtype, what: str) -> np.ndarray:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns, and stops, at text that is not a number
        try:
            return np.fromstring(text, dtype=dtype, sep=",")
        except (ValueError, DeprecationWarning):
            raise DicerError(f"{what}: not a number among the values") from None


def _tree_ids(values: list[str], what: str) -> np.ndarray:
    try:
        return np.array(values, dtype=np.int64) if values else np.zeros(0, np.int64)
    except ValueError:
        raise DicerError(f"{what}: an id that is not an integer") from None


def _read_febio_tree(path: str | Path) -> dict:
    """The former reader (one ElementTree event per row): the reference of ``read_febio``.

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
            _tree_end_element(path_, el, stack, parents, out, got)
    except ET.ParseError as exc:
        raise DicerError(f"not well-formed XML ({exc})") from None
    _complete(out, sections)  # the closing checks are the same function as the bulk reader's
    return out


def _tree_end_element(path_: str, el, stack: list[str], parents: list, out: dict, got: dict) -> None:
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
        ids = _tree_ids(got["node_ids"], "node")
        if not np.array_equal(ids, np.arange(1, ids.size + 1)):
            raise DicerError("node ids must run 1..N in order")
        out["points"] = _tree_numbers(got["node_text"], 3, np.float64, "node")
        got["node_ids"], got["node_text"] = [], []
        el.clear()
    elif path_ == "febio_spec/Mesh/Elements":
        etype = el.get("type")
        if etype not in FEBIO_TYPES.values():
            raise DicerError(f"element type {etype!r}, expected hex8 or hex20")
        k = 8 if etype == "hex8" else 20
        conn = _tree_numbers(got["text"], k, np.int64, f"element of {el.get('name')}")
        out["blocks"].append((etype, el.get("name"), _tree_ids(got["ids"], "element"), conn - 1))
        el.clear()
    elif path_ == "febio_spec/Mesh/NodeSet":
        name = el.get("name")
        text = (el.text or "").strip()
        ids = _tree_parse(text, np.int64, f"node set {name}") if text else np.zeros(0, np.int64)
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
        ids = _tree_ids(got["ids"], "facet")
        if not np.array_equal(ids, np.arange(1, ids.size + 1)):
            raise DicerError(f"surface {name}: facet ids must run 1..F in order")
        conn = _tree_numbers(got["text"], 4 if ftype == "quad4" else 8, np.int64, f"facet of {name}")
        out["surfaces"][name] = (ftype, conn - 1)
        el.clear()
    elif path_ == "febio_spec/MeshDomains/SolidDomain":
        out["domains"].append((el.get("name"), el.get("mat")))
    elif len(stack) == 2 and stack[1] == "Mesh" and el.tag not in ("Nodes", "Elements", "NodeSet", "Surface"):
        raise DicerError(f"unexpected <{el.tag}> in <Mesh>")




MATERIALS3 = [{"name": "fat", "youngs_modulus": 0.5, "poissons_ratio": 0.49, "density": 0.9e-9},
              {"name": "muscle", "youngs_modulus": 10.0, "poissons_ratio": 0.45, "density": 1.06e-9},
              {"name": "bone", "youngs_modulus": 15000.0, "poissons_ratio": 0.3, "density": 1.9e-9}]


@pytest.fixture
def mesh3():
    """Three materials, so three interfaces besides the exterior; coordinates of both signs."""
    lab = np.zeros((4, 5, 6), np.uint8)
    lab[:, :, :2] = 1
    lab[:, 1:4, 2:] = 2
    lab[1:3, 2:4, 3:5] = 3
    m = voxel_mesh(lab, spacing=(0.5, 0.75, 1.25), origin=(-1.0, -2.0, -0.5))
    m.points += np.random.default_rng(1).uniform(-0.05, 0.05, m.points.shape)
    return m


def _assert_same(got, want, where="read"):
    """Equal, to the dtype, shape and bit (a float -0.0 is not 0.0)."""
    if isinstance(want, np.ndarray):
        assert isinstance(got, np.ndarray) and got.dtype == want.dtype and got.shape == want.shape, where
        assert np.array_equal(got.view(np.uint8), want.view(np.uint8)), where
    elif isinstance(want, dict):
        assert list(got) == list(want), where
        for key in want:
            _assert_same(got[key], want[key], f"{where}[{key!r}]")
    elif isinstance(want, (list, tuple)):
        assert type(got) is type(want) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want)):
            _assert_same(g, w, f"{where}[{i}]")
    else:
        assert type(got) is type(want) and got == want, where


def _with_rows(text: str, tag: str, ids_values: dict) -> str:
    """``text`` with the values of the rows ``<tag id=ID>`` replaced."""
    for i, values in ids_values.items():
        text, n = re.subn(rf'(<{tag} id="{i}">)[^<]*(</{tag}>)', rf"\g<1>{values}\g<2>", text, count=1)
        assert n == 1
    return text


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("digits", [9, 13])
def test_febio_reader_equals_the_element_tree_reader(tmp_path, mesh3, order, digits):
    config = load_config(settings={"materials": MATERIALS3, "export": {"order": order, "digits": digits}})
    export_mesh(mesh3, tmp_path / "m.feb", config)
    want = _read_febio_tree(tmp_path / "m.feb")
    assert len(want["blocks"]) == 3 and len(want["surfaces"]) >= 3
    assert np.any(want["points"] < 0)
    _assert_same(read_febio(tmp_path / "m.feb"), want)

    # numbers as a hand might write them (other notations, exponents beyond 22, a
    # negative zero), a comment that splits a run in two, empty blocks: still the same
    text = (tmp_path / "m.feb").read_text()
    text = _with_rows(text, "node", {1: "1.5,-2,+3.25e-30", 2: "1.00000000e+99,-0.00000000e+00,7.5E-05",
                                     3: "-1.23456789e-23,1.23456789e+23,0.1", 4: "13,.5,5.",
                                     5: "-9.99999999e-01,1.0000000000000000001e+00,4.2e+001"})
    text = text.replace('\t\t\t<node id="7">', '\t\t\t<!-- the next rows -->\n\t\t\t<node id="7">', 1)
    # ids of 8 to 16 digits (meshes of tens of millions of nodes), leading zeros
    text = text.replace('<node id="1">', '<node id="00000001">', 1)
    text = re.sub(r'(<quad[48] id=")1(">)', r"\g<1>0001\g<2>", text, count=1)
    blocks = text.split("\t\t<Elements ")
    assert len(blocks) == 4
    for i, new_id in zip((1, 2, 3), ("1234567890123456", "123456789012", "0000000042")):
        blocks[i] = re.sub(r'<elem id="\d+"', f'<elem id="{new_id}"', blocks[i], count=1)
    text = "\t\t<Elements ".join(blocks)
    text = text.replace("\t</Mesh>", '\t\t<Surface name="EMPTY">\n\t\t</Surface>\n\t</Mesh>', 1)
    text = text.replace("\t\t<NodeSet ", '\t\t<Elements type="hex8" name="none">\n\t\t</Elements>\n\t\t<NodeSet ', 1)
    (tmp_path / "h.feb").write_text(text)
    want = _read_febio_tree(tmp_path / "h.feb")
    assert want["points"][1, 1] == 0 and np.signbit(want["points"][1, 1])
    assert want["surfaces"]["EMPTY"][1].shape == (0, 4) and want["blocks"][-1][3].shape == (0, 8)
    assert [b[2][0] for b in want["blocks"][:3]] == [1234567890123456, 123456789012, 42]
    _assert_same(read_febio(tmp_path / "h.feb"), want)


def test_febio_reader_refuses_corrupted_rows(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.feb", cfg())
    text = (tmp_path / "m.feb").read_text()
    node1 = re.search(r'\t\t\t<node id="1">[^\n]*\n', text).group()
    elem = '\t\t\t<elem id="1">'
    first = re.search(r'<elem id="1">([^<]*)<', text).group(1)
    bad = {
        "truncated": (text[: len(text) // 2], "not well-formed"),
        "truncated within a row": (text[: text.index(elem) + len(elem) + 3], "not well-formed"),
        "a value missing (element)": (text.replace(elem + first, elem + first.split(",", 1)[1], 1),
                                      r"element of soft_tissue 1 has 7 values, expected 8 \(line \d+\)"),
        "a value missing (node)": (_with_rows(text, "node", {4: "1.0,2.0"}), "node 4 has 2 values, expected 3"),
        "a letter in a number (node)": (_with_rows(text, "node", {3: "1.0,2.0x,3.0"}), r"node 3 .*not a number"),
        "a letter in a number (element)": (text.replace(elem + "1,", elem + "1a,", 1), "not a number"),
        "a blank in a number": (text.replace(elem + "1,", elem + "1 ,", 1), "not a number"),
        "an exponent cut short": (_with_rows(text, "node", {5: "1.0,2.0,3.0e"}), "not a number"),
        "an extra comma": (text.replace(elem + "1,", elem + "1,,", 1), "has 9 values, expected 8"),
        "a comma at the end": (text.replace(first + "</elem>", first + ",</elem>", 1), "has 9 values, expected 8"),
        "an id that is no integer": (text.replace(elem, '\t\t\t<elem id="1x">', 1), "integer ID"),
        "a node row copied into <Elements>": (text.replace(elem, node1 + elem, 1), "sit in <Elements>"),
        "a node row moved into <Elements>": (text.replace(node1, "", 1).replace(elem, node1 + elem, 1),
                                             "node ids must run 1..N|sit in <Elements>"),
        "a wrong closing tag": (text.replace("</elem>", "</node>", 1), "does not end with </elem>"),
        "a row in a comment": (text.replace("\t\t</Nodes>", "<!--\n" + node1 + "-->\n\t\t</Nodes>", 1),
                               "are not elements of the file"),
        "a row not indented as written": (text.replace(node1, node1[1:], 1), "not on a line of its own"),
        "two rows on a line": (text.replace(node1, node1[:-1], 1), "more than one element on the line"),
        "a number of 19 digits": (text.replace(elem + "1,", elem + "1" * 19 + ",", 1), "more than 18 digits"),
    }
    for case, (content, message) in bad.items():
        (tmp_path / "bad.feb").write_text(content)
        with pytest.raises(DicerError, match=message):
            read_febio(tmp_path / "bad.feb")
        with pytest.raises(DicerError):  # the former reader refused these too, or the corrupted XML
            if case not in ("a row not indented as written", "a row in a comment", "a blank in a number",
                            "a node row copied into <Elements>", "two rows on a line"):
                _read_febio_tree(tmp_path / "bad.feb")
            else:
                raise DicerError("accepted by ElementTree: dicer's layout is stricter")
    (tmp_path / "empty.feb").write_bytes(b"")
    with pytest.raises(DicerError, match="not well-formed"):
        read_febio(tmp_path / "empty.feb")


def test_febio_reader_names_the_file_line_of_an_xml_error(tmp_path, mesh):
    # the rows are taken out before ElementTree reads the rest; its errors still name the
    # file's line and column
    export_mesh(mesh, tmp_path / "m.feb", cfg())
    text = (tmp_path / "m.feb").read_text().replace("\t\t</NodeSet>", "\t\t</NodeSt>", 1)
    (tmp_path / "bad.feb").write_text(text)
    with pytest.raises(ET.ParseError) as want:
        ET.parse(tmp_path / "bad.feb")
    assert want.value.position[0] > text.count("<elem ")
    with pytest.raises(DicerError, match=re.escape(f"not well-formed XML ({want.value})")):
        read_febio(tmp_path / "bad.feb")


def test_febio_check_computes_the_printed_coordinates(tmp_path):
    # check_febio finds the values the written text reads back as from the numbers
    # (mantissa and exponent), not by printing and parsing them: bit for bit the same
    from dicer.export.febio import _printed_values
    from dicer.export.textfmt import Sci, sci_digits

    rng = np.random.default_rng(7)
    x = rng.normal(size=(20000, 3)) * 10.0 ** rng.integers(-40, 40, size=(20000, 3))
    x[:4] = [[0.0, -0.0, 1e-100], [-1e-100, 5e-324, 1.5], [0.1, 0.2, 0.3], [123456789.5, 1.0000000005, -2.5e-8]]
    for fmt in (Sci(9), Sci(13)):
        printed = sci_digits(x.ravel(), fmt)
        want = printed.view(f"S{printed.shape[1]}").ravel().astype(np.float64).reshape(-1, 3)
        got = _printed_values(x, fmt)
        assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("order", [1, 2])
def test_febio_reader_on_mutated_files_refuses_or_agrees(tmp_path, mesh, order):
    # bytes changed, deleted or added, mostly in rows: read_febio raises DicerError (and no
    # other error), or reads what ElementTree reads
    import random

    export_mesh(mesh, tmp_path / "m.feb", cfg(order=order))
    base = (tmp_path / "m.feb").read_bytes()
    rows = [m.start() for m in re.finditer(rb"\t\t\t<", base)]
    rng = random.Random(order)
    agreed = 0
    for _ in range(150):
        data = bytearray(base)
        for _ in range(rng.choice([1, 1, 2, 3])):
            at = min(rng.choice(rows) + rng.randrange(60) if rng.random() < 0.8 else rng.randrange(len(data)),
                     len(data) - 1)
            what = rng.random()
            if what < 0.5:
                data[at] = rng.choice(b'0123456789,<>"/ \n\te.-+Ex=a')
            elif what < 0.75:
                del data[at]
            else:
                data.insert(at, rng.choice(b'0123456789,<>"/ \n\te.-+E'))
        (tmp_path / "f.feb").write_bytes(bytes(data))
        try:
            got = read_febio(tmp_path / "f.feb")
        except DicerError:
            continue
        _assert_same(got, _read_febio_tree(tmp_path / "f.feb"))
        agreed += 1
    assert agreed > 10  # digits changed in values: still files


@pytest.mark.parametrize("seed", range(4))
def test_the_least_netcdf_variables_counted_from_the_labels_bound_the_files(seed):
    """dicer run refuses an Exodus file of too many variables after the fix, from the labels
    (least_arrays); the bound may not exceed what the export then counts, or a file the export
    would write would be refused."""
    from dicer.export.exodus import least_arrays

    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 6, (8, 7, 5)).astype(np.int32) * 7  # values 0, 7, ..., 35
    mesh = voxel_mesh((labels // 7).astype(np.uint8))
    names = [f"m{i}" for i in range(1, 6)]
    for sets in (["planes", "materials", "interfaces", "exterior"], ["exterior"], ["interfaces"], []):
        model = prepare_model(mesh, load_config(settings={"export": {"sets": sets},
                                                          "materials": [{"name": n} for n in names]}))
        counted = len(model.blocks()) + len(model.node_sets) + 2 * len(model.face_sets())
        variables, materials, pairs = least_arrays(labels, sets)
        assert materials == len(model.blocks()) and variables <= counted
        if "interfaces" in sets:
            assert pairs == len(model.interfaces)


def test_dicer_run_refuses_an_exodus_file_of_too_many_variables_before_the_meshing(tmp_path, capsys):
    """A 3,000-parcel atlas with exo among the exports ran every stage and the other exports,
    then was refused; now it is refused at the fix, from its labels."""
    from dicer.cli import main

    labels = np.arange(1, 10_001, dtype=np.int32).reshape(100, 100, 1).repeat(2, axis=2)
    np.save(tmp_path / "atlas.npy", labels)
    args = ["run", "--labels", str(tmp_path / "atlas.npy"), "-o", str(tmp_path / "out"), "-q", "--set",
            "workflow.exports=[exo]", "--set", "image.spacing=[1, 1, 1]", "--set", "fix.min_component_voxels=0",
            "--set", "smooth.surface_from_labels=false"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "atlas.npy: the Exodus file of workflow.exports would hold at least" in err
    assert "(10000 materials' blocks and boundary sets" in err and "stopped at the fix stage" in err


def test_an_exodus_file_that_cannot_be_written_whole_raises(tmp_path):
    """The file is built in netCDF's memory and written by Python: a write cut short (here a
    file-size limit of 20 kB, as a full disk cuts it) raises, where the library's own write at
    close returned without a word and left a truncated file."""
    script = f"""
import resource, signal, numpy as np
from dicer.config import load_config
from dicer.export import prepare_model
from dicer.export.exodus import write_exodus
from dicer.mesh.voxel import voxel_mesh
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
model = prepare_model(voxel_mesh(np.ones((12, 12, 12), np.uint8)), load_config())
try:
    write_exodus(model, {str(tmp_path / "m.exo")!r})
except OSError as exc:
    print("raised", exc.errno)
"""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("raised"), out.stdout + out.stderr
