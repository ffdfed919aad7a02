"""Finite-element validation (docs/validation.md): dicer's models of a plate with a hole
(Kirsch) and a thick-walled tube (Lamé), made from label images by ``dicer run --labels``
and from CT-like grey-value images by ``dicer run`` on the image (the surface pulled onto
the image's iso-line), solved with CalculiX; stresses from its .frd output against the
closed-form values.

Each assertion pins the figure the current code measures (docs/validation.md's tables)
within a small margin. The accuracy targets at dicer run's defaults are the tests at the end;
"the former defaults" are those until 7 December 2026 (the preset explicit-dynamics: no pillow
layer, the labels' faces, the fit over 5 voxels, midpoint mid-edge nodes;
``dicer.validation.study.TODAY`` over the study's base), and the strict xfail tests record the
targets those and other settings miss.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calculix import needs_ccx

from dicer.validation import cases, geometry, reference, study
from dicer.validation.study import CURVED, DEFAULTS, FIT, FIT_TO_SCAN, MIN_SJ_03, NO_MERGE, OFFSET, PILLOW, TODAY, UNPLACED

pytestmark = [pytest.mark.calculix, needs_ccx]


def test_lame_quarter_tube_end_to_end(tmp_path):
    """Fast: the smallest case through dicer run, export, ccx and the .frd reader (a = 7 voxels)."""
    r = cases.lame(tmp_path, "quarter", [NO_MERGE], inner=7.0, outer=14.0, orders=(1,))
    assert r["inverted"] == 0 and r["min_sj"] == pytest.approx(0.4287, abs=0.005)
    e = r[1]
    assert e["elements"] == 230 and e["bore_nodes"] > 20
    assert e["exact"] == pytest.approx(5 / 3)
    assert e["error_mean"] == pytest.approx(-0.1415, abs=0.01)  # bore nodes' mean, 14 % low
    assert e["error_wall_fit"] == pytest.approx(0.049, abs=0.01)  # the field inside the wall
    assert e["bore_radius_mean"] == pytest.approx(7.036, abs=0.01)


def test_grey_value_images():
    """The CT-like images: the quarter is the full plate's image cut; thresholded at the
    half contrast they are the label images but for the few voxels the edge's curvature
    and the noise tip."""
    full, quarter = geometry.kirsch_scan(part="full"), geometry.kirsch_scan(part="quarter")
    assert full.shape == (140, 140) and full.dtype == np.float32
    assert np.array_equal(quarter, full[70:, 70:])
    labels = geometry.kirsch_plate(part="full")
    differ = np.count_nonzero((full >= geometry.THRESHOLD) != labels.astype(bool))
    assert 0 < differ <= 4  # measured 1 of the 44 voxels along the rim
    # far from the rim: the contrast and the noise
    assert np.mean(full[:20, :20]) == pytest.approx(geometry.CONTRAST, abs=5.0)
    assert np.std(full[:20, :20]) == pytest.approx(30.0, rel=0.15)
    tube = geometry.lame_scan(part="quarter")
    ring = geometry.lame_cylinder(part="quarter").astype(bool)
    assert tube.shape == ring.shape == (15, 15, 2)
    assert np.count_nonzero((tube >= geometry.THRESHOLD) != ring) <= 4  # measured 2


def test_lame_quarter_tube_from_a_grey_value_image(tmp_path):
    """Fast: the grey-value path end to end (dicer run on the image, manual threshold, the bore
    pulled onto the iso-line; a = 7 voxels, C3D8)."""
    r = cases.lame(tmp_path, "quarter", [NO_MERGE], inner=7.0, outer=14.0, orders=(1,), scan=True)
    assert r["inverted"] == 0 and r["min_sj"] == pytest.approx(0.22, abs=0.005)
    e = r[1]
    assert e["error_mean"] == pytest.approx(-0.043, abs=0.01)  # from labels: -0.1415
    assert e["error_wall_fit"] == pytest.approx(-0.008, abs=0.01)
    assert e["bore_radius_mean"] == pytest.approx(6.982, abs=0.01)


def test_lame_quarter_tube_from_a_grey_value_image_with_a_pillow_layer(tmp_path):
    """Fast: the pillow layer over the bore (smooth.pillow, a = 7 voxels, C3D8): the bore's mean
    hoop stress within 3 % (without the layer -4.8 %)."""
    r = cases.lame(tmp_path, "quarter", [NO_MERGE, PILLOW], inner=7.0, outer=14.0, orders=(1,), scan=True)
    assert r["inverted"] == 0 and r["min_sj"] == pytest.approx(0.225, abs=0.005)
    e = r[1]
    assert e["elements"] == 312  # 228 and a layer of 84
    assert e["error_mean"] == pytest.approx(0.004, abs=0.01) and abs(e["error_mean"]) <= 0.03
    assert abs(e["error_wall_fit"]) < 0.01


def test_lame_quarter_tube_from_labels_with_the_fitted_surface(tmp_path):
    """Fast: the bore fitted to the labels' staircase (smooth.surface_from_labels, a = 7 voxels,
    C3D8): the mean hoop stress -7.6 %, from -14.2 % without the fit."""
    r = cases.lame(tmp_path, "quarter", [NO_MERGE, FIT], inner=7.0, outer=14.0, orders=(1,))
    assert r["inverted"] == 0 and r["min_sj"] == pytest.approx(0.22, abs=0.005)
    e = r[1]
    assert e["elements"] == 230
    assert e["error_mean"] == pytest.approx(-0.076, abs=0.01)
    assert e["bore_radius_mean"] == pytest.approx(7.044, abs=0.01)


RELAXED = "smooth.label_samples=relaxed"


def test_lame_quarter_tube_from_labels_relaxed_with_a_pillow_layer_meets_3_percent(tmp_path):
    """The Lamé target from labels alone (inner radius 7 voxels, C3D8 and C3D20): the fit to the
    staircase relaxed within its voxels, a pillow layer, no merging: the bore's mean hoop stress
    +0.7 % and -1.2 % (measured; at a = 14 -0.2 % and -1.1 %; with the umbrella energy before
    late on 6 December 2026 +0.0 % and -0.6 %; the faces' centres read -2.7 % and -4.9 %)."""
    r = cases.lame(tmp_path, "quarter", [NO_MERGE, FIT, MIN_SJ_03, PILLOW, RELAXED], inner=7.0, outer=14.0)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.3
    for order, measured in ((1, 0.0074), (2, -0.0122)):
        assert r[order]["error_mean"] == pytest.approx(measured, abs=0.005)
        assert abs(r[order]["error_mean"]) < 0.03


def test_lame_quarter_tube_from_a_grey_value_image_with_the_faces_placed_by_it_meets_3_percent(tmp_path):
    """The Lamé target from the CT-like image (inner radius 7 voxels, C3D8 and C3D20): the fit to
    the threshold's labels with their faces placed by the scan (smooth.fit_to_scan), a pillow
    layer, no merging, the floor 0.3: the bore's mean hoop stress +1.7 % and +0.7 % (measured;
    its mean radius 7.018; at a = 14 +0.9 % and +0.0 %)."""
    r = cases.lame(tmp_path, "quarter", ["smooth.surface_from_image=false", FIT, FIT_TO_SCAN, NO_MERGE, MIN_SJ_03,
                                         PILLOW], inner=7.0, outer=14.0, scan=True)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.3
    for order, measured in ((1, 0.0172), (2, 0.0065)):
        assert r[order]["error_mean"] == pytest.approx(measured, abs=0.005)
        assert abs(r[order]["error_mean"]) < 0.03
    assert r[1]["bore_radius_mean"] == pytest.approx(7.018, abs=0.005)


@pytest.mark.parametrize("scan,c3d8,c3d20", [(False, -0.0155, -0.0296), (True, -0.0065, 0.0073)],
                         ids=["labels", "image"])
def test_lame_quarter_tube_at_former_defaults_with_a_pillow_layer_meets_3_percent(tmp_path, scan, c3d8, c3d20):
    """dicer run's former defaults (plane merging: 53 elements with the layer, the labels' fit, the floor
    0.3) and smooth.pillow: the bore within 3 %, C3D8 and C3D20, from labels and from the image
    (measured; at a = 14 -0.4 / -2.2 % and +0.2 / -0.0 %; -1.1 / -2.3 % and -0.6 / +1.5 % at a = 7
    while the layer's copies could come within a twentieth of a voxel of their nodes, not an
    eighth). Until plane nodes' normals counted their
    mirror images (6 December 2026) the quarter's bore nodes on the planes stayed inside the hole:
    -6.1 / -13.8 % and -5.6 / -9.2 %."""
    r = cases.lame(tmp_path, "quarter", TODAY + [PILLOW], inner=7.0, outer=14.0, scan=scan)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.3
    for order, measured in ((1, c3d8), (2, c3d20)):
        assert r[order]["error_mean"] == pytest.approx(measured, abs=0.005)
        assert abs(r[order]["error_mean"]) < 0.03


@pytest.mark.parametrize("order,at_90", [(1, 3.0503), (2, 3.0213)])
def test_kirsch_ogrid_reference(tmp_path, order, at_90):
    """An ideal mesh of dicer's element size (11 elements along the quarter rim, 1 voxel deep,
    exact displacements at r = 5a): CPS4 reads 1.7 %, CPS8 0.7 % above Kirsch's 3.0."""
    r = reference.kirsch_ogrid(tmp_path, order)
    assert r["elements"] == 143
    assert r["sigma_x_90"] == pytest.approx(at_90, abs=0.002)
    assert r["sigma_x_90"] == pytest.approx(3.0, rel=0.03)


def test_the_cases_square_plate_under_tension_reads_above_kirschs_value(tmp_path):
    """The finite plate the Kirsch cases solve (L = 20 a, uniform tension on X1) on a mapped
    8-node mesh: converged to 3.09, not Kirsch's 3.0 (measured 3.0861, 3.0931, 3.0949 at 32, 64
    and 128 elements along the quarter rim): the cases are read against 3.0 with Kirsch's
    displacements on their outer edges (cases.kirsch_edges)."""
    coarse = reference.kirsch_square(tmp_path / "coarse", n=32)
    fine = reference.kirsch_square(tmp_path / "fine", n=64)
    assert coarse["elements"] == 1024 and fine["elements"] == 4096
    assert fine["sigma_x_90"] == pytest.approx(3.0931, abs=0.001)
    assert coarse["sigma_x_90"] < fine["sigma_x_90"] < 3.1  # from below, by less each time
    assert fine["sigma_x_90"] - 3.0 > 0.03  # outside a 1 % tolerance about Kirsch's 3.0


def test_kirsch_displacement_is_kirsch():
    # at the rim: u_r = sigma0 a / E (1 + 2 cos 2 theta) in plane stress
    t = np.linspace(0.0, np.pi / 2, 7)
    ux, uy = reference.kirsch_displacement(7.0 * np.cos(t), 7.0 * np.sin(t), 7.0)
    ur = ux * np.cos(t) + uy * np.sin(t)
    assert ur == pytest.approx(7.0 / 1000.0 * (1 + 2 * np.cos(2 * t)), rel=1e-12)


@pytest.fixture(scope="module")
def kirsch_defaults(tmp_path_factory):
    """Quarter and full plate at the default smoothing, no merging, CPS4 and CPS8."""
    return {part: cases.kirsch(tmp_path_factory.mktemp(f"kirsch_{part}"), part, [NO_MERGE],
                               on_circle=part == "quarter") for part in ("quarter", "full")}


@pytest.mark.slow
@pytest.mark.parametrize("order,at_90,peak,angle", [(1, 2.4604, 3.0091, 74.0), (2, 2.3060, 4.0197, 67.0)])
def test_kirsch_plate_at_default_smoothing(kirsch_defaults, order, at_90, peak, angle):
    q, f = kirsch_defaults["quarter"], kirsch_defaults["full"]
    assert q["min_sj"] == pytest.approx(0.396, abs=0.005) and q["inverted"] == 0
    assert q[order]["sigma_x_90"] == pytest.approx(at_90, abs=0.02)
    assert q[order]["peak"] == pytest.approx(peak, abs=0.03)
    assert q[order]["peak_angle_deg"] == pytest.approx(angle, abs=3.0)
    assert q[order]["rim_radius_90"] == pytest.approx(7.007, abs=0.005)
    # the full plate is the quarter mirrored (hole centre on a voxel corner): the same stresses
    assert f[order]["sigma_x_90_each"][0] == pytest.approx(f[order]["sigma_x_90_each"][1], abs=1e-4)
    assert f[order]["sigma_x_90"] == pytest.approx(q[order]["sigma_x_90"], abs=2e-4)
    assert f[order]["peak"] == pytest.approx(q[order]["peak"], abs=2e-4)


@pytest.mark.slow
@pytest.mark.parametrize("k,min_sj,cps4,cps8", [(0.0, 1.0, 2.3394, 2.1795), (0.8, 0.311, 2.7673, 2.5469)])
def test_kirsch_quarter_plate_against_the_coefficient(tmp_path, k, min_sj, cps4, cps8):
    r = cases.kirsch(tmp_path, "quarter", [NO_MERGE, f"smooth.coefficient={k}"])
    assert r["min_sj"] == pytest.approx(min_sj, abs=0.005) and r["inverted"] == 0
    assert r[1]["sigma_x_90"] == pytest.approx(cps4, abs=0.02)
    assert r[2]["sigma_x_90"] == pytest.approx(cps8, abs=0.02)


@pytest.mark.slow
def test_label_only_targets_with_a_pillow_layer_relaxed_samples_and_curved_mid_edge_nodes(tmp_path):
    """dicer run --labels at its former defaults (plane merging, the labels' fit, the floor 0.3) with
    smooth.pillow, smooth.label_samples: relaxed (the staircase relaxed to least variation of
    curvature) and export.midside_nodes: curved meets every label-only target (docs/validation.md
    §4): the Kirsch plate within 8 %, largest at 90 deg, CPS4 and CPS8 (measured 2.856 and 2.890
    against Kirsch's field; the umbrella energy until late on 6 December 2026 read 2.750, -8.3 %), the
    Lame bore within 3 %, C3D8 and C3D20 (measured +0.3 / -2.1 % at a = 7, +0.2 / -1.4 % at 14;
    the faces' centres -1.6 / -7.2 %)."""
    sets = [FIT, MIN_SJ_03, PILLOW, RELAXED, CURVED]
    k = cases.kirsch(tmp_path / "plate", "quarter", sets)
    assert k["inverted"] == 0 and k["min_sj"] >= 0.3
    for order, measured in ((1, 2.856), (2, 2.890)):
        e = k[order]["kirsch_edges"]
        assert e["sigma_x_90"] == pytest.approx(measured, abs=0.01) and abs(e["sigma_x_90"] / 3.0 - 1) < 0.08
        assert abs(e["peak"] / 3.0 - 1) < 0.08 and abs(e["peak_angle_deg"] - 90) <= 10
    for a, c3d8, c3d20 in ((7.0, 0.0031, -0.0210), (14.0, 0.0015, -0.0138)):
        r = cases.lame(tmp_path / f"tube{a:g}", "quarter", sets, inner=a, outer=2 * a)
        assert r["inverted"] == 0 and r["min_sj"] >= 0.3
        for order, measured in ((1, c3d8), (2, c3d20)):
            assert r[order]["error_mean"] == pytest.approx(measured, abs=0.005)
            assert abs(r[order]["error_mean"]) < 0.03


def test_kirsch_cps8_with_curved_mid_edge_nodes_at_former_defaults_from_labels(tmp_path):
    """dicer run --labels at its former defaults (plane merging, the labels' fit, the floor 0.3) and
    export.midside_nodes: curved, which on the merged mesh puts the rim's mid-edge nodes on
    arcs through the next rim nodes (docs/validation.md §1c); with midpoints 3.187 (+6.2 %)."""
    r = cases.kirsch(tmp_path, "quarter", [FIT, MIN_SJ_03, CURVED], orders=(2,))
    assert r["min_sj"] == pytest.approx(0.319, abs=0.005) and r["inverted"] == 0
    assert r[2]["sigma_x_90"] == pytest.approx(3.057, abs=0.01)  # +1.9 %
    assert r[2]["peak"] == pytest.approx(3.112, abs=0.01) and r[2]["peak_angle_deg"] == pytest.approx(82, abs=3)
    assert r[2]["rim_fit_90"] == pytest.approx(3.034, abs=0.01)
    # against Kirsch's own field (his displacements on the outer edges): the finite plate's
    # 3.2 % gone, 2.965 (-1.2 %) at 90 deg, the largest 3.020 at 82 deg
    e = r[2]["kirsch_edges"]
    assert e["sigma_x_90"] == pytest.approx(2.965, abs=0.01) and e["sigma_x_90"] < r[2]["sigma_x_90"] - 0.07
    assert e["peak"] == pytest.approx(3.020, abs=0.01) and e["peak_angle_deg"] == pytest.approx(82, abs=3)


@pytest.mark.slow
def test_kirsch_quarter_plate_dicer_run_defaults(tmp_path):
    # the whole default chain, plane merging included: the merged rim smooths inward at 90 deg
    r = cases.kirsch(tmp_path, "quarter", [])
    assert r["min_sj"] == pytest.approx(0.574, abs=0.005) and r["inverted"] == 0
    assert r[1]["sigma_x_90"] == pytest.approx(2.6193, abs=0.02)
    assert r[2]["sigma_x_90"] == pytest.approx(2.7624, abs=0.02)
    assert r[1]["rim_radius_90"] == pytest.approx(6.46, abs=0.02)


@pytest.mark.slow
def test_kirsch_full_plate_off_the_lattice(tmp_path):
    # hole centre off the lattice: +90 and -90 deg see different staircases
    r = cases.kirsch(tmp_path, "full", [NO_MERGE], offset=OFFSET)
    assert r["min_sj"] == pytest.approx(0.239, abs=0.005) and r["inverted"] == 0
    assert r[1]["sigma_x_90_each"] == pytest.approx([2.547, 3.177], abs=0.03)
    assert r[2]["sigma_x_90_each"] == pytest.approx([2.411, 2.965], abs=0.03)


@pytest.mark.slow
@pytest.mark.parametrize("a,c3d8,c3d20", [(14.0, -0.110, -0.194), (28.0, -0.103, -0.202)])
def test_lame_refined(tmp_path, a, c3d8, c3d20):
    # the bore nodes stay low as the tube is refined (the voxel-scale ripple refines with
    # it), while the field inside the wall converges
    r = cases.lame(tmp_path, "quarter", [NO_MERGE], inner=a, outer=2 * a)
    assert r["inverted"] == 0
    assert r[1]["error_mean"] == pytest.approx(c3d8, abs=0.01)
    assert r[2]["error_mean"] == pytest.approx(c3d20, abs=0.01)
    assert abs(r[1]["error_wall_fit"]) < 0.01 and abs(r[2]["error_wall_fit"]) < 0.015


def kirsch_target(quarter: dict, full: dict, order: int, rel: float, edges: bool = False) -> None:
    """The Kirsch target (docs/validation.md): sigma_x at 90 deg and the largest rim stress
    within ``rel`` of 3.0, the largest at 90 +- 10 deg, min SJ >= 0.3, 0 inverted, quarter and
    full plate within 1 %; ``edges``: read with Kirsch's displacements on the outer edges (exact
    3.0), else under the uniform tension (the finite plate: exact 3.095)."""
    for r in (quarter, full):
        assert r["min_sj"] >= 0.3 and r["inverted"] == 0
        e = r[order]["kirsch_edges"] if edges else r[order]
        assert e["sigma_x_90"] == pytest.approx(3.0, rel=rel)
        assert e["peak"] == pytest.approx(3.0, rel=rel)
        assert abs(e["peak_angle_deg"] - 90.0) <= 10.0
    q, f = (quarter[order], full[order]) if not edges else (quarter[order]["kirsch_edges"], full[order]["kirsch_edges"])
    assert q["sigma_x_90"] == pytest.approx(f["sigma_x_90"], rel=0.01)


def kirsch_figures(r: dict, min_sj: float, cps4: tuple, cps8: tuple, peak_abs: float = 0.02) -> None:
    """One Kirsch result against its recorded figures: min SJ, 0 inverted, and per element type
    (sigma_x at 90 deg, largest rim stress, its angle)."""
    assert r["min_sj"] == pytest.approx(min_sj, abs=0.005) and r["inverted"] == 0
    for order, (at_90, peak, angle) in ((1, cps4), (2, cps8)):
        assert r[order]["sigma_x_90"] == pytest.approx(at_90, abs=0.02)
        assert r[order]["peak"] == pytest.approx(peak, abs=peak_abs)
        assert r[order]["peak_angle_deg"] == pytest.approx(angle, abs=3.0)


@pytest.fixture(scope="module")
def kirsch_fit(tmp_path_factory):
    """Quarter and full plate from the labels with the surface fitted to their staircase
    (smooth.surface_from_labels), the guard's floor at 0.3: without plane merging and with it
    (the default chain)."""
    return {(part, merge): cases.kirsch(tmp_path_factory.mktemp(f"kirsch_fit_{part}"), part,
                                        ([] if merge else [NO_MERGE]) + [FIT, MIN_SJ_03])
            for part in ("quarter", "full") for merge in (False, True)}


@pytest.mark.slow
@pytest.mark.parametrize("merge,cps4,cps8", [(False, (3.1262, 3.1789, 82.5), (2.9369, 3.2377, 75.3)),
                                             (True, (3.2391, 3.2391, 90.0), (3.1872, 3.1872, 90.0))])
def test_kirsch_plate_from_labels_with_the_fitted_surface(kirsch_fit, merge, cps4, cps8):
    q, f = kirsch_fit[("quarter", merge)], kirsch_fit[("full", merge)]
    for r in (q, f):
        kirsch_figures(r, 0.32, cps4, cps8)
    for order in (1, 2):  # the cut plate fits as the whole one
        assert f[order]["sigma_x_90"] == pytest.approx(q[order]["sigma_x_90"], abs=2e-4)


@pytest.mark.slow
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_from_labels_with_the_fitted_surface(kirsch_fit, order):
    """The Kirsch target from the label image alone (within 8 % of 3.0 at 90 deg, the largest
    rim stress within 8 % and at 90 +- 10 deg, min SJ >= 0.3, quarter and full within 1 %),
    met by dicer run's default chain (since 5 December 2026 with smooth.surface_from_labels and
    smooth.min_scaled_jacobian 0.3; measured: CPS4 3.233 (+7.8 %), CPS8 3.184 (+6.1 %), both
    largest at 90 deg, min SJ 0.320, the fit taking the labels before merging; fitted to the
    merged mesh's faces, whose chamfers lie inside the labels' rim, 3.025 and 3.106; the labels'
    smoothing alone at 0.2 read 2.619, -12.7 %). Without plane merging the CPS8 largest rim stress sits at 72-75 deg (two rim
    nodes read within 0.001 of each other)."""
    kirsch_target(kirsch_fit[("quarter", True)], kirsch_fit[("full", True)], order, 0.08)


@pytest.mark.slow
@pytest.mark.parametrize("order,at_90", [(1, 3.150), (2, 3.094)])
def test_kirsch_from_labels_at_former_defaults_against_kirschs_field(kirsch_fit, order, at_90):
    """The same decks with Kirsch's displacements on the outer edges (exact 3.0): CPS4 +5.0 %,
    CPS8 +3.1 % (under the finite plate's tension +8.0 / +6.2 % against 3.0, +4.7 / +3.0 %
    against its own 3.095), quarter and full alike."""
    kirsch_target(kirsch_fit[("quarter", True)], kirsch_fit[("full", True)], order, 0.08, edges=True)
    for part in ("quarter", "full"):
        assert kirsch_fit[(part, True)][order]["kirsch_edges"]["sigma_x_90"] == pytest.approx(at_90, abs=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("a,c3d8,c3d20", [(14.0, -0.0448, -0.0626), (28.0, -0.0227, -0.0467)])
def test_lame_from_labels_with_the_fitted_surface_refined(tmp_path, a, c3d8, c3d20):
    r = cases.lame(tmp_path, "quarter", [NO_MERGE, FIT], inner=a, outer=2 * a)
    assert r["inverted"] == 0
    assert r[1]["error_mean"] == pytest.approx(c3d8, abs=0.01)
    assert r[2]["error_mean"] == pytest.approx(c3d20, abs=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("a,c3d8,c3d20", [(7.0, -0.0482, -0.0685), (14.0, -0.0773, -0.1073)])
def test_lame_at_former_defaults(tmp_path, a, c3d8, c3d20):
    """dicer run's former defaults (the labels' fit, the floor 0.3, plane merging: 33 and 125 elements);
    fitted to the merged mesh's faces, before the fit took the labels, a = 7 read -13.1 % / -15.7 %;
    until the fit mirrored the normals of plane nodes (6 December 2026) -9.6 % / -15.0 %, the
    bore's nodes on the planes 0.3 voxel inside the hole."""
    r = cases.lame(tmp_path, "quarter", [FIT, MIN_SJ_03], inner=a, outer=2 * a)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.3
    assert r[1]["error_mean"] == pytest.approx(c3d8, abs=0.01)
    assert r[2]["error_mean"] == pytest.approx(c3d20, abs=0.01)
    assert r[1]["bore_radius_mean"] == pytest.approx(a, abs=0.1)  # measured 7.044 and 13.99


# --- from a grey-value image: dicer run on a CT-like image, the rim on its iso-line ---------


@pytest.fixture(scope="module")
def kirsch_scan(tmp_path_factory):
    """Quarter and full plate from the grey-value image, no merging, at the default smoothing
    and with the guard's floor at 0.3."""
    return {(part, name): cases.kirsch(tmp_path_factory.mktemp(f"kirsch_scan_{part}"), part, sets, scan=True,
                                       on_circle=(part, name) == ("quarter", "defaults"))
            for part in ("quarter", "full") for name, sets in (("defaults", [NO_MERGE]),
                                                               ("min SJ 0.3", [NO_MERGE, MIN_SJ_03]))}


@pytest.mark.slow
@pytest.mark.parametrize("part,name,min_sj,cps4,cps8", [
    ("quarter", "defaults", 0.220, (3.2296, 3.2296, 90.0), (3.0775, 3.2912, 79.1)),
    ("full", "defaults", 0.220, (3.1466, 3.1894, 83.0), (3.0104, 3.3308, 79.2)),
    ("quarter", "min SJ 0.3", 0.320, (3.2176, 3.2176, 90.0), (3.0562, 3.3272, 79.1)),
    ("full", "min SJ 0.3", 0.320, (3.1394, 3.1895, 83.0), (3.0014, 3.3670, 79.2)),
])
def test_kirsch_plate_from_a_grey_value_image(kirsch_scan, part, name, min_sj, cps4, cps8):
    kirsch_figures(kirsch_scan[(part, name)], min_sj, cps4, cps8, peak_abs=0.03)


@pytest.mark.slow
def test_kirsch_rim_from_a_grey_value_image(kirsch_scan, kirsch_defaults):
    # the rim nodes' distance from the hole's circle: labels 0.186 mean, 0.52 largest;
    # from the image 0.060 and 0.13 (noise of 30 on 1000 and the guard's sharpened corners)
    labels, scan = kirsch_defaults["quarter"][1], kirsch_scan[("quarter", "defaults")][1]
    assert labels["rim_radius_error_mean"] == pytest.approx(0.186, abs=0.005)
    assert labels["rim_radius_error_max"] == pytest.approx(0.522, abs=0.005)
    assert scan["rim_radius_error_mean"] == pytest.approx(0.060, abs=0.005)
    assert scan["rim_radius_error_max"] == pytest.approx(0.129, abs=0.005)
    assert scan["rim_radius_90"] == pytest.approx(7.039, abs=0.005)
    floor = kirsch_scan[("quarter", "min SJ 0.3")][1]  # a higher floor sharpens the corners more
    assert floor["rim_radius_error_mean"] == pytest.approx(0.069, abs=0.005)
    # the field about the hole: Kirsch's form fitted through the rim nodes, at 90 deg (about
    # 3.03 for this finite plate): the labels' rim makes it 12 % (CPS4) and 18 % (CPS8) low,
    # the image's 2.7 %; the nodes scatter about it by 0.17 (CPS4) and 0.31 (CPS8)
    for order, from_labels, from_scan, scatter in ((1, 2.636, 2.946, 0.17), (2, 2.474, 2.958, 0.31)):
        assert kirsch_defaults["quarter"][order]["rim_fit_90"] == pytest.approx(from_labels, abs=0.01)
        assert kirsch_scan[("quarter", "defaults")][order]["rim_fit_90"] == pytest.approx(from_scan, abs=0.01)
        assert kirsch_scan[("full", "defaults")][order]["rim_fit_90"] == pytest.approx(from_scan, abs=0.05)
        assert kirsch_scan[("quarter", "defaults")][order]["rim_fit_scatter"] == pytest.approx(scatter, abs=0.02)


@pytest.mark.slow
def test_kirsch_rim_on_the_exact_circle(kirsch_defaults, kirsch_scan):
    """The rim nodes moved onto r = a exactly: the same elements still read 5-6 % above 3.0
    (the O-grid of this size: CPS4 +1.7 %, CPS8 +0.7 %, and the finite plate about 1 % more),
    whether the mesh came from the labels or from the image: the element layout, not the
    rim's position."""
    for r, cps4, cps8 in ((kirsch_defaults["quarter"], 3.175, 3.182), (kirsch_scan[("quarter", "defaults")],
                                                                        3.183, 3.156)):
        assert r["1 on circle"]["rim_radius_error_max"] < 1e-9
        assert r["1 on circle"]["sigma_x_90"] == pytest.approx(cps4, abs=0.01)
        assert r["2 on circle"]["sigma_x_90"] == pytest.approx(cps8, abs=0.01)


@pytest.fixture(scope="module")
def kirsch_scan_clean(tmp_path_factory):
    """Quarter and full plate from the grey-value image without noise, guard's floor 0.3."""
    return {part: cases.kirsch(tmp_path_factory.mktemp(f"kirsch_clean_{part}"), part, [NO_MERGE, MIN_SJ_03],
                               scan=True, noise=0.0) for part in ("quarter", "full")}


@pytest.mark.slow
def test_kirsch_plate_from_a_noise_free_image(kirsch_scan_clean):
    # without noise the quarter and the full plate agree again (the full plate is the quarter
    # mirrored), and the rim fit is the finite plate's 3.0
    q, f = kirsch_scan_clean["quarter"], kirsch_scan_clean["full"]
    for r in (q, f):
        assert r["min_sj"] == pytest.approx(0.320, abs=0.005) and r["inverted"] == 0
        assert r[1]["sigma_x_90"] == pytest.approx(3.150, abs=0.01)
        assert r[2]["sigma_x_90"] == pytest.approx(3.060, abs=0.01)
        assert r[2]["peak"] == pytest.approx(3.076, abs=0.01) and r[2]["peak_angle_deg"] == pytest.approx(82.4, abs=1)
        assert r[1]["rim_fit_90"] == pytest.approx(3.0, abs=0.02)
    for order in (1, 2):
        assert f[order]["sigma_x_90"] == pytest.approx(q[order]["sigma_x_90"], abs=1e-3)
        assert f[order]["peak"] == pytest.approx(q[order]["peak"], abs=1e-3)


@pytest.mark.slow
def test_target_kirsch_cps8_from_a_noise_free_image(kirsch_scan_clean):
    """The Kirsch target holds for CPS8 from the grey-value image without noise, at
    smooth.min_scaled_jacobian 0.3 (measured: 3.060 at 90 deg, largest 3.076 at 82 deg, min SJ
    0.320, quarter and full within 0.02 %)."""
    q, f = kirsch_scan_clean["quarter"], kirsch_scan_clean["full"]
    for r in (q, f):
        assert r["min_sj"] >= 0.3 and r["inverted"] == 0
        assert r[2]["sigma_x_90"] == pytest.approx(3.0, rel=0.03)
        assert r[2]["peak"] == pytest.approx(3.0, rel=0.03)
        assert abs(r[2]["peak_angle_deg"] - 90.0) <= 10.0
    assert q[2]["sigma_x_90"] == pytest.approx(f[2]["sigma_x_90"], rel=0.01)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="CPS4 from the noise-free image at min SJ 0.3: sigma_x(90) 3.150 (+5.0 %); "
                   "the O-grid reference of the same element size reads +1.7 % (infinite plate)")
def test_target_kirsch_cps4_from_a_noise_free_image(kirsch_scan_clean):
    for r in kirsch_scan_clean.values():
        assert r[1]["sigma_x_90"] == pytest.approx(3.0, rel=0.03)


@pytest.fixture(scope="module")
def kirsch_scan_clean_pillow(tmp_path_factory):
    """Quarter and full plate from the grey-value image without noise, with the pillow layer,
    guard's floor 0.3."""
    return {part: cases.kirsch(tmp_path_factory.mktemp(f"kirsch_pillow_{part}"), part,
                               [NO_MERGE, PILLOW, MIN_SJ_03], scan=True, noise=0.0) for part in ("quarter", "full")}


@pytest.mark.slow
def test_target_kirsch_with_a_pillow_layer_from_a_noise_free_image(kirsch_scan_clean_pillow):
    """The Kirsch target, CPS4 and CPS8, from the partial-volume image with the pillow layer at
    smooth.min_scaled_jacobian 0.3 (measured: CPS4 3.077 at 90 deg, the largest there; CPS8
    3.034, largest 3.082 at 82 deg; min SJ 0.324; quarter and full within 0.03 %)."""
    q, f = kirsch_scan_clean_pillow["quarter"], kirsch_scan_clean_pillow["full"]
    for r in (q, f):
        assert r["min_sj"] >= 0.3 and r["inverted"] == 0
        for order in (1, 2):
            assert r[order]["sigma_x_90"] == pytest.approx(3.0, rel=0.03)
            assert r[order]["peak"] == pytest.approx(3.0, rel=0.03)
            assert abs(r[order]["peak_angle_deg"] - 90.0) <= 10.0
        # the figures measured (docs/validation.md §4)
        assert r["min_sj"] == pytest.approx(0.324, abs=0.005)
        assert r[1]["sigma_x_90"] == pytest.approx(3.077, abs=0.01)
        assert r[2]["sigma_x_90"] == pytest.approx(3.034, abs=0.01)
        assert r[2]["peak"] == pytest.approx(3.082, abs=0.01)
        assert r[1]["rim_radius_error_mean"] == pytest.approx(0.016, abs=0.005)
    for order in (1, 2):
        assert q[order]["sigma_x_90"] == pytest.approx(f[order]["sigma_x_90"], rel=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("a,c3d8,c3d20", [(7.0, 0.004, -0.012), (14.0, 0.001, -0.010)])
def test_target_lame_with_a_pillow_layer_from_a_grey_value_image(tmp_path, a, c3d8, c3d20):
    """The Lamé target from the image with the pillow layer: the bore's mean hoop stress
    within 3 %, C3D8 and C3D20 (measured +0.4 / -1.2 % at a = 7, +0.1 / -1.0 % at a = 14)."""
    r = cases.lame(tmp_path, "quarter", [NO_MERGE, PILLOW], inner=a, outer=2 * a, scan=True)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.2
    for order, measured in ((1, c3d8), (2, c3d20)):
        assert abs(r[order]["error_mean"]) <= 0.03
        assert r[order]["error_mean"] == pytest.approx(measured, abs=0.005)


@pytest.mark.slow
@pytest.mark.parametrize("a,c3d8,c3d20", [(7.0, -0.043, -0.058), (14.0, -0.024, -0.043)])
def test_lame_from_a_grey_value_image(tmp_path, a, c3d8, c3d20):
    r = cases.lame(tmp_path, "quarter", [NO_MERGE], inner=a, outer=2 * a, scan=True)
    assert r["inverted"] == 0 and r["min_sj"] == pytest.approx(0.22, abs=0.005)
    assert r[1]["error_mean"] == pytest.approx(c3d8, abs=0.01)
    assert r[2]["error_mean"] == pytest.approx(c3d20, abs=0.01)
    assert abs(r[1]["error_wall_fit"]) < 0.02 and abs(r[2]["error_wall_fit"]) < 0.01


# --- the accuracy targets, not met by the current defaults (numbers in docs/validation.md); the
# cases start from the labels' smoothing alone at the floor 0.2 (validation.models.BASE_SMOOTHING) ---


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="target: within 3 % of 3.0 at defaults; measured 2.460 (CPS4), 2.306 (CPS8)")
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_within_3_percent(kirsch_defaults, order):
    for part in ("quarter", "full"):
        r = kirsch_defaults[part]
        assert r[order]["sigma_x_90"] == pytest.approx(3.0, rel=0.03)
        assert r[order]["peak"] == pytest.approx(3.0, rel=0.03)
        assert abs(r[order]["peak_angle_deg"] - 90.0) <= 10.0


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="target: bore hoop within 3 %; measured at the former defaults (the labels' fit, "
                   "min SJ 0.3, plane merging: 33 elements) mean -4.8 % (C3D8), -6.9 % (C3D20); without merging "
                   "(floor 0.2) -8.2 % / -10.2 %; the labels' smoothing alone -14.2 % / -20.6 %")
def test_target_lame_within_3_percent(tmp_path):
    r = cases.lame(tmp_path, "quarter", [FIT, MIN_SJ_03], inner=7.0, outer=14.0)
    assert abs(r[1]["error_mean"]) <= 0.03 and abs(r[2]["error_mean"]) <= 0.03


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="target from a grey-value image at min SJ >= 0.3 (smooth.min_scaled_jacobian "
                   "0.3): sigma_x(90) quarter / full 3.218 / 3.143 (CPS4, +7.3 / +4.8 %), 3.057 / 3.005 (CPS8); "
                   "largest rim stress (CPS8) 3.329 / 3.369 at 79 deg; quarter and full 2.4 % (CPS4), "
                   "1.7 % (CPS8) apart")
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_from_a_grey_value_image(kirsch_scan, order):
    kirsch_target(kirsch_scan[("quarter", "min SJ 0.3")], kirsch_scan[("full", "min SJ 0.3")], order, 0.03)


@pytest.fixture(scope="module")
def kirsch_scan_today(tmp_path_factory):
    """Quarter and full plate from the grey-value image by dicer run at the former defaults: the
    surface fitted to the segmentation's labels with their faces placed by the scan (no pull
    onto the image), the floor 0.3, plane merging."""
    return {part: cases.kirsch(tmp_path_factory.mktemp(f"kirsch_scan_today_{part}"), part, TODAY, scan=True)
            for part in ("quarter", "full")}


@pytest.mark.slow
@pytest.mark.parametrize("part,cps4,cps8", [("quarter", (3.1364, 3.1364, 90.0), (3.3401, 3.3401, 90.0)),
                                            ("full", (3.1134, 3.1310, 90.0), (3.2892, 3.3241, 89.4))])
def test_kirsch_plate_from_a_grey_value_image_at_former_defaults(kirsch_scan_today, part, cps4, cps8):
    """The rim 0.103 / 0.117 voxel off the circle on average, 0.30 at most (with the labels'
    faces as they are: 0.172, 0.41), closer readings, still outside 3 %."""
    r = kirsch_scan_today[part]
    kirsch_figures(r, 0.32, cps4, cps8)
    assert r[1]["rim_radius_error_mean"] == pytest.approx(0.103 if part == "quarter" else 0.117, abs=0.01)
    assert r[1]["rim_radius_error_max"] == pytest.approx(0.303, abs=0.01)
    # Kirsch's displacements on the outer edges: 3.054 / 3.030 (CPS4), 3.247 / 3.197 (CPS8)
    edges = {1: 3.054 if part == "quarter" else 3.030, 2: 3.247 if part == "quarter" else 3.197}
    for order, at_90 in edges.items():
        assert r[order]["kirsch_edges"]["sigma_x_90"] == pytest.approx(at_90, abs=0.01)


@pytest.fixture(scope="module")
def kirsch_scan_today_curved(tmp_path_factory):
    """The former defaults with export.midside_nodes: curved, by (part, noise), made once each."""
    made = {}

    def get(part: str, noise: float) -> dict:
        if (part, noise) not in made:
            made[(part, noise)] = cases.kirsch(tmp_path_factory.mktemp(f"kirsch_curved_{part}"), part,
                                               TODAY + [CURVED], scan=True, noise=noise)
        return made[(part, noise)]
    return get


@pytest.mark.slow
@pytest.mark.parametrize("part,noise,cps4,cps8,edges", [
    ("quarter", 30.0, (3.1364, 3.1364, 90.0), (3.2027, 3.2027, 90.0), (3.054, 3.111)),
    ("full", 30.0, (3.1134, 3.1310, 90.0), (3.1661, 3.1971, 89.4), (3.030, 3.075)),
    ("quarter", 0.0, (3.0940, 3.0940, 90.0), (3.0923, 3.0923, 90.0), (3.012, 3.003)),
    ("full", 0.0, (3.0940, 3.0940, 90.0), (3.0923, 3.0923, 90.0), (3.012, 3.003))])
def test_kirsch_plate_from_a_grey_value_image_at_former_defaults_curved(kirsch_scan_today_curved, part, noise, cps4,
                                                                        cps8, edges):
    """The former defaults with export.midside_nodes: curved: the merged rim's mid-edge nodes on
    arcs (CPS8 3.340 / 3.289 / 3.212 with midpoints); the linear deck unchanged. ``edges``:
    sigma_x at 90 deg with Kirsch's displacements on the outer edges (CPS4, CPS8)."""
    r = kirsch_scan_today_curved(part, noise)
    kirsch_figures(r, 0.32, cps4, cps8)
    assert r[2]["rim_fit_90"] == pytest.approx(3.0503 if part == "quarter" and noise else 3.029, abs=0.01)
    for order, at_90 in zip((1, 2), edges):
        assert r[order]["kirsch_edges"]["sigma_x_90"] == pytest.approx(at_90, abs=0.01)


@pytest.mark.slow
def test_target_kirsch_cps4_from_a_grey_value_image_at_former_defaults_against_kirschs_field(kirsch_scan_today):
    """The Kirsch target from a grey-value image at dicer run's former defaults, read against Kirsch's
    own field (his displacements on the outer edges; under the finite plate's uniform tension
    the exact value is 3.095, not 3.0): CPS4 3.054 / 3.030 (quarter / full, +1.8 / +1.0 %), the
    largest rim stress 3.054 / 3.047 at 90 deg, quarter and full 0.8 % apart, min SJ 0.32."""
    kirsch_target(kirsch_scan_today["quarter"], kirsch_scan_today["full"], 1, 0.03, edges=True)


@pytest.mark.slow
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_from_a_noise_free_grey_value_image_at_former_defaults_against_kirschs_field(
        kirsch_scan_today_curved, order):
    """Without noise, dicer run's former defaults and curved mid-edge nodes meet the 3 % target with both
    element types against Kirsch's field: CPS4 3.012 (+0.4 %), CPS8 3.003 (+0.1 %), largest at 90
    deg, quarter and full alike."""
    kirsch_target(kirsch_scan_today_curved("quarter", 0.0), kirsch_scan_today_curved("full", 0.0), order, 0.03,
                  edges=True)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="CPS8 with curved mid-edge nodes, against Kirsch's field: quarter / full "
                   "3.111 / 3.075 (+3.7 / +2.5 %), largest 3.111 / 3.105 at 90 / 89 deg, 1.2 % apart: the noise's "
                   "dent in the rim, which the arcs through single rim nodes follow (without noise 3.003, +0.1 %)")
def test_target_kirsch_cps8_from_a_grey_value_image_at_former_defaults_against_kirschs_field(kirsch_scan_today_curved):
    kirsch_target(kirsch_scan_today_curved("quarter", 30.0), kirsch_scan_today_curved("full", 30.0), 2, 0.03,
                  edges=True)


@pytest.mark.slow
@pytest.mark.parametrize("radius,cps4,cps8", [
    (5, (3.019, 0.037, 3.011, 0.015, 6, 3), (3.024, 0.106, 3.034, 0.032, 2, 1)),
    (7, (3.014, 0.019, 3.005, 0.011, 6, 6), (2.985, 0.049, 2.981, 0.025, 5, 2))])
def test_kirsch_plate_from_six_draws_of_the_images_noise(tmp_path, radius, cps4, cps8):
    """dicer run's former defaults with curved mid-edge nodes on six draws of the grey-value image's
    noise, against Kirsch's field: (quarter mean, sd, full mean, sd, draws within 3 %, draws
    within the whole target). The quarter reads one point whose noise its mirror doubles, the
    full plate the mean of two: the quarter spreads two to three times as much, and on one draw
    the two part by up to 1.7 % (CPS4) and 6 % (CPS8) at the fit's radius 5, 1.0 % and 2.3 % at
    radius 7 (docs/validation.md §1e)."""
    r = study.kirsch_noise_draws(tmp_path, TODAY + [CURVED, f"smooth.label_surface_radius={radius}"], 6,
                                 log=lambda *a: None)
    assert all(row["min_sj"] >= 0.3 and row["inverted"] == 0 for row in r["draws"])
    for name, (q_mean, q_sd, f_mean, f_sd, within, target) in (("CPS4", cps4), ("CPS8", cps8)):
        got = r[name]
        assert got["quarter_mean"] == pytest.approx(q_mean, abs=0.01)
        assert got["full_mean"] == pytest.approx(f_mean, abs=0.01)
        assert got["quarter_sd"] == pytest.approx(q_sd, abs=0.005)
        assert got["full_sd"] == pytest.approx(f_sd, abs=0.005)
        assert got["quarter_sd"] > 1.4 * got["full_sd"]
        assert (got["within_3_percent"], got["within_target"]) == (within, target)


@pytest.mark.slow
def test_the_static_stress_preset_on_six_draws_of_the_images_noise(tmp_path):
    """The static-stress preset (its layer, the scan's placed faces, the fit's radius 7, curved
    mid-edge nodes) on the six draws of the noisy grey-value plate (docs/validation.md §1e):
    CPS8 within 3 % on every draw, quarter and full within 1 % on three; CPS4 reads 2 % low. At
    the fit's radius 5 (the preset until 7 December 2026) the layer follows the noise closer:
    CPS4 2.953 +- 0.045 (quarter), within 3 % on five draws, the target on two, CPS8 3.048 +- 0.121
    within 3 % on one, the target on none."""
    r = study.kirsch_noise_draws(tmp_path, TODAY + _preset_sets(), 6, log=lambda *a: None)
    assert all(row["min_sj"] >= 0.3 and row["inverted"] == 0 for row in r["draws"])
    for name, (q_mean, q_sd, f_mean, f_sd, within, target) in (("CPS4", (2.943, 0.021, 2.932, 0.008, 5, 4)),
                                                              ("CPS8", (3.004, 0.054, 3.004, 0.027, 6, 3))):
        got = r[name]
        assert got["quarter_mean"] == pytest.approx(q_mean, abs=0.01)
        assert got["full_mean"] == pytest.approx(f_mean, abs=0.01)
        assert got["quarter_sd"] == pytest.approx(q_sd, abs=0.005)
        assert got["full_sd"] == pytest.approx(f_sd, abs=0.005)
        assert (got["within_3_percent"], got["within_target"]) == (within, target)
    assert r["every_type_within_target"] == 3


@pytest.mark.slow
@pytest.mark.parametrize("part,cps4,cps8", [("quarter", (3.3463, 3.3463, 90.0), (3.8421, 3.8421, 90.0)),
                                            ("full", (3.2469, 3.2915, 89.4), (3.3151, 3.4993, 89.4))])
def test_kirsch_plate_from_a_grey_value_image_with_the_labels_faces_as_they_are(tmp_path, part, cps4, cps8):
    """The former defaults with smooth.fit_to_scan: false (the defaults until 5 December 2026): the
    noisy threshold's labels put the top of the hole outward, and the merged rim's corner kinks
    under the floor read it."""
    r = cases.kirsch(tmp_path, part, TODAY + [UNPLACED], scan=True)
    kirsch_figures(r, 0.32, cps4, cps8)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="target from a grey-value image at the former defaults under the finite "
                   "plate's uniform tension, whose own exact value is 3.095 (+3.2 % over 3.0): CPS4 sigma_x(90) "
                   "quarter / full 3.136 / 3.113 (+4.5 / +3.8 %), CPS8 3.340 / 3.289 (+11.3 / +9.6 %), largest "
                   "rim stress at 89-90 deg; quarter and full 0.7 % (CPS4) and 1.5 % (CPS8) apart; against "
                   "Kirsch's own field CPS4 meets the target (the test above)")
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_from_a_grey_value_image_at_former_defaults(kirsch_scan_today, order):
    kirsch_target(kirsch_scan_today["quarter"], kirsch_scan_today["full"], order, 0.03)


@pytest.mark.parametrize("a,c3d8,c3d20,radius", [(7.0, -0.0757, -0.0695, 7.017), (14.0, -0.0509, -0.0824, 13.999)])
def test_lame_from_a_grey_value_image_at_former_defaults(tmp_path, a, c3d8, c3d20, radius):
    """dicer run's former defaults on the CT-like image (the threshold's labels fitted with their faces
    placed by the scan, the floor 0.3, plane merging: 33 and 125 elements); with the labels' faces
    as they are (the defaults until 5 December 2026) a = 7 read -9.1 % / -15.6 %, a = 14 -7.1 % /
    -10.6 %; until the fit mirrored the normals of plane nodes (6 December 2026) a = 7 read
    -11.1 % / -13.6 %, the bore's radius 6.893."""
    r = cases.lame(tmp_path, "quarter", TODAY, inner=a, outer=2 * a, scan=True)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.3
    assert r[1]["error_mean"] == pytest.approx(c3d8, abs=0.005)
    assert r[2]["error_mean"] == pytest.approx(c3d20, abs=0.005)
    assert r[1]["bore_radius_mean"] == pytest.approx(radius, abs=0.005)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="target from a grey-value image: bore hoop within 3 %; measured at a = 7 "
                   "mean -4.3 % (C3D8), -5.7 % (C3D20)")
def test_target_lame_from_a_grey_value_image(tmp_path):
    r = cases.lame(tmp_path, "quarter", [NO_MERGE], inner=7.0, outer=14.0, scan=True)
    assert abs(r[1]["error_mean"]) <= 0.03 and abs(r[2]["error_mean"]) <= 0.03


def _preset_sets() -> list[str]:
    """The static-stress preset as --set items (its order aside: every case exports both)."""
    from dicer.config import preset_settings

    preset = preset_settings("static-stress")
    return [f"{section}.{key}={str(value).lower() if isinstance(value, bool) else value}"
            for section, keys in preset.items() for key, value in keys.items() if key != "order"]


def test_the_defaults_are_the_validated_settings_and_meet_the_lame_target(tmp_path):
    """The defaults since 7 December 2026 are the settings that meet every label-only target
    (docs/validation.md §4): the layer, relaxed samples, the fit's radius 7, curved mid-edge
    nodes. The static-stress preset adds order 2 to them; explicit-dynamics takes back the four.
    The Lamé bore from labels at a = 7 within 3 %, C3D8 and C3D20 (measured +0.9 / -1.1 %; at the
    radius 5 +0.3 / -2.1 %)."""
    from dicer.config import default_config, load_config

    defaults = default_config()

    def changed(preset):
        config = load_config(sets=[f"preset={preset}"])
        return {(s, k) for s in defaults if isinstance(defaults[s], dict)
                for k in defaults[s] if config[s].get(k) != defaults[s][k]}

    assert changed("static-stress") == {("export", "order")}
    assert changed("explicit-dynamics") == {("smooth", "pillow"), ("smooth", "label_samples"),
                                            ("smooth", "label_surface_radius"), ("export", "midside_nodes")}
    assert sorted(_preset_sets()) == sorted(DEFAULTS[len(TODAY):])  # labels: relaxed
    assert load_config(sets=DEFAULTS) == defaults
    # the cases start from the smoothing before the defaults (BASE_SMOOTHING): DEFAULTS restores them
    r = cases.lame(tmp_path, "quarter", DEFAULTS, inner=7.0, outer=14.0)
    assert r["inverted"] == 0 and r["min_sj"] >= 0.3
    for order, measured in ((1, 0.0090), (2, -0.0107)):
        assert r[order]["error_mean"] == pytest.approx(measured, abs=0.005)
        assert abs(r[order]["error_mean"]) < 0.03


# --- the targets at dicer run's defaults (since 7 December 2026: the pillow layer, a label
# volume's staircase relaxed or a scan's faces placed by it, the fit over 7 voxels, curved
# mid-edge nodes; docs/validation.md §4) ---------------------------------------------------


@pytest.fixture(scope="module")
def at_the_defaults(tmp_path_factory):
    """The Kirsch plate at dicer run's defaults by (part, scan): from the label image, or from
    the grey-value image (the study's draw of its noise), made once each."""
    made = {}

    def get(part: str, scan: bool) -> dict:
        if (part, scan) not in made:
            made[(part, scan)] = cases.kirsch(tmp_path_factory.mktemp(f"kirsch_defaults_{part}"), part, DEFAULTS,
                                              scan=scan)
        return made[(part, scan)]
    return get


@pytest.mark.slow
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_from_a_grey_value_image_at_the_defaults(at_the_defaults, order):
    """σx at 90° and the largest rim stress within 3 % of Kirsch's 3.0 (his field on the plate's
    edges), the largest at 90 ± 10°, quarter and full plate within 1 %, min SJ ≥ 0.3, 0 inverted.
    Measured: CPS4 2.970 / 2.944 (quarter / full, 0.9 % apart), CPS8 3.063 / 3.039 (0.8 %), the
    largest at 90°, min SJ 0.327-0.328."""
    quarter, full = at_the_defaults("quarter", True), at_the_defaults("full", True)
    kirsch_target(quarter, full, order, 0.03, edges=True)
    for r, measured in ((quarter, {1: 2.970, 2: 3.063}), (full, {1: 2.944, 2: 3.039})):
        assert r[order]["kirsch_edges"]["sigma_x_90"] == pytest.approx(measured[order], abs=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("order", [1, 2])
def test_target_kirsch_from_labels_at_the_defaults(at_the_defaults, order):
    """The same from the label image alone, within 8 %. Measured: CPS4 2.876 (-4.1 %), CPS8 2.937
    (-2.1 %), the largest at 90°, quarter and full alike, min SJ 0.325."""
    quarter, full = at_the_defaults("quarter", False), at_the_defaults("full", False)
    kirsch_target(quarter, full, order, 0.08, edges=True)
    for r in (quarter, full):
        assert r[order]["kirsch_edges"]["sigma_x_90"] == pytest.approx({1: 2.876, 2: 2.937}[order], abs=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("scan", [False, True], ids=["labels", "image"])
def test_target_lame_at_the_defaults(tmp_path, scan):
    """The bore's mean hoop stress within 3 % of Lamé's, C3D8 and C3D20, inner radius 7 and 14
    voxels, from the label image and from the grey-value image. Measured (C3D8 / C3D20): from
    labels +1.1 / -0.7 % (a = 7), +0.2 / -1.3 % (a = 14); from the image -0.2 / -1.3 %, +0.2 /
    -0.9 %; min SJ 0.326-0.334."""
    measured = {False: {7.0: (0.0108, -0.0074), 14.0: (0.0020, -0.0130)},
                True: {7.0: (-0.0024, -0.0133), 14.0: (0.0022, -0.0089)}}[scan]
    for a in (7.0, 14.0):
        r = cases.lame(tmp_path / f"tube{a:g}", "quarter", DEFAULTS, inner=a, outer=2 * a, scan=scan)
        assert r["inverted"] == 0 and r["min_sj"] >= 0.3
        for order in (1, 2):
            assert abs(r[order]["error_mean"]) <= 0.03, (a, order, r[order]["error_mean"])
            assert r[order]["error_mean"] == pytest.approx(measured[a][order - 1], abs=0.005)
