"""The real head CT (``../shared/data/cranium_ct.nii.gz``) through ``dicer run``, solved by CalculiX.

Skipped when the shared data folder is not beside the repository (a clone without it).

Default suite: the segmentation acceptance on the real scan and a coarse (factor 8) run whose
``model.inp`` CalculiX solves. ``-m slow``: the literal acceptance run at full resolution with
the default configuration, every fourth slice (6 mm) through the default chain, and CalculiX
(iterative solver) on that deck and on the factor-2 deck, the largest one seen solved within
minutes on two shared cores.

Load case for CalculiX: the head stands on its cut plane (``Z0``, the skull base: the only
bounding plane the scan's body touches at every resolution), clamped there, under its own
weight. For voxel hexahedra the consistent gravity load puts 1/8 of an element's weight on
each of its nodes, and the share on the clamped nodes goes straight into the support, so the
reaction on ``Z0`` is the weight of the model less half the weight of its bottom element layer
— an exact check of the deck's geometry, materials, densities and element sets.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

from calculix import needs_ccx, run_ccx, total_force

from dicer.cli import main

CT = Path(__file__).parents[1] / ".." / "shared" / "data" / "cranium_ct.nii.gz"
G = 9810.0  # mm/s^2 (units: mm, N, MPa, t/mm^3)
FACE3 = ndi.generate_binary_structure(3, 1)

pytestmark = pytest.mark.skipif(not CT.exists(), reason=f"shared head CT not present ({CT.resolve()})")


def dicer(*argv) -> None:
    code = main([str(a) for a in argv])
    assert code == 0, f"dicer {' '.join(map(str, argv))} exited with {code}"


def gravity_deck(materials: list[str], solver: str = "") -> str:
    """A deck that includes model.inp, clamps Z0 and loads every material ELSET with gravity (-z)."""
    loads = "".join(f"{name}, GRAV, {G!r}, 0., 0., -1.\n" for name in materials)
    return (
        "*INCLUDE, INPUT=model.inp\n*BOUNDARY\nZ0, 1, 3, 0\n"
        f"*STEP\n*STATIC{', SOLVER=' + solver if solver else ''}\n*DLOAD\n{loads}"
        "*NODE PRINT, NSET=Z0, TOTALS=ONLY\nRF\n*NODE FILE\nU\n*END STEP\n"
    )


def reaction_bounds(model_vtu: Path, densities: list[float]) -> tuple[float, float]:
    """Bounds (N) on the Z0 reaction of the model under gravity: its weight, less at most
    the weight of the elements touching Z0 (ccx leaves the load lumped on held nodes out)."""
    import meshio

    from dicer.mesh.metrics import element_volumes

    model = meshio.read(model_vtu)
    cells = model.cells[0].data
    rho = np.array([0.0, *densities])[model.cell_data["material"][0]]
    weight = G * rho * element_volumes(model.points, cells)
    z0 = model.points[:, 2] <= model.points[:, 2].min() + 1e-9
    touching = z0[cells].any(axis=1)
    return float(weight.sum() - weight[touching].sum()), float(weight.sum())


def deck_sets(inp: Path) -> set[str]:
    with open(inp, "rb") as f:
        return {m.decode() for m in re.findall(rb"^\*NSET, NSET=(\w+)", f.read(), re.M)}


def check_solved(folder: Path, dat: str, model_vtu: Path) -> float:
    from dicer.config import load_config

    densities = [m["density"] for m in load_config()["materials"]]
    force = total_force(dat, "Z0")
    low, high = reaction_bounds(model_vtu, densities)
    assert low <= force[2] <= high
    assert abs(force[0]) < 0.01 * high and abs(force[1]) < 0.01 * high
    frd = (folder / "job.frd").read_bytes()
    assert b"DISP" in frd  # a displacement result block
    return float(force[2])


# --- default suite: segmentation acceptance and a coarse model ---------------------------


@pytest.fixture(scope="module")
def coarse_run(tmp_path_factory):
    """``dicer run CT -o out --set downsample.factor=8`` (the full-resolution labels come with it)."""
    out = tmp_path_factory.mktemp("cranium") / "out"
    dicer("run", CT, "-o", out, "--set", "downsample.factor=8", "-q")
    return out


@pytest.fixture(scope="module")
def coarse_run_without_the_layer(tmp_path_factory):
    """The same run at the explicit-dynamics preset: no pillow layer, one element per merged one."""
    out = tmp_path_factory.mktemp("cranium") / "out"
    dicer("run", CT, "-o", out, "--set", "downsample.factor=8", "--set", "preset=explicit-dynamics", "-q")
    return out


def test_run_writes_every_output(coarse_run):
    for name in ("labels.nii.gz", "labels_ds.nii.gz", "mesh.vtu", "model.inp", "model.vtu", "quality.json",
                 "report.html", "segmentation.json", "segmentation.png", "thresholds.png"):
        assert (coarse_run / name).stat().st_size > 0, name


def test_segmentation_acceptance(coarse_run):
    from dicer.io.images import read_image, read_labels

    info = json.loads((coarse_run / "segmentation.json").read_text())
    assert info["method"] == "shape_connectivity"
    t1, t2 = info["thresholds"]
    (lo1, hi1), (lo2, hi2) = info["ranges"]
    assert (lo1, hi1, lo2, hi2) == (-400, 0, 100, 1000)  # the default search ranges
    # inside the ranges, not stuck at an end, and near the scan's known soft tissue / bone bounds
    assert lo1 < t1 < hi1 and lo2 < t2 < hi2
    assert -200 <= t1 <= -100 and 110 <= t2 <= 260                    # measured: -144 and 140 HU
    fractions = {name: c["fraction"] for name, c in info["classes"].items()}
    assert 0.05 < fractions["bone"] < 0.08                            # ~6.7 % above 226 HU
    assert 0.22 < fractions["soft_tissue"] < 0.29
    assert 0.64 < fractions["background"] < 0.72
    assert sum(fractions.values()) == pytest.approx(1.0, abs=1e-4)

    image, labels = read_image(CT), read_labels(coarse_run / "labels.nii.gz")
    a, lab = image.array, labels.array
    assert lab.shape == a.shape == (256, 256, 108)
    assert np.allclose(labels.spacing, image.spacing)
    assert set(np.unique(lab)) == {0, 1, 2}
    assert ndi.label(lab > 0, FACE3)[1] == 1  # one body
    # the headrest: the raw body mask (>= t1) holds the head and two big separate parts; both are dropped
    comp, _ = ndi.label(a >= t1, FACE3)
    sizes = np.bincount(comp.ravel())
    sizes[0] = 0
    head, rest1, rest2 = np.argsort(sizes)[::-1][:3]
    assert sizes[rest1] > 20000 and sizes[rest2] > 20000
    assert not lab[(comp == rest1) | (comp == rest2)].any()
    assert (lab[comp == head] > 0).mean() > 0.99
    # the skull is one component: at least 99 % of the bone
    bone, _ = ndi.label(lab == 2, FACE3)
    bone_sizes = np.bincount(bone.ravel())[1:]
    assert bone_sizes.max() >= 0.99 * bone_sizes.sum()


def test_coarse_model_matches_its_labels(coarse_run_without_the_layer):
    import meshio

    from dicer.io.images import read_labels

    coarse_run = coarse_run_without_the_layer

    labels = read_labels(coarse_run / "labels_fixed.nii.gz")
    assert labels.array.shape == (32, 32, 14)  # 256/8, 256/8, ceil(108/8)
    assert np.allclose(labels.spacing, np.array([0.957031, 0.957031, 1.5]) * 8, rtol=1e-5)
    voxels = np.bincount(labels.array.ravel(), minlength=3)
    merge = json.loads((coarse_run / "merge.json").read_text())
    assert merge["elements_before"] == voxels[1:].sum() >= merge["elements_after"]
    model = meshio.read(coarse_run / "model.vtu")
    assert [c.type for c in model.cells] == ["hexahedron"]
    n_elements = model.cells[0].data.shape[0]
    assert n_elements == merge["elements_after"]
    inp = (coarse_run / "model.inp").read_text()
    assert f"{model.points.shape[0]} nodes, {n_elements} C3D8 elements" in inp
    assert inp.count("*ELEMENT, TYPE=C3D8, ELSET=") == 2
    assert "Z0" in deck_sets(coarse_run / "model.inp")
    assert "*STEP" not in inp
    # smoothing keeps nodes inside the grid's box (bounding-plane nodes stay on their planes):
    # in the lattice frame, which reading model.vtu with dicer gives back
    from dicer.io.meshes import read_mesh
    from dicer.mesh.frame import to_scanner

    lattice_frame = read_mesh(coarse_run / "model.vtu")
    lo = np.asarray(labels.origin) - 1e-6
    hi = np.asarray(labels.origin) + np.array(labels.array.shape) * np.asarray(labels.spacing) + 1e-6
    assert np.all((lattice_frame.points >= lo) & (lattice_frame.points <= hi))
    # the file itself is in scanner coordinates: this NIfTI's direction is diag(-1, -1, 1) (RAS
    # storage read as LPS), so the model turns half a turn about z through voxel (0, 0, 0)'s centre
    assert np.array_equal(np.reshape(labels.direction, (3, 3)), np.diag([-1.0, -1.0, 1.0]))
    assert np.abs(model.points - to_scanner(lattice_frame.points, labels.spacing, labels.origin,
                                            np.diag([-1.0, -1.0, 1.0]))).max() < 1e-9
    quality = json.loads((coarse_run / "quality.json").read_text())
    assert quality["elements"] == n_elements and quality["inverted_elements"] == 0
    assert quality["scaled_jacobian"]["min"] >= 0.2 - 1e-9
    assert set(quality["stages"]) == {"fix", "merge", "smooth"}
    fix = json.loads((coarse_run / "fix.json").read_text())
    assert fix["converged"] and fix["remaining"] == {"type_a": 0, "type_b": 0, "type_c": 0}
    from dicer.connectivity import connectivity_defects

    assert connectivity_defects(labels.array) == {"type_a": 0, "type_b": 0, "type_c": 0}


@pytest.mark.calculix
@needs_ccx
def test_ccx_solves_coarse_model(coarse_run, tmp_path):
    shutil.copy(coarse_run / "model.inp", tmp_path / "model.inp")
    dat = run_ccx(tmp_path, gravity_deck(["soft_tissue", "bone"]), model=None, timeout=300)
    check_solved(tmp_path, dat, coarse_run / "model.vtu")


# --- slow: the literal acceptance run ------------------------------------------------------


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    """``dicer run ../shared/data/cranium_ct.nii.gz -o out/`` with the default configuration."""
    out = tmp_path_factory.mktemp("cranium_full") / "out"
    dicer("run", CT, "-o", out, "-q")
    return out


@pytest.mark.slow
def test_full_resolution_run(full_run):
    from dicer.io.images import read_labels

    labels = read_labels(full_run / "labels_ds.nii.gz")
    assert labels.array.shape == (256, 256, 108)  # factor 1: the labels unchanged
    assert np.array_equal(labels.array, read_labels(full_run / "labels.nii.gz").array)
    quality = json.loads((full_run / "quality.json").read_text())
    assert quality["elements"] > 2_000_000
    assert quality["inverted_elements"] == 0 and quality["scaled_jacobian"]["min"] >= 0.2 - 1e-9
    with open(full_run / "model.inp", "rb") as f:
        head = f.read(4096).decode()
    assert f"{quality['nodes']} nodes, {quality['elements']} C3D8 elements" in head
    assert "Z0" in deck_sets(full_run / "model.inp")


@pytest.fixture(scope="module")
def half_run(tmp_path_factory):
    """``dicer run CT -o out --set downsample.factor=2``: the largest model seen solved here (292 k elements)."""
    out = tmp_path_factory.mktemp("cranium_half") / "out"
    dicer("run", CT, "-o", out, "--set", "downsample.factor=2", "-q")
    return out


@pytest.mark.slow
def test_half_resolution_smooths_at_a_floor_of_0_3(half_run, tmp_path):
    """Merging leaves chamfers at a scaled Jacobian of 0.29 under a floor of 0.3: the guard
    stops their nodes at once and holds their band nodes (it used to halve their coefficients
    round by round, and failed after 12 rounds with 12 elements at 0.257)."""
    dicer("smooth", half_run / "merged.vtu", "-o", tmp_path / "s.vtu", "--report", tmp_path / "s.json",
          "--set", "smooth.min_scaled_jacobian=0.3", "-q")
    report = json.loads((tmp_path / "s.json").read_text())
    assert report["backoff_rounds"] <= 4 and report["inverted_elements"] == 0  # measured 3
    assert report["min_scaled_jacobian"] > 0.26  # 0.2666: chamfers below 0.3 before, no worse


def solve_iteratively(run: Path, folder: Path, timeout: float) -> None:
    # ccx's conjugate gradient solver with an incomplete Cholesky preconditioner: SPOOLES' direct
    # factorisation already took 1.3 GB and 44 s at factor 4 (126 k degrees of freedom), and its
    # fill-in grows faster than the model
    os.symlink((run / "model.inp").resolve(), folder / "model.inp")
    deck = gravity_deck(["soft_tissue", "bone"], solver="ITERATIVE CHOLESKY")
    dat = run_ccx(folder, deck, model=None, timeout=timeout)
    check_solved(folder, dat, run / "model.vtu")


@pytest.mark.slow
@pytest.mark.calculix
@needs_ccx
def test_ccx_solves_half_resolution_model(half_run, tmp_path):
    # measured: 0.92 M degrees of freedom, 566 iterations, 145 s and 1.35 GB on one core (3 December 2026)
    solve_iteratively(half_run, tmp_path, timeout=1800)


@pytest.mark.slow
@pytest.mark.calculix
@needs_ccx
def test_ccx_solves_full_resolution_model(full_run, tmp_path):
    # 2.35 M nodes (7 M degrees of freedom): measured 3 December 2026, 1,038 iterations in
    # 38 minutes at 10.3 GB with the error stuck at 1.5e-5 to 3e-5 against a limit of 2.9e-8
    # (docs/exports.md): fails until a solver that fits the full model is used
    solve_iteratively(full_run, tmp_path, timeout=7200)


# --- slow: plane merging on the real bone ------------------------------------------------------


def _surface_faces(cells: np.ndarray, material: np.ndarray | None = None) -> np.ndarray:
    """(F, 4) node rows of the hexahedron faces used by one element only; with ``material``,
    those between two elements of different materials instead (the interfaces)."""
    faces = cells[:, [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]]
    faces = faces.reshape(-1, 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    key = key[order]
    start = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
    group = np.cumsum(start) - 1
    count = np.bincount(group)
    first = order[start]
    if material is None:
        return faces[first[count == 1]]
    owner_material = np.repeat(material, 6)[order]
    differs = np.zeros(count.size, dtype=bool)
    differs[group[1:][(group[1:] == group[:-1]) & (owner_material[1:] != owner_material[:-1])]] = True
    return faces[first[(count == 2) & differs]]


def _mean_distances(a, b, faces_a: np.ndarray, faces_b: np.ndarray, voxel: float) -> list[float]:
    """Mean distance, in voxels, of the nodes of ``faces_a`` to the surface ``faces_b`` and back."""
    from scipy.spatial import cKDTree

    out = []
    for x, fx, y, fy in ((a, faces_a, b, faces_b), (b, faces_b, a, faces_a)):
        d, _ = cKDTree(_surface_samples(y.points, fy)).query(x.points[np.unique(fx)])
        out.append(float(d.mean()) / voxel)
    return out


def _surface_samples(points: np.ndarray, faces: np.ndarray, k: int = 6) -> np.ndarray:
    """k x k bilinear samples on every face."""
    t = (np.arange(k) + 0.5) / k
    u, v = (a.ravel() for a in np.meshgrid(t, t))
    c = points[faces]  # (F, 4, 3)
    w = np.stack([(1 - u) * (1 - v), u * (1 - v), u * v, (1 - u) * v], axis=1)  # (k*k, 4)
    return np.einsum("sc,fcd->fsd", w, c).reshape(-1, 3)


@pytest.mark.slow
def test_merged_bone_surface_stays_within_half_a_voxel():
    """Bone of the head CT: one merge per axis, then smoothing; the merged-and-smoothed boundary
    lies on average within 0.5 voxel of the unmerged-and-smoothed one (both ways)."""
    from dicer.connectivity import fix_connectivity
    from dicer.io.images import read_image
    from dicer.mesh.merge import merge_planes
    from dicer.mesh.smooth import smooth_mesh
    from dicer.mesh.voxel import voxel_mesh

    image = read_image(CT)
    bone = ndi.binary_closing(ndi.binary_opening(image.array >= 226, FACE3), FACE3).astype(np.uint8)
    bone, _ = fix_connectivity(bone)
    mesh = voxel_mesh(bone, image.spacing)
    merged, report = merge_planes(mesh, passes=(1, 1, 1))
    # thin cranial bone on 0.96 x 0.96 x 1.5 mm voxels: 1.749 at merging's floor 0.3 (1.796 at
    # 0.2, the floor until 5 December 2026)
    assert report["element_ratio"] >= 1.7
    assert abs(report["volume"]["1"]["change_percent"]) <= 10.0
    fine, _ = smooth_mesh(mesh, {})
    coarse, rep = smooth_mesh(merged, {})
    assert rep["inverted_elements"] == 0 and rep["min_scaled_jacobian"] >= 0.3
    distances = _mean_distances(coarse, fine, _surface_faces(coarse.cells), _surface_faces(fine.cells),
                                float(min(image.spacing)))
    assert max(distances) <= 0.5, distances


@pytest.mark.slow
def test_merged_head_surfaces_stay_within_half_a_voxel(full_run):
    """Soft tissue + bone of the default full-resolution run: the merged-and-smoothed outer
    surface and bone interface lie on average within 0.5 voxel of the unmerged-and-smoothed ones."""
    from dicer.io.meshes import read_mesh
    from dicer.mesh.smooth import smooth_mesh

    report = json.loads((full_run / "merge.json").read_text())
    assert report["elements_after"] < report["elements_before"]
    assert all(abs(v["change_percent"]) <= 1.0 for v in report["volume"].values())
    fine, _ = smooth_mesh(read_mesh(full_run / "mesh.vtu"), {})
    coarse = read_mesh(full_run / "smoothed.vtu")
    voxel = float(min(fine.spacing))
    outer = _mean_distances(coarse, fine, _surface_faces(coarse.cells), _surface_faces(fine.cells), voxel)
    interface = _mean_distances(coarse, fine, _surface_faces(coarse.cells, coarse.material),
                                _surface_faces(fine.cells, fine.material), voxel)
    assert max(outer) <= 0.5 and max(interface) <= 0.5, (outer, interface)


@pytest.mark.slow  # the whole head CT through dicer run: about a minute
def test_six_mm_slices_merge_in_bounded_rounds_and_smooth_at_defaults(tmp_path):
    """Every fourth slice of the head CT (0.96 x 0.96 x 6 mm) with the default chain: a
    merge step moved rim nodes and back a few a round, 282 rounds (22 s), and smoothing
    stopped with an error (a row of merged elements failing one a round)."""
    import json

    import SimpleITK as sitk

    image = sitk.ReadImage(str(CT))
    thick = image[:, :, ::4]
    thick.SetSpacing((image.GetSpacing()[0], image.GetSpacing()[1], image.GetSpacing()[2] * 4))
    sitk.WriteImage(thick, str(tmp_path / "thick.nii.gz"))
    dicer("run", tmp_path / "thick.nii.gz", "-o", tmp_path / "out", "-q")
    merge = json.loads((tmp_path / "out" / "merge.json").read_text())
    assert all(step["retry_rounds"] <= 16 + step["regions"] + 1 for step in merge["steps"])
    quality = json.loads((tmp_path / "out" / "quality.json").read_text())
    assert quality["scaled_jacobian"]["min"] >= 0.2 and quality["inverted_elements"] == 0
