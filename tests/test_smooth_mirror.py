"""Bounding planes as mirrors: smoothing a cut model gives what smoothing the whole model
gives, restricted to the part."""

import numpy as np
import pytest

from dicer.config import preset_settings
from dicer.connectivity import fix_connectivity
from dicer.mesh import smooth as smooth_module
from dicer.image import Volume
from dicer.mesh.boundary import boundary_graph
from dicer.mesh.merge import merge_planes
from dicer.mesh.smooth import smooth_mesh
from dicer.mesh.voxel import voxel_mesh

WITHOUT_THE_LAYER = preset_settings("explicit-dynamics")["smooth"]
"""The settings some figures here were measured at: no pillow layer (the preset explicit-dynamics)."""


def shells(n, dim, layers):
    """An n^dim label image of concentric shells (r_in, r_out, material) about the
    image centre, a voxel corner: exactly symmetric about the mid planes."""
    g = np.arange(n) + 0.5 - n / 2
    r = np.sqrt(sum(x**2 for x in np.meshgrid(*([g] * dim), indexing="ij")))
    lab = np.zeros((n,) * dim, np.uint8)
    for lo, hi, mat in layers:
        lab[(r >= lo) & (r < hi)] = mat
    return lab


def node_index(mesh):
    """Lookup array: lattice (i, j, k) -> node number (-1: none)."""
    shape = tuple(int(s) + 1 for s in mesh.grid_shape)
    table = np.full(shape, -1, np.int64)
    table[tuple(mesh.lattice.T)] = np.arange(mesh.n_points)
    return table


def layer_copies(part, n_part, full, n_full, offset):
    """The full model's rows of the part's pillow-layer copies (nodes from ``n_part`` on; -1:
    none): the copy of the same lattice node nearest to each, and the part's copies must be as
    many as the full model's within the part (a copy one side has and the other has not either
    fails that count or lies an eighth of a voxel or more from the nearest other)."""
    from scipy.spatial import cKDTree

    lattice = part.lattice[n_part:] + offset
    held = np.all(full.lattice[n_full:] >= offset, axis=1)
    copies = n_full + np.flatnonzero(held)
    assert copies.size == lattice.shape[0]
    if copies.size == 0:
        return np.zeros(0, np.int64)
    shift = offset * part.spacing
    _, nearest = cKDTree(full.points[copies]).query(part.points[n_part:] + shift)
    rows = copies[nearest]
    same_node = np.all(full.lattice[rows] == lattice, axis=1)
    return np.where(same_node, rows, -1)


def mirror_asymmetry(mesh, out, axes):
    """Largest change of the smoothed nodes under reflection across each mid plane."""
    table = node_index(mesh)
    worst = 0.0
    for a in axes:
        n = int(mesh.grid_shape[a])
        lat = mesh.lattice.copy()
        lat[:, a] = n - lat[:, a]
        nodes = out.points[: mesh.n_points]  # the layer's copies: compared by cut_versus_full
        image = nodes[table[tuple(lat.T)]].copy()
        image[:, a] = n * mesh.spacing[a] - image[:, a]
        worst = max(worst, float(np.abs(image - nodes).max()))
    return worst


def cut_versus_full(lab, cut_axes, settings=None, merged=False):
    """Smooth the full model and its part beyond the mid planes normal to ``cut_axes``;
    (part's max difference from the full model's nodes, full model's asymmetry, reports).
    ``merged``: plane-merged meshes, smoothed with their label volumes (as ``dicer run`` does)."""
    half = [int(s) // 2 for s in lab.shape]
    part_lab = lab[tuple(slice(half[a], None) if a in cut_axes else slice(None) for a in range(lab.ndim))]
    meshes, smoothed = [], []
    for image in (lab, part_lab):
        mesh = voxel_mesh(image)
        if merged:
            mesh, _ = merge_planes(mesh, passes=(1, 1, 1))
        meshes.append(mesh)
        smoothed.append(smooth_mesh(mesh, settings or {}, labels=Volume(image, (1.0,) * image.ndim) if merged else None))
    (full_mesh, part_mesh), ((full, rep_full), (part, rep_part)) = meshes, smoothed
    offset = np.zeros(3, np.int64)
    offset[list(cut_axes)] = [half[a] for a in cut_axes]
    rows = np.concatenate([node_index(full_mesh)[tuple((part_mesh.lattice + offset).T)],
                           layer_copies(part, part_mesh.n_points, full, full_mesh.n_points, offset)])
    assert np.all(rows >= 0)
    diff = float(np.abs(part.points + offset * part_mesh.spacing - full.points[rows]).max())
    same_classes = np.array_equal(part.point_data["node_class"], full.point_data["node_class"][rows])
    return diff, same_classes, mirror_asymmetry(full_mesh, full, cut_axes), rep_full, rep_part


DISC = [(7.3, 11.2, 1), (11.2, 15.6, 2)]  # a disc with a hole, two materials
BALL = [(5.2, 8.1, 2), (8.1, 12.3, 1)]  # a ball with a cavity, two materials


@pytest.fixture(scope="module")
def disc():
    lab = shells(40, 2, DISC)
    fixed, _ = fix_connectivity(lab)
    assert np.array_equal(fixed, lab)  # nothing to fix: the image stays symmetric
    return lab


@pytest.fixture(scope="module")
def ball():
    lab = shells(32, 3, BALL)
    fixed, _ = fix_connectivity(lab)
    assert np.array_equal(fixed, lab)
    return lab


@pytest.mark.parametrize("cut", [(0,), (0, 1)], ids=["half", "quarter"])
def test_2d_quarter_smooths_like_the_whole_disc(disc, cut):
    diff, same_classes, asym, rep_full, rep_part = cut_versus_full(disc, cut)
    assert asym < 1e-7  # measured 1.9e-8: the whole model smooths symmetrically
    assert diff < 1e-6  # measured 1.3e-7 (quarter), with the labels' fit (the default)
    assert same_classes
    # same solves: the same conjugate-gradient iterations, the same back-off
    assert rep_part["boundary_iterations"] == rep_full["boundary_iterations"] == 37
    assert rep_part["backoff_rounds"] == rep_full["backoff_rounds"] == 0
    labels = cut_versus_full(disc, cut, {"surface_from_labels": False, "min_scaled_jacobian": 0.2})
    assert labels[0] < 1e-6 and labels[3]["backoff_rounds"] == labels[4]["backoff_rounds"] == 1  # measured 2.5e-7
    assert rep_part["bounding_planes"] == "mirror"


@pytest.mark.parametrize("cut", [(0,), (0, 1), (0, 1, 2)], ids=["half", "quarter", "octant"])
def test_3d_octant_smooths_like_the_whole_ball(ball, cut):
    diff, same_classes, asym, rep_full, rep_part = cut_versus_full(ball, cut)
    assert asym < 1e-6  # measured 1.6e-7
    assert diff < 1e-6  # measured 2.4e-7 (octant)
    assert same_classes
    assert rep_part["boundary_iterations"] == rep_full["boundary_iterations"]
    assert rep_part["interior_iterations"] == rep_full["interior_iterations"]


@pytest.mark.parametrize("depth", [0, 2], ids=["disc", "tube"])
def test_merged_quarter_fitted_to_its_labels_smooths_like_the_whole(disc, depth):
    """dicer run's chain: plane merging, then the fit to the label volume. A merged element at
    a mirror plane is two voxels long, so its node's normal (towards the element) lies mostly
    in the plane; the mirrored model's images add up its one free component (until 6 December
    2026 the quarter's rim nodes on the planes were left where the labels' smoothing put them,
    0.43 voxel inside the hole of a tube with a = 7 that the whole tube fits)."""
    lab = disc if depth == 0 else np.repeat(disc[:, :, None], depth, axis=2)
    diff, same_classes, asym, rep_full, rep_part = cut_versus_full(lab, (0, 1), merged=True)
    assert rep_part["surface_from_labels"]["nodes_moved"] > 0
    assert diff < 1e-6  # measured 1.4e-7 (tube), 1.8e-7 (disc)
    assert asym < 1e-6
    assert same_classes


def test_merged_octant_fitted_to_its_labels_smooths_like_the_whole_ball(ball):
    """dicer run's chain on the 32^3 ball with a cavity and its octant: merged (mirror images
    counted at the cut planes), fitted to the label volume, smoothed. Measured 2.2e-7 voxel;
    until the merge counted mirror images the octant's mesh had 6 nodes the whole ball's has
    not."""
    diff, same_classes, asym, rep_full, rep_part = cut_versus_full(ball, (0, 1, 2), merged=True)
    assert rep_part["surface_from_labels"]["nodes_moved"] > 0
    assert diff < 1e-6 and asym < 1e-6
    assert same_classes


def merged_corners(lab, cuts):
    """Corner lattice points of every element of the merged model of ``lab`` (set of tuples),
    and of the merged part beyond its mid planes normal to ``cuts``, in the whole's frame."""
    half = [int(s) // 2 for s in lab.shape]
    part = lab[tuple(slice(half[a], None) if a in cuts else slice(None) for a in range(lab.ndim))]
    offset = np.zeros(3, np.int64)
    offset[list(cuts)] = [half[a] for a in cuts]
    whole, _ = merge_planes(voxel_mesh(lab), passes=(1,) * lab.ndim)
    cut, _ = merge_planes(voxel_mesh(part), passes=(1,) * lab.ndim)
    inside = np.all(whole.lattice[whole.cells][:, :, list(cuts)] >= offset[list(cuts)], axis=(1, 2))
    return ({tuple(map(tuple, e)) for e in whole.lattice[whole.cells[inside]]},
            {tuple(map(tuple, e)) for e in cut.lattice[cut.cells] + offset})


@pytest.mark.parametrize("cut", [(0,), (0, 1)], ids=["half", "quarter"])
def test_merged_quarter_is_the_whole_disc_merged(disc, cut):
    whole, part = merged_corners(disc, cut)
    assert whole == part


@pytest.mark.parametrize("cut", [(0,), (0, 1, 2)], ids=["half", "octant"])
def test_merged_octant_is_the_whole_ball_merged(ball, cut):
    # the merge's checks count the mirror images at a bounding plane (until 6 December 2026
    # the octant kept 6 of 758 rim nodes a lattice step off the cut planes that the whole
    # ball's merge moves onto them: it saw 6 of a plane node's 7 neighbours)
    whole, part = merged_corners(ball, cut)
    assert whole == part


STATIC_STRESS = {"label_samples": "relaxed", "pillow": True, "label_surface_radius": 7}  # the preset's smoothing


@pytest.mark.parametrize("settings", [{"label_samples": "relaxed"}, STATIC_STRESS], ids=["relaxed", "static-stress"])
def test_a_cut_staircase_relaxed_smooths_like_the_whole(disc, ball, settings):
    """A label volume's staircase relaxed within its voxels (smooth.label_samples: relaxed), the
    static-stress preset's pillow layer over it: the quarter disc, the quarter tube and the
    octant of the ball get the whole models' nodes, layer copies too. Measured 1.7e-7 (disc)
    and 2.3e-7 voxel (ball); until the relaxation took the mirrors as an endless staircase
    (8 voxels of reflected labels before) 0.046 and 0.139 voxel."""
    for lab, cuts in ((disc, (0, 1)), (np.repeat(disc[:, :, None], 2, axis=2), (0, 1)), (ball, (0, 1, 2))):
        diff, same_classes, asym, rep_full, rep_part = cut_versus_full(lab, cuts, settings, merged=True)
        assert rep_part["surface_from_labels"]["nodes_moved"] > 0
        assert diff < 1e-6 and asym < 1e-6
        assert same_classes
        if settings.get("pillow"):
            assert rep_part["pillow"]["elements"] > 0


def test_free_and_fixed_planes_do_not_mirror(ball, disc):
    # the former behaviour (free) and held planes (fixed) smooth the cut face as a surface.
    # Measured without the pillow layer (the preset explicit-dynamics): with it a free cut face
    # gets a layer the whole model has not
    diff, same_classes, *_ = cut_versus_full(disc, (0, 1), {**WITHOUT_THE_LAYER, "bounding_planes": "free"})
    assert diff > 0.3 and not same_classes
    diff, same_classes, *_ = cut_versus_full(ball, (0, 1, 2), {**WITHOUT_THE_LAYER, "bounding_planes": "fixed"})
    assert diff > 0.2 and not same_classes


def test_graph_interior_solve_mirrors_alike(ball, monkeypatch):
    # the interior solve of graded meshes (from element edges) mirrors like the lattice one
    part = voxel_mesh(ball[16:, 16:, 16:])
    lattice, _ = smooth_mesh(part, {})
    monkeypatch.setattr(smooth_module, "is_graded", lambda mesh: True)
    graph, rep = smooth_mesh(part, {})
    assert rep["interior_nodes_solved"] > 0
    assert np.abs(graph.points - lattice.points).max() < 1e-6


def test_plane_nodes_inside_a_material_are_interior(ball):
    part = voxel_mesh(ball[16:, 16:, 16:])
    on_plane = np.any(part.points == 0, axis=1)
    mirrored = boundary_graph(part, mirror=True)
    cut = boundary_graph(part)
    assert cut.boundary[on_plane].all()  # without mirrors the cut face is a surface
    # with mirrors only the cavity's and the ball's outlines and the interface stay boundary
    assert 0 < mirrored.boundary[on_plane].sum() < 0.5 * on_plane.sum()
    assert mirrored.node_class.max() < 7  # every boundary node in a class A-F


def kirsch_quarter(n=40, a=7.0):
    g = np.arange(n) + 0.5
    return (np.sqrt(g[:, None] ** 2 + g[None, :] ** 2) >= a).astype(np.uint8)  # hole about the corner


def test_kirsch_quarter_plate_rim_stays_on_the_hole():
    lab = kirsch_quarter()
    fixed, _ = fix_connectivity(lab)
    assert np.array_equal(fixed, lab)
    m = voxel_mesh(lab)
    rim = np.concatenate([np.flatnonzero(np.all(m.points[:, :2] == p, axis=1)) for p in ([7.0, 0.0], [0.0, 7.0])])
    assert rim.size == 2  # on y = 0 and on x = 0
    # the labels' smoothing, without the pillow layer over it (the preset explicit-dynamics)
    out, _ = smooth_mesh(m, {**WITHOUT_THE_LAYER, "surface_from_labels": False, "min_scaled_jacobian": 0.2})
    r = np.linalg.norm(out.points[rim, :2], axis=1)
    assert np.abs(r - 7.0).max() < 0.01  # measured 7.0070 on both symmetry lines
    assert np.all(out.points[rim[0], 1:] == 0) and np.all(out.points[rim[1], [0, 2]] == 0)
    free, _ = smooth_mesh(m, {**WITHOUT_THE_LAYER, "bounding_planes": "free", "surface_from_labels": False})
    assert np.linalg.norm(free.points[rim, :2], axis=1).min() > 7.4  # measured 7.478: the corner rounds


def test_slabs_mirrored_at_both_faces_are_one_endless_prism(disc):
    # the low and high plane of an axis are two mirrors: slabs of the disc 1, 2 and 4 voxels
    # thick are all the same endless prism. At tolerance 1e-7 (at the default 1e-4 the
    # thicker slabs' slice-to-slice modes, seeded by rounding, leave up to 1e-4)
    layers = []
    for thickness in (1, 2, 4):
        m = voxel_mesh(np.repeat(disc[:, :, None], thickness, axis=2))
        # the labels' smoothing (the corner sharpening of the labels' fit treats a slab's inner
        # layers apart from its mirrored ones: up to 0.03 voxel between 1 and 4 voxels thick)
        out, rep = smooth_mesh(m, {"tolerance": 1e-7, "surface_from_labels": False})
        assert rep["node_classes"]["X"] == 0 and rep["node_classes"]["A"] == 0
        bottom = np.flatnonzero(m.lattice[:, 2] == 0)
        bottom = bottom[np.lexsort((m.lattice[bottom, 1], m.lattice[bottom, 0]))]
        layers.append((out.points[bottom, :2], out.point_data["node_class"][bottom]))
    for xy, cls in layers[1:]:
        assert np.abs(xy - layers[0][0]).max() < 1e-6  # measured 2.2e-7
        assert np.array_equal(cls, layers[0][1])


def test_chamfer_meeting_a_mirror_plane_keeps_its_rim_node_on_the_boundary():
    # merged 2D mesh: a chamfer runs from node (0, 2) on the plane x = 0 to (1, 0), so (0, 2)
    # holds two elements of one material (four, mirrored) yet lies on a boundary edge. The
    # merge, which counts mirror images at the image's planes, makes no such chamfer there:
    # merged with a background layer before x = 0, then the layer taken off (a mesh merged
    # elsewhere, or cut after merging)
    from dataclasses import replace

    merge = pytest.importorskip("dicer.mesh.merge")
    lab = np.zeros((5, 21), np.uint8)
    lab[1, 2:4] = [2, 1]
    lab[2, 1:3] = 2
    lab[3, 0:2] = 1
    lab[4, 20] = 1
    padded, _ = merge.merge_planes(voxel_mesh(lab), passes=(1, 1), axes=(0, 1, 2))
    lattice, points, grid = padded.lattice.copy(), padded.points.copy(), padded.grid_shape.copy()
    lattice[:, 0] -= 1
    points[:, 0] -= padded.spacing[0]
    grid[0] -= 1
    merged = replace(padded, points=points, lattice=lattice, grid_shape=grid)
    g = boundary_graph(merged, mirror=True)
    rim = np.flatnonzero(np.all(merged.points[:, :2] == [0.0, 2.0], axis=1))
    assert rim.size == 1 and g.boundary[rim[0]] and g.node_class[rim[0]] != 0
    out, rep = smooth_mesh(merged, {})
    assert rep["inverted_elements"] == 0 and rep["min_scaled_jacobian"] >= 0.2


def test_a_repeated_interior_solve_near_a_change_mirrors_alike(ball, monkeypatch):
    """A pull round's interior solve first solves near the nodes that moved (``_near_first``):
    an octant and the whole ball, moved alike, decide and solve alike."""
    monkeypatch.setattr(smooth_module, "_NEAR_HOPS", 2)  # a small ball's band: 12 edges reach more than an eighth of it
    settings = smooth_module.smoothing_settings({})
    full_mesh, part_mesh = voxel_mesh(ball), voxel_mesh(ball[16:, 16:, 16:])
    near_iterations = []
    solved = {}
    for name, mesh, centre in (("full", full_mesh, 16.0), ("part", part_mesh, 0.0)):
        st = smooth_module._set_up(mesh, settings, None, 0.0, 0.0)
        rel = st.xb0 - centre
        r = np.linalg.norm(rel, axis=1)
        ub = 0.05 * np.sin(r)[:, None] * rel  # radial: alike under the mirrors
        u1, _ = st.interior.solve(ub, settings["tolerance"])
        spot = np.array([4.0, 6.0, 9.0])  # a patch off the planes, in every octant of the whole
        moved = np.linalg.norm(np.abs(rel) - spot, axis=1) < 1.2
        ub2 = ub.copy()
        ub2[moved] += 0.3 * np.sign(rel[moved])
        first = smooth_module._Interior._near_first

        def near(self, b, x0, tol, apply):
            x, it = first(self, b, x0, tol, apply)
            near_iterations.append(it)
            return x, it

        smooth_module._Interior._near_first = near
        try:
            u2, it = st.interior.solve(ub2, settings["tolerance"], u1)
        finally:
            smooth_module._Interior._near_first = first
        solved[name] = (st.band_nodes, u2, it)
    assert len(near_iterations) == 2 and near_iterations[0] == near_iterations[1] > 0
    (band_f, u_f, it_f), (band_p, u_p, it_p) = solved["full"], solved["part"]
    assert it_f == it_p
    rows = node_index(full_mesh)[tuple((part_mesh.lattice[band_p] + 16).T)]
    at = np.full(full_mesh.n_points, -1)
    at[band_f] = np.arange(band_f.size)
    assert np.all(at[rows] >= 0)
    assert np.abs(u_p - u_f[at[rows]]).max() < 1e-6, np.abs(u_p - u_f[at[rows]]).max()  # voxels
