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
from dicer.export.febio import read_febio
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
    config = cfg(order=order)
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
    # an atlas of thousands of labels: netCDF's time to define the variables grows faster
    # than their count (hours), so the export stops at once and says what to do
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
