"""`dicer surface`: one closed, outward STL surface per material."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dicer.cli import main
from dicer.connectivity import fix_connectivity
from dicer.errors import DicerError
from dicer.export.stl import enclosed_volume, open_edges, read_stl, weld, write_surfaces
from dicer.io.meshes import write_mesh
from dicer.mesh.merge import merge_mesh
from dicer.mesh.metrics import element_volumes
from dicer.mesh.smooth import smooth_mesh
from dicer.mesh.voxel import voxel_mesh

NAMES = ["soft_tissue", "bone"]


def shell_labels(n=14):
    """A ball of material 1 around a ball of material 2, fixed (no edge- or corner-only contacts)."""
    x, y, z = np.indices((n, n, n)) - (n - 1) / 2
    r = np.sqrt(x**2 + y**2 + 1.3 * z**2)
    labels = np.where(r < 0.45 * n, 1, 0).astype(np.uint8)
    labels[r < 0.25 * n] = 2
    return fix_connectivity(labels)[0]


def check_folder(folder, mesh, names=NAMES):
    """Every file closed (each welded edge in exactly two triangles, opposite ways) and its
    enclosed volume that of the material's elements; returns the worst relative volume error."""
    worst = 0.0
    volumes = np.bincount(mesh.material, weights=element_volumes(mesh.points, mesh.cells))
    for label in np.unique(mesh.material):
        _, corners = read_stl(folder / f"{names[label - 1]}.stl")
        points, tris = weld(corners)
        assert open_edges(tris) == 0
        a = tris[:, [0, 1, 2]].ravel(), tris[:, [1, 2, 0]].ravel()
        edges = np.sort(np.column_stack(a), axis=1)
        _, uses = np.unique(edges, axis=0, return_counts=True)
        assert np.all(uses == 2)  # every edge shared by exactly two triangles
        vol = enclosed_volume(points.astype(np.float64), tris)
        worst = max(worst, abs(vol / volumes[label] - 1.0))
    return worst


def test_voxel_surfaces_are_closed_and_enclose_the_material(tmp_path):
    mesh = voxel_mesh(shell_labels(), spacing=(0.5, 0.7, 0.9), origin=(-90.0, -125.0, -71.0))
    info = write_surfaces(mesh, tmp_path, NAMES)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bone.stl", "soft_tissue.stl"]
    for label, name in enumerate(NAMES, start=1):
        # voxel faces are flat: the triangles enclose the elements' volume to rounding
        assert info[name]["volume_mm3"] == pytest.approx(info[name]["element_volume_mm3"], rel=1e-12)
        assert info[name]["triangles"] % 2 == 0
    assert check_folder(tmp_path, mesh) < 1e-6  # float32 corners in the file


def test_smoothed_surfaces_close_and_volume_error(tmp_path):
    mesh = voxel_mesh(shell_labels(18), spacing=(1.0, 1.0, 1.0))
    mesh = smooth_mesh(merge_mesh(mesh)[0])[0]
    write_surfaces(mesh, tmp_path, NAMES)
    # smoothed faces need not be flat, yet the triangles enclose the trilinear elements' volume
    # to 3e-9 here (float32 corners in the file)
    error = check_folder(tmp_path, mesh)
    assert error < 1e-6, error


def test_mirrored_direction_keeps_the_surface_outward(tmp_path):
    mesh = voxel_mesh(shell_labels(), spacing=(1.0, 1.0, 1.0), origin=(10.0, 0.0, 0.0))
    mesh.direction = np.diag([-1.0, 1.0, 1.0])  # a flipped x axis
    info = write_surfaces(mesh, tmp_path, NAMES)
    assert all(v["volume_mm3"] > 0 for v in info.values())
    assert check_folder(tmp_path, mesh) < 1e-6
    _, corners = read_stl(tmp_path / "bone.stl")
    # scanner coordinates: x mirrored about the origin's x (10 mm), as the exports put it
    assert set(np.unique(corners[:, :, 0]).tolist()) <= set(np.float32(20.0 - mesh.points[:, 0]).tolist())
    assert corners[:, :, 0].min() < 9.0


@settings(max_examples=25, deadline=None)
@given(arrays(np.uint8, (5, 4, 4), elements=st.integers(0, 2)))
def test_random_fixed_labels_give_closed_surfaces(tmp_path_factory, labels):
    fixed = fix_connectivity(labels)[0]
    if not fixed.any():
        return
    mesh = voxel_mesh(fixed, spacing=(1.0, 2.0, 0.5))
    folder = tmp_path_factory.mktemp("stl")
    info = write_surfaces(mesh, folder, NAMES)
    for v in info.values():
        assert v["volume_mm3"] == pytest.approx(v["element_volume_mm3"], rel=1e-12)
    assert check_folder(folder, mesh) < 1e-6


def test_edge_contact_is_refused_and_nothing_written(tmp_path):
    labels = np.zeros((3, 3, 1), np.uint8)
    labels[0, 0, 0] = labels[1, 1, 0] = 1  # two voxels touching along one edge
    mesh = voxel_mesh(labels)
    with pytest.raises(DicerError, match="not closed.*dicer fix"):
        write_surfaces(mesh, tmp_path / "out", NAMES)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_cli_surface(tmp_path, capsys, caplog):
    vtu = tmp_path / "mesh.vtu"
    write_mesh(voxel_mesh(shell_labels(10)), vtu)
    for out in ("a", "b"):
        assert main(["surface", str(vtu), "-o", str(tmp_path / out), "-q"]) == 0, capsys.readouterr().err
    for name in ("soft_tissue.stl", "bone.stl"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    caplog.clear()
    assert main(["surface", str(vtu), "-o", str(tmp_path / "c"), "--material", "bone", "-q"]) == 0
    assert [p.name for p in (tmp_path / "c").iterdir()] == ["bone.stl"]
    assert not [r for r in caplog.records if "did not write" in r.getMessage()]
    # into a folder holding surfaces it did not write: said (they would pass for this model's)
    assert main(["surface", str(vtu), "-o", str(tmp_path / "a"), "--material", "bone", "-q"]) == 0
    said = [r.getMessage() for r in caplog.records if "did not write" in r.getMessage()]
    assert len(said) == 1 and "1 .stl file(s) this mesh did not write (soft_tissue.stl)" in said[0]
    code = main(["surface", str(vtu), "-o", str(tmp_path / "d"), "--material", "skull", "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "skull" in err and "soft_tissue, bone" in err
    assert not (tmp_path / "d").exists()
    (tmp_path / "f").write_text("x")
    code = main(["surface", str(vtu), "-o", str(tmp_path / "f"), "-q"])
    assert code == 2 and "not a folder" in capsys.readouterr().err
