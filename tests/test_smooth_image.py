"""Sub-voxel surfaces: smoothing that places boundary nodes on the scan's iso-surfaces."""

import json

import numpy as np
import pytest
from scipy import ndimage

from dicer.cli import main
from dicer.config import preset_settings
from dicer.connectivity import fix_connectivity
from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.images import write_image
from dicer.io.meshes import read_mesh, write_mesh
from dicer.mesh.boundary import boundary_graph
from dicer.mesh.metrics import element_volumes, scaled_jacobian
from dicer.mesh.smooth import smooth_mesh

ON = {"surface_from_image": True, "min_scaled_jacobian": 0.2}
"""The scan is used only when asked for (off by default); at the floor 0.2 the figures were
measured at (the default floor 0.3 sharpens more corners: the ball's mean 0.046 -> 0.066)."""
WITHOUT_THE_LAYER = preset_settings("explicit-dynamics")["smooth"]
"""The phantom's figures were measured without the pillow layer: the preset explicit-dynamics."""
from dicer.mesh.voxel import voxel_mesh

R = 16.3
N = 48
CENTRE = np.array([24.31, 23.77, 24.13])  # off the lattice


def ct_ball(dim=3, supersample=5, blur=0.6, noise=30.0, seed=0):
    """A CT-like ball of radius R voxels: supersampled ball -> block average (partial
    volume), Gaussian blur (sigma ``blur`` voxels), Gaussian noise (HU); 0 / 1000 HU."""
    g = (np.arange(N * supersample) + 0.5) / supersample
    grids = np.meshgrid(*([g] * dim), indexing="ij", sparse=True)
    inside = sum((grid - c) ** 2 for grid, c in zip(grids, CENTRE[:dim])) < R * R
    fraction = inside.reshape(sum(((N, supersample) for _ in range(dim)), ())).mean(axis=tuple(range(1, 2 * dim, 2)))
    image = ndimage.gaussian_filter(1000.0 * fraction, blur)
    image += np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return image.astype(np.float32)


def measure(mesh, out, dim):
    nodes = np.flatnonzero(boundary_graph(mesh).boundary)
    r = np.linalg.norm(out.points[nodes, :dim] - CENTRE[:dim], axis=1) - R
    exact = 4 / 3 * np.pi * R**3 if dim == 3 else np.pi * R**2
    sj = scaled_jacobian(out.points, out.cells)
    return {"mean": float(np.abs(r).mean()), "max": float(np.abs(r).max()),
            "volume": float(element_volumes(out.points, out.cells).sum() / exact - 1),
            "min_sj": float(sj.min()), "inverted": int(np.count_nonzero(sj <= 0))}


@pytest.fixture(scope="module", params=[3, 2], ids=["3d", "2d"])
def phantom(request):
    dim = request.param
    image = ct_ball(dim, supersample=5 if dim == 3 else 8)
    labels, _ = fix_connectivity((image >= 500).astype(np.uint8))
    mesh = voxel_mesh(labels)
    labels_only, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, "surface_from_labels": False})
    scan, report = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **ON}, image=Volume(image, (1.0,) * dim),
                               thresholds=[500.0])
    return dim, image, mesh, labels_only, scan, report


def test_surface_from_the_scan(phantom):
    dim, _, mesh, labels_only, scan, report = phantom
    before, after = measure(mesh, labels_only, dim), measure(mesh, scan, dim)
    # measured (docs/smoothing.md): 3D 0.140 -> 0.046 mean, 0.46 -> 0.167 max;
    # 2D 0.121 -> 0.044 mean, 0.36 -> 0.145 max. The 3D figures are the sphere target of
    # docs/validation.md: mean <= 0.05, max <= 0.2, volume within 0.5 %
    if dim == 3:
        assert before["mean"] > 0.13 and after["mean"] <= 0.05 and after["max"] <= 0.2
    else:
        assert before["mean"] > 0.11 and after["mean"] <= 0.05 and after["max"] <= 0.16
    assert abs(after["volume"]) <= 0.005
    assert after["min_sj"] >= 0.2 and after["inverted"] == 0
    assert report["inverted_elements"] == 0 and report["min_scaled_jacobian"] >= 0.2
    info = report["surface_from_image"]
    assert info["nodes_moved"] >= 0.95 * info["nodes_between_two_kinds"]
    assert 0.3 < info["edge_variance_mm2"]["0|1"] < 1.5  # blur 0.6^2 + smoothing 0.5^2 + partial volume
    assert np.array_equal(scan.cells, mesh.cells)


def test_labels_only_unchanged(phantom):
    dim, image, mesh, labels_only, _, _ = phantom
    off, report = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, "surface_from_image": False, "surface_from_labels": False},
                              image=Volume(image, (1.0,) * dim),
                              thresholds=[500.0])
    assert off.points.tobytes() == labels_only.points.tobytes()
    assert "surface_from_image" not in report


def test_deterministic(phantom):
    dim, image, mesh, _, scan, _ = phantom
    again, _ = smooth_mesh(mesh, {**WITHOUT_THE_LAYER, **ON}, image=Volume(image, (1.0,) * dim), thresholds=[500.0])
    assert again.points.tobytes() == scan.points.tobytes()


def test_bad_image_or_thresholds():
    image = ct_ball(2, supersample=4)
    labels, _ = fix_connectivity((image >= 500).astype(np.uint8))
    mesh = voxel_mesh(labels)
    with pytest.raises(DicerError, match="not strictly increasing"):
        smooth_mesh(mesh, ON, image=Volume(image, (1.0, 1.0)), thresholds=[500.0, 100.0])
    with pytest.raises(DicerError, match="span"):
        smooth_mesh(mesh, ON, image=Volume(image[:30], (1.0, 1.0)), thresholds=[500.0])
    # the same scan stored with its x axis flipped: the same place, another frame, said so
    n = image.shape[0]
    flipped = Volume(image[::-1].copy(), (1.0, 1.0), (float(n), 0.0), (-1.0, 0.0, 0.0, 1.0))
    with pytest.raises(DicerError, match=r"axes are turned or flipped \(direction cosines \(-1, 0, 0, 1\)\)"):
        smooth_mesh(mesh, ON, image=flipped, thresholds=[500.0])
    with pytest.raises(DicerError, match="2D image for a 3D mesh"):
        smooth_mesh(voxel_mesh(np.ones((4, 4, 4), np.uint8)), ON, image=Volume(image, (1.0, 1.0)),
                    thresholds=[500.0])
    with pytest.raises(DicerError, match="image_sigma"):
        smooth_mesh(mesh, {"image_sigma": -1})


def test_thresholds_outside_the_scans_values_are_said(caplog):
    image = ct_ball(2, supersample=4)  # values about -30 to 1030
    labels, _ = fix_connectivity((image >= 500).astype(np.uint8))
    mesh = voxel_mesh(labels)
    caplog.set_level("WARNING", logger="dicer")
    smooth_mesh(mesh, ON, image=Volume(image, (1.0, 1.0)), thresholds=[5000.0], image_source="scan.nii.gz")
    said = [r.getMessage() for r in caplog.records if "lie outside" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("smooth: the thresholds 5000 lie outside the values of scan.nii.gz")
    caplog.clear()
    smooth_mesh(mesh, ON, image=Volume(image, (1.0, 1.0)), thresholds=[500.0])
    assert not [r for r in caplog.records if "lie outside" in r.getMessage()]


def test_cli_smooth_with_image(tmp_path, capsys, caplog):
    image = ct_ball(2, supersample=4)
    labels, _ = fix_connectivity((image >= 500).astype(np.uint8))
    write_mesh(voxel_mesh(labels), tmp_path / "mesh.vtu")
    write_image(Volume(image, (1.0, 1.0)), tmp_path / "scan.nii.gz")
    (tmp_path / "segmentation.json").write_text(json.dumps({"thresholds": [500.0]}))
    args = ["smooth", str(tmp_path / "mesh.vtu"), "--image", str(tmp_path / "scan.nii.gz"),
            "--set", "smooth.surface_from_image=true"]
    assert main(args + ["-o", str(tmp_path / "a.vtu"), "--thresholds", str(tmp_path / "segmentation.json"),
                        "--report", str(tmp_path / "a.json"), "-q"]) == 0
    assert "surface_from_image" in json.loads((tmp_path / "a.json").read_text())
    assert main(args + ["-o", str(tmp_path / "b.vtu"), "--thresholds", str(tmp_path / "segmentation.json"),
                        "-q"]) == 0
    assert (tmp_path / "a.vtu").read_bytes() == (tmp_path / "b.vtu").read_bytes()
    plain = tmp_path / "plain.vtu"
    assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(plain), "-q"]) == 0
    assert not np.array_equal(read_mesh(plain).points, read_mesh(tmp_path / "a.vtu").points)
    capsys.readouterr()
    # asked for without a scan (a label volume's chain): said, and the labels' surface made
    assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / "l.vtu"), "-q",
                 "--set", "smooth.surface_from_image=true"]) == 0
    assert "smooth.surface_from_image is set, but there is no scan" in caplog.text
    assert (tmp_path / "l.vtu").read_bytes() == plain.read_bytes()
    # no thresholds (the default segmentation is not manual), a missing file, a bad file
    assert main(args + ["-o", str(tmp_path / "c.vtu")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "--thresholds" in err and err.count("\n") == 1
    assert main(args + ["-o", str(tmp_path / "c.vtu"), "--thresholds", str(tmp_path / "none.json")]) == 2
    assert "not found" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text("{}")
    assert main(args + ["-o", str(tmp_path / "c.vtu"), "--thresholds", str(tmp_path / "bad.json")]) == 2
    assert "no thresholds" in capsys.readouterr().err
    assert not (tmp_path / "c.vtu").exists()


def test_nodes_that_miss_the_iso_surface_are_counted_and_warned_of(tmp_path, caplog):
    """image_sigma 3 on the shell phantom (a skull a voxel or two thick) blurs its edges away:
    2 of 2,392 nodes found the iso-surface, while smooth.json said 2,260 were on it (it
    counted every node with its whole pull left)."""
    assert main(["phantom", "shell", "-o", str(tmp_path / "shell.nii.gz"), "--size", "24", "-q"]) == 0
    for sigma, warned in ((0.5, False), (3.0, True)):
        caplog.clear()
        out = tmp_path / f"out{sigma}"
        assert main(["run", str(tmp_path / "shell.nii.gz"), "-o", str(out), "-q", "--set",
                     "smooth.surface_from_image=true", "--set", f"smooth.image_sigma={sigma}"]) == 0
        pull = json.loads((out / "smooth.json").read_text())["surface_from_image"]
        said = [r.getMessage() for r in caplog.records if "reach the scan's iso-surface" in r.getMessage()]
        assert len(said) == int(warned)
        on, kinds = pull["nodes_on_the_image_surface"], pull["nodes_between_two_kinds"]
        if warned:
            assert on <= pull["nodes_moved"] < 0.1 * kinds  # 0 and 132 of 2,392
            assert said[0].startswith(f"smooth: {on} of the {kinds} boundary nodes")
            assert "smooth.image_sigma=3" in said[0]
        else:
            assert on > 0.9 * kinds


def test_volume_warning_names_the_pull_onto_the_scan(tmp_path, caplog):
    """A ball labelled at 500 HU, its surface pulled onto the 850 HU iso-surface: the volume
    drops by 15 %, which the scan's surface did, not the smoothing coefficients."""
    g = np.indices((24, 24, 24)).astype(float) - 11.7
    image = ndimage.gaussian_filter(np.where(np.sqrt((g ** 2).sum(0)) < 7.3, 1000.0, 0.0), 1.0).astype(np.float32)
    labels, _ = fix_connectivity((image >= 500).astype(np.uint8))
    mesh = voxel_mesh(labels)
    mesh.names = ["bone"]
    write_mesh(mesh, tmp_path / "mesh.vtu")
    write_image(Volume(image, (1.0, 1.0, 1.0)), tmp_path / "scan.nii.gz")
    (tmp_path / "c.yaml").write_text("materials: [{name: bone, youngs_modulus: 15000, poissons_ratio: 0.3}]\n"
                                     "smooth: {surface_from_image: true, min_scaled_jacobian: 0.2}\n")
    change = {}
    for threshold in (850, 500):
        (tmp_path / "segmentation.json").write_text(json.dumps({"thresholds": [threshold]}))
        caplog.clear()
        assert main(["smooth", str(tmp_path / "mesh.vtu"), "-o", str(tmp_path / f"s{threshold}.vtu"), "--image",
                     str(tmp_path / "scan.nii.gz"), "--thresholds", str(tmp_path / "segmentation.json"),
                     "--config", str(tmp_path / "c.yaml"), "--report", str(tmp_path / "s.json"), "-q"]) == 0
        report = json.loads((tmp_path / "s.json").read_text())
        change[threshold] = 100 * report["volume_change_by_material"]["1"]
        warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        if threshold == 850:  # the pull's own warnings come too (105 of 974 nodes reach that iso-surface)
            assert any("reach the scan's iso-surface" in m for m in warned)
            warned = [m for m in warned if "material volume changed" in m]
            assert change[850] < -10 and report["surface_from_image"]["nodes_moved"] > 100 and len(warned) == 1
            assert warned[0] == (
                f"smooth: material volume changed by more than 5 % (bone {change[850]:+.1f} %); the surface went "
                "onto the scan's iso-surfaces (smooth.surface_from_image) at the thresholds 850 (segmentation.json), "
                "so the volume follows the scan where they lie away from the labels' surface (the segmentation's "
                "clean-up, thresholds other than the segmentation's, or smooth.image_sigma 0.5 blurring thin "
                "parts): check the thresholds and smooth.image_sigma, or set smooth.surface_from_image: false to "
                "smooth from the labels alone")
        else:  # the thresholds the labels were made with: the volume stays
            assert abs(change[500]) < 1 and not warned


def test_pillow_puts_the_surface_on_the_scan(phantom):
    # a pillow layer (smooth.pillow) frees the surface nodes from the corners the quality
    # floor otherwise leaves: they stay where the iso-surface projection put them.
    # Measured (docs/smoothing.md §3b): 3D mean 0.030, max 0.124, volume -0.35 % (without the
    # layer 0.046, 0.167); 2D mean 0.040, max 0.120, volume -0.17 %
    from dicer.mesh.boundary import plane_bits
    from dicer.mesh.pillow import surface_faces

    dim, image, mesh, _, scan, _ = phantom
    out, report = smooth_mesh(mesh, {**ON, "pillow": True}, image=Volume(image, (1.0,) * dim), thresholds=[500.0])
    faces, _ = surface_faces(mesh.cells, dim, mesh.n_points, plane_bits(mesh))
    copies = out.points[mesh.n_points:]
    assert copies.shape[0] == np.unique(faces).size == report["pillow"]["nodes_added"]
    r = np.linalg.norm(copies[:, :dim] - CENTRE[:dim], axis=1) - R
    exact = 4 / 3 * np.pi * R**3 if dim == 3 else np.pi * R**2
    volume = float(element_volumes(out.points, out.cells).sum() / exact - 1)
    before = measure(mesh, scan, dim)
    assert np.abs(r).mean() <= 0.045 and np.abs(r).max() <= 0.15 and abs(volume) <= 0.005
    assert np.abs(r).mean() < 0.7 * before["mean"] if dim == 3 else np.abs(r).mean() <= before["mean"]
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.2 and report["inverted_elements"] == 0 and report["min_scaled_jacobian"] == pytest.approx(sj.min())
    assert report["pillow"]["surface"] == "image" and report["pillow"]["faces_without_layer"] == 0
    assert report["volume_change"] == pytest.approx(
        element_volumes(out.points, out.cells).sum() / element_volumes(mesh.points, mesh.cells).sum() - 1)


def test_thresholds_of_another_material_count_are_refused():
    """Three thresholds for a mesh of two materials (another scan's segmentation.json) were
    taken, and the extra one ignored."""
    from dataclasses import replace

    from dicer.mesh.subvoxel import check_thresholds_for_mesh

    mesh = replace(voxel_mesh(np.ones((3, 3, 3), np.uint8)), names=["soft_tissue", "bone"])
    assert check_thresholds_for_mesh([-200.0, 300.0], mesh).tolist() == [-200.0, 300.0]
    with pytest.raises(DicerError, match=r"t1.json: 3 threshold\(s\) for a mesh of 2 materials \(soft_tissue, bone\)"):
        check_thresholds_for_mesh([-200.0, 300.0, 900.0], mesh, "t1.json")


@pytest.fixture(scope="module")
def hard_pull():
    """The 3D scan at a floor of 0.5: the guard backs the pull off over several rounds."""
    image = ct_ball(3)
    labels, _ = fix_connectivity((image >= 500).astype(np.uint8))
    mesh = voxel_mesh(labels)
    settings = {**ON, "min_scaled_jacobian": 0.5}
    return mesh, settings, Volume(image, (1.0,) * 3)


def test_pull_rounds_check_only_what_moved(hard_pull, monkeypatch):
    """A pull round rechecks the elements whose nodes moved or that sat near the floor: it
    decides as a whole check does, so the result is the same to the bit."""
    import dicer.mesh.smooth as smooth

    mesh, settings, image = hard_pull
    partial, report = smooth_mesh(mesh, settings, image=image, thresholds=[500.0])
    assert report["surface_from_image"]["pull_backoff_rounds"] >= 3
    whole = smooth._rechecked
    monkeypatch.setattr(smooth, "_rechecked", lambda st: None if whole(st) is None else
                        (np.ones(st.touched.size, bool),) * 2)
    full, again = smooth_mesh(mesh, settings, image=image, thresholds=[500.0])
    assert full.points.tobytes() == partial.points.tobytes()
    assert again["surface_from_image"] == report["surface_from_image"]


def test_a_partial_check_never_accepts(hard_pull, monkeypatch):
    """Positions are accepted on a whole check only: a partial check that missed every failing
    element (here made to) still leaves no element under the floor."""
    import dicer.mesh.smooth as smooth

    mesh, settings, image = hard_pull
    check = smooth._check_quality

    def blind(st, whole=False):
        check(st, whole)
        if not whole:
            st.bad[:] = False

    monkeypatch.setattr(smooth, "_check_quality", blind)
    out, report = smooth_mesh(mesh, settings, image=image, thresholds=[500.0])
    sj = scaled_jacobian(out.points, out.cells)
    assert sj.min() >= 0.5 - 1e-9 and report["min_scaled_jacobian"] >= 0.5 - 1e-9
