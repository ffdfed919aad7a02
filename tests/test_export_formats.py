"""Quadratic elements, PATRAN neutral, LS-DYNA keyword, Gmsh and VTU: round trips and layouts."""

from __future__ import annotations

import itertools
import logging
import re

import meshio
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from dicer.config import load_config
from dicer.errors import DicerError
from dicer.export import export_mesh, prepare_model
from dicer.export.lsdyna import read_lsdyna
from dicer.export.patran import read_patran
from dicer.mesh import quadratic
from dicer.mesh.metrics import quality_arrays
from dicer.mesh.quadratic import quadratic_mesh
from dicer.mesh.topology import HEX_EDGES, QUAD_EDGES
from dicer.mesh.voxel import voxel_mesh

# PATRAN's 20-node hexahedron, from its element library: corners, then the mid-edge
# nodes of the bottom edges, the vertical edges and the top edges (1-based corners)
PATRAN_HEX20_EDGES = [(1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (2, 6), (3, 7), (4, 8),
                      (5, 6), (6, 7), (7, 8), (8, 5)]


@pytest.fixture
def labels():
    lab = np.zeros((3, 4, 5), np.uint8)
    lab[:, :, :2] = 1
    lab[:, 1:3, 2:] = 2
    return lab


@pytest.fixture
def mesh(labels):
    m = voxel_mesh(labels, spacing=(0.5, 0.75, 1.25), origin=(-1.0, 2.0, 0.5))
    # a smoothed-looking mesh: move nodes a little, keep elements valid; nodes on the
    # image's bounding planes stay in them, as smoothing keeps them
    rng = np.random.default_rng(0)
    on_plane = (m.lattice == 0) | (m.lattice == m.grid_shape)
    m.points += np.where(on_plane, 0.0, rng.uniform(-0.05, 0.05, m.points.shape))
    return m


def cfg(**export):
    return load_config(settings={"export": export})


def _edge_count(labels: np.ndarray) -> int:
    solid = np.pad(labels > 0, 1)
    total = 0
    for axis in range(3):
        # an edge along `axis` exists where any of the 4 voxels around it is solid
        others = [a for a in range(3) if a != axis]
        s = solid
        around = s | np.roll(s, 1, others[0])
        around = around | np.roll(around, 1, others[1])
        total += np.count_nonzero(around)
    return total


# --- quadratic elements ---------------------------------------------------------------------


def test_mid_edge_nodes_are_shared_and_at_midpoints(mesh, labels):
    points, cells, lattice2 = quadratic_mesh(mesh)
    n = mesh.n_points
    assert cells.shape == (mesh.n_cells, 20)
    assert points.shape[0] - n == _edge_count(labels)  # one node per mesh edge, never duplicated
    mids = cells[:, 8:]
    ends = cells[:, HEX_EDGES]
    assert np.allclose(points[mids], 0.5 * (points[ends[..., 0]] + points[ends[..., 1]]))
    assert np.array_equal(lattice2[mids], mesh.lattice[ends[..., 0]] + mesh.lattice[ends[..., 1]])
    assert np.unique(points.round(9), axis=0).shape[0] == points.shape[0]  # no two nodes coincide
    # every element edge slot refers to the same node from all elements around the edge
    key = np.sort(ends, axis=-1).reshape(-1, 2)
    node = mids.ravel()
    order = np.lexsort(key.T[::-1])
    same = (key[order][1:] == key[order][:-1]).all(axis=1)
    assert np.array_equal(node[order][1:][same], node[order][:-1][same])


def test_mid_edge_nodes_without_lattice_boxes(mesh):
    # a mesh whose lattice indices are not boxes: edges are found by sorting end-node pairs
    points, cells, _ = quadratic_mesh(mesh)
    other = mesh.copy()
    other.lattice = other.lattice[::-1].copy()
    points2, cells2, _ = quadratic_mesh(other)
    assert points2.shape == points.shape and np.array_equal(cells2[:, :8], cells[:, :8])
    assert np.allclose(points2[cells2], points[cells])  # same node at every element slot


def test_curved_mid_edge_nodes_keep_flat_faces_flat(mesh):
    straight = voxel_mesh(np.ones((3, 4, 2), np.uint8), spacing=(0.5, 1.0, 2.0))
    a = prepare_model(straight, cfg(order=2, midside_nodes="midpoint"))
    b = prepare_model(straight, cfg(order=2, midside_nodes="curved"))
    assert np.allclose(a.points, b.points)  # collinear boundary nodes: the cubic is the midpoint
    # on a bumpy boundary only boundary edges move, interior ones stay at their midpoints
    c = prepare_model(mesh, cfg(order=2, midside_nodes="midpoint"))
    d = prepare_model(mesh, cfg(order=2, midside_nodes="curved"))
    moved = np.flatnonzero(np.abs(c.points - d.points).max(axis=1) > 1e-12)
    assert moved.size and np.all(moved >= mesh.n_points)
    assert set(moved) <= set(np.concatenate([d.node_sets["EXTERIOR"], d.node_sets["soft_tissue_bone"]]))


def _sagged(mesh):
    """Mean radius of a ball's exterior corner nodes less that of its exterior mid-edge
    nodes, with ``midpoint`` and ``curved`` mid-edge nodes; and the curved model."""
    centre = mesh.points.mean(axis=0)
    sag = {}
    for mode in ("midpoint", "curved"):
        model = prepare_model(mesh, cfg(order=2, midside_nodes=mode))
        ext = model.node_sets["EXTERIOR"]
        r = np.linalg.norm(model.points[ext] - centre, axis=1)
        sag[mode] = r[ext < mesh.n_points].mean() - r[ext >= mesh.n_points].mean()
        interior = np.setdiff1d(np.arange(mesh.n_points, model.n_points), ext)
        if mode == "curved":  # only boundary edges bend
            assert np.array_equal(model.points[interior], plain.points[interior])
        plain = model
    return sag, model


def test_curved_mid_edge_nodes_follow_a_smoothed_sphere():
    smooth = pytest.importorskip("dicer.mesh.smooth")
    from dicer.phantoms import sphere_labels

    volume = sphere_labels(24)
    settings = load_config(settings={"preset": "explicit-dynamics"})["smooth"]  # no pillow layer
    mesh, _ = smooth.smooth_mesh(voxel_mesh(volume.array, volume.spacing), settings)
    sag, _ = _sagged(mesh)
    # chords cut inside a convex surface; bending boundary edges takes back part of that sag
    assert 0 < sag["curved"] < 0.8 * sag["midpoint"]


def test_curved_mid_edge_nodes_never_fold_an_element(tmp_path, caplog):
    """The head phantom (36 voxels, merging off, its headrest kept: segment.keep all, since the
    body's parts are chosen before the closing, which had joined the headrest to the head): bent
    boundary edges turned 19 of its 20-node elements inside out at integration points
    (CalculiX: "nonpositive jacobian"); 582 of the 14,002 bent nodes go back."""
    from dicer.cli import main
    from dicer.io.meshes import read_mesh
    from dicer.mesh import quadratic
    from dicer.mesh.faces import neighbour_materials

    assert main(["phantom", "head", "--size", "36", "-o", str(tmp_path / "head.nii.gz"), "-q"]) == 0
    assert main(["run", str(tmp_path / "head.nii.gz"), "-o", str(tmp_path / "out"), "-q",
                 "--set", "merge.passes=[0,0,0]", "--set", "smooth.surface_from_labels=false",
                 "--set", "segment.keep=all", "--set", "preset=explicit-dynamics"]) == 0
    mesh = read_mesh(tmp_path / "out" / "smoothed.vtu")
    grads = quadratic._serendipity_gradients(quadratic._HEX_NODES, quadratic._check_points(3))

    def smallest_det(points, cells):
        return np.linalg.det(np.einsum("pka,bkc->bpac", grads, points[cells])).min(axis=1)

    # without the check: the curve folds some elements
    nb = neighbour_materials(mesh)
    edges, index, along_lines = quadratic.edges_by_lattice(mesh, np.asarray(mesh.cells, np.int64))
    assert along_lines
    raw = quadratic.curved_midpoints(mesh, edges, index, nb != mesh.material[:, None].astype(nb.dtype))
    cells = np.concatenate([mesh.cells, index + mesh.n_points], axis=1)
    assert np.count_nonzero(smallest_det(np.concatenate([mesh.points, raw]), cells) <= 0) > 0
    # the export: every element positive at every integration point, most bent nodes kept
    plain = prepare_model(mesh, cfg(order=2, midside_nodes="midpoint"))
    with caplog.at_level("INFO", logger="dicer"):
        curved = prepare_model(mesh, cfg(order=2, midside_nodes="curved"))
    assert smallest_det(curved.points, curved.cells).min() > 0
    bent = np.count_nonzero(np.abs(curved.points - plain.points).max(axis=1) > 1e-12)
    said = [r.getMessage() for r in caplog.records if "put back at their edge's midpoint" in r.getMessage()]
    assert len(said) == 1
    back = int(said[0].split()[1])
    assert 0 < back and bent > 10 * back


def test_curved_mid_edge_nodes_never_fold_an_element_at_its_nodes_or_faces(tmp_path):
    """An atlas of 200 parcels in a ball with the pillow layer: 3 of its 23,549 curved 20-node
    elements were positive at every integration point and corner but turned inside out at a
    mid-edge node and the Gauss points of a face (det J -5.6e-4 of +1.2e-2), which the check
    did not look at; a pressure on that face would be integrated there."""
    from itertools import product

    from scipy.spatial import cKDTree

    from dicer.cli import main

    rng = np.random.default_rng(0)
    n = 40
    grid = np.stack(np.meshgrid(*[np.arange(n) + 0.5] * 3, indexing="ij"), -1)
    _, parcel = cKDTree(rng.uniform(0, n, (200, 3))).query(grid.reshape(-1, 3))
    atlas = (parcel.reshape((n,) * 3) + 1) * (np.linalg.norm(grid - n / 2, axis=-1) < 17)
    np.save(tmp_path / "atlas.npy", atlas.T.astype(np.int16))  # [x, y, z] as its NIfTI was read
    assert main(["run", "--labels", str(tmp_path / "atlas.npy"), "-o", str(tmp_path / "out"), "-q",
                 "--set", "smooth.pillow=true", "--set", "export.order=2",
                 "--set", "export.midside_nodes=curved"]) == 0
    model = meshio.read(tmp_path / "out" / "model.vtu")
    cells = model.get_cells_type("hexahedron20")
    nodes = np.array(list(product([-1.0, 0.0, 1.0], repeat=3)))
    grads = quadratic._serendipity_gradients(quadratic._HEX_NODES, nodes)
    det = np.linalg.det(np.einsum("pka,bkc->bpac", grads, model.points[cells]))
    assert cells.shape[0] > 20_000 and det.min() > 0


def _bent_cubes(offset: np.ndarray, size: float, bends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """20-node cubes of edge ``size`` mm at ``offset``, the mid-edge node of edge 0-1 of cube i
    moved inward by ``bends[i]`` of the edge: points (20 M, 3) and cells (M, 20)."""
    nodes = (quadratic._HEX_NODES + 1.0) / 2.0 * size + offset
    points = np.repeat(nodes[None], bends.size, axis=0)
    points[:, 8, 1] += np.asarray(bends) * size
    return points.reshape(-1, 3), np.arange(points.shape[0] * 20).reshape(-1, 20)


@settings(max_examples=60, deadline=None)
@given(st.floats(-2000.0, 2000.0), st.floats(0.01, 5.0), st.integers(0, 2**32 - 1))
def test_the_curved_elements_screen_decides_as_the_exact_sums(shift, size, seed):
    """The fold check's BLAS screen passes only elements clear of the floor by far more than it
    and the exact sums differ: the same decisions, elements far from the origin and small ones,
    those a last bit either side of the floor among them."""
    grads = quadratic._serendipity_gradients(quadratic._HEX_NODES, quadratic._check_points(3))
    rng = np.random.default_rng(seed)
    offset = np.array([shift, -0.5 * shift, 0.25 * shift])
    points, cells = _bent_cubes(offset, size, rng.uniform(0.0, 0.9, 200))
    points += rng.normal(0.0, 0.03 * size, points.shape)
    exact = quadratic._det_ratio(points, cells, grads, 3)
    screen = quadratic._det_ratio(points, cells, grads, 3, screen=True)
    finite = np.isfinite(exact)
    assert np.array_equal(finite, np.isfinite(screen))
    assert np.abs(screen - exact)[finite].max() < 1e-3 * quadratic._SCREEN_MARGIN
    assert np.array_equal(quadratic._failing(points, cells, grads, 3), ~(exact >= quadratic._CURVED_FLOOR))
    # the bend at which the exact ratio crosses the floor, to the last bit (the ratio is 1 minus
    # the bend: 0.1 at 0.9, to rounding either side, so the search starts beyond it)
    lo, hi = 0.0, 0.95
    ratio = lambda t: quadratic._det_ratio(*_bent_cubes(offset, size, np.array([t])), grads, 3)[0]  # noqa: E731
    assert ratio(lo) >= quadratic._CURVED_FLOOR > ratio(hi)
    while np.nextafter(lo, hi) < hi:
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if ratio(mid) >= quadratic._CURVED_FLOOR else (lo, mid)
    points, cells = _bent_cubes(offset, size, np.array([lo, hi]))
    assert quadratic._failing(points, cells, grads, 3).tolist() == [False, True]


@settings(max_examples=30, deadline=None)
@given(st.floats(-2000.0, 2000.0), st.floats(0.01, 5.0), st.integers(0, 2**32 - 1), st.sampled_from([2, 3]))
def test_quadratic_volumes_are_the_gauss_sums_of_the_jacobian(shift, size, seed, dim):
    """The volumes of bent quadratic elements (curved mid-edge nodes) are the 3^d-point Gauss
    sums of det J, taken here by numpy's determinant; with the mid-edge nodes put at their
    midpoints, the linear element's volume (the shoelace or the hexahedron's) to rounding."""
    from dicer.mesh.metrics import element_volumes

    rng = np.random.default_rng(seed)
    offset = np.array([shift, -0.5 * shift, 0.25 * shift])[:dim]
    nodes = quadratic._HEX_NODES if dim == 3 else quadratic._QUAD_NODES
    corners = 2**dim
    m = 50
    points = ((nodes[None] + 1.0) / 2.0 * size + offset) + rng.normal(0.0, 0.05 * size, (m,) + nodes.shape)
    points = np.concatenate([points, np.zeros((m, nodes.shape[0], 3 - dim))], axis=2).reshape(-1, 3)
    cells = np.arange(m * nodes.shape[0]).reshape(m, -1)
    g, w = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)]), np.array([5.0, 8.0, 5.0]) / 9.0
    at = np.array(list(itertools.product(g, repeat=dim)))
    weight = np.prod(np.array(list(itertools.product(w, repeat=dim))), axis=1)
    grads = quadratic._serendipity_gradients(nodes, at)
    exact = np.linalg.det(np.einsum("pka,bkc->bpac", grads, points[cells][..., :dim])) @ weight
    got = quadratic._gauss_volumes(points, cells, dim)
    assert np.allclose(got, exact, rtol=1e-9, atol=1e-9 * size**dim)
    # (the shoelace at 2,000 mm from the origin loses more than the tolerance: taken at the cubes)
    linear = element_volumes(points - np.append(offset, np.zeros(3 - dim)), cells[:, :corners])
    ends = HEX_EDGES if dim == 3 else QUAD_EDGES
    straight = points[cells].copy()
    straight[:, corners:] = 0.5 * (straight[:, ends[:, 0]] + straight[:, ends[:, 1]])
    assert np.allclose(quadratic._gauss_volumes(straight.reshape(-1, 3), cells, dim), linear, rtol=1e-9,
                       atol=1e-9 * size**dim)


def test_curved_mid_edge_nodes_that_swell_a_small_part_are_said(tmp_path, caplog):
    """A ball of radius 3 voxels under the static-stress preset: its curved mid-edge nodes add a
    tenth to the volume quality.json reports (the arcs through few nodes; measured +10.35 %: the
    deck integrated by Gmsh 160.1 mm^3 against 145.1), which the export says, naming the setting
    that keeps it; a ball of radius 8 changes by +1.60 %, said at INFO."""
    from dicer.cli import main
    from dicer.mesh.metrics import element_volumes

    z, y, x = np.mgrid[:24, :24, :24] - 11.5
    for radius in (3.01, 8.0):
        caplog.clear()
        np.save(tmp_path / "ball.npy", (x * x + y * y + z * z <= radius**2).astype(np.uint8))
        out = tmp_path / f"out{radius:g}"
        with caplog.at_level("INFO", logger="dicer"):
            assert main(["run", "--labels", str(tmp_path / "ball.npy"), "-o", str(out), "-q", "--set",
                         "preset=static-stress", "--set", "fix.min_component_voxels=0"]) == 0
        said = [r for r in caplog.records if "curved mid-edge nodes change" in r.getMessage()]
        model = meshio.read(out / "model.vtu")
        cells = model.get_cells_type("hexahedron20")
        deck = quadratic._gauss_volumes(model.points, cells, 3).sum()
        linear = element_volumes(model.points, cells[:, :8]).sum()
        change = float(re.search(r"([+-][0-9.]+) %", said[0].getMessage()).group(1))
        assert len(said) == 1 and change == pytest.approx(100 * (deck / linear - 1), abs=0.05)  # as printed
        if radius < 4:
            assert said[0].levelname == "WARNING" and change > 8
            assert "set export.midside_nodes: midpoint" in said[0].getMessage()
        else:  # against the labels' voxels (2,176): the linear mesh -0.30 %, the arcs bulge to +1.30 %
            voxels = np.count_nonzero(x * x + y * y + z * z <= radius**2)
            assert said[0].levelname == "INFO" and 0 < change < 2
            assert -0.01 < linear / voxels - 1 < 0 < deck / voxels - 1 < 0.02


def test_curved_mid_edge_nodes_on_a_merged_mesh_follow_the_sphere(caplog):
    """Plane merging's chamfers leave edges off the lattice lines: the mid-edge nodes of the
    boundary edges go onto arcs through the next boundary nodes (they stayed at the
    midpoints, with a warning)."""
    from dicer.mesh.merge import merge_mesh
    from dicer.mesh.smooth import smooth_mesh
    from dicer.phantoms import sphere_labels

    volume = sphere_labels(24)
    merged, _ = merge_mesh(voxel_mesh(volume.array, volume.spacing), {})
    mesh, _ = smooth_mesh(merged, load_config().get("smooth"))
    assert not quadratic.edges_by_lattice(mesh, np.asarray(mesh.cells, np.int64))[2]  # off the lattice lines
    caplog.set_level("INFO", logger="dicer")
    sag, model = _sagged(mesh)
    # chords cut inside a convex surface; the arcs take back part of it (measured 0.0440 and
    # 0.0389 mm: this small merged ball's smoothed surface is uneven, 0.3 mm rms in radius,
    # and arcs that would fold or worsen an element below the floor go back to midpoints)
    assert 0 < sag["curved"] < 0.95 * sag["midpoint"], sag
    grads = quadratic._serendipity_gradients(quadratic._HEX_NODES, quadratic._check_points(3))
    assert quadratic._det_ratio(model.points, model.cells, grads, 3).min() > 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "midside" in r.getMessage()]


@settings(max_examples=200, deadline=None)
@given(st.floats(0.5, 50.0), st.floats(0.02, 0.6), st.floats(0.02, 0.6), st.floats(0.0, 6.3),
       st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6))
def test_an_arc_midpoint_lies_on_the_circle_of_its_three_nodes(radius, step_a, step_b, start, frame):
    """A chord a-b of a circle and a node p beyond a: the chord's midpoint moved by the
    sagitta is the middle of the arc a-b, on any circle in space, at any spacing."""
    u, v = np.array(frame[:3]), np.array(frame[3:])
    assume(np.linalg.norm(np.cross(u, v)) > 0.1)
    u /= np.linalg.norm(u)
    v -= (v @ u) * u
    v /= np.linalg.norm(v)
    centre = np.array([3.0, -2.0, 7.0])

    def at(t):
        return centre + radius * (np.cos(t) * u + np.sin(t) * v)

    a, b, p = at(start), at(start + step_b), at(start - step_a)
    moved = 0.5 * (a + b) + quadratic._sagitta(a[None], b[None], p[None])[0]
    assert abs(np.linalg.norm(moved - centre) - radius) < 1e-9 * radius
    assert np.allclose(moved, at(start + step_b / 2), atol=1e-9 * radius)
    # three nodes in a line: the midpoint
    line = quadratic._sagitta(a[None], b[None], (2 * a - b)[None])
    assert np.abs(line).max() < 1e-9


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([2, 3]), st.sampled_from(["voxels", "planes", "templates", "pillow"]))
def test_edges_found_by_the_lattice_are_the_meshes_edges(seed, dim, kind):
    """The lattice lookup of mid-edge nodes finds each edge of the mesh once, and every element
    edge slot points to its own pair of nodes: on voxel meshes, plane merging's chamfers,
    graded templates, and a pillow layer, whose copies share their nodes' lattice indices."""
    from dicer.connectivity import fix_connectivity
    from dicer.mesh.merge import merge_mesh
    from dicer.mesh.smooth import smooth_mesh

    rng = np.random.default_rng(seed)
    shape = (14, 12, 10)[:dim]
    g = np.meshgrid(*[np.arange(s) + 0.5 for s in shape], indexing="ij")
    r = np.sqrt(sum((x - s / 2 - rng.uniform(-1, 1)) ** 2 for x, s in zip(g, shape)))
    labels = (r < rng.uniform(3.0, 5.0)).astype(np.uint8) + (r < rng.uniform(1.0, 2.5)).astype(np.uint8)
    labels[rng.random(shape) < 0.03] = 0
    labels, _ = fix_connectivity(labels)
    mesh = voxel_mesh(labels)
    if kind in ("planes", "templates"):
        mesh, _ = merge_mesh(mesh, {"method": kind})
    elif kind == "pillow":
        mesh, _ = smooth_mesh(mesh, {"pillow": True})
    cells = np.asarray(mesh.cells, np.int64)
    edges, index, along_lines = quadratic.edges_by_lattice(mesh, cells)
    table = HEX_EDGES if dim == 3 else QUAD_EDGES
    a, b = cells[:, table[:, 0]], cells[:, table[:, 1]]
    assert np.array_equal(edges[index, 0], np.minimum(a, b)) and np.array_equal(edges[index, 1], np.maximum(a, b))
    pairs, _ = quadratic.mesh_edges(cells, mesh.n_points)
    assert edges.shape == pairs.shape and np.array_equal(np.unique(edges, axis=0), pairs)
    assert np.array_equal(np.unique(index), np.arange(edges.shape[0]))
    assert along_lines == np.array_equal(*_box_edges(mesh, table))
    assert along_lines or kind != "voxels"


def _box_edges(mesh, table):
    """Each element edge's lattice axis, and the axis its slot has in a box element."""
    from dicer.mesh.topology import HEX_EDGE_AXES, QUAD_EDGE_AXES

    step = mesh.lattice[mesh.cells[:, table[:, 1]]] - mesh.lattice[mesh.cells[:, table[:, 0]]]
    axis = np.where(np.count_nonzero(step, axis=2) == 1, np.argmax(step != 0, axis=2), -1)
    return axis, np.broadcast_to(HEX_EDGE_AXES if mesh.dim == 3 else QUAD_EDGE_AXES, axis.shape)


def test_arcs_keep_mid_edge_nodes_of_bounding_plane_edges_on_the_plane():
    """A quarter disc, merged and smoothed: an edge lying in a cut plane stays in it; an
    edge meeting the plane continues through its mirror image (the whole disc's edge)."""
    from dicer.mesh.boundary import plane_bits
    from dicer.mesh.merge import merge_mesh
    from dicer.mesh.smooth import smooth_mesh
    from dicer.mesh.faces import neighbour_materials

    g = np.arange(40) + 0.5
    r = np.hypot(*np.meshgrid(g, g, indexing="ij"))
    merged, _ = merge_mesh(voxel_mesh(((r >= 9.3) & (r < 31.0)).astype(np.uint8)), {})
    mesh, _ = smooth_mesh(merged, load_config().get("smooth"))
    cells = np.asarray(mesh.cells, np.int64)
    edges, index = quadratic.mesh_edges(cells, mesh.n_points)
    nb = neighbour_materials(mesh)
    faces = nb != mesh.material[:, None].astype(nb.dtype)
    boundary = quadratic._boundary_edges(mesh, edges, index, faces)
    mid = quadratic.arc_midpoints(mesh, edges, index, faces)
    straight = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
    bits = plane_bits(mesh)
    in_plane = (bits[edges[:, 0]] & bits[edges[:, 1]]) != 0
    assert in_plane.sum() > 20 and np.array_equal(mid[in_plane], straight[in_plane])
    # the hole's rim put onto its circle: the rim's mid-edge nodes lie on it too, those
    # next to a cut plane by the mirror image of their neighbour
    rim_edges = np.flatnonzero(boundary & ~in_plane & (np.hypot(*straight[:, :2].T) < 12))
    rim = np.unique(edges[rim_edges])
    d = mesh.points[rim, :2]
    mesh.points[rim, :2] = 9.3 * d / np.hypot(*d.T)[:, None]
    mid = quadratic.arc_midpoints(mesh, edges, index, faces)
    straight = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
    assert rim_edges.size >= 8
    assert np.abs(np.hypot(*mid[rim_edges, :2].T) - 9.3).max() < 1e-9
    assert np.hypot(*straight[rim_edges, :2].T).max() < 9.3 - 0.01


def test_quadratic_quads():
    mesh = voxel_mesh(np.ones((3, 2), np.uint8), spacing=(1.0, 2.0))
    points, cells, _ = quadratic_mesh(mesh)
    assert cells.shape == (6, 8) and points.shape[0] == 12 + 17
    ends = cells[:, QUAD_EDGES]
    assert np.allclose(points[cells[:, 4:]], 0.5 * (points[ends[..., 0]] + points[ends[..., 1]]))


def test_quadratic_node_sets_include_mid_edge_nodes(mesh, labels):
    model = prepare_model(mesh, cfg(order=2))
    # the X0 plane holds its corner nodes and the mid-edge nodes between them
    x0 = model.node_sets["X0"]
    assert np.all(model.points[x0, 0] < -0.9) and np.all(np.isin(np.flatnonzero(mesh.lattice[:, 0] == 0), x0))
    inter = model.node_sets["soft_tissue_bone"]
    corners = inter[inter < mesh.n_points]
    # the bone sits on 3 x 2 voxel faces: 4 x 3 corners, 3 x 3 + 2 x 4 mid-edge nodes
    assert corners.size == 12 and inter.size == 12 + 17


# --- Abaqus order 2 ---------------------------------------------------------------------------


def test_abaqus_quadratic_deck_round_trip(tmp_path, mesh):
    info = export_mesh(mesh, tmp_path / "m.inp", cfg(order=2, element_type="C3D20R"))
    text = (tmp_path / "m.inp").read_text()
    assert "*ELEMENT, TYPE=C3D20R, ELSET=bone" in text
    body = text.split("*ELEMENT, TYPE=C3D20R, ELSET=soft_tissue\n")[1].split("*")[0].splitlines()
    assert all(line.endswith(",") and len(line.split(",")) == 17 for line in body[0::2])  # 16 entries + comma
    assert all(len(line.split(",")) == 5 for line in body[1::2])
    m = meshio.read(tmp_path / "m.inp")
    model = prepare_model(mesh, cfg(order=2))
    assert m.cells[0].type == "hexahedron20" and len(m.points) == info["nodes"] == model.n_points
    assert np.allclose(m.points, model.points, rtol=1e-8, atol=1e-8)


# --- PATRAN neutral ---------------------------------------------------------------------------


@pytest.mark.parametrize("order", [1, 2])
def test_patran_round_trip(tmp_path, mesh, order):
    info = export_mesh(mesh, tmp_path / "m.out", cfg(order=order), source="scan.nii")
    got = read_patran(tmp_path / "m.out")
    model = prepare_model(mesh, cfg(order=order))
    assert info["nodes"] == got["points"].shape[0] == model.n_points
    assert np.allclose(got["points"], model.points, rtol=1e-8, atol=1e-9)
    assert np.array_equal(got["cells"], model.cells) and np.array_equal(got["material"], mesh.material)
    assert got["title"].startswith("dicer ") and "scan.nii" not in got["title"]
    # the file holds no node sets or faces (packets 25, 26, 01, 02, 21, 99): its summary listed them
    assert "node_sets" not in info and "exterior_faces" not in info


def test_patran_cards_and_20_node_order(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.neu", cfg(order=2, midside_nodes="midpoint"))
    lines = (tmp_path / "m.neu").read_text().splitlines()
    assert lines[0] == "25       0       0       1       0       0       0       0       0"
    n_nodes, n_elems = int(lines[2][26:34]), int(lines[2][34:42])
    coords = np.array([[float(lines[4 + 3 * i + 1][16 * j : 16 * j + 16]) for j in range(3)]
                       for i in range(n_nodes)])
    assert all(len(lines[4 + 3 * i + 1]) == 48 for i in range(n_nodes))
    assert all(re.fullmatch(r"[ -]0\.\d{9}E[+-]\d\d", lines[5][k : k + 16]) for k in (0, 16, 32))  # E16.9
    first = 4 + 3 * n_nodes
    for e in range(n_elems):
        head = lines[first + 4 * e]
        assert head[:2] == " 2" and int(head[2:10]) == e + 1 and int(head[10:18]) == 8 and int(head[18:26]) == 3
        card1 = lines[first + 4 * e + 1]
        assert int(card1[0:8]) == 20 and int(card1[16:24]) == mesh.material[e]
        ids = [int(line[k : k + 8]) for line in lines[first + 4 * e + 2 : first + 4 * e + 4]
               for k in range(0, len(line), 8)]
        xyz = coords[np.array(ids) - 1]
        for m, (a, b) in enumerate(PATRAN_HEX20_EDGES):
            # each mid-edge node lies between the corners PATRAN's order gives it
            assert np.allclose(xyz[8 + m], 0.5 * (xyz[a - 1] + xyz[b - 1]), atol=1e-8)
    assert lines[-1].startswith("99")


def test_patran_reader_is_strict(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "m.out", cfg())
    text = (tmp_path / "m.out").read_text()
    (tmp_path / "cut.out").write_text(text[: len(text) // 2])
    with pytest.raises(DicerError):
        read_patran(tmp_path / "cut.out")
    lines = text.splitlines(keepends=True)
    lines[5] = lines[5][:20] + "x" + lines[5][21:]
    (tmp_path / "bad.out").write_text("".join(lines))
    with pytest.raises(DicerError, match="not a number"):
        read_patran(tmp_path / "bad.out")
    lines = text.splitlines(keepends=True)
    lines[7] = lines[7][:18] + "       3" + lines[7][26:]  # second node packet claims three cards
    (tmp_path / "kc.out").write_text("".join(lines))
    with pytest.raises(DicerError, match="node header fields"):
        read_patran(tmp_path / "kc.out")


def test_patran_two_dimensional(tmp_path):
    mesh = voxel_mesh(np.array([[1, 2], [1, 1]], np.uint8), spacing=(0.5, 0.5))
    for order in (1, 2):
        export_mesh(mesh, tmp_path / f"p{order}.out", cfg(order=order))
        got = read_patran(tmp_path / f"p{order}.out")
        assert got["dim"] == 2 and got["cells"].shape == (4, 4 * order)


# --- LS-DYNA keyword --------------------------------------------------------------------------


def test_lsdyna_round_trip(tmp_path, mesh):
    config = load_config(settings={"materials": [
        {"name": "soft_tissue", "youngs_modulus": 1.25, "poissons_ratio": 0.45, "density": 1.05e-9},
        {"name": "bone", "youngs_modulus": 17123.5, "poissons_ratio": 0.3, "density": 1.9e-9}]})
    info = export_mesh(mesh, tmp_path / "m.k", config)
    got = read_lsdyna(tmp_path / "m.k")
    model = prepare_model(mesh, config)
    assert np.allclose(got["points"], mesh.points, rtol=1e-8, atol=1e-9)
    assert np.array_equal(got["cells"], mesh.cells) and np.array_equal(got["material"], mesh.material)
    assert got["parts"][2]["title"] == "bone" and got["materials"][2] == (1.9e-9, 17123.5, 0.3)
    assert got["sections"] == {1: 2, 2: 2}
    assert sorted(got["node_sets"]) == sorted(model.node_sets) == sorted(info["node_sets"])
    for name, ids in model.node_sets.items():
        assert np.array_equal(got["node_sets"][name], ids)
    lines = (tmp_path / "m.k").read_text().splitlines()
    element_lines = lines[lines.index("*ELEMENT_SOLID") + 2 :][: mesh.n_cells]
    assert all(len(line) == 80 for line in element_lines)


def test_lsdyna_material_constants_keep_the_digits_their_fields_hold_and_rounding_is_warned_of(tmp_path, mesh,
                                                                                                caplog):
    # density 1.987654321e-9 was printed 1.9877e-09 (5 digits) without a word; the .inp keeps all
    config = load_config(settings={"materials": [
        {"name": "soft_tissue", "youngs_modulus": 17654.321987, "poissons_ratio": 0.45, "density": 1.987654321e-9},
        {"name": "bone", "youngs_modulus": 17123.5, "poissons_ratio": 0.3, "density": 1.9e-9}]})
    caplog.set_level("WARNING", logger="dicer")
    export_mesh(mesh, tmp_path / "m.k", config)
    got = read_lsdyna(tmp_path / "m.k")["materials"]
    assert got[1] == (1.98765e-9, 17654.322, 0.45) and got[2] == (1.9e-9, 17123.5, 0.3)
    warned = [r.getMessage() for r in caplog.records if "*MAT_ELASTIC" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("export: m.k: LS-DYNA's 10-column *MAT_ELASTIC fields round ")
    assert "soft_tissue density 1.987654321e-09 as 1.98765e-09" in warned[0] and "youngs" not in warned[0]
    assert "*MAT_ELASTIC\n$#     mid        ro         e        pr\n         11.98765e-9 17654.322      0.45\n" in (
        tmp_path / "m.k").read_text()


def test_lsdyna_element_formulation_and_limits(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "r.k", cfg(element_type="C3D8R"))
    assert set(read_lsdyna(tmp_path / "r.k")["sections"].values()) == {1}
    with pytest.raises(DicerError, match="8-node hexahedra only"):
        export_mesh(mesh, tmp_path / "q.k", cfg(order=2))
    assert not (tmp_path / "q.k").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["r.k"]


# --- VTU and Gmsh -----------------------------------------------------------------------------


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), dim=st.sampled_from([2, 3]), curved=st.booleans())
def test_quadratic_vtu_reads_back_as_meshio_reads_it(tmp_path_factory, seed, dim, curved):
    """dicer writes order-2 VTU itself (zlib blocks, VTK's types 25 and 23): meshio reads
    the same nodes, cells, materials, corner quality and material names the model holds."""
    from dicer.export.vtu import check_vtu
    from dicer.io.meshes import read_raw_vtu

    rng = np.random.default_rng(seed)
    lab = rng.integers(0, 3, tuple(rng.integers(2, 6, dim))).astype(np.uint8)
    lab.flat[0] = 1
    m = voxel_mesh(lab)
    m.points[:, :dim] += rng.uniform(-0.15, 0.15, (m.n_points, dim))
    config = cfg(order=2, midside_nodes="curved" if curved else "midpoint")
    path = tmp_path_factory.mktemp("q") / "q.vtu"
    export_mesh(m, path, config)
    model = prepare_model(m, config)
    k = 20 if dim == 3 else 8
    ref = meshio.read(path)
    assert ref.cells[0].type == ("hexahedron20" if dim == 3 else "quad8") and ref.cells[0].data.shape == (m.n_cells, k)
    assert np.array_equal(ref.points, model.points) and np.array_equal(ref.cells[0].data, model.cells)
    assert np.array_equal(ref.cell_data["material"][0], m.material)
    corners = quality_arrays(model.points, model.cells[:, :8 if dim == 3 else 4])
    for key, want in corners.items():
        assert np.array_equal(ref.cell_data[key][0], want, equal_nan=True)
    assert {name: list(v) for name, v in ref.field_data.items()} == {
        name: [label, dim] for label, name in enumerate(model.name_list(), start=1)}
    cell_type, points, cells, *_ = read_raw_vtu(path, str(path))
    assert cell_type == ref.cells[0].type and np.array_equal(cells, model.cells)
    check_vtu(path, model)


@pytest.mark.parametrize("what", ["points", "cells", "scaled_jacobian"])
def test_quadratic_vtu_check_finds_one_changed_value(tmp_path, monkeypatch, mesh, what):
    """dicer's own read-back of an order-2 file (the only one past 20,000 elements) finds one
    changed ulp or one swapped pair of nodes."""
    import dicer.export.vtu as vtu
    from dicer.export.vtu import check_vtu

    monkeypatch.setattr(vtu, "MESHIO_CHECK_CELLS", 0)  # as for a large model: no meshio read

    config = cfg(order=2)
    export_mesh(mesh, tmp_path / "q.vtu", config)
    model = prepare_model(mesh, config)
    check_vtu(tmp_path / "q.vtu", model)
    model.cell_data.update(quality_arrays(model.points, model.cells[:, :8]))
    if what == "points":
        model.points = model.points.copy()
        model.points[mesh.n_points + 3, 1] = np.nextafter(model.points[mesh.n_points + 3, 1], 9.0)  # a mid-edge node
    elif what == "cells":
        model.cells = model.cells.copy()
        model.cells[2, [8, 9]] = model.cells[2, [9, 8]]
    else:
        model.cell_data[what] = model.cell_data[what].copy()
        model.cell_data[what][4] = np.nextafter(model.cell_data[what][4], 2.0)
    with pytest.raises(DicerError, match={"points": "coordinates", "cells": "connectivity",
                                          "scaled_jacobian": "scaled_jacobian"}[what]):
        check_vtu(tmp_path / "q.vtu", model)


@pytest.mark.parametrize("dim", [2, 3])
def test_vtks_own_reader_reads_the_quadratic_vtu(tmp_path, mesh, dim):
    """ParaView's reader (VTK's vtkXMLUnstructuredGridReader) takes dicer's order-2 file:
    its cell types, node count per cell, connectivity and materials."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    m = mesh if dim == 3 else voxel_mesh(np.array([[1, 1, 2], [2, 2, 1]], np.uint8))
    config = cfg(order=2, midside_nodes="curved")
    export_mesh(m, tmp_path / "q.vtu", config)
    model = prepare_model(m, config)
    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(tmp_path / "q.vtu"))
    reader.Update()
    grid = reader.GetOutput()
    k = 20 if dim == 3 else 8
    assert grid.GetNumberOfCells() == m.n_cells and grid.GetNumberOfPoints() == model.n_points
    assert set(vtk_to_numpy(grid.GetCellTypes() if hasattr(grid, "GetCellTypes") else grid.GetCellTypesArray()).tolist()) == {25 if dim == 3 else 23}
    assert np.array_equal(vtk_to_numpy(grid.GetCells().GetConnectivityArray()).reshape(-1, k), model.cells)
    assert np.array_equal(vtk_to_numpy(grid.GetPoints().GetData()), model.points)
    assert np.array_equal(vtk_to_numpy(grid.GetCellData().GetArray("material")), m.material)


def test_vtu_quadratic_and_gmsh(tmp_path, mesh):
    export_mesh(mesh, tmp_path / "q.vtu", cfg(order=2))
    m = meshio.read(tmp_path / "q.vtu")
    assert m.cells[0].type == "hexahedron20"
    assert np.array_equal(np.concatenate(m.cell_data["material"]), mesh.material)
    assert np.concatenate(m.cell_data["scaled_jacobian"]).min() > 0.5
    info = export_mesh(mesh, tmp_path / "m.msh", cfg())
    # the file holds materials, no node sets or faces: its summary says none either
    assert "node_sets" not in info and "exterior_faces" not in info
    g = meshio.read(tmp_path / "m.msh")
    assert np.array_equal(g.cells[0].data, mesh.cells)
    assert np.array_equal(np.concatenate(g.cell_data["gmsh:physical"]), mesh.material)


def test_gmsh_opens_the_msh_and_lists_the_material_names(tmp_path, mesh):
    gmsh = pytest.importorskip("gmsh", reason="gmsh is in the test extras: pip install -e '.[test]'")
    export_mesh(mesh, tmp_path / "m.msh", cfg())
    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(tmp_path / "m.msh"))
        groups = gmsh.model.getPhysicalGroups(3)
        names = {tag: gmsh.model.getPhysicalName(dim, tag) for dim, tag in groups}
        counts = {}
        for dim, tag in groups:
            for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
                types, elements, _ = gmsh.model.mesh.getElements(dim, entity)
                counts[tag] = counts.get(tag, 0) + sum(len(e) for e in elements)
        _, node_coords, _ = gmsh.model.mesh.getNodes()
    finally:
        gmsh.finalize()
    assert names == {1: "soft_tissue", 2: "bone"}
    assert counts == {1: int(np.sum(mesh.material == 1)), 2: int(np.sum(mesh.material == 2))}
    assert node_coords.size == mesh.points.size


@pytest.mark.parametrize("name", ["m.inp", "m.out", "m.k", "m.vtu", "m.msh", "m.exo", "m.feb"])
def test_every_format_reruns_byte_identical(tmp_path, mesh, name):
    a, b = tmp_path / "a", tmp_path / "b"
    for folder in (a, b):
        export_mesh(mesh, folder / name, cfg(), source="scan.nii")
    assert (a / name).read_bytes() == (b / name).read_bytes()


@settings(max_examples=60, deadline=None)
@given(groups=st.lists(st.integers(0, 6), min_size=1, max_size=40),
       values=st.lists(st.sampled_from([-1.0, -0.5, 0.0, 0.5, float("nan")]), min_size=40, max_size=40),
       runs=st.booleans())
def test_first_smallest_of_each_group_is_lexsorts_first(groups, values, runs):
    """The arcs' choice of continuation (the most nearly opposite edge) equals the lexsort it
    replaced: the smallest value per group, the first on ties, NaN last."""
    group = np.array(sorted(groups) if runs else groups, np.int64)
    value = np.array(values[:group.size])
    assert quadratic._first_smallest(group[:0], value[:0]).size == 0
    got = quadratic._first_smallest(group, value)
    first = np.lexsort((value, group))
    want = first[np.r_[True, group[first][1:] != group[first][:-1]]]
    assert np.array_equal(got, want)
