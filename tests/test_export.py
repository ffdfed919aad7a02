"""Exports: the fixed-width formatter, the Abaqus deck, VTU, read-back and bad input."""

from __future__ import annotations

import hashlib
import itertools
import re

import meshio
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dicer.config import load_config, preset_settings
from dicer.errors import DicerError
from dicer.export import (
    EXPORT_SUFFIXES,
    _neighbours_by_sort,
    export_mesh,
    neighbour_materials,
    prepare_model,
    settings_hash,
)
from dicer.export.textfmt import Sci, aligned_width, int_digits, int_line_blocks, int_lines, sci_digits
from dicer.io.meshes import read_mesh
from dicer.mesh.topology import HEX_FACES
from dicer.mesh.voxel import voxel_mesh


WITHOUT_THE_LAYER = preset_settings("explicit-dynamics")["smooth"]  # smoothing with no pillow layer


@pytest.fixture
def labels():
    lab = np.zeros((4, 5, 6), np.uint8)
    lab[:, :, :3] = 1
    lab[1:3, 1:4, 3:] = 2
    lab[0, 0, 5] = 1  # a lone voxel touching the rest along an edge only
    return lab


@pytest.fixture
def mesh(labels):
    return voxel_mesh(labels, spacing=(0.5, 0.75, 1.25), origin=(-3.0, 10.0, 0.125))


@pytest.fixture
def config():
    return load_config()


# --- formatter ----------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(sizes=st.lists(st.integers(0, 40), max_size=6), per_line=st.integers(1, 16), width=st.integers(7, 11),
       sep=st.sampled_from([b",", b"", b", "]), seed=st.integers(0, 2**16))
def test_many_blocks_at_once_are_the_blocks_one_by_one(sizes, per_line, width, sep, seed):
    rng = np.random.default_rng(seed)
    blocks = [rng.integers(0, 10 ** 6, size) for size in sizes]
    headers = [f"*NSET, NSET=set_{i}\n".encode() for i in range(len(sizes))]
    expected = b"".join(h + int_lines(v, per_line, width, sep) for h, v in zip(headers, blocks))
    assert int_line_blocks(headers, blocks, per_line, width, sep) == expected


def test_integers_match_python_formatting():
    rng = np.random.default_rng(1)
    v = np.concatenate([[0, 1, 9, 10, 9999, 10000, 99999999, 100000000, 9999999999],
                        rng.integers(0, 10**10, 5000)])
    for width in (10, 11, 12):
        for lead in (b"", b",", b"\n", b",\n"):
            got = [bytes(r) for r in int_digits(v, width, lead=lead)]
            assert got == [lead + f"{x:{width}d}".encode() for x in v]
    small = v[v < 10**7]
    for width in (7, 8):
        got = [bytes(r) for r in int_digits(small, width, lead=b",")]
        assert got == [b"," + f"{x:{width}d}".encode() for x in small]
    assert [bytes(r) for r in int_digits(v, 10, zero_pad=True)] == [f"{x:010d}".encode() for x in v]
    with pytest.raises(ValueError):
        int_digits(np.array([10**7]), 7)


def test_floats_match_python_formatting_to_the_last_digit():
    rng = np.random.default_rng(2)
    x = np.concatenate([[0.0, 1.0, -1.0, 0.1, 123.456, -2.5e-7, 1 / 3, 99999.99999, 1e-99, 9.99e98],
                        rng.normal(size=20000) * 10.0 ** rng.integers(-40, 40, 20000)])
    for digits in (9, 13, 6):
        for lead in (b"", b","):
            got = [bytes(r) for r in sci_digits(x, Sci(digits), lead)]
            want = [lead + f"{v: .{digits - 1}e}".encode() for v in x]
            mismatch = [i for i, (g, w) in enumerate(zip(got, want)) if g != w]
            # a different last digit only where the decimal value sits on a rounding tie
            assert len(mismatch) <= 5e-4 * x.size
            back = np.array([float(g[len(lead):]) for g in got])
            assert np.allclose(back, x, rtol=10.0 ** (1 - digits), atol=0)
    fortran = [bytes(r) for r in sci_digits(np.array([0.0, 1.5, -0.00123]), Sci(9, b"E", fortran=True, width=16))]
    assert fortran == [b" 0.000000000E+00", b" 0.150000000E+01", b"-0.123000000E-02"]
    with pytest.raises(ValueError):
        sci_digits(np.array([np.nan]), Sci(9))
    with pytest.raises(ValueError):
        sci_digits(np.array([1e100]), Sci(9))


def test_set_lines_and_alignment():
    text = int_lines(np.arange(1, 36), 16, 3)
    lines = text.decode().splitlines()
    assert [len(line.split(",")) for line in lines] == [16, 16, 3]
    assert [int(v) for line in lines for v in line.split(",")] == list(range(1, 36))
    assert aligned_width(7, b",") == 7 and aligned_width(8, b",") == 11 and aligned_width(7, b",\n") == 10


# --- Abaqus deck --------------------------------------------------------------------------


def _blocks(text: str) -> dict[str, list[str]]:
    """Keyword line -> its data lines."""
    out: dict[str, list[str]] = {}
    key = None
    for line in text.splitlines():
        if line.startswith("*") and not line.startswith("**"):
            key = line
            out[key] = []
        elif key and not line.startswith("**"):
            out[key].append(line)
    return out


def test_abaqus_deck_content(tmp_path, mesh, labels, config):
    src = tmp_path / "scan.nii.gz"
    src.write_bytes(b"not really an image")
    info = export_mesh(mesh, tmp_path / "model.inp", config, source=src)
    text = (tmp_path / "model.inp").read_text()
    assert info["nodes"] == mesh.n_points and info["elements"] == mesh.n_cells and info["verified"]
    # provenance: version, the input's checksum, config hash; no name (a DICOM folder's name
    # can be a patient's), folder or date
    head = text.split("*NODE")[0]
    assert head.startswith("*HEADING\ndicer ")
    assert hashlib.sha256(b"not really an image").hexdigest() in head
    assert settings_hash(config) in head and "scan" not in head and str(tmp_path) not in head
    assert not re.search(r"20\d\d-\d\d-\d\d", text)
    blocks = _blocks(text)
    # nodes numbered 1..N in mesh order, coordinates to 9 significant digits
    nodes = np.array([[float(v) for v in line.split(",")] for line in blocks["*NODE"]])
    assert nodes[:, 0].tolist() == list(range(1, mesh.n_points + 1))
    assert np.allclose(nodes[:, 1:], mesh.points, rtol=1e-8, atol=1e-12)
    # one element block per material, named after it, element number = mesh order + 1
    soft = blocks["*ELEMENT, TYPE=C3D8, ELSET=soft_tissue"]
    bone = blocks["*ELEMENT, TYPE=C3D8, ELSET=bone"]
    ids = {}
    for name, rows in (("soft_tissue", soft), ("bone", bone)):
        arr = np.array([[int(v) for v in r.split(",")] for r in rows])
        ids[name] = arr[:, 0]
        assert np.array_equal(arr[:, 1:] - 1, mesh.cells[arr[:, 0] - 1])
    assert sorted(np.concatenate(list(ids.values())).tolist()) == list(range(1, mesh.n_cells + 1))
    assert np.all(mesh.material[ids["bone"] - 1] == 2) and ids["bone"].size == np.count_nonzero(labels == 2)
    # materials and sections from the config
    assert blocks["*ELASTIC"] == ["15000, 0.3"] or "15000, 0.3" in text
    assert "*SOLID SECTION, ELSET=bone, MATERIAL=bone" in blocks
    assert "*STEP" not in text
    # bounding-plane node sets from the lattice
    for axis, name in enumerate("XYZ"):
        for side, value in (("0", 0), ("1", labels.shape[axis])):
            got = [int(v) for line in blocks[f"*NSET, NSET={name}{side}"] for v in line.split(",")]
            assert got == (np.flatnonzero(mesh.lattice[:, axis] == value) + 1).tolist()
    # CalculiX limits: 16 entries a line, integers <= 10 and floats <= 20 characters
    for line in (line for key, rows in blocks.items() if key != "*HEADING" for line in rows):
        entries = [e.strip() for e in line.split(",") if e.strip()]
        assert len(entries) <= 16 and len(line) <= 132
        assert all(len(e) <= 20 for e in entries)


def test_surface_and_interface_sets(tmp_path, mesh, labels, config):
    model = prepare_model(mesh, config)
    sets = model.node_sets
    # the exterior: faces with no element behind them; the bone block sits on soft tissue
    padded = np.pad(labels > 0, 1)
    n_faces = sum(np.count_nonzero(padded & ~np.roll(padded, s, axis=a)) for a in range(3) for s in (1, -1))
    assert model.exterior.shape == (n_faces, 2)
    # interface nodes: the bone's bottom face (2 x 3 voxels -> 3 x 4 nodes at z = 3)
    inter = sets["soft_tissue_bone"]
    assert inter.size == 12 and np.all(mesh.lattice[inter, 2] == 3)
    assert set(inter) <= set(sets["bone_BOUNDARY"]) and set(inter) <= set(sets["soft_tissue_BOUNDARY"])
    assert set(sets["bone_BOUNDARY"]) - set(inter) <= set(sets["EXTERIOR"])
    # faces of the exterior surface point outward: their nodes lie on the element's outer side
    for e, s in model.exterior[:50]:
        assert 1 <= s <= 6
    text_path = tmp_path / "m.inp"
    export_mesh(mesh, text_path, config)
    text = text_path.read_text()
    assert "*SURFACE, NAME=EXTERIOR, TYPE=ELEMENT\nEXTERIOR_S1, S1\n" in text


def test_neighbours_by_lattice_equal_those_by_sort():
    rng = np.random.default_rng(3)
    lab = rng.integers(0, 3, (7, 6, 5)).astype(np.uint8)
    mesh = voxel_mesh(lab)
    nb = neighbour_materials(mesh)
    idx = _neighbours_by_sort(mesh.cells, 3, mesh.n_points)
    assert np.array_equal(nb, np.where(idx >= 0, mesh.material[np.maximum(idx, 0)], 0))
    mesh2 = voxel_mesh(lab[:, :, 0])
    idx2 = _neighbours_by_sort(mesh2.cells, 2, mesh2.n_points)
    assert np.array_equal(neighbour_materials(mesh2), np.where(idx2 >= 0, mesh2.material[np.maximum(idx2, 0)], 0))
    # a mesh whose lattice is not boxes (shuffled corners) falls back to the sort
    mesh.lattice = mesh.lattice[::-1].copy()
    assert np.array_equal(neighbour_materials(mesh), np.where(idx >= 0, mesh.material[np.maximum(idx, 0)], 0))


def test_reruns_are_byte_identical_and_meshio_reads_the_deck(tmp_path, mesh, config):
    export_mesh(mesh, tmp_path / "a.inp", config, source="scan.nii")
    export_mesh(mesh, tmp_path / "b.inp", config, source="scan.nii")
    assert (tmp_path / "a.inp").read_bytes() == (tmp_path / "b.inp").read_bytes()
    m = meshio.read(tmp_path / "a.inp")
    assert len(m.points) == mesh.n_points and sum(len(b.data) for b in m.cells) == mesh.n_cells
    assert sorted(m.cell_sets) == sorted(["soft_tissue", "bone", *[f"EXTERIOR_S{s}" for s in range(1, 7)]])


def test_two_dimensional_deck(tmp_path, config):
    lab = np.ones((4, 3), np.uint8)
    lab[2:, :] = 2
    mesh = voxel_mesh(lab, spacing=(0.5, 0.25))
    cfg = load_config(settings={"export": {"thickness": 2.5, "element_type": "CPE4"}})
    info = export_mesh(mesh, tmp_path / "plate.inp", cfg)
    text = (tmp_path / "plate.inp").read_text()
    assert info["element_type"] == "CPE4" and "*ELEMENT, TYPE=CPE4, ELSET=bone" in text
    assert "*SOLID SECTION, ELSET=bone, MATERIAL=bone\n2.5\n" in text
    assert "*NSET, NSET=Z0" not in text and "*NSET, NSET=Y1" in text
    assert "EXTERIOR_S4, S4" in text


@pytest.mark.parametrize("order", [1, 2])
def test_plane_sets_hold_only_nodes_on_their_plane(tmp_path, caplog, mesh, order):
    """A tube cut by the z planes, smoothed with bounding_planes free and
    keep_bounding_planes false: its cut faces leave z = 0 and z = 4, so Z0 and Z1 would
    hold nodes off the plane (a symmetry condition on them pulls them back)."""
    from dicer.mesh.quadratic import quadratic_mesh
    from dicer.mesh.smooth import smooth_mesh

    g = np.indices((12, 12, 4)).astype(float) - 5.5
    r = np.hypot(g[0], g[1])
    tube = voxel_mesh(((r < 5) & (r > 2)).astype(np.uint8))
    cfg = {"export": {"order": order, "sets": ["planes"]}}
    mirrored, _ = smooth_mesh(tube, WITHOUT_THE_LAYER)
    loose, _ = smooth_mesh(tube, {**WITHOUT_THE_LAYER, "bounding_planes": "free", "keep_bounding_planes": False})
    # mirror planes keep every plane node on its plane: the sets are those of the lattice
    model = prepare_model(mirrored, cfg, path=tmp_path / "m.inp")
    assert sorted(model.node_sets) == ["Z0", "Z1"] and "moved nodes" not in caplog.text
    z0 = np.flatnonzero(mirrored.lattice[:, 2] == 0)
    n = z0.size if order == 1 else np.count_nonzero(quadratic_mesh(tube)[2][:, 2] == 0)  # + mid-edge nodes
    assert n == (96 if order == 1 else 96 + 164) and model.node_sets["Z0"].size == n
    assert np.abs(loose.points[z0, 2]).min() > 1e-4  # every cut-face node of the loose model left the plane
    model = prepare_model(loose, cfg, path=tmp_path / "m.inp")
    assert model.node_sets == {}
    assert (f"m.inp: smoothing moved nodes of the image's bounding planes off them (Z0: {n} of {n} nodes, "
            f"Z1: {n} of {n} nodes), which smooth.keep_bounding_planes: false allows") in caplog.text
    # a plane left in part keeps the nodes still on it, within 1e-6 voxel
    x0 = np.flatnonzero(mesh.lattice[:, 0] == 0)
    mesh.points = mesh.points.copy()
    mesh.points[x0[:3], 0] += 2e-6 * mesh.spacing[0]
    mesh.points[x0[3], 0] += 5e-7 * mesh.spacing[0]
    caplog.clear()
    model = prepare_model(mesh, {"export": {"sets": ["planes"]}}, path=tmp_path / "m.inp")
    assert np.array_equal(model.node_sets["X0"], x0[3:]) and f"(X0: 3 of {x0.size} nodes)" in caplog.text
    assert sorted(model.node_sets) == ["X0", "X1", "Y0", "Y1", "Z0", "Z1"]


def test_heading_is_the_same_for_a_config_its_sections_and_the_keywords(tmp_path, mesh, config):
    # one settings path: the whole config, the export sections alone (as the workflow passes
    # them), the keywords of stage_kwargs and a partial config that leaves defaults out give
    # one heading; export.verify (how the file is checked) does not change it
    from dicer.config import stage_kwargs, stage_settings

    partial = {"materials": config["materials"]}
    calls = {
        "config": lambda p: export_mesh(mesh, p, config, source=None),
        "sections": lambda p: export_mesh(mesh, p, stage_settings(config, "export")),
        "keywords": lambda p: export_mesh(mesh, p, **stage_kwargs(config, "export")),
        "partial": lambda p: export_mesh(mesh, p, partial),
        "meshio": lambda p: export_mesh(mesh, p, **{**stage_kwargs(config, "export"), "verify": "meshio"}),
    }
    heads = set()
    for name, call in calls.items():
        call(tmp_path / f"{name}.inp")
        heads.add((tmp_path / f"{name}.inp").read_text().split("*NODE")[0])
    assert len(heads) == 1
    assert settings_hash(config) == settings_hash(partial) == settings_hash(stage_settings(config, "export"))
    assert settings_hash(config) != settings_hash({**partial, "export": {"digits": 13}})


def test_heading_can_be_left_to_the_including_deck(tmp_path, mesh):
    cfg = load_config(settings={"export": {"heading": False, "sets": ["planes"]}})
    export_mesh(mesh, tmp_path / "m.inp", cfg, source="scan.nii")
    text = (tmp_path / "m.inp").read_text()
    assert "*HEADING" not in text and text.startswith("** dicer ")
    assert "EXTERIOR" not in text and "_BOUNDARY" not in text and "*NSET, NSET=X0" in text


# --- VTU ----------------------------------------------------------------------------------


def test_vtu_export_has_material_and_quality(tmp_path, mesh, config):
    info = export_mesh(mesh, tmp_path / "model.vtu", config)
    assert info["format"] == "vtu"
    m = meshio.read(tmp_path / "model.vtu")
    assert np.array_equal(np.concatenate(m.cell_data["material"]), mesh.material)
    assert np.allclose(np.concatenate(m.cell_data["scaled_jacobian"]), 1.0)
    back = read_mesh(tmp_path / "model.vtu")  # still a dicer mesh for the quality stage
    assert np.array_equal(back.cells, mesh.cells) and np.array_equal(back.lattice, mesh.lattice)


# --- bad input ----------------------------------------------------------------------------


def _no_files(folder, keep=()):
    return sorted(p.name for p in folder.iterdir() if p.name not in keep) == []


@pytest.mark.parametrize("settings,message", [
    ({"element_type": "C3D27"}, "export.element_type': \"C3D27\" is not allowed"),
    ({"element_type": "CPS4"}, "for 2D meshes"),
    ({"element_type": "C3D20"}, "has order 2"),
    ({"element_type": "C3D8", "order": 2}, "has order 1"),
])
def test_bad_element_type_writes_nothing(tmp_path, mesh, config, settings, message):
    config["export"].update(settings)
    with pytest.raises(DicerError, match=message):
        export_mesh(mesh, tmp_path / "m.inp", config)
    assert _no_files(tmp_path)


def test_bad_format_labels_and_folder(tmp_path, mesh, config):
    with pytest.raises(DicerError, match="unknown export format"):
        export_mesh(mesh, tmp_path / "m.stl", config)
    mesh.material[0] = 3
    with pytest.raises(DicerError, match="names 2 material"):
        export_mesh(mesh, tmp_path / "m.inp", config)
    mesh.material[0] = 1
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(DicerError, match="cannot write"):
        export_mesh(mesh, blocker / "m.inp", config)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    assert ".inp" in EXPORT_SUFFIXES and ".vtu" in EXPORT_SUFFIXES


def test_failed_read_back_leaves_no_file(tmp_path, mesh, config, monkeypatch):
    from dicer.export import abaqus

    def broken(path, model):
        raise DicerError("node count changed")

    monkeypatch.setattr(abaqus, "check_abaqus", broken)
    with pytest.raises(DicerError, match="read-back check failed"):
        export_mesh(mesh, tmp_path / "m.inp", config)
    assert _no_files(tmp_path)


def test_neighbours_of_merged_elements():
    # two 2 x 1 x 1 lattice boxes side by side (as plane merging leaves them), and a unit voxel on top
    from dicer.mesh.model import HEX_CORNERS, Mesh

    lattice = np.array([[i, j, k] for i in (0, 1, 2) for j in (0, 1, 2) for k in (0, 1, 2)])
    index = {tuple(v): n for n, v in enumerate(lattice.tolist())}

    def box(lo, ext):
        return [index[tuple(np.array(lo) + c * np.array(ext))] for c in HEX_CORNERS]

    cells = np.array([box((0, 0, 0), (2, 1, 1)), box((0, 1, 0), (2, 1, 1)), box((0, 0, 1), (1, 1, 1))])
    used = np.unique(cells)
    remap = np.full(len(lattice), -1)
    remap[used] = np.arange(used.size)
    mesh = Mesh(lattice[used].astype(float), remap[cells], np.array([1, 2, 1], np.int32), lattice[used],
                np.ones(3), np.zeros(3), np.array([2, 2, 2]))
    nb = neighbour_materials(mesh)
    # S1 z-, S2 z+, S3 y-, S4 x+, S5 y+, S6 x-
    assert nb[1].tolist() == [0, 0, 1, 0, 0, 0]
    assert nb[2].tolist() == [1, 0, 0, 0, 0, 0]
    assert nb[0, 2] == 0 and nb[0, 4] == 2


def test_faces_that_share_only_a_diagonal_are_no_neighbours():
    # two chamfers of a merged mesh (lattice corners, VTK order) beside a notch: the y = 1
    # side of the first and the y = 0 side of the second share three nodes, and the
    # diagonal (4, 2, 0)-(6, 2, 1) by which faces are keyed; they are different faces.
    # A unit box under the second's top face is its true neighbour.
    from dicer.mesh.faces import face_neighbours

    corners = [[[4, 0, 0], [5, 0, 0], [5, 1, 0], [4, 2, 0], [4, 0, 1], [6, 0, 1], [6, 2, 1], [4, 2, 1]],
               [[4, 2, 0], [5, 3, 0], [5, 4, 0], [4, 4, 0], [4, 2, 1], [6, 2, 1], [6, 4, 1], [4, 4, 1]],
               [[4, 2, 1], [6, 2, 1], [6, 4, 1], [4, 4, 1], [4, 2, 2], [6, 2, 2], [6, 4, 2], [4, 4, 2]]]
    points, cells = np.unique(np.array(corners).reshape(-1, 3), axis=0, return_inverse=True)
    cells = cells.reshape(3, 8)
    for order in (cells, cells[::-1]):
        nb = face_neighbours(order, 3, len(points))
        # by the faces' full node sets
        keys = [[frozenset(c[f]) for f in HEX_FACES] for c in order]
        expected = [[next((j for j in range(3) if j != i and k in keys[j]), -1) for k in keys[i]] for i in range(3)]
        assert nb.tolist() == expected
        assert int(np.count_nonzero(nb >= 0)) == 2


def _voronoi_labels(n: int, kinds: int, seed: int) -> np.ndarray:
    """(n, n, n) uint16 Voronoi cells labelled 1..kinds, background on one face; connectivity fixed."""
    from dicer.connectivity import fix_connectivity

    rng = np.random.default_rng(seed)
    seeds = rng.uniform(0, n, (kinds, 3))
    centres = np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    lab = (1 + ((centres - seeds) ** 2).sum(axis=2).argmin(axis=1)).astype(np.uint16).reshape(n, n, n)
    lab[0] = 0
    return fix_connectivity(lab)[0]


def _faces_between(lab: np.ndarray) -> dict[tuple[int, int], set]:
    """{(a, b), a < b: lattice points of the voxel faces between labels a and b (b 0: outside)},
    straight from the label volume."""
    padded = np.pad(lab, 1).astype(np.int64)
    out: dict[tuple[int, int], set] = {}
    for axis in range(3):
        lo = padded.take(range(padded.shape[axis] - 1), axis)
        hi = padded.take(range(1, padded.shape[axis]), axis)
        for v in np.argwhere((lo != hi) & ((lo > 0) | (hi > 0))):
            a, b = sorted((int(lo[tuple(v)]), int(hi[tuple(v)])))
            pair = (b, 0) if a == 0 else (a, b)
            face = v - 1  # the face's lowest corner, in lattice (unpadded) terms
            face[axis] += 1
            others = [d for d in range(3) if d != axis]
            for i, j in itertools.product((0, 1), repeat=2):
                corner = face.copy()
                corner[others[0]] += i
                corner[others[1]] += j
                out.setdefault(pair, set()).add(tuple(corner.tolist()))
    return out


def test_sets_of_hundreds_of_materials_follow_the_faces(tmp_path):
    # 300 materials (labels above 255): one boundary set per material and one interface set
    # per pair that touches, each holding exactly the nodes of the faces concerned
    lab = _voronoi_labels(16, 300, 1)
    mesh = voxel_mesh(lab)
    names = [f"Region_{i}" for i in range(1, 301)]
    config = load_config(settings={"materials": [{"name": n} for n in names]})
    model = prepare_model(mesh, config)
    faces = _faces_between(lab)
    present = np.unique(mesh.material)
    assert present.size > 280 and int(lab.max()) > 255
    lattice = [tuple(p) for p in mesh.lattice.tolist()]

    def nodes(name):
        return {lattice[i] for i in model.node_sets[name]}

    pairs = sorted(p for p in faces if p[1] != 0)
    expected = ["X1", "Y0", "Y1", "Z0", "Z1", "EXTERIOR"]  # (no node on x = 0: background there)
    expected += [f"{names[k - 1]}_BOUNDARY" for k in present]
    expected += [f"{names[a - 1]}_{names[b - 1]}" for a, b in pairs]
    assert list(model.node_sets) == expected
    assert len(pairs) > 1000
    for a, b in pairs:
        assert nodes(f"{names[a - 1]}_{names[b - 1]}") == faces[(a, b)]
    for k in present:
        around = set().union(*(pts for pair, pts in faces.items() if k in pair))
        assert nodes(f"{names[k - 1]}_BOUNDARY") == around
    assert nodes("EXTERIOR") == set().union(*(pts for (a, b), pts in faces.items() if b == 0))
    # the voxel -> material grid (uint16 here) finds the neighbours the face sort finds
    idx = _neighbours_by_sort(mesh.cells, 3, mesh.n_points)
    assert np.array_equal(neighbour_materials(mesh), np.where(idx >= 0, mesh.material[np.maximum(idx, 0)], 0))
    # the deck holds one element set and one material per material, and reads back
    info = export_mesh(mesh, tmp_path / "m.inp", config)
    text = (tmp_path / "m.inp").read_text()
    assert len(info["materials"]) == present.size and len(info["node_sets"]) == len(expected)
    assert len(re.findall(r"^\*ELEMENT, TYPE=C3D8, ELSET=Region_\d+$", text, re.M)) == present.size
    assert len(re.findall(r"^\*SOLID SECTION, ELSET=Region_\d+, MATERIAL=Region_\d+$", text, re.M)) == present.size


def test_set_names_that_clash_are_refused(mesh, config):
    config["materials"] = [{"name": "a"}, {"name": "a_b"}, {"name": "b_c"}, {"name": "c"}]
    mesh.material = np.where(mesh.material == 2, 4, 1).astype(np.int32)
    with pytest.raises(DicerError, match="a_b_c"):
        prepare_model(mesh, config)
    config["export"]["sets"] = ["planes", "materials", "exterior"]
    assert "a_BOUNDARY" in prepare_model(mesh, config).node_sets


# --- command line ---------------------------------------------------------------------------


@pytest.mark.parametrize("output,extra,message", [
    ("model.stl", [], "must be one of"),
    ("model.k", ["--order", "2"], "8-node hexahedra only"),
    ("model.inp", ["--set", "export.element_type=C3D20"], "has order 2"),
    ("model.inp", ["--set", "export.element_type=C3D99"], "export.element_type"),
    ("file/model.inp", [], "cannot write"),
])
def test_cli_bad_export_input(tmp_path, mesh, capsys, output, extra, message):
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    write_mesh(mesh, tmp_path / "mesh.vtu")
    (tmp_path / "file").write_text("a file, not a folder")
    before = sorted(p.name for p in tmp_path.rglob("*"))
    code = main(["export", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / output), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("error: ") and message in err[-1]
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_cli_exports_every_format(tmp_path, mesh):
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    write_mesh(mesh, tmp_path / "mesh.vtu")
    for name in ("model.inp", "model.vtu", "model.out", "model.neu", "model.k", "model.msh"):
        assert main(["export", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / name)]) == 0
        assert (tmp_path / name).stat().st_size > 0
    assert main(["export", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / "q.inp"), "--order", "2"]) == 0
    assert "TYPE=C3D20," in (tmp_path / "q.inp").read_text()


def test_a_dicom_folder_name_never_reaches_the_deck(tmp_path, mesh, config):
    series = tmp_path / "DOE_JOHN_MRN12345"
    series.mkdir()
    (series / "im001.dcm").write_bytes(b"slice")
    for suffix in (".inp", ".k", ".out", ".feb", ".exo"):
        export_mesh(mesh, tmp_path / f"model{suffix}", config, source=series)
        assert b"DOE" not in (tmp_path / f"model{suffix}").read_bytes()


# --- the format registry ----------------------------------------------------------------------


def test_registry_has_one_format_a_suffix():
    from dicer.export.registry import BY_SUFFIX, FORMATS, format_of

    suffixes = [s for f in FORMATS for s in f.suffixes]
    assert len(suffixes) == len(set(suffixes)) == len(BY_SUFFIX)
    assert EXPORT_SUFFIXES == (".inp", ".vtu", ".out", ".neu", ".k", ".key", ".dyn", ".msh", ".e", ".exo", ".feb")
    assert all(s == s.lower() and s.startswith(".") for s in suffixes)
    assert format_of("A/MODEL.INP").name == "abaqus" and format_of("model.stl") is None
    for f in FORMATS:
        assert set(f.dims) <= {2, 3} and set(f.orders) <= {1, 2}
        assert (f.dims == (2, 3) and f.orders == (1, 2)) or f.limits  # a limit is explained


def test_write_vtu_takes_the_siblings_call_and_the_older_one(tmp_path, mesh, config):
    from dicer.export.model import scanner_mesh
    from dicer.export.vtu import write_vtu

    export_mesh(mesh, tmp_path / "a.vtu", config)
    model = prepare_model(mesh, config)
    write_vtu(model, tmp_path / "b.vtu")
    write_vtu(model, scanner_mesh(mesh, model), tmp_path / "c.vtu")
    want = (tmp_path / "a.vtu").read_bytes()
    assert (tmp_path / "b.vtu").read_bytes() == want == (tmp_path / "c.vtu").read_bytes()


@pytest.mark.parametrize("what", ["scaled_jacobian", "edge_ratio", "lattice"])
def test_vtu_check_compares_quality_and_lattice_exactly(tmp_path, mesh, config, what):
    from dicer.export.vtu import check_vtu, write_vtu
    from dicer.io.meshes import read_raw_vtu

    model = prepare_model(mesh, config)
    path = tmp_path / "m.vtu"
    write_vtu(model, path)
    check_vtu(path, model)  # as written: passes
    parts = read_raw_vtu(path, str(path))
    assert np.array_equal(parts[4]["scaled_jacobian"], model.cell_data["scaled_jacobian"])
    if what == "lattice":
        model.mesh = model.mesh.copy()
        model.mesh.lattice = model.mesh.lattice.copy()
        model.mesh.lattice[3, 0] += 1
    else:
        model.cell_data[what] = model.cell_data[what].copy()
        model.cell_data[what][5] = np.nextafter(model.cell_data[what][5], 2.0)  # one ulp
    with pytest.raises(DicerError, match="lattice" if what == "lattice" else what):
        check_vtu(path, model)


def test_source_digest_is_computed_once_per_unchanged_file(tmp_path, monkeypatch):
    """dicer run exports one mesh twice: the second heading reuses the digest, and a file
    changed since (same size) is hashed again."""
    import hashlib
    import importlib
    import os

    prov = importlib.import_module("dicer.export.provenance")  # dicer.export.provenance is also a function
    path = tmp_path / "mesh.vtu"
    path.write_bytes(b"a" * 1000)
    passes = []
    real = prov._sha256_of
    monkeypatch.setattr(prov, "_sha256_of", lambda p, files: passes.append(p) or real(p, files))
    first = prov.file_sha256(path)
    assert prov.file_sha256(path) == first == hashlib.sha256(b"a" * 1000).hexdigest() and len(passes) == 1
    path.write_bytes(b"b" * 1000)
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1))
    assert prov.file_sha256(path) == hashlib.sha256(b"b" * 1000).hexdigest() and len(passes) == 2


@pytest.mark.parametrize("suffix", [".inp", ".vtu", ".feb"])
def test_neighbours_handed_in_give_the_same_file(tmp_path, suffix):
    """dicer run finds the face neighbours once for the deck's sets and the quality report:
    the file is the same bytes as when the export finds what it needs itself."""
    from dicer.mesh.faces import materials_across
    from dicer.mesh.merge import merge_mesh
    from dicer.quality import element_neighbours

    lab = np.zeros((12, 10, 9), np.uint8)
    lab[1:11, 1:9, 1:8] = 1
    lab[4:8, 3:7, 2:6] = 2
    lab[2, 2, 1] = 0  # a notch: rim moves
    merged, _ = merge_mesh(voxel_mesh(lab), {})  # the config's defaults: plane merging
    assert merged.n_cells < np.count_nonzero(lab)
    calls = []

    def neighbours():
        calls.append(1)
        return element_neighbours(merged)

    assert np.array_equal(materials_across(merged.material, neighbours()), neighbour_materials(merged))
    config = load_config(settings={"export": {"order": 2, "midside_nodes": "curved"}} if suffix == ".feb" else {})
    export_mesh(merged, tmp_path / f"a{suffix}", config, source="scan.nii")
    calls.clear()
    export_mesh(merged, tmp_path / f"b{suffix}", config, source="scan.nii", neighbours=neighbours)
    assert (tmp_path / f"a{suffix}").read_bytes() == (tmp_path / f"b{suffix}").read_bytes()
    assert len(calls) == (0 if suffix == ".vtu" else 1)  # VTU holds no sets and needs none


@pytest.mark.parametrize("suffix, digits, outcome", [
    (".inp", 9, "refused"), (".inp", 13, "fine"), (".feb", 13, "fine"), (".k", 13, "refused"), (".out", 9, "refused"),
    (".exo", 9, "fine"), (".vtu", 9, "fine"),
])
def test_coordinates_printed_too_coarse_for_the_voxels_are_refused(tmp_path, caplog, suffix, digits, outcome):
    """0.1 um voxels 200 m from the origin: 9 digits moved nodes by ten voxels and CalculiX
    stopped on inverted elements, while the deck's read-back (to printed precision) passed."""
    if suffix == ".exo":
        pytest.importorskip("netCDF4")
    labels = np.zeros((6, 5, 4), np.uint8)
    labels[1:5, 1:4, 1:3] = 1
    mesh = voxel_mesh(labels, spacing=(1e-4, 1e-4, 1e-4), origin=(-1e5, 2e5, -3e4))
    path = tmp_path / f"m{suffix}"
    config = {"export": {"digits": digits}}
    if outcome == "refused":
        with pytest.raises(DicerError, match=r"printed with 9 significant digits, move nodes by up to 0\.0004 mm along "
                                             r"a voxel axis, 400 % of that axis's voxel edge: .* \(24 element\(s\) "
                                             r"turn inside out as printed\)"):
            export_mesh(mesh, path, config)
        assert not path.exists()
    else:
        export_mesh(mesh, path, config)
        assert "significant digits" not in caplog.text
    assert ("prints coordinates with 9 significant digits (its fixed columns)" in caplog.text) == (suffix == ".k")


def test_coordinates_printed_near_the_voxel_size_are_warned_of(tmp_path, caplog):
    """Nine digits of -19999.999467 mm print it to a tenth of a micrometre: 3.3 % of the 1 um
    voxels. The same model 33 nm over prints as it is: no warning."""
    labels = np.ones((3, 3, 3), np.uint8)
    mesh = voxel_mesh(labels, spacing=(1e-3, 1e-3, 1e-3), origin=(-2e4 + 3.3e-5, 0.0, 0.0))
    export_mesh(mesh, tmp_path / "m.inp")
    assert "move nodes by up to 3.3e-05 mm along a voxel axis, 3.3 % of that axis's voxel edge: the model lies up to " \
           "20000 mm from the origin and spans 0.003 mm; set export.digits: 13, or place the image's origin near the " \
           "model" in caplog.text
    caplog.clear()
    export_mesh(voxel_mesh(labels, spacing=(1e-3, 1e-3, 1e-3), origin=(-2e4, 0.0, 0.0)), tmp_path / "n.inp")
    assert "significant digits" not in caplog.text


@pytest.mark.parametrize("spacing, order, inverted", [(0.25, 1, 240), (0.5, 2, 192)])
def test_elements_printed_inside_out_are_refused(tmp_path, spacing, order, inverted):
    """A smoothed ball 10 km from the origin: 9 digits move its nodes by up to 20 % (0.25 mm
    voxels) and 10 % (0.5 mm, curved 20-node elements) of a voxel, under the 25 % refused
    before, and CalculiX stopped on the deck's nonpositive Jacobians. The elements are
    checked as printed: refused; 13 digits print them as they are."""
    from dicer.mesh.smooth import smooth_mesh

    g = np.indices((16, 16, 16)).astype(float) - 7.5
    labels = (np.sqrt((g ** 2).sum(0)) <= 6).astype(np.uint8)
    mesh = smooth_mesh(voxel_mesh(labels, spacing=(spacing,) * 3, origin=(1e7,) * 3), WITHOUT_THE_LAYER)[0]
    export = {"order": order, "midside_nodes": "curved"}
    with pytest.raises(DicerError, match=rf"\({inverted} element\(s\) turn inside out as printed\)$"):
        export_mesh(mesh, tmp_path / "m.inp", {"export": export})
    assert not (tmp_path / "m.inp").exists()
    export_mesh(mesh, tmp_path / "m.inp", {"export": export | {"digits": 13}})


def test_a_model_long_for_its_voxels_is_printed_against_each_axis_s_voxels(tmp_path, caplog):
    """Voxels 1e-4 x 1e-4 x 1000 mm, the origin at the model: 9 digits print z to 1e-5 mm
    of its 1000 mm voxels and x and y exactly. Set against the smallest voxel edge the z
    rounding was 10 % of a voxel and the export refused the model."""
    labels = np.zeros((6, 6, 24), np.uint8)
    labels[1:5, 1:5, 1:23] = 1
    mesh = voxel_mesh(labels, spacing=(1e-4, 1e-4, 1000.0))
    export_mesh(mesh, tmp_path / "m.inp")
    assert "significant digits" not in caplog.text
    deck = meshio.read(tmp_path / "m.inp")
    assert np.abs(deck.points - mesh.points).max() <= 1e-5
