"""A 2D image end to end through the ``dicer`` command (in-process): a plate with a hole.

PNG slice -> segment (manual threshold) -> downsample -> mesh (quads) -> export (.inp with CPS4
plane-stress elements, .vtu) -> quality; and a plate without a hole (a 2D .npy through
``dicer run``) whose deck CalculiX solves in uniform tension: reaction = sigma * A.
"""

from __future__ import annotations

import json
import re
import shutil

import meshio
import numpy as np
import pytest

from calculix import needs_ccx, run_ccx, total_force

from dicer.cli import main


NX, NY, PIXEL = 80, 40, 0.5             # image: 80 x 40 pixels of 0.5 mm -> 40 x 20 mm
HOLE_CENTRE, HOLE_RADIUS = (20.0, 10.0), 5.0
E, NU, THICKNESS = 2000.0, 0.3, 2.0
PLATE, AIR = 200, 0                     # grey levels
CONFIG = f"""\
materials:
  - name: plate
    youngs_modulus: {E}
    poissons_ratio: {NU}
segment:
  method: manual
  thresholds: [100.0]
image:
  spacing: [{PIXEL}, {PIXEL}]
downsample:
  factor: 2
export:
  thickness: {THICKNESS}
"""


def dicer(*argv) -> None:
    code = main([str(a) for a in argv] + ["-q"])
    assert code == 0, f"dicer {' '.join(map(str, argv))} exited with {code}"


def plate(hole: bool = True) -> np.ndarray:
    """uint8 grey levels indexed [x, y]: the plate fills the image, less a round hole in its middle."""
    x = (np.arange(NX) + 0.5) * PIXEL
    y = (np.arange(NY) + 0.5) * PIXEL
    gx, gy = np.meshgrid(x, y, indexing="ij")
    a = np.full((NX, NY), PLATE, np.uint8)
    if hole:
        a[(gx - HOLE_CENTRE[0]) ** 2 + (gy - HOLE_CENTRE[1]) ** 2 < HOLE_RADIUS ** 2] = AIR
    return a


def quad_areas(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Signed areas (shoelace; positive = counter-clockwise in x, y)."""
    x, y = points[quads, 0], points[quads, 1]
    return 0.5 * (x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1)


def node_sets(inp: str) -> dict[str, np.ndarray]:
    sets = {}
    for name, body in re.findall(r"^\*NSET, NSET=(\w+)\n((?:[^*].*\n)*)", inp, re.M):
        sets[name] = np.array([int(v) for v in body.replace(",", " ").split()])
    return sets


STRAIN = 0.01
# rollers on X0 (x) and Y0 (y), X1 pulled by STRAIN * length; reactions on X0; stresses per integration point
TENSION = ("*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\n*STEP\n*STATIC\n*BOUNDARY\n"
           f"X1, 1, 1, {STRAIN * NX * PIXEL!r}\n*NODE PRINT, NSET=X0, TOTALS=ONLY\nRF\n"
           "*EL PRINT, ELSET=plate\nS\n*END STEP\n")


@pytest.fixture(scope="module")
def staged(tmp_path_factory):
    """Each stage as its own command, on a single 2D PNG of the plate with a hole."""
    import SimpleITK as sitk

    d = tmp_path_factory.mktemp("plate2d")
    (d / "config.yaml").write_text(CONFIG)
    sitk.WriteImage(sitk.GetImageFromArray(plate().T.copy()), str(d / "plate.png"))  # PNG rows are y
    cfg = ("--config", d / "config.yaml")
    dicer("segment", d / "plate.png", "-o", d / "labels.nii.gz", *cfg)
    dicer("downsample", d / "labels.nii.gz", "-o", d / "labels_ds.nii.gz", *cfg)
    dicer("mesh", d / "labels_ds.nii.gz", "-o", d / "mesh.vtu", *cfg)
    dicer("export", d / "mesh.vtu", "-o", d / "model.inp", *cfg)
    dicer("export", d / "mesh.vtu", "-o", d / "model.vtu", *cfg)
    dicer("quality", d / "model.vtu", "-o", d / "quality.json", "--labels", d / "labels_ds.nii.gz",
          "--html", d / "report.html", *cfg)
    return d


def test_segment_and_downsample_2d(staged):
    from dicer.io.images import read_labels

    labels = read_labels(staged / "labels.nii.gz")
    assert labels.array.shape == (NX, NY) and np.allclose(labels.spacing, (PIXEL, PIXEL))
    assert np.array_equal(labels.array, (plate() >= 100).astype(labels.array.dtype))  # nothing to clean
    coarse = read_labels(staged / "labels_ds.nii.gz")
    assert coarse.array.shape == (NX // 2, NY // 2) and np.allclose(coarse.spacing, (2 * PIXEL, 2 * PIXEL))
    # the vote: plate wherever it fills at least a quarter (here: one pixel) of the 2 x 2 block
    blocks = labels.array.reshape(NX // 2, 2, NY // 2, 2).sum(axis=(1, 3))
    assert np.array_equal(coarse.array, (blocks >= 1).astype(coarse.array.dtype))


def test_mesh_is_quads_with_unit_areas(staged):
    from dicer.io.images import read_labels

    coarse = read_labels(staged / "labels_ds.nii.gz").array
    n = int(np.count_nonzero(coarse))
    for name in ("mesh.vtu", "model.vtu"):
        m = meshio.read(staged / name)
        assert [c.type for c in m.cells] == ["quad"], name
        quads = m.cells[0].data
        assert quads.shape == (n, 4)
        assert np.allclose(m.points[:, 2], 0.0)
        # nodes: the corners of the plate's voxels, each once
        corners = np.zeros((NX // 2 + 1, NY // 2 + 1), bool)
        for dx in (0, 1):
            for dy in (0, 1):
                corners[dx : dx + NX // 2, dy : dy + NY // 2] |= coarse > 0
        assert m.points.shape[0] == corners.sum() == np.unique(quads).size
        areas = quad_areas(m.points, quads)
        assert np.allclose(areas, (2 * PIXEL) ** 2)  # counter-clockwise, 1 mm^2 each
        assert np.all(m.cell_data["material"][0] == 1)
    # the voxel plate holds the true area within a few per cent (the vote keeps partly filled blocks)
    true_area = NX * PIXEL * NY * PIXEL - np.pi * HOLE_RADIUS ** 2
    assert areas.sum() == pytest.approx(true_area, rel=0.03)
    assert areas.sum() > true_area


def test_export_writes_plane_stress_deck(staged):
    inp = (staged / "model.inp").read_text()
    m = meshio.read(staged / "model.vtu")
    n_el, n_nodes = m.cells[0].data.shape[0], m.points.shape[0]
    assert f"** {n_nodes} nodes, {n_el} CPS4 elements" in inp
    assert re.findall(r"^\*ELEMENT.*$", inp, re.M) == ["*ELEMENT, TYPE=CPS4, ELSET=plate"]
    section = re.search(r"^\*SOLID SECTION, ELSET=plate, MATERIAL=plate\n(.*)$", inp, re.M)
    assert section and float(section.group(1).strip().rstrip(",")) == THICKNESS
    assert re.search(rf"^\*ELASTIC\n{E:g}, {NU:g}$", inp, re.M)
    sets = node_sets(inp)
    nx, ny = NX // 2, NY // 2
    assert {k: v.size for k, v in sets.items() if k in ("X0", "X1", "Y0", "Y1")} == \
        {"X0": ny + 1, "X1": ny + 1, "Y0": nx + 1, "Y1": nx + 1}
    assert not {"Z0", "Z1"} & sets.keys()
    # the bounding-plane sets hold the nodes on those planes, 1-based
    pts = m.points
    assert np.array_equal(np.sort(sets["X1"]) - 1, np.flatnonzero(np.isclose(pts[:, 0], NX * PIXEL)))
    assert np.array_equal(np.sort(sets["Y0"]) - 1, np.flatnonzero(np.isclose(pts[:, 1], 0.0)))
    # exterior: the outer rectangle; the hole's outline (a closed loop) is a set of its own
    assert sets["EXTERIOR"].size == 2 * (nx + ny)
    assert sets["CAVITIES"].size > 8 and not set(sets["CAVITIES"]) & set(sets["EXTERIOR"])
    assert "*STEP" not in inp


def test_quality_report_2d(staged):
    q = json.loads((staged / "quality.json").read_text())
    m = meshio.read(staged / "model.vtu")
    n = m.cells[0].data.shape[0]
    assert q["dimension"] == 2 and q["element_type"] == "quad"
    assert q["elements"] == n and q["nodes"] == m.points.shape[0]
    assert q["inverted_elements"] == 0 and q["poor_elements"] == 0
    assert q["scaled_jacobian"]["min"] == pytest.approx(1.0)
    assert q["materials"]["plate"]["volume_mm^2"] == pytest.approx(n * (2 * PIXEL) ** 2)
    assert (staged / "report.html").stat().st_size > 0


@pytest.mark.calculix
@needs_ccx
def test_ccx_plate_with_hole(staged, tmp_path):
    shutil.copy(staged / "model.inp", tmp_path / "model.inp")
    dat = run_ccx(tmp_path, TENSION)
    width, nominal = NY * PIXEL, E * STRAIN
    force = -total_force(dat, "X0")[0]
    # the hole softens the plate: less than the uniform plate's sigma * A, more than the net section's share
    uniform = nominal * width * THICKNESS
    assert 0.6 * uniform < force < 0.9 * uniform
    # stress concentration at the hole (Kirsch: 3 in an infinite plate; staircase edges here)
    rows = re.findall(r"^\s+\d+\s+\d+\s+(\S+)(?:\s+\S+){5}\s*$", dat.split("stresses")[-1], re.M)
    sxx = np.array([float(v) for v in rows])
    assert sxx.size == 8 * int(re.search(r"(\d+) CPS4 elements", (tmp_path / "model.inp").read_text()).group(1))
    assert sxx.max() > 2.5 * nominal


@pytest.mark.calculix
@needs_ccx
def test_ccx_plate_without_hole_reaction_is_sigma_times_area(tmp_path):
    # a 2D float .npy image (HU-like grey levels with noise) through `dicer run`
    rng = np.random.default_rng(0)
    image = plate(hole=False).astype(np.float32) + rng.normal(0.0, 10.0, (NX, NY)).astype(np.float32)
    np.save(tmp_path / "plate.npy", image)
    # one element per coarse pixel: no plane merging
    (tmp_path / "config.yaml").write_text(CONFIG + "merge:\n  passes: [0, 0]\n")
    out = tmp_path / "out"
    dicer("run", tmp_path / "plate.npy", "-o", out, "--config", tmp_path / "config.yaml")
    q = json.loads((out / "quality.json").read_text())
    assert q["elements"] == (NX // 2) * (NY // 2) and q["element_type"] == "quad"
    dat = run_ccx(out, TENSION)
    force = total_force(dat, "X0")
    area = NY * PIXEL * THICKNESS
    assert -force[0] == pytest.approx(E * STRAIN * area, rel=0.01)
    assert abs(force[1]) < 1e-6 * abs(force[0]) and force[2] == pytest.approx(0.0, abs=1e-6)
    # uniform stress: every integration point carries sigma_xx = E * strain, sigma_yy = 0
    rows = re.findall(r"^\s+\d+\s+\d+\s+(\S+)\s+(\S+)(?:\s+\S+){4}\s*$", dat.split("stresses")[-1], re.M)
    s = np.array(rows, float)
    assert s.shape[0] == 8 * q["elements"]
    assert np.allclose(s[:, 0], E * STRAIN, rtol=1e-3) and np.allclose(s[:, 1], 0.0, atol=1e-3 * E * STRAIN)
