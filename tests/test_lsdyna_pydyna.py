"""Ansys's own reader of LS-DYNA keyword files reads dicer's decks as dicer means them.

PyDyna (``ansys-dyna-core``) parses each keyword by the card layouts of the LS-DYNA manual:
a field in the wrong columns reads as another number there, a card too many or too few as
another set. The export's read-back uses dicer's reader (``dicer.export.lsdyna``); this one
is independent of it: nodes, solids, parts, sections, materials, node sets and segment sets
are compared with the model, and every segment is wound out of its element.
"""

from __future__ import annotations

import numpy as np
import pytest

from dicer.config import load_config
from dicer.export import export_mesh, prepare_model
from dicer.mesh.voxel import voxel_mesh

Deck = pytest.importorskip("ansys.dyna.core").Deck

MATERIALS = [{"name": "shell", "youngs_modulus": 17654.321987, "poissons_ratio": 0.45, "density": 1.987654321e-9},
             {"name": "core", "youngs_modulus": 15000.0, "poissons_ratio": 0.3, "density": 1.9e-9}]
ELFORM = {"C3D8": 2, "C3D8R": 1, "C3D8I": -2}


def _labels() -> np.ndarray:
    """A shell around a void holding a core, and a second core against the shell: an exterior,
    a cavity's walls and an interface; cut by the image's face x = 0 (a plane set)."""
    lab = np.zeros((10, 12, 9), np.uint8)
    lab[0:9, 1:11, 1:8] = 1
    lab[3:7, 3:7, 3:6] = 0
    lab[4:6, 4:6, 4:5] = 2  # floats in the void
    lab[3:6, 8:10, 2:5] = 2  # held by the shell: an interface
    return lab


def _read(path) -> dict:
    deck = Deck()
    deck.loads(path.read_text())
    found: dict = {}
    for keyword in deck.all_keywords:
        found.setdefault(type(keyword).__name__, []).append(keyword)
    return found


def _wound_out(points: np.ndarray, quads: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(F,) bool: each quad's normal (by its N1..N4 order) points out of the element holding it."""
    holder = {}
    for e, cell in enumerate(cells.tolist()):
        for face in ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)):
            holder.setdefault(frozenset(cell[c] for c in face), []).append(e)
    corner = points[quads]
    normal = np.cross(corner[:, 2] - corner[:, 0], corner[:, 3] - corner[:, 1])
    out = np.ones(len(quads), bool)
    for i, quad in enumerate(quads.tolist()):
        owners = holder[frozenset(quad)]
        # an interface face has two elements: wound out of one of them (the first material's)
        out[i] = any(float(normal[i] @ (corner[i].mean(axis=0) - points[cells[e]].mean(axis=0))) > 0 for e in owners)
        if len(owners) == 2:
            out[i] &= sum(float(normal[i] @ (corner[i].mean(axis=0) - points[cells[e]].mean(axis=0))) > 0
                          for e in owners) == 1
    return out


@pytest.mark.parametrize("element_type", sorted(ELFORM))
def test_pydyna_reads_the_deck_as_the_model(tmp_path, element_type):
    mesh = voxel_mesh(_labels(), spacing=(0.8, 0.9, 1.25), origin=(-10.0, 3.5, 100.0))
    rng = np.random.default_rng(7)
    # smoothed-like coordinates, the nodes on a bounding plane kept in it (as smoothing keeps them)
    on_plane = (mesh.lattice == 0) | (mesh.lattice == np.asarray(mesh.grid_shape))
    mesh.points += np.where(on_plane, 0.0, rng.uniform(-0.12, 0.12, mesh.points.shape))
    config = load_config(settings={"materials": MATERIALS, "export": {
        "element_type": element_type, "sets": ["materials", "interfaces", "exterior", "planes"]}})
    export_mesh(mesh, tmp_path / "m.k", config)
    model = prepare_model(mesh, config)
    got = _read(tmp_path / "m.k")

    nodes = got["Node"][0].nodes
    assert np.array_equal(nodes["nid"].to_numpy(), np.arange(1, mesh.n_points + 1))
    xyz = nodes[["x", "y", "z"]].to_numpy(float)
    digits = config["export"]["digits"]  # significant digits of the coordinates
    assert np.allclose(xyz, mesh.points, rtol=0.5 * 10.0 ** (1 - digits), atol=0)
    assert not np.allclose(xyz, mesh.points, rtol=0.5 * 10.0 ** (-1 - digits), atol=0)  # rounded: read as written

    solids = got["ElementSolid"][0].elements
    assert np.array_equal(solids["eid"].to_numpy(), np.arange(1, mesh.n_cells + 1))
    assert np.array_equal(solids["pid"].to_numpy(), mesh.material)
    assert np.array_equal(solids[[f"n{i}" for i in range(1, 9)]].to_numpy(np.int64), mesh.cells + 1)

    parts = [p.parts.iloc[0] for p in got["Part"]]
    assert [(p["heading"], int(p["pid"]), int(p["secid"]), int(p["mid"])) for p in parts] == [
        ("shell", 1, 1, 1), ("core", 2, 2, 2)]
    assert [(int(s.secid), int(s.elform)) for s in got["SectionSolid"]] == [(1, ELFORM[element_type]),
                                                                            (2, ELFORM[element_type])]
    for m, want in zip(got["MatElastic"], MATERIALS):  # 10-column fields: 6 significant digits at least
        assert np.allclose([m.ro, m.e, m.pr], [want["density"], want["youngs_modulus"], want["poissons_ratio"]],
                           rtol=5e-6, atol=0)

    node_sets = {s.title: np.asarray(s.nodes.data, np.int64) - 1 for s in got["SetNodeList"]}
    assert list(node_sets) == list(model.node_sets)
    assert {"EXTERIOR", "CAVITIES", "X0", "shell_core"} <= set(node_sets)
    for name, ids in model.node_sets.items():
        assert np.array_equal(node_sets[name], ids), name
    assert [int(s.sid) for s in got["SetNodeList"]] == list(range(1, len(node_sets) + 1))

    face_sets = model.face_sets()
    segments = {s.title: s.segments[["n1", "n2", "n3", "n4"]].to_numpy(np.int64) - 1 for s in got["SetSegment"]}
    assert list(segments) == list(face_sets) == ["EXTERIOR", "CAVITIES", "shell_core"]
    assert [int(s.sid) for s in got["SetSegment"]] == [1, 2, 3]
    for name, faces in face_sets.items():
        quads = segments[name]
        assert quads.shape == (faces.shape[0], 4), name
        want = {frozenset(q) for q in mesh.cells[faces[:, 0][:, None], _HEX_FACE_NODES[faces[:, 1] - 1]].tolist()}
        assert {frozenset(q) for q in quads.tolist()} == want, name
        assert np.all(_wound_out(xyz, quads, mesh.cells)), name
    # the cavity's walls: the void's 3 x 4 x 4 box (80 faces) and the floating core's 2 x 2 x 1 (16)
    assert segments["CAVITIES"].shape[0] == 80 + 16


# Abaqus face numbers 1..6 of a C3D8 as its corner nodes (any order: compared as sets)
_HEX_FACE_NODES = np.array([[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])
