"""CalculiX (ccx) solves the exported decks, *INCLUDEd as written from a deck that adds a step.

Each case compares the total reaction force with the analytic value (within 1 %).
Boundary conditions use the exported bounding-plane node sets: rollers on the
0-planes and a prescribed displacement on the far plane give a uniaxial stress
state, which linear and quadratic elements both reproduce.
"""

from __future__ import annotations

import re
import subprocess

import numpy as np
import pytest

from calculix import CCX, needs_ccx, run_ccx, total_force

from dicer.config import load_config
from dicer.export import export_mesh
from dicer.mesh.voxel import voxel_mesh

pytestmark = [pytest.mark.calculix, needs_ccx]


def config(*materials, **export):
    mats = [{"name": n, "youngs_modulus": e, "poissons_ratio": nu} for n, e, nu in materials]
    return load_config(settings={"materials": mats, "export": export})


def compression_step(strain: float, length: float, axis: int = 2) -> str:
    """Rollers on X0, Y0, Z0; the far plane of ``axis`` moved by -strain * length; reactions on its 0-plane."""
    name = "XYZ"[axis]
    return (
        "*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\nZ0, 3, 3, 0\n"
        "*STEP\n*STATIC\n*BOUNDARY\n"
        f"{name}1, {axis + 1}, {axis + 1}, {-strain * length!r}\n"
        f"*NODE PRINT, NSET={name}0, TOTALS=ONLY\nRF\n*END STEP\n"
    )


BLOCK_SHAPE = (3, 4, 6)
BLOCK_SPACING = (0.5, 0.75, 1.25)


@pytest.mark.parametrize("etype,order", [("C3D8", 1), ("C3D8R", 1), ("C3D8I", 1), ("C3D20", 2), ("C3D20R", 2)])
def test_block_compression_force(tmp_path, etype, order):
    e = 17000.0
    mesh = voxel_mesh(np.ones(BLOCK_SHAPE, np.uint8), BLOCK_SPACING, origin=(10.0, -5.0, 2.0))
    export_mesh(mesh, tmp_path / "model.inp", config(("cortical", e, 0.3), element_type=etype, order=order),
                source="block.npy")
    lx, ly, lz = (n * s for n, s in zip(BLOCK_SHAPE, BLOCK_SPACING))
    dat = run_ccx(tmp_path, model="model.inp", step=compression_step(0.01, lz))
    expected = e * 0.01 * lx * ly  # E * strain * area, compressive
    force = total_force(dat, "Z0")
    assert force[2] == pytest.approx(expected, rel=0.01)
    assert abs(force[0]) < 1e-3 * expected and abs(force[1]) < 1e-3 * expected


def test_block_compression_along_x_anisotropic_spacing(tmp_path):
    e = 5000.0
    mesh = voxel_mesh(np.ones(BLOCK_SHAPE, np.uint8), BLOCK_SPACING)
    export_mesh(mesh, tmp_path / "model.inp", config(("bone", e, 0.25)))
    lx, ly, lz = (n * s for n, s in zip(BLOCK_SHAPE, BLOCK_SPACING))
    force = total_force(run_ccx(tmp_path, model="model.inp", step=compression_step(0.01, lx, axis=0)), "X0")
    assert force[0] == pytest.approx(e * 0.01 * ly * lz, rel=0.01)


@pytest.mark.parametrize("order", [1, 2])
def test_two_material_bar_in_series(tmp_path, order):
    # soft layers z < 2, stiff layers above; Poisson ratio 0 keeps the layers from straining each
    # other sideways at the interface, so the stress is uniaxial and uniform
    labels = np.ones(BLOCK_SHAPE, np.uint8)
    labels[:, :, 2:] = 2
    e1, e2 = 800.0, 12000.0
    mesh = voxel_mesh(labels, BLOCK_SPACING)
    cfg = config(("soft", e1, 0.0), ("stiff", e2, 0.0), order=order)
    info = export_mesh(mesh, tmp_path / "bar.inp", cfg)
    assert info["materials"] == {"soft": 24, "stiff": 48}
    lx, ly, lz = (n * s for n, s in zip(BLOCK_SHAPE, BLOCK_SPACING))
    l1, l2 = 2 * BLOCK_SPACING[2], 4 * BLOCK_SPACING[2]
    delta = 0.01 * lz
    expected = lx * ly * delta / (l1 / e1 + l2 / e2)  # springs in series
    force = total_force(run_ccx(tmp_path, model="bar.inp", step=compression_step(0.01, lz)), "Z0")
    assert force[2] == pytest.approx(expected, rel=0.01)
    # one material everywhere would give a clearly different force: the sections are per material
    assert abs(force[2] - e1 * 0.01 * lx * ly) > 0.1 * expected


@pytest.mark.parametrize("etype,order", [("CPS4", 1), ("CPS8", 2), ("CPS4R", 1), ("CPS8R", 2)])
def test_plane_stress_plate_in_tension(tmp_path, etype, order):
    e, t = 2000.0, 2.5
    shape, spacing = (5, 3), (1.0, 0.5)
    mesh = voxel_mesh(np.ones(shape, np.uint8), spacing)
    export_mesh(mesh, tmp_path / "plate.inp", config(("plate", e, 0.3), element_type=etype, order=order, thickness=t))
    lx, ly = shape[0] * spacing[0], shape[1] * spacing[1]
    step = ("*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\n*STEP\n*STATIC\n*BOUNDARY\n"
            f"X1, 1, 1, {0.01 * lx!r}\n*NODE PRINT, NSET=X0, TOTALS=ONLY\nRF\n*END STEP\n")
    force = total_force(run_ccx(tmp_path, model="plate.inp", step=step), "X0")
    stress = -force[0] / (ly * t)
    assert stress == pytest.approx(e * 0.01, rel=0.01)


def test_exterior_surface_takes_a_pressure(tmp_path):
    # a uniform pressure on the whole exterior surface of a free block: the reactions of a
    # minimal support stay (numerically) zero and the block shrinks uniformly
    mesh = voxel_mesh(np.ones(BLOCK_SHAPE, np.uint8), BLOCK_SPACING)
    e, nu, p = 1000.0, 0.3, 1.0
    export_mesh(mesh, tmp_path / "model.inp", config(("m", e, nu)))
    step = ("*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\nZ0, 3, 3, 0\n*STEP\n*STATIC\n*DSLOAD\nEXTERIOR, P, "
            f"{p!r}\n*NODE PRINT, NSET=X0, TOTALS=ONLY\nRF\n*NODE PRINT, NSET=X1\nU\n*END STEP\n")
    dat = run_ccx(tmp_path, model="model.inp", step=step)
    lx = BLOCK_SHAPE[0] * BLOCK_SPACING[0]
    strain = -p * (1 - 2 * nu) / e  # hydrostatic
    rows = re.findall(r"^\s+\d+\s+(\S+)\s+\S+\s+\S+\s*$", dat.split("displacements")[-1], re.M)
    ux = np.array([float(v) for v in rows])
    assert ux.size and np.allclose(ux, strain * lx, rtol=0.01)


def test_a_pressure_on_the_exterior_leaves_the_cavity_walls_unloaded(tmp_path):
    """A hollow block: pressed on EXTERIOR and CAVITIES it shrinks as a solid block does
    (hydrostatic); pressed on EXTERIOR alone it shrinks more, the void giving way."""
    lab = np.ones((6, 6, 6), np.uint8)
    lab[2:4, 2:4, 2:4] = 0  # a void of 2 x 2 x 2 voxels
    e, nu, p = 1000.0, 0.3, 1.0
    export_mesh(voxel_mesh(lab), tmp_path / "model.inp", config(("m", e, nu)))

    def far_plane_ux(surfaces: str) -> np.ndarray:
        loads = "".join(f"{name}, P, {p!r}\n" for name in surfaces.split())
        step = ("*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\nZ0, 3, 3, 0\n*STEP\n*STATIC\n*DSLOAD\n"
                f"{loads}*NODE PRINT, NSET=X1\nU\n*END STEP\n")
        dat = run_ccx(tmp_path, model="model.inp", step=step)
        rows = re.findall(r"^\s+\d+\s+(\S+)\s+\S+\s+\S+\s*$", dat.split("displacements")[-1], re.M)
        return np.array([float(v) for v in rows])

    hydrostatic = -p * (1 - 2 * nu) / e * 6.0
    both = far_plane_ux("EXTERIOR CAVITIES")
    assert both.size == 7 * 7 and np.allclose(both, hydrostatic, rtol=0.01)
    outer = far_plane_ux("EXTERIOR")
    assert outer.mean() < 1.05 * hydrostatic  # 9 % more shrinkage (both negative)


@pytest.mark.parametrize("midside,merged", [("midpoint", False), pytest.param("curved", False, marks=pytest.mark.slow),
                                            pytest.param("curved", True, marks=pytest.mark.slow)])
def test_smoothed_head_phantom_at_order_2_runs(tmp_path, midside, merged):
    """A smoothed head phantom with 20-node hexahedra: ccx assembles and solves a gravity step
    (exterior held) without element errors; the reaction balances most of the weight (the
    share of the load that lands on the held nodes themselves is not part of the reactions).
    Merged: plane merging's chamfers, so the curved mid-edge nodes go onto arcs."""
    from dicer.connectivity import fix_connectivity
    from dicer.mesh.merge import merge_mesh
    from dicer.mesh.metrics import element_volumes
    from dicer.mesh.smooth import smooth_mesh
    from dicer.phantoms import head_labels

    volume = head_labels(24)
    labels, _ = fix_connectivity(volume.array)
    mesh = voxel_mesh(labels, volume.spacing)
    if merged:
        from dicer.mesh.quadratic import edges_by_lattice

        mesh, _ = merge_mesh(mesh, {})
        assert not edges_by_lattice(mesh, np.asarray(mesh.cells, np.int64))[2]  # chamfers: arcs
    mesh, _ = smooth_mesh(mesh, load_config().get("smooth"))
    cfg = load_config(settings={"export": {"order": 2, "midside_nodes": midside}})
    info = export_mesh(mesh, tmp_path / "head.inp", cfg, source="head_phantom")
    names = ", ".join(info["materials"])
    step = (f"*ELSET, ELSET=EALL\n{names}\n*BOUNDARY\nEXTERIOR, 1, 3, 0\n*STEP\n*STATIC\n*DLOAD\n"
            "EALL, GRAV, 9810., 0., 0., -1.\n*NODE PRINT, NSET=EXTERIOR, TOTALS=ONLY\nRF\n*END STEP\n")
    dat = run_ccx(tmp_path, model="head.inp", step=step)
    rho = np.array([0.0] + [m["density"] for m in cfg["materials"]])
    weight = float((element_volumes(mesh.points, mesh.cells) * rho[mesh.material]).sum() * 9810.0)
    force = total_force(dat, "EXTERIOR")
    assert np.all(np.isfinite(force)) and 0.8 * weight < force[2] <= weight * 1.001


@pytest.mark.parametrize("etype,order", [("CPE4", 1), ("CPE8", 2)])
def test_plane_strain_plate_in_tension(tmp_path, etype, order):
    # rollers on X0 and Y0, free Y1, no out-of-plane strain: sigma_x = E / (1 - nu^2) * eps_x
    e, nu, t = 2000.0, 0.3, 1.5
    shape, spacing = (4, 3), (0.5, 1.0)
    mesh = voxel_mesh(np.ones(shape, np.uint8), spacing)
    export_mesh(mesh, tmp_path / "plate.inp", config(("plate", e, nu), element_type=etype, order=order, thickness=t))
    lx, ly = shape[0] * spacing[0], shape[1] * spacing[1]
    step = ("*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\n*STEP\n*STATIC\n*BOUNDARY\n"
            f"X1, 1, 1, {0.01 * lx!r}\n*NODE PRINT, NSET=X0, TOTALS=ONLY\nRF\n*END STEP\n")
    force = total_force(run_ccx(tmp_path, model="plate.inp", step=step), "X0")
    assert -force[0] / (ly * t) == pytest.approx(e / (1 - nu**2) * 0.01, rel=0.01)


@pytest.mark.parametrize("order", [1, 2])
def test_plane_merged_bar_in_series(tmp_path, order):
    # plane merging leaves elements two lattice steps long: sets, faces and mid-edge nodes still hold
    merge = pytest.importorskip("dicer.mesh.merge")
    labels = np.ones((4, 6, 8), np.uint8)
    labels[:, :, 4:] = 2
    spacing = (0.5, 0.75, 1.25)
    mesh, _ = merge.merge_planes(voxel_mesh(labels, spacing), passes=(1, 1, 1))
    assert mesh.n_cells < labels.size
    e1, e2 = 800.0, 12000.0
    export_mesh(mesh, tmp_path / "bar.inp", config(("soft", e1, 0.0), ("stiff", e2, 0.0), order=order))
    lx, ly, lz = (n * s for n, s in zip(labels.shape, spacing))
    expected = lx * ly * 0.01 * lz / (0.5 * lz / e1 + 0.5 * lz / e2)
    force = total_force(run_ccx(tmp_path, model="bar.inp", step=compression_step(0.01, lz)), "Z0")
    assert force[2] == pytest.approx(expected, rel=0.01)


def test_model_deck_alone_is_read_to_the_end(tmp_path):
    # the deck as written, without a step: ccx reads every section (nodes, per-material element
    # blocks, all four set kinds, the element-face surface, materials) and stops -- the run
    # docs/exports.md uses to time input reading apart from the solver
    labels = np.ones(BLOCK_SHAPE, np.uint8)
    labels[:, :, 2:] = 2
    labels[0, 0, 0] = 0
    info = export_mesh(voxel_mesh(labels, BLOCK_SPACING), tmp_path / "model.inp",
                       config(("soft", 800.0, 0.3), ("stiff", 12000.0, 0.3)))
    assert {"X0", "Z1", "EXTERIOR", "soft_BOUNDARY", "stiff_BOUNDARY", "soft_stiff"} <= set(info["node_sets"])
    assert info["exterior_faces"] > 0
    proc = subprocess.run([CCX, "-i", "model"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "*ERROR" not in log and "Job finished" in log, log[-2000:]
    sets = int(re.search(r"^\s*sets:\s+(\d+)", log, re.M).group(1))
    # node sets, EXTERIOR_S1..S6, the two material element sets
    assert sets >= len(info["node_sets"]) + 6 + 2
    assert re.search(rf"^\s*elements:\s+{info['elements']}\s*$", log, re.M)


@pytest.mark.parametrize("etype,order", [("CPS4", 1), ("CPS8", 2)])
def test_graded_plate_in_series(tmp_path, etype, order):
    # transition templates pass the patch test: a graded two-material plate under uniaxial
    # tension (Poisson ratio 0) carries the springs-in-series force
    from dicer.mesh.coarsen import coarsen_mesh

    labels = np.ones((54, 36), np.uint8)
    labels[27:] = 2
    spacing = (0.5, 0.5)
    graded, report = coarsen_mesh(voxel_mesh(labels, spacing), levels=2, min_distance=1, keep_fine=())
    assert report["element_ratio"] > 1.9  # 1944 -> 1012: the plate is only 12 cells wide
    e1, e2, t = 800.0, 12000.0, 1.0
    export_mesh(graded, tmp_path / "plate.inp",
                config(("soft", e1, 0.0), ("stiff", e2, 0.0), element_type=etype, order=order, thickness=t))
    lx, ly = 54 * 0.5, 36 * 0.5
    step = ("*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\n*STEP\n*STATIC\n*BOUNDARY\n"
            f"X1, 1, 1, {0.01 * lx!r}\n*NODE PRINT, NSET=X0, TOTALS=ONLY\nRF\n*END STEP\n")
    force = total_force(run_ccx(tmp_path, model="plate.inp", step=step), "X0")
    expected = ly * t * 0.01 * lx / (0.5 * lx / e1 + 0.5 * lx / e2)
    assert -force[0] == pytest.approx(expected, rel=0.01)
