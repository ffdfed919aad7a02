"""Sub-voxel surfaces from the labels: the staircase's samples and the quadric fit onto them
(``smooth.surface_from_labels``)."""

import json

import numpy as np
import pytest
from scipy import ndimage, special
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from dicer.cli import main
from dicer.config import preset_settings
from dicer.connectivity import fix_connectivity
from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.meshes import read_mesh, write_mesh
from dicer.mesh.boundary import boundary_graph
from dicer.mesh.labelsurface import LabelSurface, label_image_samples, scan_crossings, staircase_samples
from dicer.mesh.merge import merge_planes
from dicer.mesh.metrics import element_volumes, scaled_jacobian
from dicer.mesh.smooth import smooth_mesh
from dicer.mesh.voxel import voxel_mesh
from tests.test_smooth_mirror import BALL, DISC, cut_versus_full, shells

ON = {"surface_from_labels": True}  # the default, named for the tests that compare with OFF
OFF = {"surface_from_labels": False}  # the labels' smoothing alone
# the fit's own figures were measured without the pillow layer, on the labels' faces, over 5
# voxels: the preset explicit-dynamics, laid under the cases that pin them
WITHOUT_THE_LAYER = preset_settings("explicit-dynamics")["smooth"]
R = 16.3
CENTRE = np.array([20.31, 19.77, 20.13])  # off the lattice


def ball_labels(dim, radii=(R,), n=40):
    g = np.arange(n) + 0.5
    r = np.sqrt(sum((x - c) ** 2 for x, c in zip(np.meshgrid(*([g] * dim), indexing="ij"), CENTRE)))
    lab = np.zeros((n,) * dim, np.uint8)
    for i, rad in enumerate(radii):
        lab[r < rad] = i + 1
    return fix_connectivity(lab)[0]


def radial(mesh, out, dim, radius=R, kinds=None):
    """Mean and largest |r - radius| of the boundary nodes (of the elements of ``kinds``)."""
    nodes = np.flatnonzero(boundary_graph(mesh).boundary)
    if kinds is not None:
        nodes = np.intersect1d(nodes, np.unique(mesh.cells[np.isin(mesh.material, kinds)]))
        r = np.linalg.norm(out.points[nodes, :dim] - CENTRE[:dim], axis=1)
        nodes = nodes[np.abs(r - radius) < 1.5]
    r = np.linalg.norm(out.points[nodes, :dim] - CENTRE[:dim], axis=1) - radius
    return float(np.abs(r).mean()), float(np.abs(r).max())


def box_labels(shape=(7, 8, 9), lo=(2, 2, 2), hi=(5, 6, 7)):
    lab = np.zeros(shape, np.uint8)
    lab[tuple(slice(a, b) for a, b in zip(lo, hi))] = 1
    return lab


# --- the samples -------------------------------------------------------------------------------


def test_samples_of_a_box_are_its_faces_with_inward_normals():
    mesh = voxel_mesh(box_labels(), spacing=(0.5, 1.0, 2.0))
    points, normals, kinds, weights = staircase_samples(mesh)
    assert points.shape == (2 * (3 * 4 + 4 * 5 + 3 * 5), 3)  # one per voxel face
    assert np.array_equal(kinds, np.tile([0, 1], (points.shape[0], 1)))
    # areas in mm^2: the box is 1.5 x 4 x 10 mm
    assert weights.sum() == pytest.approx(2 * (1.5 * 4 + 4 * 10 + 1.5 * 10))
    assert np.allclose(np.abs(normals).sum(axis=1), 1.0)  # axis-aligned unit normals
    # into the box: half a voxel along the normal from each face lies inside it
    inside = points + 0.25 * normals * np.array([0.5, 1.0, 2.0])
    assert np.all((inside > [1.0, 2.0, 4.0]) & (inside < [2.5, 6.0, 14.0]))


def test_merged_faces_give_the_voxel_faces_samples():
    lab = box_labels((12, 12, 12), (2, 3, 1), (10, 9, 11))
    lab[5:7, 5:7, 5:7] = 2  # an inclusion: two pairs of kinds
    vox = voxel_mesh(lab)
    merged, _ = merge_planes(vox)
    assert merged.n_cells < vox.n_cells
    a = staircase_samples(vox)
    b = staircase_samples(merged)
    key = lambda s: np.lexsort(s[0].T[::-1])  # noqa: E731
    ka, kb = key(a), key(b)
    for x, y in zip(a, b):
        assert np.allclose(x[ka], y[kb])
    assert {tuple(k) for k in a[2]} == {(0, 1), (1, 2)}


def test_faces_on_a_bounding_plane_are_no_surface_and_are_mirrored():
    lab = box_labels((7, 8, 9), (0, 2, 2), (3, 6, 7))  # touches the plane x = 0
    mesh = voxel_mesh(lab)
    plain = staircase_samples(mesh)[0]
    assert plain.shape[0] == 4 * 5 + 2 * (3 * 5 + 3 * 4)  # the x = 0 face is left out
    near = plain[:, 0] < 2.0
    mirrored = staircase_samples(mesh, mirror_reach=2.0)[0]
    # the samples within 2 mm of x = 0 gain their mirror images (no other plane is that near)
    assert mirrored.shape[0] == plain.shape[0] + near.sum()
    assert np.allclose(np.sort(mirrored[mirrored[:, 0] < 0, 0]), np.sort(-plain[near, 0]))


# --- the fit -----------------------------------------------------------------------------------


def plane_fit(n, offset):
    """A half space below the plane (x - 12) . n = offset in a 24^3 image: the signed distances
    from the plane of its staircase's samples in the middle and of the fitted points there."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    g = np.arange(24) + 0.5
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    surface = LabelSurface(voxel_mesh(((x - 12.0) @ n < offset).astype(np.uint8)), 5.0, mirror=False)
    p = surface.points[np.all(np.abs(surface.points - 12.0) < 5.0, axis=1)]
    normal = np.tile(-n, (p.shape[0], 1))  # into the material
    height, fitted, direction = surface.offsets(p, normal, np.ones(p.shape[0], np.int64))
    assert fitted.all()
    fit = p + height[:, None] * direction
    return (p - 12.0) @ n - offset, (fit - 12.0) @ n - offset, fit


@pytest.mark.parametrize("offset", [0.0, 0.31])
def test_a_plane_at_a_generic_tilt_is_found_from_its_staircase(offset):
    staircase, err, _ = plane_fit([0.37, -0.21, 0.9], offset)
    assert np.abs(staircase).mean() > 0.15  # the samples scatter about the plane
    assert np.abs(err).mean() < 0.05 and abs(err.mean()) < 0.02 and np.abs(err).max() < 0.2


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.floats(0.25, 4), st.floats(0, 2 * np.pi), st.floats(0, 1))
def test_the_fit_of_a_tilted_plane_is_flat_and_no_farther_than_its_staircase(slope, azimuth, offset):
    # a step at least every 6 voxels. At a lattice-rational tilt (45 degrees) the labels are
    # the same for a range of offsets, so no fit can place the plane better than that; but the
    # fit is flat to a fraction of the staircase's steps and no farther off than its samples
    nx, ny, nz = slope * np.cos(azimuth), slope * np.sin(azimuth), 1.0
    staircase, err, fit = plane_fit([nx, ny, nz], offset + 0.0123)  # no voxel centre on the plane
    assert np.abs(err).mean() <= np.abs(staircase).mean() + 0.01
    centred = fit - fit.mean(axis=0)
    flatness = np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(fit.shape[0])  # rms off their plane
    # measured up to 0.13 (150 random planes): near 45 degrees the steps make a pattern 8 to 16
    # voxels long, which the fit's window (radius 5) does not average out
    assert flatness < 0.16


@pytest.fixture(scope="module", params=[3, 2], ids=["3d", "2d"])
def sphere(request):
    dim = request.param
    mesh = voxel_mesh(ball_labels(dim))
    labels_only, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **OFF})
    fitted, report = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **ON})
    return dim, mesh, labels_only, fitted, report


def test_sphere_from_labels_alone(sphere):
    dim, mesh, labels_only, fitted, report = sphere
    before, after = radial(mesh, labels_only, dim), radial(mesh, fitted, dim)
    # measured at the default floor 0.3: 3D 0.137 -> 0.075 mean (the fit itself 0.046, the
    # floor's corner sharpening the rest; 0.061 at a floor of 0.2), 0.46 -> 0.53 max; 2D 0.123 ->
    # 0.098 mean. The 3D mean is the sphere-from-labels target of docs/validation.md (0.12)
    if dim == 3:
        assert before[0] > 0.13 and after[0] < 0.085 and after[1] < 0.55
    else:
        assert before[0] > 0.11 and after[0] < 0.105 and after[1] < 0.42
    exact = 4 / 3 * np.pi * R**3 if dim == 3 else np.pi * R**2
    assert abs(element_volumes(fitted.points, fitted.cells).sum() / exact - 1) < 0.003  # measured -0.22 / -0.06 %
    sj = scaled_jacobian(fitted.points, fitted.cells)
    assert sj.min() >= 0.3 and report["inverted_elements"] == 0
    info = report["surface_from_labels"]
    assert info["nodes_moved"] >= 0.99 * info["nodes_between_two_kinds"]
    assert info["label_surface_radius"] == 5.0
    assert "surface_from_image" not in report
    assert np.array_equal(fitted.cells, mesh.cells)


def test_on_by_default_and_reproducible(sphere):
    dim, mesh, labels_only, fitted, _ = sphere
    again, _ = smooth_mesh(mesh, WITHOUT_THE_LAYER)  # the fit not named
    assert np.array_equal(again.points, fitted.points)  # threads fit disjoint chunks
    assert not np.array_equal(labels_only.points, fitted.points)


def test_two_interfaces_each_fitted_to_its_own_staircase():
    # the outer surface (0|1) and the interface (1|2) of a ball in a shell, each from the faces
    # of its own pair of kinds
    mesh = voxel_mesh(ball_labels(3, radii=(R, 9.7)))
    before, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **OFF})
    after, report = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **ON})
    inner = radial(mesh, before, 3, 9.7, kinds=[2]), radial(mesh, after, 3, 9.7, kinds=[2])
    outer = radial(mesh, before, 3, R, kinds=[1]), radial(mesh, after, 3, R, kinds=[1])
    assert outer[1][0] < 0.6 * outer[0][0]  # measured 0.137 -> 0.078 (floor 0.2: 0.061)
    assert inner[1][0] < 0.7 * inner[0][0]  # measured 0.141 -> 0.095 (floor 0.2: 0.078)
    assert report["surface_from_labels"]["pairs_left_to_the_labels"] == []
    assert report["inverted_elements"] == 0


def test_a_pair_the_sharpening_would_roughen_stays_with_the_labels(monkeypatch):
    # where the corner sharpening takes a pair's nodes farther from its surface than the
    # labels' smoothing left them (here made so: the interface's nodes pushed 0.4 voxel off),
    # that pair keeps the labels' positions and the others are pulled
    from dicer.mesh import subvoxel

    mesh = voxel_mesh(ball_labels(3, radii=(R, 9.7)))
    lift = subvoxel.lift

    def rough(sides, y, floor, share=None):
        out = lift(sides, y, floor, share)
        out[sides.pair == 1 * sides.top + 2, 0] += 0.4
        return out

    monkeypatch.setattr(subvoxel, "lift", rough)
    before, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **OFF})
    after, report = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **ON})
    assert report["surface_from_labels"]["pairs_left_to_the_labels"] == ["1|2"]
    assert radial(mesh, after, 3, 9.7, kinds=[2]) == radial(mesh, before, 3, 9.7, kinds=[2])
    assert radial(mesh, after, 3, R, kinds=[1])[0] < 0.085


def test_a_thin_plate_keeps_its_thickness():
    # a plate 2.4 voxels thick, tilted: each face is fitted from its own side's staircase (the
    # other side faces away), so the plate is not thinned as blurring the labels would thin it
    n = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
    g = np.arange(28) + 0.5
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1)
    d = (x - 14.0) @ n
    lab = fix_connectivity((np.abs(d) < 1.2).astype(np.uint8))[0]
    mesh = voxel_mesh(lab)
    out, report = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **ON, "bounding_planes": "mirror"})
    nodes = np.flatnonzero(boundary_graph(mesh).boundary)
    nodes = nodes[np.all(np.abs(mesh.points[nodes, :2] - 14.0) < 8, axis=1)]
    half = np.abs((out.points[nodes] - 14.0) @ n)
    assert abs(half.mean() - 1.2) < 0.05
    base, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **OFF})
    assert np.abs(half - 1.2).mean() < np.abs(np.abs((base.points[nodes] - 14.0) @ n) - 1.2).mean()


@pytest.mark.parametrize("cut", [(0,), (0, 1)], ids=["half", "quarter"])
def test_a_cut_disc_is_fitted_like_the_whole(cut):
    diff, same_classes, asym, *_ = cut_versus_full(shells(40, 2, DISC), cut, ON)
    assert asym < 1e-7 and diff < 1e-6 and same_classes


def test_a_cut_ball_is_fitted_like_the_whole():
    diff, same_classes, asym, *_ = cut_versus_full(shells(32, 3, BALL), (0, 1, 2), ON)
    assert asym < 1e-6 and diff < 1e-6 and same_classes


def test_the_scan_wins_over_the_labels_fit():
    lab = ball_labels(2)
    mesh = voxel_mesh(lab)
    image = Volume(lab.astype(np.float32) * 1000.0, (1.0, 1.0))
    out, report = smooth_mesh(mesh, {**ON, "surface_from_image": True}, image=image, thresholds=[500.0])
    assert "surface_from_image" in report and "surface_from_labels" not in report
    alone, report = smooth_mesh(mesh, ON, image=image, thresholds=[500.0])  # the scan's pull off
    assert "surface_from_labels" in report


def test_smooth_command_reports_the_fit(tmp_path, caplog):
    write_mesh(voxel_mesh(ball_labels(2)), tmp_path / "mesh.vtu")
    out = tmp_path / "smoothed.vtu"
    with caplog.at_level("INFO", logger="dicer"):
        # without the pillow layer (the preset explicit-dynamics): the output has the input's nodes
        assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(out), "--set", "preset=explicit-dynamics",
                     "--set", "smooth.label_surface_radius=4", "--report", str(tmp_path / "smooth.json")]) == 0
    report = json.loads((tmp_path / "smooth.json").read_text())
    # progress on the stage's longest step: the fit, before and after
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("smooth: fit")]
    assert said[0] == (f"smooth: fitting {report['surface_from_labels']['nodes_between_two_kinds']} boundary nodes to "
                       "the labels' staircase (smooth.surface_from_labels, radius 4 voxels)")
    assert len(said) == 2 and said[1].startswith("smooth: fitted in ")
    assert report["surface_from_labels"]["label_surface_radius"] == 4.0
    assert report["surface_from_labels"]["nodes_moved"] > 100
    assert read_mesh(out).n_points == voxel_mesh(ball_labels(2)).n_points
    assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(out), "--set", "smooth.label_surface_radius=1",
                 "-q"]) == 2


def test_a_fit_that_reaches_few_nodes_is_warned_of(tmp_path, caplog):
    # a cube of 2 voxels holds too few faces for a fit of 6 coefficients around any node: the
    # nodes keep the labels' smoothing, and the command says so
    lab = np.zeros((12, 12, 12), np.uint8)
    lab[5:7, 5:7, 5:7] = 1
    write_mesh(voxel_mesh(lab), tmp_path / "mesh.vtu")
    out = tmp_path / "smoothed.vtu"
    # measured at the fit over 5 voxels: the preset explicit-dynamics
    assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(out), "--set", "preset=explicit-dynamics", "--set",
                 "smooth.surface_from_labels=true", "--report", str(tmp_path / "smooth.json")]) == 0
    report = json.loads((tmp_path / "smooth.json").read_text())["surface_from_labels"]
    assert report["nodes_on_the_fitted_surface"] == 0 and report["nodes_between_two_kinds"] == 26
    warned = [r.getMessage() for r in caplog.records if "fitted to the labels" in r.getMessage()]
    assert len(warned) == 1 and "0 of the 26" in warned[0] and "label_surface_radius=5" in warned[0]


def test_a_slab_between_two_mirrors_is_fitted_as_an_endless_prism(monkeypatch):
    """The two bounding planes of an axis are two mirrors: a slab of the disc 1, 2 or 4 voxels
    thick is one endless prism, its samples mirrored again and again across both planes (once
    across each, a slab thinner than the radius had too few). Before the corner sharpening,
    which is left out here."""
    from dicer.mesh import subvoxel

    monkeypatch.setattr(subvoxel, "lift", lambda sides, y, floor, share=None: y)
    disc = fix_connectivity(shells(40, 2, DISC))[0]
    layers = []
    for thickness in (1, 2, 4):
        m = voxel_mesh(np.repeat(disc[:, :, None], thickness, axis=2))
        out, rep = smooth_mesh(m, {**ON, "tolerance": 1e-7})
        assert rep["surface_from_labels"]["nodes_moved"] > 0
        for z in range(thickness + 1):
            at = np.flatnonzero(m.lattice[:, 2] == z)
            at = at[np.lexsort((m.lattice[at, 1], m.lattice[at, 0]))]
            layers.append(out.points[at, :2])
    assert max(float(np.abs(xy - layers[0]).max()) for xy in layers[1:]) < 1e-6  # measured 2.9e-7 (0.035 before)


# --- the labels before merging -----------------------------------------------------------------


def _sorted_samples(samples):
    points, normals, kinds, weights = samples
    order = np.lexsort(np.c_[np.round(points, 9), normals, kinds].T[::-1])  # rounded: ties sort alike
    return points[order], normals[order], kinds[order], weights[order]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(dim=st.sampled_from([2, 3]), seed=st.integers(0, 2**31 - 1), reach=st.sampled_from([0.0, 1.3]))
@example(dim=3, seed=43708, reach=0.0)  # points equal but for rounding: sorted alike only when rounded
@example(dim=3, seed=32768, reach=1.3)  # a reach of 1.5 mm: samples at exactly the reach, in by rounding or out
# (the fit gives such a sample no weight: it lies on the edge of the fit's window too)
def test_a_label_volume_gives_its_voxel_meshs_samples(dim, seed, reach):
    rng = np.random.default_rng(seed)
    shape = tuple(rng.integers(2, 7, size=dim))
    lab = rng.integers(0, 4, size=shape).astype(np.uint8)
    assume(lab.any())  # a volume of background alone is refused before any mesh
    spacing, origin = (0.5, 1.0, 2.0)[:dim], tuple(rng.uniform(-3, 3, size=dim))
    mesh = voxel_mesh(lab, spacing, origin)
    a = _sorted_samples(staircase_samples(mesh, reach))
    b = _sorted_samples(label_image_samples(Volume(lab, spacing, origin), mesh, reach))
    assert a[0].shape == b[0].shape
    for x, y in zip(a, b):
        assert np.allclose(x, y, rtol=0, atol=1e-12)
    # every face between two kinds once: a face between two materials is not counted from both sides
    faces = sum(np.count_nonzero(np.diff(lab.astype(int), axis=d)) for d in range(dim))
    if reach == 0:
        assert a[0].shape[0] == faces


def merged_ball(dim):
    lab = ball_labels(dim)
    vox = voxel_mesh(lab)
    merged, _ = merge_planes(vox)
    return lab, vox, merged


@pytest.mark.parametrize("dim", [2, 3])
def test_a_merged_ball_fitted_to_its_labels_keeps_their_surface(dim):
    lab, vox, merged = merged_ball(dim)
    exact = 4 / 3 * np.pi * R**3 if dim == 3 else np.pi * R**2
    # measured without the pillow layer, on the labels' faces: the preset explicit-dynamics
    on_faces, _ = smooth_mesh(merged, WITHOUT_THE_LAYER)
    on_labels, report = smooth_mesh(merged, WITHOUT_THE_LAYER, labels=Volume(lab, (1.0,) * dim))
    # measured: the merged mesh's faces (chamfers fill steps, +5.5 % / +2.3 % volume) put the
    # surface 0.327 / 0.224 voxel off the sphere on average, +4.8 % / +2.2 % volume; the labels
    # 0.111 / 0.114, -0.55 % / -0.06 % (the voxel mesh's own fit: 0.075 / 0.098); in 3D the
    # sphere-from-labels target of docs/validation.md (0.12) at dicer run's defaults, merging on
    faces_error, labels_error = radial(merged, on_faces, dim), radial(merged, on_labels, dim)
    assert faces_error[0] > 0.2 and labels_error[0] < (0.113 if dim == 3 else 0.118) and labels_error[1] < 0.55
    volume = element_volumes(on_labels.points, on_labels.cells).sum()
    assert abs(volume / exact - 1) < 0.008
    assert element_volumes(on_faces.points, on_faces.cells).sum() / exact - 1 > 0.02
    # the report compares with the labels' voxels
    voxels = np.count_nonzero(lab)
    assert report["volume_change_from_labels_by_material"]["1"] == pytest.approx(volume / voxels - 1, abs=1e-9)
    assert report["min_scaled_jacobian"] >= 0.3 and report["inverted_elements"] == 0
    # the voxel mesh itself fits alike with its labels or its faces (the same samples)
    alone, _ = smooth_mesh(vox, WITHOUT_THE_LAYER)
    given, _ = smooth_mesh(vox, WITHOUT_THE_LAYER, labels=Volume(lab, (1.0,) * dim))
    assert np.abs(alone.points - given.points).max() < 1e-9


def test_labels_that_are_not_the_meshs_are_refused():
    lab, _, merged = merged_ball(3)
    wrong = {
        "a 2D label volume for a 3D mesh": Volume(lab[:, :, 0], (1.0, 1.0)),
        "but the mesh was made from 40x40x40": Volume(lab[:, :, :-1], (1.0,) * 3),
        "voxel size 1 x 1 x 2 mm": Volume(lab, (1.0, 1.0, 2.0)),
        "origin 0 x 0 x 1 mm": Volume(lab, (1.0,) * 3, (0.0, 0.0, 1.0)),
        "elements of the mesh hold no voxel of their material": Volume(np.roll(lab, 9, axis=0), (1.0,) * 3),
        # a shift of one voxel: 110 of 2,603 elements (4.2 %) miss, which the share of 0.9 asked
        # until 6 December 2026 let through (as a head's labels flipped left to right, 2.6 %)
        "110 of 2603 elements of the mesh hold no voxel": Volume(np.roll(lab, 1, axis=0), (1.0,) * 3),
    }
    for said, labels in wrong.items():
        with pytest.raises(DicerError, match=f"^other.nii.gz: .*{said}.*labels_fixed.nii.gz of dicer run"):
            smooth_mesh(merged, labels=labels, labels_source="other.nii.gz")
    # turned axes: the direction cosines differ (both files have them)
    turned = merged.copy()
    turned.direction = np.eye(3)
    flipped = Volume(lab, (1.0,) * 3, (0.0,) * 3, (-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    with pytest.raises(DicerError, match="^other.nii.gz: the labels' direction cosines differ from the mesh's"):
        smooth_mesh(turned, labels=flipped, labels_source="other.nii.gz")
    smooth_mesh(turned, labels=Volume(lab, (1.0,) * 3, (0.0,) * 3, tuple(np.eye(3).ravel())))  # the same: fitted


def test_smooth_command_fits_the_labels_dicer_run_made(tmp_path, caplog, capsys):
    lab = ball_labels(3).astype(np.uint8)
    np.save(tmp_path / "ball.npy", lab)
    run = tmp_path / "run"
    assert main(["run", "--labels", str(tmp_path / "ball.npy"), "-o", str(run), "-q"]) == 0
    report = json.loads((run / "smooth.json").read_text())
    # measured: the merge adds 5.5 %, the fit to the labels takes it back (-0.64 % from the voxels)
    assert abs(report["volume_change_from_labels_by_material"]["1"]) < 0.008
    assert report["volume_change_by_material"]["1"] < -0.04
    out = tmp_path / "again.vtu"
    argv = ["smooth", str(run / "merged.vtu"), "-o", str(out), "--labels", str(run / "labels_fixed.nii.gz"), "-q"]
    assert main(argv) == 0
    assert out.read_bytes() == (run / "smoothed.vtu").read_bytes()  # what dicer run made
    # without the labels: fitted to the merged faces, more than half of them slopes, and said
    caplog.clear()
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(tmp_path / "faces.vtu"), "--report",
                 str(tmp_path / "faces.json")]) == 0
    fit = json.loads((tmp_path / "faces.json").read_text())["surface_from_labels"]
    assert fit["samples_on_sloped_faces"] > 0.5 * fit["samples"]  # measured 2,683 of 4,851
    said = [r.getMessage() for r in caplog.records if "merging's slopes" in r.getMessage()]
    assert said == [f"smooth: {fit['samples_on_sloped_faces']} of the fit's {fit['samples']} samples lie on merging's "
                    "slopes (chamfers), which stand off the labels' surface: give --labels with the label volume the "
                    "mesh was made from (labels_fixed.nii.gz), as dicer run does"]
    assert report["surface_from_labels"]["samples_on_sloped_faces"] == 0  # the labels' faces: all on the axes
    # labels of another scan: one line, exit 2, no output
    np.save(tmp_path / "other.npy", np.roll(lab, 9, axis=0))
    capsys.readouterr()
    bad = tmp_path / "bad.vtu"
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(bad), "--labels", str(tmp_path / "other.npy")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {tmp_path / 'other.npy'}: ") and err.count("\n") == 1
    assert "hold no voxel of their material" in err
    assert not bad.exists() and not list(tmp_path.glob("bad*"))
    # --labels without the fit: said, not read
    caplog.clear()
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(bad), "--labels", str(tmp_path / "other.npy"),
                 "--set", "smooth.surface_from_labels=false"]) == 0
    assert any("--labels is read by smooth.surface_from_labels only, which is off" in r.getMessage()
               for r in caplog.records)
    # --image without the scan's surface or fit_to_scan: said, not read (the output is the labels')
    caplog.clear()
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(bad), "--image", str(tmp_path / "other.npy")]) == 0
    assert [r.getMessage() for r in caplog.records if "--image" in r.getMessage()] == [
        "smooth: smooth.fit_to_scan places the labels' faces by the scan: it needs --labels beside --image "
        "(labels_fixed.nii.gz of dicer run); without it the fit takes the mesh's faces, and the scan is not read"]
    caplog.clear()
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(bad), "--image", str(tmp_path / "other.npy"),
                 "--set", "smooth.fit_to_scan=false"]) == 0
    assert [r.getMessage() for r in caplog.records if "--image" in r.getMessage()] == [
        "smooth: --image is read by smooth.surface_from_image, or by smooth.fit_to_scan with --labels (the fit's "
        "faces placed by the scan), and these settings use neither: "
        f"{tmp_path / 'other.npy'} is not read"]


# --- the labels' faces placed by the scan (smooth.fit_to_scan) ---------------------------------


def _placed(volume, mesh, scan):
    """The label volume's samples with their faces placed by ``scan`` (as ``LabelSurface`` does)."""
    points, normals, kinds, weights = label_image_samples(volume, mesh)
    step = np.abs(normals) @ np.asarray(volume.spacing, float)
    return scan_crossings(points, normals, kinds, step, scan), normals, kinds, weights


class _Scan:
    """An ImageSurface stand-in: the scan's values by a function of position, one threshold."""

    def __init__(self, value, threshold=500.0):
        self.value, self.thresholds = value, np.array([threshold])

    def sample(self, points):
        return self.value(points).astype(np.float32)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_scan_places_each_face_at_its_crossing_within_half_a_voxel(dim):
    spacing = (0.5, 1.0, 2.0)[:dim]
    centres = np.meshgrid(*[(np.arange(n) + 0.5) * h for n, h in zip((12, 5, 4)[:dim], spacing)], indexing="ij")
    # a blurred step (sigma 0.4 mm) crossing 500 at x = 2.6 mm, 0.1 mm past the faces at x = 2.5
    step = lambda p: 1000.0 * special.ndtr((2.6 - p[..., 0]) / 0.4)  # noqa: E731
    lab = (step(np.stack(centres, axis=-1)) >= 500.0).astype(np.uint8)
    mesh = voxel_mesh(lab, spacing)
    volume = Volume(lab, spacing)
    plain = label_image_samples(volume, mesh)
    placed = _placed(volume, mesh, _Scan(step))
    across = np.abs(plain[1][:, 0]) == 1  # the faces across x
    assert np.allclose(plain[0][across, 0], 2.5)
    # on the step's own scale the crossing is the step's (measured 2.5999); the straight line
    # between the centres' values (2.25 and 2.75 mm) would say 2.5895
    assert np.allclose(placed[0][across, 0], 2.6, atol=2e-3)
    assert np.array_equal(placed[0][:, 1:], plain[0][:, 1:])  # along the normal only
    # a ramp, whose values 2.5 voxels out do not level off: still between the centres, past the face
    ramp = _placed(volume, mesh, _Scan(lambda p: 500.0 + 400.0 * (2.6 - p[..., 0])))
    assert np.all((ramp[0][across, 0] > 2.5) & (ramp[0][across, 0] < 2.75))
    # a scan above the threshold on both sides (the segmentation's clean-up): the faces stay
    stay = _placed(volume, mesh, _Scan(lambda p: np.full(p.shape[0], 900.0)))
    assert np.array_equal(stay[0], plain[0])
    # noise: never more than half a voxel along the normal
    rng = np.random.default_rng(0)
    noisy = _placed(volume, mesh, _Scan(lambda p: rng.normal(500.0, 300.0, p.shape[0])))
    half = 0.5 * (np.abs(plain[1]) @ np.asarray(spacing))
    assert np.all(np.abs(noisy[0] - plain[0]).sum(axis=1) <= half + 1e-12)


def test_faces_the_scan_does_not_cross_stay_and_thin_plates_are_read_as_they_are():
    """Where both sides lie above the threshold (the segmentation's clean-up), noise moved half
    the faces by half a voxel; across a plate of two voxels, whose far side spoils the contrast
    read 2.5 voxels out, the blurred step's crossing missed by 0.2 voxel."""
    lab = np.zeros((20, 20, 20), np.uint8)
    lab[5:15, 5:15, 5:15] = 1
    mesh = voxel_mesh(lab)
    volume = Volume(lab, (1.0,) * 3)
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 30.0, (40, 40, 40))
    placed = _placed(volume, mesh, _Scan(lambda p: 900.0 + ndimage.map_coordinates(noise, p.T + 10, order=1)))
    plain = label_image_samples(volume, mesh)
    assert np.array_equal(placed[0], plain[0])  # measured before: 309 of 600 moved
    # a plate two voxels thick, blurred by 0.8 voxel, its rising edge 0.3 voxel past the face at x = 10
    plate = lambda x: 1000.0 * (special.ndtr((x - 10.3) / 0.8) - special.ndtr((x - 12.3) / 0.8))  # noqa: E731
    points, normals = np.array([[10.0, 0.5]]), np.array([[1.0, 0.0]])
    x = scan_crossings(points, normals, np.array([[0, 1]]), np.array([1.0]), _Scan(lambda p: plate(p[..., 0])))
    # the true crossing 10.313, the straight line between the centres 10.298 (the step's scale: 10.500)
    assert x[0, 0] == pytest.approx(10.298, abs=1e-3)
    # the far value on the higher side below the lower side's (noise beyond a thin plate): the
    # straight line, not the step's scale run backwards (which put the face half a voxel out)
    table = {9.5: 10.0, 10.5: 95.0, 7.5: 15.0, 12.5: 14.0}
    x = scan_crossings(points, normals, np.array([[0, 1]]), np.array([1.0]),
                       _Scan(lambda p: np.array([table[round(float(v), 1)] for v in p[..., 0]]), threshold=50.0))
    assert x[0, 0] == pytest.approx(10.0 + 40.0 / 85.0 - 0.5, abs=1e-9)


@pytest.mark.parametrize("dim", [3, 2])
def test_a_ct_ball_fitted_to_its_labels_placed_by_the_scan(dim):
    from tests.test_smooth_image import CENTRE as CT_CENTRE, R as CT_R, ct_ball

    image = ct_ball(dim)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    mesh = voxel_mesh(lab)
    labels, scan = Volume(lab, (1.0,) * dim), Volume(image, (1.0,) * dim)
    nodes = np.flatnonzero(boundary_graph(mesh).boundary)

    def error(out):
        return np.linalg.norm(out.points[nodes, :dim] - CT_CENTRE[:dim], axis=1) - CT_R

    # measured without the pillow layer, over 5 voxels: the preset explicit-dynamics
    alone, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, "fit_to_scan": False}, labels=labels, image=scan,
                           thresholds=[500.0])
    placed, report = smooth_mesh(mesh, WITHOUT_THE_LAYER, labels=labels, image=scan,
                                 thresholds=[500.0])  # fit_to_scan: the default
    relaxed = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, "label_samples": "relaxed"}, labels=labels, image=scan,
                          thresholds=[500.0])
    # the staircase relaxed through the faces' places: mean / max |r - R| measured 3D 0.067 / 0.25,
    # 2D 0.059 / 0.24 (not placed: 0.072 / 0.34, 0.093 / 0.30)
    assert relaxed[1]["surface_from_labels"]["share_of_faces_placed_by_the_scan"] > 0.5
    assert np.abs(error(relaxed[0])).mean() < (0.07 if dim == 3 else 0.062)
    assert np.abs(error(relaxed[0])).max() < 0.26
    # measured, mean |r - R|: 3D 0.083 -> 0.064 (the pull onto the scan: 0.066), 2D 0.117 -> 0.046 (0.056);
    # largest 0.17 and 0.13; mean r - R +0.012 and +0.002 (without the blur's shift taken back -0.035
    # and -0.022: the iso-surface of the blurred ball lies inside it by about s^2 / R)
    assert np.abs(error(alone)).mean() > (0.08 if dim == 3 else 0.11)
    assert np.abs(error(placed)).mean() < (0.066 if dim == 3 else 0.05)
    assert np.abs(error(placed)).max() < (0.18 if dim == 3 else 0.14)
    assert abs(error(placed).mean()) < (0.015 if dim == 3 else 0.005)
    fit = report["surface_from_labels"]
    assert fit["samples_placed_by_the_scan"] > 0.5 * fit["samples"]
    # the edge's variance: 1/12 (partial volume) + 0.6^2 (the phantom's blur) + 0.5^2 (image_sigma)
    assert fit["edge_variance_mm2"]["0|1"] == pytest.approx(1 / 12 + 0.36 + 0.25, rel=0.02)  # measured 0.691, 0.685
    assert report["min_scaled_jacobian"] >= 0.3 and report["inverted_elements"] == 0
    assert "samples_placed_by_the_scan" not in smooth_mesh(mesh, WITHOUT_THE_LAYER, labels=labels)[1][
        "surface_from_labels"]


@pytest.mark.parametrize("dim", [3, 2])
def test_a_part_smaller_than_the_fits_window_is_not_grown_by_the_blurs_shift(dim, monkeypatch):
    """A CT-like ball of radius 3.5 voxels (the fit's window: 5): the fit's samples reach past its
    equator and read it more curved than it is, so the blur's shift taken back is at most a
    sphere's (circle's) of the window's radius. Measured volume against the exact ball, noise-free:
    3D +2.8 % (without the limit +20.1 %, the labels' faces as they are -8.7 %), 2D -0.3 % (+4.2 %,
    -4.5 %); radius 4.5: 3D +1.3 % (+7.0 %)."""
    import tests.test_smooth_image as phantom

    monkeypatch.setattr(phantom, "R", 3.5)
    image = phantom.ct_ball(dim, supersample=5 if dim == 3 else 8, noise=0.0)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    mesh = voxel_mesh(lab)
    exact = 4 / 3 * np.pi * 3.5**3 if dim == 3 else np.pi * 3.5**2
    out, report = smooth_mesh(mesh, labels=Volume(lab, (1.0,) * dim), image=Volume(image, (1.0,) * dim),
                              thresholds=[500.0])
    assert report["surface_from_labels"]["samples_placed_by_the_scan"] > 0
    assert abs(element_volumes(out.points, out.cells).sum() / exact - 1) < (0.04 if dim == 3 else 0.01)


@pytest.mark.parametrize("dim", [3, 2])
def test_the_edge_is_measured_where_the_scan_crosses_between_the_centres(dim):
    """Half the CT-like ball's labels a voxel larger than the scan's (as a coarser downsampling
    makes a part): those faces go to the voxels' centres, off the edge, where the gradient is
    flatter; the edge's variance is read at the crossings only: 0.689 / 0.693 (exact 0.693; taken at
    every placed sample 0.763 / 0.841)."""
    from tests.test_smooth_image import ct_ball

    image = ct_ball(dim, supersample=5 if dim == 3 else 8)
    inside = image >= 500
    larger = ndimage.binary_dilation(inside)
    larger[: inside.shape[0] // 2] = inside[: inside.shape[0] // 2]
    lab = fix_connectivity(larger.astype(np.uint8))[0]
    _, report = smooth_mesh(voxel_mesh(lab), labels=Volume(lab, (1.0,) * dim), image=Volume(image, (1.0,) * dim),
                            thresholds=[500.0])
    assert report["surface_from_labels"]["edge_variance_mm2"]["0|1"] == pytest.approx(1 / 12 + 0.36 + 0.25, rel=0.02)


def test_an_edge_wider_than_a_voxel_takes_no_shift_back():
    """A ball blurred by 2 voxels (an MR image's shading, not a scanner's step): its edge reads
    wider than a voxel squared plus image_sigma squared, so no blur's shift is taken back (0)."""
    from tests.test_smooth_image import ct_ball

    image = ct_ball(3, blur=2.0, noise=0.0)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    _, report = smooth_mesh(voxel_mesh(lab), labels=Volume(lab, (1.0,) * 3), image=Volume(image, (1.0,) * 3),
                            thresholds=[500.0])
    fit = report["surface_from_labels"]
    assert fit["samples_placed_by_the_scan"] > 0.5 * fit["samples"] and fit["edge_variance_mm2"]["0|1"] == 0.0


def test_labels_larger_than_the_scan_shrink_and_the_warning_names_the_scan(tmp_path, caplog, monkeypatch):
    """Labels a voxel larger than the scan's ball of radius 8 all round (as a coarse downsampling
    makes a thin part): the faces placed by the scan take the surface back in, by half a voxel at
    most; the volume warning names the placement, not small parts."""
    import tests.test_smooth_image as phantom
    from dicer.io.images import write_image

    monkeypatch.setattr(phantom, "R", 8.0)
    image = phantom.ct_ball(3)
    lab = fix_connectivity(ndimage.binary_dilation(image >= 500).astype(np.uint8))[0]
    write_mesh(voxel_mesh(lab), tmp_path / "mesh.vtu")
    write_image(Volume(lab, (1.0,) * 3), tmp_path / "labels.nii.gz")
    write_image(Volume(image, (1.0,) * 3), tmp_path / "scan.nii.gz")
    caplog.clear()
    assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / "s.vtu"), "--labels",
                 str(tmp_path / "labels.nii.gz"), "--image", str(tmp_path / "scan.nii.gz"), "--set",
                 "segment.method=manual", "--set", "segment.thresholds=[500]", "--report",
                 str(tmp_path / "s.json")]) == 0
    change = json.loads((tmp_path / "s.json").read_text())["volume_change_from_labels_by_material"]["1"]
    assert -0.12 < change < -0.06  # measured -8.0 %
    said = [r.getMessage() for r in caplog.records if "from the labels' voxels" in r.getMessage()]
    assert len(said) == 1 and "the labels' faces placed by the scan (smooth.fit_to_scan) take the surface in" in said[0]


def test_dicer_run_on_a_scan_places_the_faces_by_it(tmp_path, caplog):
    from dicer.io.images import write_image
    from tests.test_smooth_image import ct_ball

    write_image(Volume(ct_ball(3), (1.0, 1.0, 1.0)), tmp_path / "ball.nii.gz")
    # the labels' faces (placed or not) as the fit's samples: the preset explicit-dynamics
    (tmp_path / "c.yaml").write_text("preset: explicit-dynamics\n"
                                     "materials:\n  - {name: solid, youngs_modulus: 1000, poissons_ratio: 0.3}\n"
                                     "segment: {method: manual, thresholds: [500], opening_radius: 0, "
                                     "closing_radius: 0, keep: all}\n")
    reports = {}
    for on in (False, True):
        out = tmp_path / f"run_{on}"
        assert main(["run", str(tmp_path / "ball.nii.gz"), "-o", str(out), "--config", str(tmp_path / "c.yaml"),
                     "--set", f"smooth.fit_to_scan={str(on).lower()}", "-q"]) == 0
        reports[on] = json.loads((out / "smooth.json").read_text())["surface_from_labels"]
    assert "samples_placed_by_the_scan" not in reports[False]
    assert reports[True]["samples_placed_by_the_scan"] > 0.5 * reports[True]["samples"]
    assert reports[True]["samples"] == reports[False]["samples"]  # the same faces, placed
    # the default (on) is the run with it set
    assert main(["run", str(tmp_path / "ball.nii.gz"), "-o", str(tmp_path / "run_default"), "--config",
                 str(tmp_path / "c.yaml"), "-q"]) == 0
    for name in ("smooth.json", "smoothed.vtu", "model.inp"):
        assert (tmp_path / "run_default" / name).read_bytes() == (tmp_path / "run_True" / name).read_bytes()
    # without a scan (dicer smooth --labels, dicer run --labels) the labels' faces are fitted as they are,
    # without a word: the default finds nothing to place them by
    caplog.clear()
    run = tmp_path / "run_True"
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(tmp_path / "s.vtu"), "--labels",
                 str(run / "labels_fixed.nii.gz")]) == 0
    assert main(["run", "--labels", str(run / "labels_fixed.nii.gz"), "-o", str(tmp_path / "from_labels"), "--config",
                 str(tmp_path / "c.yaml")]) == 0
    assert not [r.getMessage() for r in caplog.records if "fit_to_scan" in r.getMessage()]
    assert "samples_placed_by_the_scan" not in json.loads(
        (tmp_path / "from_labels" / "smooth.json").read_text())["surface_from_labels"]
    # label_samples: relaxed is relaxed through the faces' places: the scan is read, nothing said
    caplog.clear()
    assert main(["run", str(tmp_path / "ball.nii.gz"), "-o", str(tmp_path / "relaxed"), "--config",
                 str(tmp_path / "c.yaml"), "--set", "smooth.label_samples=relaxed", "-q"]) == 0
    assert not [r.getMessage() for r in caplog.records if "fit_to_scan" in r.getMessage() or "--image" in
                r.getMessage()]
    assert json.loads((tmp_path / "relaxed" / "smooth.json").read_text())["surface_from_labels"][
        "samples_placed_by_the_scan"] > 0
    # dicer smooth with --labels and --image: the same, nothing said
    caplog.clear()
    assert main(["smooth", str(run / "merged.vtu"), "-o", str(tmp_path / "r.vtu"), "--labels",
                 str(run / "labels_fixed.nii.gz"), "--image", str(tmp_path / "ball.nii.gz"), "--config",
                 str(tmp_path / "c.yaml"), "--set", "smooth.label_samples=relaxed", "-q"]) == 0
    assert not [r for r in caplog.records if "--image" in r.getMessage() or "fit_to_scan" in r.getMessage()]


def test_stage_by_stage_on_a_scan_gives_the_run_bytes(tmp_path):
    """The README's stages on a scan (segment --info, ..., smooth --labels --image --thresholds)
    write dicer run's files: the faces placed by the scan alike."""
    from dicer.io.images import write_image
    from tests.test_smooth_image import ct_ball

    write_image(Volume(ct_ball(3), (1.0, 1.0, 1.0)), tmp_path / "ball.nii.gz")
    cfg = tmp_path / "c.yaml"
    cfg.write_text("materials:\n  - {name: solid, youngs_modulus: 1000, poissons_ratio: 0.3}\n"
                   "segment: {method: manual, thresholds: [500], opening_radius: 0, closing_radius: 0, keep: all}\n")
    run = tmp_path / "run"
    assert main(["run", str(tmp_path / "ball.nii.gz"), "-o", str(run), "--config", str(cfg), "-q"]) == 0
    t = tmp_path

    def stage(*args):
        assert main([*map(str, args), "--config", str(cfg), "-q"]) == 0

    stage("segment", t / "ball.nii.gz", "-o", t / "labels.nii.gz", "--info", t / "segmentation.json")
    stage("downsample", t / "labels.nii.gz", "-o", t / "labels_ds.nii.gz")
    stage("fix", t / "labels_ds.nii.gz", "-o", t / "labels_fixed.nii.gz")
    stage("mesh", t / "labels_fixed.nii.gz", "-o", t / "mesh.vtu")
    stage("merge", t / "mesh.vtu", "-o", t / "merged.vtu")
    stage("smooth", t / "merged.vtu", "-o", t / "smoothed.vtu", "--labels", t / "labels_fixed.nii.gz",
          "--image", t / "ball.nii.gz", "--thresholds", t / "segmentation.json")
    stage("export", t / "smoothed.vtu", "-o", t / "model.inp")
    for name in ("labels_fixed.nii.gz", "merged.vtu", "smoothed.vtu", "model.inp"):
        assert (t / name).read_bytes() == (run / name).read_bytes(), name


def test_a_scan_that_is_not_the_labels_own_is_said(tmp_path, caplog):
    """The scan given beside the labels places few of their faces when it is another one on the
    same grid (this ball's scan moved by 6 voxels: 24 % of the faces; its own: 99.9 %)."""
    from dicer.io.images import write_image
    from tests.test_smooth_image import ct_ball

    image = ct_ball(3)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    write_mesh(voxel_mesh(lab), tmp_path / "mesh.vtu")
    write_image(Volume(lab, (1.0,) * 3), tmp_path / "labels.nii.gz")
    said = {}
    for name, scan in (("own", image), ("moved", np.roll(image, 6, axis=0))):
        write_image(Volume(scan, (1.0,) * 3), tmp_path / f"{name}.nii.gz")
        caplog.clear()
        assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / f"{name}.vtu"), "--labels",
                     str(tmp_path / "labels.nii.gz"), "--image", str(tmp_path / f"{name}.nii.gz"), "--set",
                     "segment.method=manual", "--set", "segment.thresholds=[500]", "--report",
                     str(tmp_path / f"{name}.json")]) == 0
        said[name] = [r.getMessage() for r in caplog.records if "may not be theirs" in r.getMessage()]
        share = json.loads((tmp_path / f"{name}.json").read_text())["surface_from_labels"]
        said[name + "_share"] = share["share_of_faces_placed_by_the_scan"]
    assert said["own"] == [] and said["own_share"] > 0.95
    assert said["moved_share"] < 0.4 and len(said["moved"]) == 1
    assert said["moved"][0].startswith("smooth: the scan crosses its thresholds between the voxels of only ")
    # labels with no face between two kinds (a crop within one material): nothing to place, nothing said
    block = np.ones((12, 12, 12), np.uint8)
    write_mesh(voxel_mesh(block), tmp_path / "block.vtu")
    write_image(Volume(block, (1.0,) * 3), tmp_path / "block_labels.nii.gz")
    write_image(Volume(np.full(block.shape, 900.0, np.float32), (1.0,) * 3), tmp_path / "block.nii.gz")
    caplog.clear()
    assert main(["smooth", str(tmp_path / "block.vtu"), "-o", str(tmp_path / "b.vtu"), "--labels",
                 str(tmp_path / "block_labels.nii.gz"), "--image", str(tmp_path / "block.nii.gz"), "--set",
                 "segment.method=manual", "--set", "segment.thresholds=[500]", "--report", str(tmp_path / "b.json")]) == 0
    assert not [r for r in caplog.records if "may not be theirs" in r.getMessage()]
    assert "share_of_faces_placed_by_the_scan" not in json.loads((tmp_path / "b.json").read_text())["surface_from_labels"]


def test_a_short_fit_is_said_with_its_cause(tmp_path, caplog):
    """The fit that reached no node was blamed on small parts with 'a smaller radius fits smaller
    parts', at the smallest radius (too few samples in the window) and at a coefficient of 0."""
    from dicer.io.images import write_image

    g = np.arange(24) + 0.5
    r = np.sqrt(sum(x**2 for x in np.meshgrid(g - 12.3, g - 12.3, indexing="ij")))
    write_image(Volume((r < 8.0).astype(np.uint8), (1.0, 1.0)), tmp_path / "disc.nii.gz")
    said = {}
    for name, value in (("radius", "smooth.label_surface_radius=2"), ("still", "smooth.coefficient=0"),
                        ("each", "smooth.coefficients={A: 0, B: 0, C: 0, D: 0, E: 0, F: 0}")):
        caplog.clear()
        assert main(["run", "--labels", str(tmp_path / "disc.nii.gz"), "-o", str(tmp_path / name), "--set",
                     value]) == 0
        said[name] = [m for m in (r.getMessage() for r in caplog.records) if "boundary nodes between" in m]
    assert len(said["radius"]) == 1 and said["radius"][0].endswith(
        "within smooth.label_surface_radius=2 voxels (three per coefficient of the quadric; fewer lie in the window on "
        "elongated voxels or in 2D): a larger smooth.label_surface_radius (more than 2) fits them")
    assert len(said["still"]) == 1 and said["still"][0].endswith(
        "a coefficient of 0 (smooth.coefficient or smooth.coefficients) holds every boundary node where it is")
    assert said["each"] == said["still"]


@pytest.mark.parametrize("part", ["quarter", "full"])
def test_a_node_in_the_middle_of_a_flat_run_is_fitted(part, monkeypatch):
    """The Kirsch plate's hole (radius 7 voxels) in its CT-like image: at the middle of a flat run
    of the staircase the smoothed mesh's normal stands on the run, 25 degrees off the circle's, and
    the fit along it faces too few of the placed faces. It is fitted again along the staircase's
    mean normal about it: every node between the kinds fitted (measured before: 13 of 15, 55 of
    56), the fitted rim within 0.032 / 0.078 voxel of the circle (before: 0.233 and 0.235, the
    node left at the labels' smoothing)."""
    import dicer.mesh.subvoxel as subvoxel
    from dicer.validation import geometry

    image = geometry.kirsch_scan(7.0, 70 if part == "quarter" else 140, part)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    targets = []
    lift = subvoxel.lift

    def capture(sides, on_surface, floor, weight):
        targets.append(on_surface.copy())
        return lift(sides, on_surface, floor, weight)

    monkeypatch.setattr(subvoxel, "lift", capture)
    # measured over 5 voxels, without the pillow layer: the preset explicit-dynamics
    out, report = smooth_mesh(voxel_mesh(lab), WITHOUT_THE_LAYER, labels=Volume(lab, (1.0, 1.0)),
                              image=Volume(image, (1.0, 1.0)), thresholds=[500.0])
    fit = report["surface_from_labels"]
    assert fit["nodes_moved"] == fit["nodes_between_two_kinds"] == (15 if part == "quarter" else 56)
    centre = np.zeros(2) if part == "quarter" else np.array(lab.shape) / 2
    radius = np.linalg.norm(targets[0][:, :2] - centre, axis=1)
    rim = np.abs(radius[radius < 8.5] - 7.0)
    assert rim.size == fit["nodes_between_two_kinds"]
    assert rim.max() < (0.04 if part == "quarter" else 0.09) and rim.mean() < 0.04
    assert report["min_scaled_jacobian"] >= 0.3 and report["inverted_elements"] == 0


def test_a_leaning_fit_is_fitted_again_along_its_own_normal():
    """The CT-like ball (radius 16.3) plane-merged as dicer run merges it, fitted to its labels
    placed by the scan at the floor 0.3: a node whose fit leans more than 17 degrees from the mesh's
    normal is fitted again along the fit's own normal. Measured: the nodes' largest |r - R| 0.259
    voxel, mean 0.101, 82 nodes more than 0.2 off (fitted along the mesh's normals only: 0.724,
    0.108, 150); a part smaller than the window keeps its first fit (the small-part test above)."""
    from tests.test_smooth_image import CENTRE as CT_CENTRE, R as CT_R, ct_ball

    image = ct_ball(3)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    merged, _ = merge_planes(voxel_mesh(lab))
    # measured without the pillow layer, over 5 voxels: the preset explicit-dynamics
    out, report = smooth_mesh(merged, WITHOUT_THE_LAYER, labels=Volume(lab, (1.0,) * 3),
                              image=Volume(image, (1.0,) * 3), thresholds=[500.0])
    nodes = np.flatnonzero(boundary_graph(merged).boundary)
    error = np.abs(np.linalg.norm(out.points[nodes] - CT_CENTRE, axis=1) - CT_R)
    assert error.max() < 0.3 and error.mean() < 0.105 and np.count_nonzero(error > 0.2) < 100
    assert report["min_scaled_jacobian"] >= 0.3 and report["inverted_elements"] == 0


@pytest.mark.parametrize("dim", [3, 2])
def test_a_pillow_layer_puts_the_merged_ct_ball_on_its_sphere(dim):
    """The surface target of docs/validation.md (mean |r - R| <= 0.05 voxel, largest <= 0.2,
    volume within 0.5 %) at dicer run's defaults on the scan but smooth.pillow: the CT-like ball
    plane-merged, its labels' faces placed by the scan, the floor 0.3. The layer's outer nodes lie
    on the fitted surface, which no element with two faces on it bends away, but where the layer
    would be thinner than an eighth of a voxel. Measured 0.022 / 0.155, -0.30 % (3D), 0.025 /
    0.088, -0.19 % (2D); 0.013 / 0.08, -0.40 % (3D) while copies could come within a twentieth of
    a voxel of their nodes; without the layer 0.101 / 0.26 and 0.071 / 0.14 (the floor's corner
    sharpening)."""
    from tests.test_smooth_image import CENTRE as CT_CENTRE, R as CT_R, ct_ball

    image = ct_ball(dim)
    lab = fix_connectivity((image >= 500).astype(np.uint8))[0]
    merged, _ = merge_planes(voxel_mesh(lab))
    out, report = smooth_mesh(merged, {"pillow": True}, labels=Volume(lab, (1.0,) * dim),
                              image=Volume(image, (1.0,) * dim), thresholds=[500.0])
    surface = np.arange(merged.n_points, out.n_points)  # the layer's outer nodes: the surface
    assert surface.size == report["pillow"]["nodes_added"] and report["pillow"]["faces_without_layer"] == 0
    error = np.linalg.norm(out.points[surface, :dim] - CT_CENTRE[:dim], axis=1) - CT_R
    exact = 4 / 3 * np.pi * CT_R**3 if dim == 3 else np.pi * CT_R**2
    volume = element_volumes(out.points, out.cells).sum() / exact - 1
    assert np.abs(error).mean() <= 0.03 and np.abs(error).max() <= (0.17 if dim == 3 else 0.1)
    assert abs(volume) <= 0.005
    assert report["min_scaled_jacobian"] >= 0.3 and report["inverted_elements"] == 0


@pytest.mark.parametrize("dim", [3, 2])
def test_the_ball_at_dicer_runs_defaults_meets_the_surface_targets(dim):
    """The surface targets of docs/validation.md at dicer run's defaults (plane merging, the fit
    over 7 voxels, the floor 0.3, the pillow layer): the CT-like ball (radius 16.3 voxels,
    blurred, noisy), its labels' faces placed by the scan, within 0.05 voxel on average and 0.2
    at most, volume within 0.5 % (measured 0.023 / 0.153, -0.21 %; 2D 0.019 / 0.073, -0.16 %);
    the off-lattice ball from its label volume alone (its staircase relaxed) within 0.12 on
    average (measured 0.038, largest 0.29, -0.23 %; 2D 0.060; the faces' fit without the layer
    0.075, the labels' smoothing alone 0.137). The surface is the layer's outer nodes."""
    from tests.test_smooth_image import CENTRE as CT_CENTRE, R as CT_R, ct_ball

    image = ct_ball(dim)
    for scan, lab, centre, radius in ((True, fix_connectivity((image >= 500).astype(np.uint8))[0], CT_CENTRE, CT_R),
                                      (False, ball_labels(dim), CENTRE, R)):
        merged, _ = merge_planes(voxel_mesh(lab))
        extra = {"image": Volume(image, (1.0,) * dim), "thresholds": [500.0]} if scan else {}
        out, report = smooth_mesh(merged, {}, labels=Volume(lab, (1.0,) * dim), **extra)
        surface = np.arange(merged.n_points, out.n_points)
        assert report["pillow"]["faces_without_layer"] == 0 and surface.size == report["pillow"]["nodes_added"]
        error = np.abs(np.linalg.norm(out.points[surface, :dim] - centre[:dim], axis=1) - radius)
        exact = 4 / 3 * np.pi * radius**3 if dim == 3 else np.pi * radius**2
        volume = element_volumes(out.points, out.cells).sum() / exact - 1
        if scan:
            assert error.mean() <= 0.05 and error.max() <= 0.2 and abs(volume) <= 0.005
            assert error.mean() == pytest.approx(0.023 if dim == 3 else 0.019, abs=0.005)
        else:
            assert error.mean() <= 0.12 and abs(volume) <= 0.005
            assert error.mean() == pytest.approx(0.038 if dim == 3 else 0.060, abs=0.005)
        assert report["min_scaled_jacobian"] >= 0.3 and report["inverted_elements"] == 0


# --- the fit is the same at any voxel size -----------------------------------------------------


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scale=st.sampled_from([1e-4, 0.001, 0.005, 0.37, 3.0, 1000.0]), dim=st.sampled_from([2, 3]),
       scan=st.sampled_from(["none", "faces placed", "pulled onto it"]), relaxed=st.booleans(), pillow=st.booleans())
@example(scale=0.001, dim=3, scan="none", relaxed=False, pillow=False)  # the damping flattened it (-14 % of a ball)
@example(scale=1000.0, dim=3, scan="faces placed", relaxed=False, pillow=False)  # the fit did nothing
def test_a_volume_on_voxels_of_any_size_smooths_as_on_millimetre_ones(scale, dim, scan, relaxed, pillow):
    """The same labels (and scan) on voxels ``scale`` times as large, merged and smoothed as
    ``dicer run`` does (the labels' fit; their faces placed by the scan, or the surface pulled
    onto it; relaxed samples; a pillow layer): the nodes ``scale`` times as far from the origin,
    to 1e-5 voxel (rounding: measured up to 4e-6 at any scale, 0.37 and 3 among them), after as
    many solver iterations and back-off rounds. Until the fit worked in voxels its least-squares damping, relative to terms
    in mm, flattened the quadric at micrometre voxels (a ball's core -14.6 % at 1 um) and pinned
    its height at metre ones."""
    base = (0.8, 1.0, 1.6)[:dim]
    lab = ball_labels(dim, radii=(9.3, 5.2), n=24)
    # a blurred, partial-volume image of the same labels
    image = ndimage.gaussian_filter(np.where(lab > 0, 1000.0, 0.0) + 400.0 * (lab == 2), 0.7)
    settings = {"pillow": pillow, "label_samples": "relaxed" if relaxed else "faces",
                "surface_from_image": scan == "pulled onto it"}
    out = []
    for factor in (1.0, scale):
        spacing = tuple(factor * h for h in base)
        mesh, _ = merge_planes(voxel_mesh(lab, spacing), passes=(1,) * dim)
        extra = {"image": Volume(image, spacing), "thresholds": [500.0, 1200.0]} if scan != "none" else {}
        labels = Volume(lab, spacing) if scan != "pulled onto it" else None
        smoothed, report = smooth_mesh(mesh, settings, labels=labels, **extra)
        out.append((smoothed.points[:, :dim] / np.asarray(spacing),
                    [report[k] for k in ("boundary_iterations", "interior_iterations", "backoff_rounds")]))
    assert out[0][0].shape == out[1][0].shape and out[0][1] == out[1][1]
    assert np.abs(out[1][0] - out[0][0]).max() < 1e-5
