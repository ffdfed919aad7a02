"""Finite-element validation (docs/validation.md): dicer's models of a plate with a hole
(Kirsch) and a thick-walled tube (Lamé), made from label images by ``dicer run``, solved
with CalculiX; stresses from its .frd output against the closed-form values.

Each assertion pins the figure the current code measures (docs/validation.md's tables)
within a small margin; the accuracy targets of issue #17 are the strict xfail tests at the
end, which fail (and so must be turned into plain tests) once the targets are met.
"""

from __future__ import annotations

import pytest

from calculix import needs_ccx

from dicer.validation import cases
from dicer.validation.study import NO_MERGE, OFFSET

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


@pytest.fixture(scope="module")
def kirsch_defaults(tmp_path_factory):
    """Quarter and full plate at the default smoothing, no merging, CPS4 and CPS8."""
    return {part: cases.kirsch(tmp_path_factory.mktemp(f"kirsch_{part}"), part, [NO_MERGE])
            for part in ("quarter", "full")}


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


# --- issue #17's targets, not met by the current defaults (numbers in docs/validation.md) ---


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
@pytest.mark.xfail(strict=True, reason="target: bore hoop within 3 %; measured mean -14.2 % (C3D8), -20.6 % (C3D20)")
def test_target_lame_within_3_percent(tmp_path):
    r = cases.lame(tmp_path, "quarter", [NO_MERGE], inner=7.0, outer=14.0)
    assert abs(r[1]["error_mean"]) <= 0.03 and abs(r[2]["error_mean"]) <= 0.03
