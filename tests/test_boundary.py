"""Boundary edges, the boundary graph and node classes A-F (Fig. 5)."""

import itertools
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dicer.connectivity import boundary_edge_counts, connectivity_defects, fix_connectivity
from dicer.errors import DicerError
from dicer.mesh import boundary
from dicer.mesh.boundary import NODE_CLASSES, boundary_graph, class_counts, with_node_classes
from dicer.mesh.model import Mesh
from dicer.mesh.voxel import voxel_mesh

CODE = {name: i for i, name in enumerate(NODE_CLASSES)}


def centre_class(lab: np.ndarray) -> str:
    m = voxel_mesh(lab)
    g = boundary_graph(m)
    c = np.flatnonzero((m.lattice == 1).all(axis=1))[0]
    return NODE_CLASSES[g.node_class[c]]


def block(*octants) -> np.ndarray:
    lab = np.zeros((2, 2, 2), np.uint8)
    for o in octants:
        lab[o] = 1
    return lab


# one representative of each class of Fig. 5, with its number of boundary edges
FIG5 = {
    "A": (block((0, 0, 0)), 3),  # a single element: corner
    "B": (block((0, 0, 0), (0, 0, 1)), 4),  # two elements along an edge: ridge
    "C": (block((0, 0, 0), (1, 0, 0), (0, 1, 0)), 5),  # three elements in an L
    "D": (block((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)), 4),  # a flat layer of four
    "E": (block((0, 0, 0), (1, 0, 0), (1, 1, 0), (1, 1, 1)), 6),  # a staircase of four
    "F": (block((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)), 6),  # a tripod of four
}


@pytest.mark.parametrize("name", sorted(FIG5))
def test_fig5_configurations_and_complements(name):
    lab, edges = FIG5[name]
    for labels in (lab, 1 - lab):
        assert centre_class(labels) == name
        assert boundary_edge_counts(labels)[1, 1, 1] == edges
        # every rotation and mirror image gives the same class
        for perm in itertools.permutations(range(3)):
            for flips in itertools.product((False, True), repeat=3):
                t = labels.transpose(perm)
                for ax, f in enumerate(flips):
                    if f:
                        t = np.flip(t, ax)
                assert centre_class(np.ascontiguousarray(t)) == name


def test_every_fixed_binary_unit_block_is_one_of_the_six():
    seen = {}
    for bits in range(1, 255):
        lab = np.array([(bits >> i) & 1 for i in range(8)], np.uint8).reshape(2, 2, 2)
        d = connectivity_defects(lab, type_c=False)
        if d["type_a"] or d["type_b"]:
            continue
        name = centre_class(lab)
        seen[name] = seen.get(name, 0) + 1
    # counts of the configurations (with rotations, mirror images and complements)
    assert seen == {"A": 16, "B": 24, "C": 48, "D": 6, "E": 24, "F": 8}


def test_three_material_unit_blocks_are_classified():
    names = set()
    for v in itertools.product(range(3), repeat=8):
        lab = np.array(v, np.uint8).reshape(2, 2, 2)
        if lab.max() == 0:
            continue
        d = connectivity_defects(lab, type_c=False)
        if d["type_a"] or d["type_b"]:
            continue
        names.add(centre_class(lab))
    assert "X" not in names
    assert names <= {"interior", "A", "B", "C", "D", "E", "F"}


def test_interface_node_between_two_materials_is_flat():
    lab = np.ones((2, 2, 2), np.uint8)
    lab[:, :, 1] = 2
    assert centre_class(lab) == "D"
    lab = np.ones((2, 2, 2), np.uint8)
    assert centre_class(lab) == "interior"


def test_cube_counts():
    lab = np.zeros((5, 5, 5), np.uint8)
    lab[1:4, 1:4, 1:4] = 1
    m = voxel_mesh(lab)
    g = boundary_graph(m)
    counts = class_counts(g.node_class)
    assert counts["A"] == 8  # the corners
    assert counts["B"] == 12 * 2  # edge nodes
    assert counts["D"] == 6 * 4  # face nodes
    assert counts["interior"] == 8
    assert g.edges.shape[0] == 12 * 3 + 6 * 12  # 12 cube edges of 3, 6 faces with 12 inner edges
    assert np.all(g.degree[g.boundary] >= 3)


def _stretched(m: Mesh, widths) -> Mesh:
    """The same topology on a non-uniform grid (as after plane merging): node i on axis d
    sits at sum(widths[:i])."""
    edges = np.concatenate([[0], np.cumsum(widths)])
    lat = edges[m.lattice]
    return Mesh(lat.astype(float) * m.spacing + m.origin, m.cells.copy(), m.material.copy(), lat.astype(np.int64),
                m.spacing.copy(), m.origin.copy(), np.array([edges[n] for n in m.grid_shape]))


def test_classes_do_not_depend_on_the_lattice():
    rng = np.random.default_rng(0)
    g0 = np.arange(14) + 0.5 - 7.2
    r = np.sqrt(g0[:, None, None] ** 2 + g0[None, :, None] ** 2 + g0[None, None, :] ** 2)
    lab = (r < 5.5).astype(np.uint8) + (r < 3).astype(np.uint8)
    from dicer.connectivity import fix_connectivity

    lab, _ = fix_connectivity(lab)
    m = voxel_mesh(lab)
    widths = rng.integers(1, 4, 20)
    ms = _stretched(m, widths)
    a = boundary_graph(m).node_class
    b = boundary_graph(ms).node_class
    assert np.array_equal(a, b)
    assert CODE["X"] not in set(a.tolist())


@pytest.mark.parametrize("dims", [(9, 8, 7), (13, 11)])
def test_corner_table_gives_the_same_graph(dims):
    # the smoother passes its corner table (no pass over all elements); same graph
    from dicer.mesh.smooth import _corner_slots

    rng = np.random.default_rng(len(dims))
    for kinds in (1, 2, 4):
        m = voxel_mesh(rng.integers(0, kinds + 1, dims).astype(np.uint8))
        a = boundary_graph(m)
        b = boundary_graph(m, None, _corner_slots(m.cells, m.n_points))
        for f in ("boundary", "edges", "degree", "node_class", "boundary_cells"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f


def test_2d_square_corners_and_sides():
    lab = np.zeros((5, 5), np.uint8)
    lab[1:4, 1:4] = 1
    m = voxel_mesh(lab)
    g = boundary_graph(m)
    counts = class_counts(g.node_class)
    assert counts["B"] == 4 and counts["D"] == 8 and counts["interior"] == 4


def test_node_class_is_point_data_in_the_vtu(tmp_path):
    from dicer.io.meshes import read_mesh, write_mesh

    lab = np.zeros((4, 4, 4), np.uint8)
    lab[1:3, 1:3, 1:3] = 1
    m, counts = with_node_classes(voxel_mesh(lab))
    write_mesh(m, tmp_path / "m.vtu")
    back = read_mesh(tmp_path / "m.vtu")
    assert np.array_equal(back.point_data["node_class"].ravel(), m.point_data["node_class"])
    assert counts["A"] == 8 and counts["interior"] == 1


def test_empty_mesh_is_an_error():
    m = Mesh(np.zeros((0, 3)), np.zeros((0, 8), np.int64), np.zeros(0, np.int32), np.zeros((0, 3), np.int64),
             np.ones(3), np.zeros(3), np.ones(3, np.int64))
    with pytest.raises(DicerError):
        boundary_graph(m)


_GRAPH_FIELDS = ("boundary", "edges", "degree", "node_class", "boundary_cells")


def _graphs_by_every_count(m: Mesh, slots=None) -> list:
    """The boundary graph of ``m`` with the packed per-edge histogram, the sorted count
    with one int64 key, and the sorted count by lexsort."""
    out = [boundary_graph(m, None, slots)]
    with mock.patch.object(boundary, "_PACKED_KINDS", 0):
        out.append(boundary_graph(m, None, slots))
        with mock.patch.object(boundary, "_KEY_MAX", 0):
            out.append(boundary_graph(m, None, slots))
    return out


@settings(max_examples=40, deadline=None)
@given(arrays(np.uint8, st.one_of(st.tuples(*[st.integers(2, 7)] * 3), st.tuples(*[st.integers(2, 9)] * 2)),
              elements=st.integers(0, 6)),
       st.sampled_from([1, 37, 4000]))
def test_sorted_edge_counts_equal_the_packed_histogram(labels, scale):
    # random fixed meshes of up to 6 materials (label values spread out by ``scale``):
    # the count for any number of materials gives exactly the graph of the packed one
    from dicer.mesh.smooth import _corner_slots

    labels = labels.astype(np.uint16) * scale
    labels, _ = fix_connectivity(labels)
    if not labels.any():
        labels[(0,) * labels.ndim] = scale
    m = voxel_mesh(labels)
    for slots in (None, _corner_slots(m.cells, m.n_points)):
        first, *others = _graphs_by_every_count(m, slots)
        for g in others:
            for f in _GRAPH_FIELDS:
                assert np.array_equal(getattr(g, f), getattr(first, f)), f
                assert getattr(g, f).dtype == getattr(first, f).dtype, f


def _many_labels(n: int, kinds: int, seed: int) -> np.ndarray:
    """(n, n, n) uint16 Voronoi cells of ``kinds`` random seeds, labelled with values scattered
    over 1..65535, background on one face; connectivity fixed."""
    rng = np.random.default_rng(seed)
    values = np.sort(rng.choice(np.arange(1, 65536), kinds, replace=False)).astype(np.uint16)
    seeds = rng.uniform(0, n, (kinds, 3))
    centres = np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    lab = values[((centres - seeds) ** 2).sum(axis=2).argmin(axis=1)].reshape(n, n, n)
    lab[0] = 0
    return fix_connectivity(lab)[0]


def test_many_materials_give_the_voxel_space_counts():
    # 300 labels up to 65535: the boundary edges per node are those counted on the label
    # volume itself, every node gets one of the six classes, and the two sorted counts agree
    lab = _many_labels(20, 300, 0)
    m = voxel_mesh(lab)
    assert np.unique(m.material).size > 250
    g, by_key, by_lexsort = _graphs_by_every_count(m)
    for f in _GRAPH_FIELDS:
        assert np.array_equal(getattr(by_key, f), getattr(g, f)), f
        assert np.array_equal(getattr(by_lexsort, f), getattr(g, f)), f
    assert np.array_equal(g.degree, boundary_edge_counts(lab)[tuple(m.lattice.T)])
    counts = class_counts(g.node_class)
    assert counts["X"] == 0
    assert sum(counts.values()) == m.n_points
    assert counts["interior"] == np.count_nonzero(~g.boundary)
    assert min(counts[c] for c in "ABCDEF") > 0


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 20), st.integers(0, 2**32 - 1))
def test_edge_counts_by_sorting_and_packing_agree_with_a_tally(n, kinds, seed):
    # per distinct edge: its nodes, its elements and the most of one material, checked
    # against a plain tally (up to 7 elements of a material on an edge)
    rng = np.random.default_rng(seed)
    size = int(rng.integers(0, 200))
    a, b = rng.integers(0, n, (2, size)).astype(np.int32)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    rank = rng.integers(0, kinds, size).astype(np.int8)
    tally = {}
    for x, y, r in zip(lo.tolist(), hi.tolist(), rank.tolist()):
        tally.setdefault((x, y), []).append(r)
    tally = {e: r for e, r in tally.items() if max(np.bincount(r)) <= 7}
    keep = np.array([(x, y) in tally for x, y in zip(lo.tolist(), hi.tolist())], bool)
    lo, hi, rank = lo[keep], hi[keep], rank[keep]
    expected = sorted((x, y, len(r), int(np.bincount(r).max())) for (x, y), r in tally.items())
    results = [boundary._edge_counts_packed(lo, hi, rank, n, kinds),
               boundary._edge_counts_sorted(lo, hi, rank, n, kinds)]
    with mock.patch.object(boundary, "_KEY_MAX", 0):
        results.append(boundary._edge_counts_sorted(lo, hi, rank, n, kinds))
    for first, second, total, top in results:
        assert list(zip(first.tolist(), second.tolist(), total.tolist(), top.tolist())) == expected
        assert first.dtype == second.dtype == np.int32
