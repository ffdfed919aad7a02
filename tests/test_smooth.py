"""Boundary and interior smoothing with the quality guard: the measured acceptance figures.

These are the figures of the per-class smoothing itself, so every case here smooths without the
pillow layer that the defaults add over it (the preset explicit-dynamics' smooth settings;
the layer: tests/test_pillow.py).
"""

import numpy as np
import pytest

from dicer.connectivity import fix_connectivity
from dicer.errors import DicerError
from dicer.mesh.boundary import boundary_graph
from dicer.mesh.metrics import element_volumes, scaled_jacobian
from dicer.mesh.model import Mesh
from dicer.config import preset_settings
from dicer.mesh.smooth import DEFAULTS, smoothing_settings
from dicer.mesh.smooth import smooth_mesh as smooth_with_the_layer
from dicer.mesh.voxel import voxel_mesh

WITHOUT_THE_LAYER = preset_settings("explicit-dynamics")["smooth"]


def smooth_mesh(mesh, settings=None, **kwargs):
    """``dicer.mesh.smooth.smooth_mesh`` without the pillow layer (``settings`` laid over that)."""
    return smooth_with_the_layer(mesh, {**WITHOUT_THE_LAYER, **(settings or {})}, **kwargs)


CENTRE = np.array([20.31, 19.77, 20.13])  # off the lattice


def ball(n=40, radii=(16.3,), centre=CENTRE):
    g = np.arange(n) + 0.5
    r = np.sqrt((g[:, None, None] - centre[0]) ** 2 + (g[None, :, None] - centre[1]) ** 2
                + (g[None, None, :] - centre[2]) ** 2)
    lab = np.zeros((n, n, n), np.uint8)
    for i, rad in enumerate(radii):
        lab[r < rad] = i + 1
    lab, _ = fix_connectivity(lab)
    return voxel_mesh(lab)


@pytest.fixture(scope="module")
def sphere():
    m = ball()
    out, rep = smooth_mesh(m, {})
    return m, out, rep


@pytest.fixture(scope="module")
def nested():
    m = ball(radii=(16.3, 9.7))
    out, rep = smooth_mesh(m, {})
    return m, out, rep


def radial_error(points, nodes, radius):
    return float(np.abs(np.linalg.norm(points[nodes] - CENTRE, axis=1) - radius).mean())


def test_sphere_acceptance(sphere):
    m, out, rep = sphere
    g = boundary_graph(m)
    nodes = np.flatnonzero(g.boundary)
    before = radial_error(m.points, nodes, 16.3)
    after = radial_error(out.points, nodes, 16.3)
    assert 0.33 < before < 0.43  # the stair-stepped voxel surface
    assert after <= 0.15
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.3
    assert np.count_nonzero(sj <= 0) == 0
    v0 = element_volumes(m.points, m.cells).sum()
    v1 = element_volumes(out.points, out.cells).sum()
    assert abs(v1 - v0) / v0 <= 0.02
    assert rep["volume_change"] == pytest.approx((v1 - v0) / v0, abs=1e-9)
    assert rep["inverted_elements"] == 0 and rep["min_scaled_jacobian"] == pytest.approx(sj.min())
    # same topology, classes kept as point data
    assert np.array_equal(out.cells, m.cells) and np.array_equal(out.lattice, m.lattice)
    assert np.array_equal(out.point_data["node_class"], g.node_class)


def test_nested_spheres_acceptance(nested):
    m, out, rep = nested
    g = boundary_graph(m)
    d = np.linalg.norm(m.points - CENTRE, axis=1)
    outer = np.flatnonzero(g.boundary & (d > 13))
    inner = np.flatnonzero(g.boundary & (d < 13))
    # the interface is a boundary too, and is smoothed
    assert inner.size > 1000
    assert radial_error(m.points, inner, 9.7) > 0.3
    assert radial_error(out.points, inner, 9.7) <= 0.15
    assert radial_error(out.points, outer, 16.3) <= 0.15
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.3 and np.count_nonzero(sj <= 0) == 0
    for kind in (1, 2):
        sel = m.material == kind
        v0 = element_volumes(m.points, m.cells[sel]).sum()
        v1 = element_volumes(out.points, out.cells[sel]).sum()
        assert abs(v1 - v0) / v0 <= 0.02
        assert rep["volume_change_by_material"][str(kind)] == pytest.approx((v1 - v0) / v0, abs=1e-9)
    # conforming: both materials still share their interface nodes
    n1 = np.unique(out.cells[out.material == 1])
    n2 = np.unique(out.cells[out.material == 2])
    assert np.intersect1d(n1, n2).size == inner.size


def test_interior_nodes_follow_the_boundary(sphere):
    m, out, rep = sphere
    g = boundary_graph(m)
    moved = np.linalg.norm(out.points - m.points, axis=1)
    assert moved[~g.boundary].max() > 0.05
    assert rep["interior_nodes_solved"] > 0
    # interior node next to the boundary sits at the centroid of its neighbours (whole-interior solve)
    full, _ = smooth_mesh(m, {"interior_band": 0})
    sj = scaled_jacobian(full.points, full.cells)
    assert sj.min() >= 0.3


def test_bounding_planes_stay_flat():
    lab = np.zeros((20, 20, 12), np.uint8)
    g = np.arange(20) + 0.5
    r = np.sqrt((g[:, None] - 10.2) ** 2 + (g[None, :] - 9.7) ** 2)
    lab[r < 7.3, :] = 1  # a cylinder cut by the z = 0 and z = 12 planes
    lab, _ = fix_connectivity(lab)
    m = voxel_mesh(lab)
    out, rep = smooth_mesh(m, {})
    assert rep["bounding_planes"] == "mirror"
    on_lo = m.points[:, 2] == 0
    on_hi = m.points[:, 2] == 12
    assert on_lo.sum() > 100
    assert np.all(out.points[on_lo, 2] == 0) and np.all(out.points[on_hi, 2] == 12)
    assert np.abs(out.points[on_lo, :2] - m.points[on_lo, :2]).max() > 0.05  # they still move in the plane
    # mirrored at both planes the cylinder is endless: every slice smooths alike (to 4e-5
    # at the default tolerance: single-precision rounding seeds slice-to-slice modes that
    # the early-stopped CG does not damp; 2e-7 at tolerance 1e-7)
    order = np.lexsort((m.lattice[:, 1], m.lattice[:, 0], m.lattice[:, 2]))
    xy = out.points[order, :2].reshape(13, -1, 2)
    assert np.abs(xy - xy[0]).max() < 1e-4
    tight, _ = smooth_mesh(m, {"tolerance": 1e-7})
    xy = tight.points[order, :2].reshape(13, -1, 2)
    assert np.abs(xy - xy[0]).max() < 1e-6
    # free (the former default): the cut face is a surface of its own, its rim rounds off
    free, rep = smooth_mesh(m, {"bounding_planes": "free"})
    assert np.all(free.points[on_lo, 2] == 0)
    xy = free.points[order, :2].reshape(13, -1, 2)
    assert np.abs(xy - xy[6]).max() > 0.05
    loose, _ = smooth_mesh(m, {"bounding_planes": "free", "keep_bounding_planes": False})
    assert np.abs(loose.points[on_lo, 2]).max() > 0.01
    held, _ = smooth_mesh(m, {"bounding_planes": "fixed"})
    assert np.array_equal(held.points[on_lo | on_hi], m.points[on_lo | on_hi])
    assert np.abs(held.points - m.points).max() > 0.05
    with pytest.raises(DicerError, match="bounding_planes: free"):
        smooth_mesh(m, {"keep_bounding_planes": False})
    with pytest.raises(DicerError, match="smooth.bounding_planes.*not one of mirror, fixed, free"):
        smooth_mesh(m, {"bounding_planes": "periodic"})


def test_coefficients_control_the_motion():
    m = ball(n=24, radii=(8.3,), centre=np.array([12.2, 11.9, 12.1]))
    alone = {"surface_from_labels": False}  # the labels' smoothing: no fit to move the nodes besides
    still, rep = smooth_mesh(m, {"coefficient": 0.0, **alone})
    assert np.allclose(still.points, m.points)
    weak, _ = smooth_mesh(m, {"coefficient": 0.5, **alone})
    strong, _ = smooth_mesh(m, {"coefficient": 0.9, **alone})
    d_weak = np.linalg.norm(weak.points - m.points, axis=1).mean()
    d_strong = np.linalg.norm(strong.points - m.points, axis=1).mean()
    assert 0 < d_weak < d_strong
    s = smoothing_settings({"coefficient": 0.7, "coefficients": {"D": 0.2}})
    assert set(s["coefficients"].values()) == {0.7}
    s = smoothing_settings({"coefficients": {"D": 0.2}})
    assert s["coefficients"]["D"] == 0.2 and s["coefficients"]["A"] == DEFAULTS["coefficients"]["A"]


def test_one_coefficient_beside_a_coefficients_map_is_warned_of(tmp_path, caplog):
    from dicer.config import load_config, stage_kwargs

    said = "smooth.coefficient 0.7 is used for every node class, so the smooth.coefficients map given"
    s = smoothing_settings({"coefficient": 0.7, "coefficients": {"D": 0.2, "A": 0.5}})
    assert set(s["coefficients"].values()) == {0.7}
    assert caplog.text.count(said) == 1 and "given (A 0.5, D 0.2) is not used; leave smooth.coefficient out" \
        in caplog.text
    # a map at its defaults (as config/config.yaml spells them) loses nothing: no warning
    caplog.clear()
    s = smoothing_settings({"coefficient": 0.7, "coefficients": dict(DEFAULTS["coefficients"])})
    assert set(s["coefficients"].values()) == {0.7} and "smooth.coefficient" not in caplog.text
    smoothing_settings({"coefficients": {"D": 0.2}})
    assert "smooth.coefficient" not in caplog.text
    # the map in a config file, the one value from --set
    (tmp_path / "c.yaml").write_text("smooth:\n  coefficients: {E: 0.6}\n")
    config = load_config(tmp_path / "c.yaml", sets=["smooth.coefficient=0.7"])
    smoothing_settings(**stage_kwargs(config, "smooth"))
    assert caplog.text.count(said) == 1 and "given (E 0.6)" in caplog.text


def test_the_labels_surface_built_beside_the_classification_gives_the_same_mesh(monkeypatch):
    """With two cores the fit's surface is built in a thread while the nodes are classified;
    one core builds it first. The smoothed nodes are the same bit for bit, and a fault of the
    surface is raised where it is taken, not lost in the thread."""
    import dicer.parallel
    from dicer.image import Volume
    from dicer.mesh import labelsurface

    m = ball(n=24, radii=(9.3,), centre=CENTRE / 2)
    lab = np.zeros(m.grid_shape, np.uint8)
    lab[tuple(np.asarray(m.lattice)[np.asarray(m.cells)].min(axis=1).T)] = m.material
    out = {}
    for n in (2, 1):
        monkeypatch.setattr(dicer.parallel, "cores", lambda n=n: n)
        out[n] = smooth_mesh(m, {}, labels=Volume(lab, (1.0, 1.0, 1.0)))[0].points
    assert np.array_equal(out[1], out[2])

    def fails(*args, **kwargs):
        raise DicerError("the surface failed")

    monkeypatch.setattr(labelsurface, "LabelSurface", fails)
    for n in (2, 1):
        monkeypatch.setattr(dicer.parallel, "cores", lambda n=n: n)
        with pytest.raises(DicerError, match="the surface failed"):
            smooth_mesh(m, {})


def test_guard_backs_off_locally():
    m = ball(n=24, radii=(8.3,), centre=np.array([12.2, 11.9, 12.1]))
    out, rep = smooth_mesh(m, {"min_scaled_jacobian": 0.6})
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.6
    assert rep["backoff_rounds"] >= 1 and 0 < rep["backed_off_nodes"] < rep["boundary_nodes"]


def test_back_off_rounds_solve_the_boundary_from_the_last_round():
    """A back-off round changes a few coefficients: its boundary solves start from the last
    round's displacements (0 iterations from the solution itself) and end where a solve from
    zero ends, to the solver's tolerance, in fewer iterations."""
    from dicer.mesh.smooth import _BoundarySystem, _set_up

    m = ball(n=32, radii=(11.3,), centre=np.array([16.2, 15.9, 16.1]))
    st = _set_up(m, smoothing_settings({"surface_from_labels": False}), None, 0.0, 0.0)
    tol = st.s["tolerance"]
    d, _ = _BoundarySystem(st.adj, st.degree, st.k, st.fixed, st.weight).step(st.xb0, tol)
    same, it_same = _BoundarySystem(st.adj, st.degree, st.k, st.fixed, st.weight).step(st.xb0, tol, d)
    assert it_same == 0 and np.array_equal(same, d)
    k = st.k.copy()
    near = np.linalg.norm(st.xb0 - st.xb0[0], axis=1) < 3.0  # a back-off round: the nodes about a failure
    k[near] *= 0.5
    system = _BoundarySystem(st.adj, st.degree, k, st.fixed, st.weight)
    warm, it_warm = system.step(st.xb0, tol, d)
    cold, it_cold = system.step(st.xb0, tol)
    assert 0 < it_warm < 0.8 * it_cold
    assert np.abs(warm - cold).max() < 1e-3 * np.abs(cold).max()


def test_a_pull_rounds_interior_solve_solves_near_the_change_first(monkeypatch):
    """A pull round moves a few boundary nodes: the interior solve from the last solution first
    solves for the change near them, and then meets the whole band's stopping rule with few
    passes over the whole band; it ends where a solve over the whole band ends, to the
    tolerance."""
    import dicer.mesh.smooth as sm

    monkeypatch.setattr(sm, "_NEAR_HOPS", 10)  # a small ball's band: 12 edges reach more than an eighth of it
    m = ball(n=40, radii=(14.3,), centre=np.array([20.2, 19.9, 20.1]))
    st = sm._set_up(m, smoothing_settings({"surface_from_labels": False}), None, 0.0, 0.0)
    tol, interior = st.s["tolerance"], st.interior
    rel = st.xb0 - 20.0
    ub = 0.05 * np.sin(np.linalg.norm(rel, axis=1))[:, None] * rel  # smooth, as the labels' smoothing
    u1, _ = interior.solve(ub, tol / 10)  # a last solution well inside the rule: room for the change
    ub2 = ub.copy()
    near = np.linalg.norm(st.xb0 - st.xb0[0], axis=1) < 1.5  # the nodes one pull round moves
    ub2[near] += 0.05
    whole_passes = []
    laplace = sm._laplace

    def counted(m_bb, deg, free):
        apply = laplace(m_bb, deg, free)
        if m_bb.shape[0] < interior.nodes.size:
            return apply

        def whole(v):
            whole_passes.append(1)
            return apply(v)
        return whole

    monkeypatch.setattr(sm, "_laplace", counted)
    warm, _ = interior.solve(ub2, tol, u1)
    passes_near = len(whole_passes)
    interior._last_b = None  # the same solve over the whole band only
    whole_passes.clear()
    plain, _ = interior.solve(ub2, tol, u1)
    assert 2 <= passes_near <= 3 < len(whole_passes) // 2, (passes_near, len(whole_passes))  # measured 2, 11
    fresh, _ = interior.solve(ub2, 1e-7)
    scale = np.abs(fresh).max()
    assert np.abs(warm - fresh).max() < 1e-3 * scale and np.abs(plain - fresh).max() < 1e-3 * scale


def test_guard_error_names_the_worst_element():
    # an input element that is already inverted cannot be rescued by backing off
    m = ball(n=24, radii=(8.3,), centre=np.array([12.2, 11.9, 12.1]))
    bad = m.copy()
    g = boundary_graph(m)
    node = np.flatnonzero(g.boundary & (m.points[:, 0] > 16))[0]
    bad.points[node] += (np.array([12.2, 11.9, 12.1]) - bad.points[node]) * 0.3  # deep inside
    # (the labels' fit would pull the node back onto the surface and mend the element)
    with pytest.raises(DicerError, match=r"element \d+ \(material 1, centre .* mm\).*scaled Jacobian"):
        smooth_mesh(bad, {"surface_from_labels": False})


@pytest.mark.parametrize("section, match", [
    # the schema checks the settings (dicer.config.stage_kwargs), whatever the entry point
    ({"coefficient": 1.0}, r"smooth.coefficient': 1.0 is not allowed; give null or a number >= 0 and < 1"),
    ({"coefficient": -0.1}, r"smooth.coefficient': -0.1 is not allowed"),
    ({"coefficients": {"A": 1.2}}, r"smooth.coefficients.A"),
    ({"coefficients": {"Q": 0.5}}, r"unknown key 'smooth.coefficients.Q'; known keys here: A, B, C, D, E, F"),
    ({"min_scaled_jacobian": 1.5}, r"min_scaled_jacobian"),
    ({"colour": 1}, r"unknown key 'smooth.colour'"),
])
def test_bad_settings(section, match):
    m = ball(n=12, radii=(4.3,), centre=np.array([6.1, 5.9, 6.2]))
    with pytest.raises(DicerError, match=match):
        smooth_mesh(m, section)


def test_bad_meshes():
    empty = Mesh(np.zeros((0, 3)), np.zeros((0, 8), np.int64), np.zeros(0, np.int32), np.zeros((0, 3), np.int64),
                 np.ones(3), np.zeros(3), np.ones(3, np.int64))
    with pytest.raises(DicerError, match="empty"):
        smooth_mesh(empty, {})
    m = ball(n=12, radii=(4.3,), centre=np.array([6.1, 5.9, 6.2]))
    m.lattice = None
    with pytest.raises(DicerError, match="lattice"):
        smooth_mesh(m, {})


def test_stretched_mesh_like_after_plane_merging():
    m = ball(n=24, radii=(8.3, 4.1), centre=np.array([12.2, 11.9, 12.1]))
    widths = np.tile([1, 2], 20)
    edges = np.concatenate([[0], np.cumsum(widths)])
    lat = edges[m.lattice]
    ms = Mesh(lat.astype(float), m.cells.copy(), m.material.copy(), lat, m.spacing.copy(), m.origin.copy(),
              np.array([edges[n] for n in m.grid_shape]))
    out, rep = smooth_mesh(ms, {})
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.2 and rep["inverted_elements"] == 0
    assert rep["node_classes"]["X"] == 0
    # the interior keeps its graded spacing: the displacement, not the position, is
    # harmonic, so with the boundary held still no interior node moves (a centroid rule on
    # positions would move them by up to 0.5 towards even spacing)
    still, _ = smooth_mesh(ms, {"coefficient": 0.0, "interior_band": 0})
    assert np.array_equal(still.points, ms.points)


def test_2d_disc():
    n = 40
    g = np.arange(n) + 0.5
    r = np.sqrt((g[:, None] - 20.3) ** 2 + (g[None, :] - 19.8) ** 2)
    lab, _ = fix_connectivity((r < 14.6).astype(np.uint8))
    m = voxel_mesh(lab)
    out, rep = smooth_mesh(m, {})
    nodes = np.flatnonzero(boundary_graph(m).boundary)
    err0 = np.abs(np.linalg.norm(m.points[nodes, :2] - [20.3, 19.8], axis=1) - 14.6).mean()
    err1 = np.abs(np.linalg.norm(out.points[nodes, :2] - [20.3, 19.8], axis=1) - 14.6).mean()
    assert err1 < 0.5 * err0
    assert np.all(out.points[:, 2] == 0)
    assert scaled_jacobian(out.points, out.cells).min() >= 0.2


def test_deterministic():
    m = ball(n=20, radii=(7.3, 3.9), centre=np.array([10.2, 9.9, 10.1]))
    a, ra = smooth_mesh(m, {})
    b, rb = smooth_mesh(m, {})
    assert np.array_equal(a.points, b.points)


def test_plane_merged_mesh():
    merge = pytest.importorskip("dicer.mesh.merge")
    m = ball(radii=(16.3, 9.7))
    merged, _ = merge.merge_planes(m, passes=(1, 1, 1))
    assert merged.n_cells < m.n_cells
    out, rep = smooth_mesh(merged, {})
    assert rep["node_classes"]["X"] == 0
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.2 and np.count_nonzero(sj <= 0) == 0
    assert abs(rep["volume_change"]) <= 0.02


@pytest.mark.slow
def test_head_ct_chain():
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "cranium_ct.nii.gz"
    if not path.exists():
        pytest.skip("the shared head CT is not present")
    from dicer.io.images import read_image

    image = read_image(str(path))
    hu = image.array
    lab = (hu >= -140).astype(np.uint8) + (hu >= 226).astype(np.uint8)
    lab = lab[::2, ::2, ::2]
    fixed, frep = fix_connectivity(lab)
    assert frep["converged"] and frep["remaining"] == {"type_a": 0, "type_b": 0, "type_c": 0}
    m = voxel_mesh(fixed, [2 * s for s in image.spacing])
    out, rep = smooth_mesh(m, {})
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.2 and np.count_nonzero(sj <= 0) == 0
    assert rep["node_classes"]["X"] == 0


@pytest.mark.parametrize("merged", [False, True])
def test_smoothing_of_int32_connectivity_is_the_smoothing_of_int64(merged):
    """`dicer smooth` reads the stage file's Int32 connectivity read-only (read_mesh mapped); the
    smoothed nodes are those `dicer run` gets from int64 cells in memory."""
    from dicer.mesh.smooth import smooth_mesh

    lab = np.zeros((12, 11, 10), np.uint8)
    zz, yy, xx = np.mgrid[:12, :11, :10]
    lab[(zz - 5.5) ** 2 + (yy - 5) ** 2 + (xx - 4.5) ** 2 < 16] = 1
    lab[(zz - 5.5) ** 2 + (yy - 5) ** 2 + (xx - 4.5) ** 2 < 5] = 2
    wide = voxel_mesh(lab)
    if merged:
        from dicer.mesh.merge import merge_planes

        wide, _ = merge_planes(wide)
    narrow = wide.copy()
    narrow.cells = narrow.cells.astype(np.int32)
    narrow.cells.flags.writeable = False
    a, _ = smooth_mesh(wide)
    b, _ = smooth_mesh(narrow)
    assert not np.array_equal(a.points, wide.points)  # it moved nodes
    assert np.array_equal(a.points, b.points) and np.array_equal(a.cells, b.cells)


def test_thick_slices_keep_the_floor_at_default_settings(tmp_path):
    # an ellipsoid head with a skull shell on 0.4 x 0.4 x 5 mm voxels, merged: backing off one
    # element a round moved the failure along a row of merged elements until the rounds ran
    # out (an error at default settings); elements near the floor now back off with them
    import json

    import SimpleITK as sitk

    from dicer.cli import main

    shape, spacing, radii = (128, 128, 16), np.array([0.4, 0.4, 5.0]), np.array([22.0, 24.0, 35.0])
    c = (np.array(shape) - 1) / 2
    idx = np.indices(shape).astype(float)
    r = np.sqrt(sum(((idx[i] - c[i]) * spacing[i] / radii[i]) ** 2 for i in range(3)))
    labels = np.zeros(shape, np.uint8)
    labels[r < 1] = 1
    labels[(r < 0.88) & (r >= 0.76)] = 2
    image = sitk.GetImageFromArray(labels.T.copy())
    image.SetSpacing(tuple(spacing))
    sitk.WriteImage(image, str(tmp_path / "thick.nii.gz"))
    assert main(["run", "--labels", str(tmp_path / "thick.nii.gz"), "-o", str(tmp_path / "out"), "-q"]) == 0
    quality = json.loads((tmp_path / "out" / "quality.json").read_text())
    report = json.loads((tmp_path / "out" / "smooth.json").read_text())
    assert quality["scaled_jacobian"]["min"] >= 0.2 and quality["inverted_elements"] == 0
    assert 2 <= report["backoff_rounds"] <= 12


def test_short_edges_are_those_shrunk_below_a_twentieth():
    from dicer.mesh.smooth import _short_edges

    x0 = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    cells = np.arange(8)[None, :]
    x = x0.copy()
    x[4:, 2] = 0.04  # the vertical edges down to 0.04 of their length: a sliver with square corners
    short = _short_edges(cells, x, x0, np.ones(8, bool))
    assert short.shape == (1, 12) and np.flatnonzero(short[0]).tolist() == [8, 9, 10, 11]
    assert scaled_jacobian(x, cells)[0] == pytest.approx(1.0)  # what the scaled Jacobian alone passes
    moved = np.zeros(8, bool)
    moved[[1, 5]] = True  # only edge 1-5 has a moved end
    assert np.flatnonzero(_short_edges(cells, x, x0, moved)[0]).tolist() == [9]
    x[4:, 2] = 0.06
    assert not _short_edges(cells, x, x0, np.ones(8, bool)).any()


def test_a_pillow_copy_stops_where_the_layer_keeps_its_thinnest():
    from dicer.mesh.smooth import _hold_thickness

    # copies start 0.25 above their nodes and are pulled to goals 0.1 and 0.3 below the start
    under = np.zeros((3, 3))
    start = np.array([[0, 0, 0.25], [0, 0, 0.25], [0, 0, 0.25]])
    goal = np.array([[0, 0, 0.15], [0, 0, -0.05], [0, 0, 0.4]])
    share = np.ones(3)
    _hold_thickness(share, np.arange(3), start, goal, under, np.full(3, 0.05))
    copy = start + share[:, None] * (goal - start)
    assert share[0] == 1.0 and share[2] == 1.0  # 0.15 thick, and outward: as pulled
    assert copy[1, 2] == pytest.approx(0.05 * 1.001)  # stopped at the thinnest, not at -0.05 (inverted)


def test_guard_error_names_the_element_where_the_exported_model_has_it():
    import re

    labels = np.zeros((10, 10, 10), np.uint8)
    labels[2:8, 2:8, 2:8] = 1
    centres = []
    for direction in (None, (-1.0, 0, 0, 0, -1.0, 0, 0, 0, 1.0)):
        with pytest.raises(DicerError) as err:
            smooth_mesh(voxel_mesh(labels, (1, 1, 1), (0, 0, 0), direction),
                        {"min_scaled_jacobian": 0.99, "max_backoff_rounds": 0})
        assert "raise smooth.max_backoff_rounds" in str(err.value)
        centres.append([float(v) for v in re.search(r"centre ([-\d., ]+) mm", str(err.value)).group(1).split(", ")])
    lattice, scanner = np.array(centres)
    # scanner = c + D (lattice - c), c the centre of voxel 0 (0.5, 0.5, 0.5)
    assert scanner == pytest.approx([1.0 - lattice[0], 1.0 - lattice[1], lattice[2]], abs=0.011)


def test_conjugate_gradients_from_a_start_meet_the_same_rule_in_fewer_iterations():
    """A guard round re-solves the interior from the last solution: the same residual rule,
    0 iterations from the solution itself, fewer from one close to it."""
    from dicer.mesh.smooth import _pcg

    n = 400  # a 1D graph Laplacian with a diagonal shift (as a band with held neighbours): SPD
    diag = np.full(n, 2.05, np.float32)

    def apply(v):
        out = diag * v
        out[1:] -= v[:-1]
        out[:-1] -= v[1:]
        return out

    rng = np.random.default_rng(0)
    b = rng.normal(size=n).astype(np.float32)
    cold, it_cold = _pcg(apply, b, None, 1e-4, 5000)
    assert np.linalg.norm(b - apply(cold)) <= 1e-4 * np.linalg.norm(b)
    same, it_same = _pcg(apply, b, None, 1e-4, 5000, start=cold)
    assert it_same == 0 and np.array_equal(same, cold)
    b2 = b.copy()
    b2[190:210] += 0.5  # a few "nodes" moved
    warm, it_warm = _pcg(apply, b2, None, 1e-4, 5000, start=cold)
    fresh, it_fresh = _pcg(apply, b2, None, 1e-4, 5000)
    assert np.linalg.norm(b2 - apply(warm)) <= 1e-4 * np.linalg.norm(b2)
    assert 0 < it_warm < it_fresh
    assert np.abs(warm - fresh).max() < 1e-3 * np.abs(fresh).max()


def test_rounds_after_the_back_off_keep_the_failing_elements_as_they_were(monkeypatch, caplog, tmp_path):
    """When the back-off rounds do not hold the floor (here made so: they back nothing off), the
    guard keeps the failing elements and those around them as they were before smoothing, round
    by round, and says so; with max_backoff_rounds 0 it stops with the error at once."""
    import dicer.mesh.smooth as smooth

    m = ball(n=24, radii=(8.3,), centre=np.array([12.2, 11.9, 12.1]))
    settings = {"coefficient": 0.9, "min_scaled_jacobian": 0.4, "surface_from_labels": False}
    monkeypatch.setattr(smooth, "_back_off", lambda st: None)
    out, rep = smooth_mesh(m, {**settings, "max_backoff_rounds": 2})
    assert scaled_jacobian(out.points, out.cells).min() >= 0.4 and rep["min_scaled_jacobian"] >= 0.4
    assert rep["backoff_rounds"] == 2 and 1 <= rep["frozen_rounds"] <= 20
    assert 0 < rep["frozen_nodes"] < rep["boundary_nodes"]  # measured: 2 rounds, 1,022 of 1,274
    smoothed = np.linalg.norm(out.points - m.points, axis=1) > 1e-9
    assert smoothed.any()  # the rest keeps its smoothing
    with pytest.raises(DicerError, match="scaled Jacobian of at least 0.4"):
        smooth_mesh(m, {**settings, "max_backoff_rounds": 0})
    # the command says how many nodes kept their place
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    write_mesh(m, tmp_path / "m.vtu")
    with caplog.at_level("INFO", logger="dicer"):
        assert main(["smooth", str(tmp_path / "m.vtu"), "-o", str(tmp_path / "s.vtu"), "--set",
                     "smooth.coefficient=0.9", "--set", "smooth.min_scaled_jacobian=0.4", "--set",
                     "smooth.surface_from_labels=false", "--set", "smooth.max_backoff_rounds=2", "--set",
                     "preset=explicit-dynamics"]) == 0
    said = [r.getMessage() for r in caplog.records if "back-off rounds did not keep" in r.getMessage()]
    assert len(said) == 1 and f"kept {rep['frozen_nodes']} boundary nodes" in said[0]
    rounds = [r.getMessage() for r in caplog.records if "below smooth.min_scaled_jacobian=0.4: back-off round" in
              r.getMessage()]  # progress, a line a round
    assert len(rounds) == rep["backoff_rounds"] + rep["frozen_rounds"] and rounds[0].endswith("back-off round 1")


@pytest.mark.parametrize("piece", [1, 7, 1 << 18])
def test_guard_passes_in_pieces_match_one_pass(piece, monkeypatch):
    """The guard's row-wise passes (the elements holding marked nodes, the nodes moved farther
    than a reach, the edge lengths), in pieces side by side, equal the same work in one pass."""
    import dicer.mesh.smooth as smooth_module
    import dicer.parallel
    from dicer.mesh.topology import HEX_EDGES

    monkeypatch.setattr(smooth_module, "_PIECE", piece)
    monkeypatch.setattr(smooth_module, "_EDGE_PIECE", piece)
    monkeypatch.setattr(dicer.parallel, "cores", lambda: 2)
    rng = np.random.default_rng(5)
    mesh = voxel_mesh((rng.random((9, 8, 7)) < 0.6).astype(np.uint8))
    cells = np.asarray(mesh.cells, np.int64)
    elements = np.sort(rng.choice(mesh.n_cells, mesh.n_cells // 2, replace=False))
    checked = smooth_module._Elements(cells, elements, mesh.n_points)
    mark = rng.random(mesh.n_points) < 0.03
    expected = mark[cells[elements]].any(axis=1)
    assert 0 < expected.sum() < elements.size
    assert np.array_equal(checked.holding(mark), expected)
    x = mesh.points + rng.normal(0.0, 0.05, mesh.points.shape)
    step2 = ((x - mesh.points) ** 2).sum(axis=1)
    reach = float(np.sqrt(np.median(step2)))
    assert np.array_equal(smooth_module._moved_farther(x, mesh.points, reach), step2 > reach**2)
    assert np.array_equal(smooth_module._moved_farther(x, mesh.points, reach, True), step2 >= reach**2)
    d = x[cells[:, HEX_EDGES[:, 1]]] - x[cells[:, HEX_EDGES[:, 0]]]
    assert np.allclose(smooth_module._edge_lengths2(cells, x), (d * d).sum(axis=2), rtol=1e-15, atol=0)
