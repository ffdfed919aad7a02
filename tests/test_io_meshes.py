import meshio
import numpy as np
import pytest

from dicer.errors import DicerError
from dicer.io.meshes import read_mesh, write_mesh
from dicer.mesh.voxel import voxel_mesh


@pytest.fixture
def mesh():
    labels = np.zeros((3, 4, 2), np.uint8)
    labels[0:2, 1:3, :] = 1
    labels[2, 3, 1] = 2
    return voxel_mesh(labels, spacing=(0.5, 0.75, 2.0), origin=(1.0, -2.0, 3.0))


def test_vtu_round_trip_keeps_everything(tmp_path, mesh):
    mesh.point_data["node_class"] = np.arange(mesh.n_points, dtype=np.int8) % 7
    path = tmp_path / "m.vtu"
    write_mesh(mesh, path)
    back = read_mesh(path)
    assert np.array_equal(back.cells, mesh.cells)
    assert np.array_equal(back.points, mesh.points)
    assert np.array_equal(back.lattice, mesh.lattice)
    assert np.array_equal(back.material, mesh.material)
    assert np.array_equal(back.point_data["node_class"], mesh.point_data["node_class"])
    assert back.spacing.tolist() == [0.5, 0.75, 2.0]
    assert back.origin.tolist() == [1.0, -2.0, 3.0]
    assert back.grid_shape.tolist() == [3, 4, 2]
    # ParaView-readable VTU, nothing else left in the folder
    assert [p.name for p in tmp_path.iterdir()] == ["m.vtu"]
    assert meshio.read(path).cells[0].type == "hexahedron"


def test_writes_are_byte_identical(tmp_path, mesh):
    write_mesh(mesh, tmp_path / "a.vtu")
    write_mesh(mesh, tmp_path / "b.vtu")
    assert (tmp_path / "a.vtu").read_bytes() == (tmp_path / "b.vtu").read_bytes()


def test_2d_round_trip(tmp_path):
    labels = np.array([[1, 1, 0], [0, 2, 2]], np.uint8)
    mesh = voxel_mesh(labels, spacing=(2.0, 3.0))
    write_mesh(mesh, tmp_path / "q.vtu")
    back = read_mesh(tmp_path / "q.vtu")
    assert back.dim == 2 and back.n_cells == 4
    assert np.array_equal(back.cells, mesh.cells)


def test_inverted_mesh_is_refused_and_not_written(tmp_path, mesh):
    bad = mesh.copy()
    bad.points[bad.cells[0, 6]] = bad.points[bad.cells[0, 0]] - 1.0
    with pytest.raises(DicerError, match="inverted"):
        write_mesh(bad, tmp_path / "bad.vtu")
    assert list(tmp_path.iterdir()) == []


def test_read_errors(tmp_path, mesh):
    with pytest.raises(DicerError, match="not found"):
        read_mesh(tmp_path / "none.vtu")
    truncated = tmp_path / "t.vtu"
    write_mesh(mesh, truncated)
    truncated.write_bytes(truncated.read_bytes()[:300])
    with pytest.raises(DicerError, match="cannot read"):
        read_mesh(truncated)
    foreign = tmp_path / "foreign.vtu"
    meshio.write(foreign, meshio.Mesh(mesh.points, [("hexahedron", mesh.cells)], cell_data={"material": [mesh.material]}))
    with pytest.raises(DicerError, match="lattice"):
        read_mesh(foreign)
    tets = tmp_path / "tets.vtu"
    meshio.write(tets, meshio.Mesh(np.eye(4, 3), [("tetra", np.array([[0, 1, 2, 3]]))]))
    with pytest.raises(DicerError, match="hexahedron or only quad"):
        read_mesh(tets)


def test_wrong_extension(tmp_path, mesh):
    with pytest.raises(DicerError, match="VTU"):
        write_mesh(mesh, tmp_path / "m.inp")
