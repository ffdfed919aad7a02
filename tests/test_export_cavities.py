"""The walls of enclosed voids are a surface of their own (CAVITIES), apart from EXTERIOR.

A pressure on EXTERIOR stands for what surrounds the model; a sinus or an unlabelled hole
inside it is not loaded by that. Every format with face sets holds both; the exports' own
read-back checks compare them with the model.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from dicer.config import load_config, name_clash
from dicer.connectivity import fix_connectivity
from dicer.errors import DicerError
from dicer.export import export_mesh, prepare_model
from dicer.export.abaqus import read_abaqus
from dicer.export.exodus import least_arrays
from dicer.export.lsdyna import read_lsdyna
from dicer.image import enclosed_voids
from dicer.mesh.voxel import voxel_mesh


def _free_faces(labels: np.ndarray) -> int:
    solid = np.pad(labels > 0, 1)
    return sum(np.count_nonzero(solid & ~np.roll(solid, s, axis=a)) for a in range(labels.ndim) for s in (1, -1))


def _hollow_cube(body_inside: bool) -> np.ndarray:
    lab = np.zeros((10, 10, 10), np.uint8)
    lab[1:9, 1:9, 1:9] = 1
    lab[3:7, 3:7, 3:7] = 0  # a void of 4 x 4 x 4 voxels: 96 faces of wall
    if body_inside:
        lab[4:6, 4:6, 4:6] = 2  # a core the void holds: its 24 faces face the void
    return lab


@pytest.mark.parametrize("body_inside", [False, True])
def test_cavity_walls_are_apart_from_the_exterior_in_every_format(tmp_path, body_inside):
    lab = _hollow_cube(body_inside)
    cfg = load_config(settings={"materials": [{"name": "shell"}, {"name": "core"}]})
    model = prepare_model(voxel_mesh(lab), cfg)
    # the void's 96 faces of wall and the core's 24 (it floats in the void: it faces the hole)
    walls = 96 + 24 * body_inside
    assert model.cavities.shape == (walls, 2) and walls == enclosed_voids(lab)[1]
    assert model.exterior.shape == (384, 2) and _free_faces(lab) == 384 + walls
    assert model.node_sets["CAVITIES"].size == walls + 2 * (1 + body_inside)  # closed quad surfaces: faces + 2
    assert not set(model.node_sets["CAVITIES"]) & set(model.node_sets["EXTERIOR"])
    for suffix in ("inp", "exo", "feb", "k"):  # each read back and compared by the export
        info = export_mesh(voxel_mesh(lab), tmp_path / f"m.{suffix}", cfg)
        assert (info["exterior_faces"], info["cavity_faces"]) == (384, walls)
        assert info["node_sets"]["CAVITIES"] == walls + 2 * (1 + body_inside)
    deck = read_abaqus(tmp_path / "m.inp")
    assert list(deck["surfaces"]) == ["EXTERIOR", "CAVITIES"]
    assert sum(deck["element_sets"][f"CAVITIES_S{s}"].size for s in range(1, 7)) == walls
    # the wall's faces are faces of elements around the void, none of the outer shell's
    centre = np.array([5.0, 5.0, 5.0])
    points = voxel_mesh(lab).points
    for s in range(1, 7):
        rows = deck["element_sets"][f"CAVITIES_S{s}"]
        assert np.all(np.abs(points[deck["cells"][rows]].mean(axis=1) - centre).max(axis=1) <= 2.5)


@pytest.mark.parametrize("body_inside", [False, True])
def test_lsdyna_segment_sets_are_the_faces_wound_outward(tmp_path, body_inside):
    """The keyword file's *SET_SEGMENT_TITLE sets hold each face set's faces, N1..N4 counter-clockwise
    seen from outside the element they bound: a segment's normal points out of its element (into
    the void for CAVITIES, out of the model for EXTERIOR), so a positive *LOAD_SEGMENT_SET pressure
    presses on the material."""
    lab = _hollow_cube(body_inside)
    cfg = load_config(settings={"materials": [{"name": "shell"}, {"name": "core"}],
                                "export": {"sets": ["materials", "interfaces", "exterior"]}})
    export_mesh(voxel_mesh(lab), tmp_path / "m.k", cfg)
    deck = read_lsdyna(tmp_path / "m.k")
    walls = 96 + 24 * body_inside
    sets = deck["segment_sets"]
    assert list(sets) == ["EXTERIOR", "CAVITIES"]
    assert (sets["EXTERIOR"].shape, sets["CAVITIES"].shape) == ((384, 4), (walls, 4))
    points, cells = deck["points"], deck["cells"]
    # each face's element: the one holding its four nodes
    holder = {frozenset(cells[e][list(c)]): e for e in range(cells.shape[0])
              for c in ((0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))}
    centre = np.array([5.0, 5.0, 5.0])
    for name, faces in sets.items():
        corner = points[faces]
        normal = np.cross(corner[:, 2] - corner[:, 0], corner[:, 3] - corner[:, 1])
        element = np.array([holder[frozenset(f)] for f in faces.tolist()])
        out = corner.mean(axis=1) - points[cells[element]].mean(axis=1)
        assert np.all(np.einsum("ij,ij->i", normal, out) > 0), name
        if name == "CAVITIES" and not body_inside:  # the walls' normals point into the void
            assert np.all(np.einsum("ij,ij->i", normal, centre - corner.mean(axis=1)) > 0)
    # an interface's segments: one face per pair of elements across it, wound out of its element
    solid = lab.copy()
    solid[3:7, 3:7, 3:7] = 2
    export_mesh(voxel_mesh(solid), tmp_path / "solid.k", cfg)
    both = read_lsdyna(tmp_path / "solid.k")["segment_sets"]
    assert list(both) == ["EXTERIOR", "shell_core"] and both["shell_core"].shape == (96, 4)
    # a segment card cut short is refused, naming its line
    text = (tmp_path / "m.k").read_text().splitlines()
    at = next(i for i in range(len(text)) if text[i : i + 2] == ["*SET_SEGMENT_TITLE", "CAVITIES"]) + 4
    text[at] = text[at][:35]
    (tmp_path / "bad.k").write_text("\n".join(text) + "\n")
    with pytest.raises(DicerError, match=rf"line {at + 1}: segment set CAVITIES: a segment card is four"):
        read_lsdyna(tmp_path / "bad.k")


@pytest.mark.parametrize("dim", [2, 3])
def test_bodies_nested_in_voids_face_the_voids_whatever_the_corner_order(dim):
    """Shells in shells: every surface inside the outermost wall faces an enclosed void. The
    same with every element's corners in mirrored order (the volumes change sign together)."""
    from dicer.mesh.faces import cavity_faces, neighbour_materials
    from dicer.mesh.topology import HEX_FACE_MIRROR, HEX_MIRROR, QUAD_REVERSED

    n = 30
    g = np.indices((n,) * dim) - (n - 1) / 2
    r = np.sqrt((g**2).sum(axis=0))
    lab = (((r < 14) & (r > 11)) | ((r < 9) & (r > 6)) | (r < 3)).astype(np.uint8)
    lab, _ = fix_connectivity(lab)
    voids, walls = enclosed_voids(lab)
    assert voids == 2
    mesh = voxel_mesh(lab)
    e, f = np.nonzero(neighbour_materials(mesh) == 0)
    wall = cavity_faces(mesh.points, mesh.cells, dim, e, f)
    assert wall.sum() == walls and (~wall).sum() == _free_faces(lab) - walls
    if dim == 3:
        cells, faces = mesh.cells[:, HEX_MIRROR], HEX_FACE_MIRROR[f + 1] - 1
    else:  # corners reversed: side k (corners k, k + 1) becomes side 3 - k
        cells, faces = mesh.cells[:, QUAD_REVERSED], 3 - f
    assert np.array_equal(cavity_faces(mesh.points, cells, dim, e, faces), wall)


def test_a_mirrored_scan_keeps_the_same_walls():
    lab = _hollow_cube(False)
    cfg = load_config()
    plain = prepare_model(voxel_mesh(lab), cfg)
    flipped = prepare_model(voxel_mesh(lab, direction=np.diag([1.0, 1.0, -1.0])), cfg)
    assert flipped.cavities.shape == plain.cavities.shape == (96, 2)
    assert np.array_equal(np.sort(flipped.cavities[:, 0]), np.sort(plain.cavities[:, 0]))
    assert np.array_equal(flipped.node_sets["CAVITIES"], plain.node_sets["CAVITIES"])


def test_a_hole_open_to_a_cut_plane_is_outside():
    lab = _hollow_cube(False)
    lab[3:7, 3:7, :7] = 0  # the void now runs out through the bottom plane
    model = prepare_model(voxel_mesh(lab), load_config())
    assert model.cavities.size == 0 and "CAVITIES" not in model.node_sets
    assert model.exterior.shape[0] == _free_faces(lab)


def test_two_dimensional_holes():
    lab = np.zeros((12, 9), np.uint8)
    lab[1:11, 1:8] = 1
    lab[3:5, 3:6] = 0  # a hole of 2 x 3 pixels: 10 edges of wall
    lab[7, 4] = 0  # a hole of one pixel: 4 edges
    model = prepare_model(voxel_mesh(lab, spacing=(0.5, 0.5)), load_config())
    assert model.cavities.shape == (14, 2)
    assert model.exterior.shape == (2 * (10 + 7), 2)
    assert model.node_sets["CAVITIES"].size == 14  # two closed loops: as many nodes as edges


@pytest.mark.parametrize("order", [1, 2])
def test_smoothed_walls_stay_cavities(order):
    """Smoothing moves the wall's nodes; the surfaces and their sides stay (order 2: the
    mid-edge nodes join the node set)."""
    from dicer.mesh.smooth import smooth_mesh

    g = np.indices((22, 22, 22)) - 10.5
    r = np.sqrt((g**2).sum(axis=0))
    lab = ((r < 9.5) & (r > 4.5)).astype(np.uint8)
    lab, _ = fix_connectivity(lab)
    voids, walls = enclosed_voids(lab)
    assert voids == 1
    mesh, _ = smooth_mesh(voxel_mesh(lab))
    cfg = load_config(settings={"export": {"order": order}})
    model = prepare_model(mesh, cfg)
    assert model.cavities.shape[0] == walls
    assert model.exterior.shape[0] == _free_faces(lab) - walls
    corners = set(np.unique(mesh.cells[model.cavities[:, 0]]).tolist())
    if order == 1:
        assert set(model.node_sets["CAVITIES"].tolist()) <= corners
    radius = np.linalg.norm(model.points[model.node_sets["CAVITIES"]] - 10.5 - 0.5, axis=1)
    assert radius.max() < 7.0  # all on the inner wall (radius about 5), none on the outer (about 9.5)


@pytest.mark.parametrize("dim", [2, 3])
def test_many_bodies_in_one_void_face_it(dim):
    """Cubes (squares) strewn in one large void, as bone fragments in a marrow cavity: each
    body's surface is tested along a ray against the faces it passes (a winding number over
    every face of the wall took 351 s for 6,859 bodies in a 160³ box; now 1.6 s)."""
    from dicer.mesh.faces import cavity_faces, neighbour_materials

    n = 40 if dim == 3 else 64
    a = np.zeros((n,) * dim, np.uint8)
    a[(slice(1, -1),) * dim] = 1
    a[(slice(4, -4),) * dim] = 0
    starts = range(6, n - 9, 8)
    for corner in itertools.product(starts, repeat=dim):
        a[tuple(slice(c, c + 4) for c in corner)] = 2
    voids, walls = enclosed_voids(a)
    mesh = voxel_mesh(a)
    e, f = np.nonzero(neighbour_materials(mesh) == 0)
    wall = cavity_faces(mesh.points, mesh.cells, dim, e, f)
    bodies = len(starts) ** dim
    void_wall = 4 * (n - 8) if dim == 2 else 6 * (n - 8) ** 2  # the void's own wall
    assert voids == 1 and walls == void_wall + bodies * (16 if dim == 2 else 96)
    assert int(wall.sum()) == walls and int((~wall).sum()) == _free_faces(a) - walls


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), dim=st.sampled_from([2, 3]))
def test_cavity_faces_are_the_walls_of_the_enclosed_voids(seed, dim):
    """Nested shells and cores with random pits, repaired as `dicer fix` does: the CAVITIES
    faces are exactly the voxel faces between material and enclosed background (a body
    floating in a void among them), the rest of the free faces EXTERIOR. Checked by hand on
    150 such volumes, 90 of them with voids and 21 with a body in one."""
    rng = np.random.default_rng(seed)
    n = 16
    g = np.indices((n,) * dim) - rng.uniform(6.5, 8.5, dim).reshape((dim,) + (1,) * dim)
    r = np.sqrt((g**2).sum(axis=0))
    lab = np.zeros((n,) * dim, np.uint8)
    for i, radius in enumerate(np.sort(rng.uniform(1.0, 7.5, rng.integers(2, 6)))[::-1]):
        lab[r < radius] = 0 if i % 2 else rng.integers(1, 3)
    lab[rng.random(lab.shape) < 0.03] = 0
    lab, _ = fix_connectivity(lab)
    assume(lab.any())
    _, walls = enclosed_voids(lab)
    model = prepare_model(voxel_mesh(lab), load_config(settings={"materials": [{"name": "a"}, {"name": "b"}],
                                                                 "export": {"sets": ["exterior"]}}))
    assert model.cavities.shape[0] == walls
    assert model.exterior.shape[0] + walls == _free_faces(lab)
    # the Exodus file's least count, known from the labels alone, stays below what it holds
    variables, _, _ = least_arrays(lab, ["exterior"])
    assert variables + (3 if walls else 0) == len(model.blocks()) + len(model.node_sets) + 2 * len(model.face_sets())


def test_cavities_is_a_reserved_name():
    assert "exterior face set" in name_clash(["bone", "cavities"])
    assert "exterior face set" in name_clash(["Cavities_S3"])
    assert name_clash(["cavities"], sets=("planes",)) is None


def test_vtks_exodus_reader_reads_both_surfaces(tmp_path):
    """ParaView's reader (VTK's vtkExodusIIReader) gives EXTERIOR and CAVITIES as side sets
    of the faces counted here, on the nodes of the node sets of the same names."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    lab = _hollow_cube(True)
    cfg = load_config(settings={"materials": [{"name": "shell"}, {"name": "core"}]})
    export_mesh(voxel_mesh(lab), tmp_path / "m.exo", cfg)
    reader = vtk.vtkExodusIIReader()
    reader.SetFileName(str(tmp_path / "m.exo"))
    reader.UpdateInformation()
    for kind in (vtk.vtkExodusIIReader.SIDE_SET, vtk.vtkExodusIIReader.NODE_SET):
        for i in range(reader.GetNumberOfObjects(kind)):
            reader.SetObjectStatus(kind, i, 1)
    reader.Update()
    out = reader.GetOutput()

    def named(group) -> dict:
        return {group.GetMetaData(j).Get(vtk.vtkCompositeDataSet.NAME()): group.GetBlock(j)
                for j in range(group.GetNumberOfBlocks())}

    side, node = (named(named(out)[kind]) for kind in ("Side Sets", "Node Sets"))
    assert {name: grid.GetNumberOfCells() for name, grid in side.items()} == {"EXTERIOR": 384, "CAVITIES": 120}
    for name in ("EXTERIOR", "CAVITIES"):
        faces = {tuple(p) for p in np.round(vtk_to_numpy(side[name].GetPoints().GetData()), 9)}
        nodes = {tuple(p) for p in np.round(vtk_to_numpy(node[name].GetPoints().GetData()), 9)}
        assert faces == nodes and len(nodes) == (386 if name == "EXTERIOR" else 124)


def test_fix_report_counts_the_voids_a_cohort_deck_may_load(tmp_path):
    """fix.json gives the voids and their voxel faces of wall; the deck of the same labels
    holds as many CAVITIES faces when merging leaves the walls alone."""
    import json

    from dicer.cli import main

    lab = _hollow_cube(True)
    np.save(tmp_path / "hollow.npy", lab)
    spacing = "image.spacing=[1, 1, 1]"
    assert main(["fix", str(tmp_path / "hollow.npy"), "-o", str(tmp_path / "f.nii.gz"), "--set", spacing,
                 "--set", "materials=[{name: shell}, {name: core}]", "--set", "fix.min_component_voxels=0",
                 "--report", str(tmp_path / "fix.json")]) == 0  # the core kept: 8 voxels
    report = json.loads((tmp_path / "fix.json").read_text())
    assert (report["enclosed_voids"], report["void_wall_faces"]) == (1, 120)
    assert main(["mesh", str(tmp_path / "f.nii.gz"), "-o", str(tmp_path / "m.vtu"), "--set", spacing,
                 "--set", "materials=[{name: shell}, {name: core}]"]) == 0
    assert main(["export", str(tmp_path / "m.vtu"), "-o", str(tmp_path / "m.inp"),
                 "--set", "materials=[{name: shell}, {name: core}]"]) == 0
    deck = read_abaqus(tmp_path / "m.inp")
    assert sum(deck["element_sets"][f"CAVITIES_S{s}"].size for s in range(1, 7)) == 120
