import meshio
import numpy as np
import pytest

from dicer.errors import DicerError
from dicer.io.meshes import read_mesh, write_mesh
from dicer.mesh.metrics import edge_ratio, scaled_jacobian
from dicer.mesh.voxel import voxel_mesh
from meshcheck import meshio_vtu_with_grid


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
    # the metrics are computed beside the write of the first arrays: the refusal still
    # comes before the rename, and the folder made for the file goes again
    with pytest.raises(DicerError, match=r"bad\.vtu: 7 degenerate or inverted element\(s\), e\.g\. element 1 "):
        write_mesh(bad, tmp_path / "new" / "bad.vtu")
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


def _with_extra_data(mesh):
    rng = np.random.default_rng(0)
    mesh.point_data["node_class"] = np.arange(mesh.n_points, dtype=np.int8) % 7
    mesh.point_data["displacement"] = rng.normal(size=(mesh.n_points, 3))
    mesh.cell_data["coarsening_level"] = np.arange(mesh.n_cells, dtype=np.int64) % 3
    quality = rng.random(mesh.n_cells).astype(np.float32)
    quality[0] = np.nan  # free data may hold NaN; the exact check compares bits
    mesh.cell_data["quality"] = quality
    return mesh


def _assert_same(back, mesh):
    for a, b in [(back.cells, mesh.cells), (back.points, mesh.points), (back.lattice, mesh.lattice),
                 (back.material, mesh.material), (back.spacing, mesh.spacing), (back.origin, mesh.origin),
                 (back.grid_shape, mesh.grid_shape)]:
        assert np.array_equal(a, b)
    assert back.cells.dtype == np.int64 and back.material.dtype == np.int32 and back.lattice.dtype == np.int64
    for got, want in [(back.point_data, mesh.point_data), (back.cell_data, mesh.cell_data)]:
        assert list(got) == list(want)
        for key, v in want.items():
            assert got[key].dtype == v.dtype and got[key].shape == v.shape
            assert np.array_equal(got[key], v, equal_nan=v.dtype.kind == "f")


@pytest.mark.parametrize("dim", [2, 3])
def test_raw_vtu_round_trip_exact_and_meshio_reads_it(tmp_path, mesh, dim):
    if dim == 2:
        mesh = voxel_mesh(np.array([[1, 1, 0], [0, 2, 2]], np.uint8), spacing=(2.0, 3.0), origin=(0.1, -0.7))
    mesh = _with_extra_data(mesh)
    path = tmp_path / "m.vtu"
    write_mesh(mesh, path)
    head = path.read_bytes()[:2000]
    assert b'header_type="UInt64"' in head and b'<AppendedData encoding="raw">' in head
    _assert_same(read_mesh(path), mesh)
    # meshio (the reference reader) gets the same arrays
    # (with the quality arrays the file adds, which read_mesh leaves out)
    # (Float32 in stage files: STAGE_QUALITY_TYPE)
    from dicer.io.meshes import STAGE_QUALITY_TYPE, _assemble, _read_meshio, with_quality
    stage_quality = {k: v.astype(STAGE_QUALITY_TYPE) for k, v in with_quality(mesh).cell_data.items()
                     if k in ("scaled_jacobian", "edge_ratio")}
    _assert_same(_assemble("m", *_read_meshio(path, "m")), with_quality(mesh, stage_quality))
    m = meshio.read(path)
    assert m.cells[0].type == ("quad" if dim == 2 else "hexahedron")
    assert np.array_equal(m.point_data["lattice"], mesh.lattice)
    assert np.array_equal(m.cell_data["material"][0], mesh.material)
    assert list(m.cell_data)[:3] == ["material", "scaled_jacobian", "edge_ratio"]
    assert m.cell_data["scaled_jacobian"][0].dtype == m.cell_data["edge_ratio"][0].dtype == np.float32
    assert np.array_equal(m.cell_data["scaled_jacobian"][0], scaled_jacobian(mesh.points, mesh.cells).astype(np.float32))
    assert np.array_equal(m.cell_data["edge_ratio"][0], edge_ratio(mesh.points, mesh.cells).astype(np.float32))


def test_quality_arrays_follow_the_nodes(tmp_path, mesh):
    """Each written mesh holds the quality of its own nodes, not values carried from its input."""
    path = tmp_path / "a.vtu"
    write_mesh(mesh, path)
    moved = read_mesh(path)
    assert "scaled_jacobian" not in moved.cell_data and "edge_ratio" not in moved.cell_data
    assert np.allclose(meshio.read(path).cell_data["edge_ratio"][0], 2.0 / 0.5, rtol=1e-12)
    moved.points = moved.points * [1.0, 1.0, 3.0]  # every element 3 times as tall: 6 mm by 0.5 mm
    write_mesh(moved, tmp_path / "b.vtu")
    m = meshio.read(tmp_path / "b.vtu")
    assert np.allclose(m.cell_data["edge_ratio"][0], 6.0 / 0.5, rtol=1e-12)
    assert np.allclose(m.cell_data["scaled_jacobian"][0], 1.0, rtol=1e-12)


def test_large_mesh_is_checked_without_meshio(tmp_path, mesh, monkeypatch):
    import dicer.io.meshes as meshes

    def no_meshio(*args):
        raise AssertionError("meshio read a large mesh")

    monkeypatch.setattr(meshes, "MESHIO_CHECK_CELLS", mesh.n_cells - 1)
    monkeypatch.setattr(meshes, "_read_meshio", no_meshio)
    write_mesh(mesh, tmp_path / "m.vtu")
    _assert_same(read_mesh(tmp_path / "m.vtu"), mesh)


def test_raw_vtu_reruns_are_byte_identical(tmp_path, mesh):
    mesh = _with_extra_data(mesh)
    write_mesh(mesh, tmp_path / "a.vtu")
    write_mesh(mesh.copy(), tmp_path / "b.vtu")
    assert (tmp_path / "a.vtu").read_bytes() == (tmp_path / "b.vtu").read_bytes()


@pytest.mark.parametrize("cut", [-1, -20, -200, 0.9, 0.5])
def test_truncated_raw_vtu_names_the_file(tmp_path, mesh, cut):
    path = tmp_path / "t.vtu"
    write_mesh(_with_extra_data(mesh), path)
    data = path.read_bytes()
    path.write_bytes(data[:cut] if isinstance(cut, int) else data[:int(len(data) * cut)])
    with pytest.raises(DicerError, match=r"t\.vtu: cannot read mesh .*is the file complete\?"):
        read_mesh(path)


@pytest.mark.parametrize("old, new", [
    (b'offset="0"', b'offset="8"'),  # an array points at the wrong place
    (b'NumberOfPoints="', b'NumberOfPoints="1'),  # counts do not match the data
    (b'type="UInt8" Name="material"', b'type="Int42" Name="material"'),
    (b"</Points>", b"</Pointz>"),  # not XML any more
])
def test_corrupted_raw_vtu_header_names_the_file(tmp_path, mesh, old, new):
    path = tmp_path / "c.vtu"
    write_mesh(mesh, path)
    data = path.read_bytes()
    assert old in data
    path.write_bytes(data.replace(old, new, 1))
    with pytest.raises(DicerError, match=r"c\.vtu: cannot read mesh") as err:
        read_mesh(path)
    assert "\n" not in str(err.value)


def test_data_vtu_cannot_hold_is_refused(tmp_path, mesh):
    mesh.cell_data["flag"] = np.ones(mesh.n_cells, bool)
    with pytest.raises(DicerError, match="'flag' has type bool"):
        write_mesh(mesh, tmp_path / "m.vtu")
    assert list(tmp_path.iterdir()) == []


def test_meshio_written_vtu_is_still_read(tmp_path, mesh):
    # files of earlier dicer versions: meshio's VTU (zlib) with the grid's field data put in
    from dicer.errors import DicerError
    path = tmp_path / "old.vtu"
    raw = meshio_vtu_with_grid(mesh, path)
    back = read_mesh(path)
    assert np.array_equal(back.cells, mesh.cells) and np.array_equal(back.lattice, mesh.lattice)
    assert np.array_equal(back.spacing, mesh.spacing) and np.array_equal(back.grid_shape, mesh.grid_shape)
    # saved again by meshio, the grid is gone: the image border would be guessed from the mesh
    with pytest.raises(DicerError, match="raw.vtu: the mesh file has no grid data .* use the file the dicer stage "
                                         "wrote"):
        read_mesh(raw)


def test_a_damaged_size_word_is_refused_before_reading(tmp_path):
    import numpy as np

    from dicer.errors import DicerError
    from dicer.io.meshes import read_mesh, write_mesh
    from dicer.mesh.voxel import voxel_mesh

    path = tmp_path / "m.vtu"
    write_mesh(voxel_mesh(np.ones((3, 3, 3), np.uint8)), path)
    data = bytearray(path.read_bytes())
    at = data.index(b"<AppendedData encoding=\"raw\">\n_") + len(b"<AppendedData encoding=\"raw\">\n_")
    data[at:at + 8] = (2**60).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    with pytest.raises(DicerError, match="m.vtu: .*more than the file holds"):
        read_mesh(path)


@pytest.mark.parametrize("cut", [-1, -20, -200, 0.9, 0.5])
def test_mapped_read_back_agrees_and_refuses_damage(tmp_path, mesh, cut):
    """The read-back check reads the file mapped (arrays are views, no copy): the same
    arrays as the reading into memory, and the same refusal of a file cut short."""
    from dicer.io.meshes import _read_mapped_vtu, _read_raw_vtu

    path = tmp_path / "m.vtu"
    write_mesh(_with_extra_data(mesh), path)
    copied, mapped = _read_raw_vtu(path, "m.vtu"), _read_mapped_vtu(path, "m.vtu")
    assert copied[0] == mapped[0]
    # the file holds connectivity as Int32 and the lattice as Int16: read into memory they
    # are widened to int64, mapped they stay the file's
    assert copied[2].dtype == copied[3]["lattice"].dtype == np.int64
    assert mapped[2].dtype == np.dtype("<i4") and mapped[3]["lattice"].dtype == np.dtype("<i2")
    for a, b in zip(copied[1:3], mapped[1:3]):
        assert a.dtype.kind == b.dtype.kind and np.array_equal(a, b)
    for a, b in zip(copied[3:5], mapped[3:5]):
        assert list(a) == list(b)
        assert all(np.array_equal(a[k], b[k]) if a[k].dtype.kind == "i" else a[k].tobytes() == b[k].tobytes()
                   for k in a)  # NaN too
    data = path.read_bytes()
    path.write_bytes(data[:cut] if isinstance(cut, int) else data[:int(len(data) * cut)])
    with pytest.raises(DicerError, match=r"m\.vtu: cannot read mesh .*is the file complete\?"):
        _read_mapped_vtu(path, "m.vtu")


def test_mapped_read_keeps_the_files_int32_connectivity_read_only(tmp_path, mesh):
    """read_mesh(mapped=True), as the stages that only read their mesh do: the same mesh as
    read into memory, its connectivity the file's Int32 (not writable), the lattice widened."""
    path = tmp_path / "m.vtu"
    write_mesh(mesh, path)
    wide, narrow = read_mesh(path), read_mesh(path, mapped=True)
    assert wide.cells.dtype == np.int64 and narrow.cells.dtype.kind == "i" and narrow.cells.dtype.itemsize == 4
    assert not narrow.cells.flags.writeable
    assert narrow.lattice.dtype == np.int64
    assert np.array_equal(wide.cells, narrow.cells) and np.array_equal(wide.lattice, narrow.lattice)
    assert np.array_equal(wide.points, narrow.points) and np.array_equal(wide.material, narrow.material)


def test_lattice_minus_one_only_on_template_nodes_of_graded_meshes(tmp_path):
    # a graded mesh's template nodes lie between lattice points (lattice -1): written and
    # read back exactly; the same marker on a node of a voxel element is damage
    from dataclasses import replace

    from dicer.mesh.coarsen import coarsen_mesh
    from dicer.mesh.model import LEVEL_DATA

    labels = np.ones((12, 12, 12), np.uint8)
    graded, _ = coarsen_mesh(voxel_mesh(labels), levels=1, min_distance=1, keep_fine=())
    between = np.all(graded.lattice == -1, axis=1)
    assert between.sum() > 0
    write_mesh(graded, tmp_path / "graded.vtu")
    back = read_mesh(tmp_path / "graded.vtu")
    assert np.array_equal(back.lattice, graded.lattice) and np.array_equal(back.cells, graded.cells)
    # a voxel element's node marked -1: refused, naming the file
    voxel_node = graded.cells[np.flatnonzero(graded.cell_data[LEVEL_DATA] == 0)[0], 0]
    lattice = graded.lattice.copy()
    lattice[voxel_node] = -1
    with pytest.raises(DicerError, match=r"bad.vtu: .*1 node\(s\) have a negative lattice index"):
        write_mesh(replace(graded, lattice=lattice), tmp_path / "bad.vtu")
    assert not (tmp_path / "bad.vtu").exists()


# --- zlib-compressed VTU (model.vtu) -------------------------------------------------------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import dicer.io.meshes as meshes_io  # noqa: E402


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000), dim=st.sampled_from([2, 3]), block=st.sampled_from([64, 1000, 1 << 18]))
def test_compressed_vtu_reads_as_meshio_reads_it(tmp_path, monkeypatch, seed, dim, block):
    rng = np.random.default_rng(seed)
    shape = tuple(rng.integers(2, 7, dim))
    labels = rng.integers(0, 3, shape).astype(np.uint8)
    labels.flat[0] = 1
    m = voxel_mesh(labels)
    m.points[:, :dim] += rng.uniform(-0.2, 0.2, (m.n_points, dim))
    plain, m = m, meshes_io.with_quality(m)
    monkeypatch.setattr(meshes_io, "_ZLIB_BLOCK", block)  # many blocks, a partial last one
    path = tmp_path / f"c{seed}_{dim}_{block}.vtu"
    meshes_io.write_raw_vtu(m, path, compress=True)
    assert b'compressor="vtkZLibDataCompressor"' in path.read_bytes()[:300]
    cell_type, points, cells, point_data, cell_data, fields = meshes_io.read_raw_vtu(path, str(path))
    ref = meshio.read(path)
    assert np.array_equal(points, ref.points) and np.array_equal(points, m.points)
    assert np.array_equal(cells, ref.cells[0].data) and np.array_equal(cells, m.cells)
    assert np.array_equal(point_data["lattice"], ref.point_data["lattice"])
    for key in ("material", "scaled_jacobian", "edge_ratio"):
        assert np.array_equal(cell_data[key], ref.cell_data[key][0])
    assert meshes_io._same_mesh(plain, read_mesh(path))  # the reader drops the quality data


def test_compressed_vtu_refuses_damage(tmp_path, mesh):
    path = tmp_path / "c.vtu"
    meshes_io.write_raw_vtu(meshes_io.with_quality(mesh), path, compress=True)
    data = path.read_bytes()
    at = data.index(b"_", data.index(b"<AppendedData")) + 1
    for name, damaged in (("flipped", data[:at + 200] + bytes([data[at + 200] ^ 0xFF]) + data[at + 201:]),
                          ("cut", data[: (at + len(data)) // 2]),
                          ("header", data[:at] + (10**12).to_bytes(8, "little") + data[at + 8:])):
        bad = tmp_path / f"{name}.vtu"
        bad.write_bytes(damaged)
        with pytest.raises(DicerError, match="cannot read mesh"):
            read_mesh(bad)


def test_integer_arrays_written_narrow_unless_they_do_not_fit(tmp_path):
    # connectivity and offsets Int32, the lattice Int16 and the material UInt8 in the file
    # when their values fit, wider when not; either way they read back exactly, as the
    # Mesh's int64 (int32 for the material)
    from dataclasses import replace

    mesh = voxel_mesh(np.ones((3, 3, 3), np.uint8))
    path = tmp_path / "small.vtu"
    write_mesh(mesh, path)
    head = path.read_bytes()[:4000].decode("latin-1")
    for name, kind in (("connectivity", "Int32"), ("offsets", "Int32"), ("lattice", "Int16"), ("material", "UInt8"),
                       ("scaled_jacobian", "Float32"), ("edge_ratio", "Float32")):
        assert f'type="{kind}" Name="{name}"' in head
    cases = {
        "far.vtu": (replace(mesh, lattice=mesh.lattice + 2**31, grid_shape=np.asarray(mesh.grid_shape) + 2**31 + 1),
                    "Int64", "UInt8"),
        "wide.vtu": (replace(mesh, lattice=mesh.lattice + 40_000, grid_shape=np.asarray(mesh.grid_shape) + 40_001,
                             material=np.arange(300, 300 + mesh.n_cells, dtype=np.int32)), "Int32", "Int16"),
        "atlas.vtu": (replace(mesh, material=np.arange(1, 1 + mesh.n_cells, dtype=np.int32) * 70_000), "Int16",
                      "Int32"),
    }
    for name, (m, lattice_type, material_type) in cases.items():
        write_mesh(m, tmp_path / name)
        head = (tmp_path / name).read_bytes()[:4000].decode("latin-1")
        assert f'type="{lattice_type}" Name="lattice"' in head and 'type="Int32" Name="connectivity"' in head
        assert f'type="{material_type}" Name="material"' in head
    for m, p in [(mesh, path)] + [(m, tmp_path / name) for name, (m, _, _) in cases.items()]:
        back = read_mesh(p)
        assert back.cells.dtype == back.lattice.dtype == np.int64 and back.material.dtype == np.int32
        assert np.array_equal(back.cells, m.cells) and np.array_equal(back.lattice, m.lattice)
        assert np.array_equal(back.material, m.material)


def test_index_types_chosen_so_that_meshio_finds_every_array(tmp_path):
    # meshio's raw-data reader finds arrays by offsets it rewrites as it goes; for some
    # array sizes (a 2 x 2 x 2 voxel mesh's, with Int32 indices) it would take an earlier
    # array's tag again and drop the lattice. The writer then widens an index array.
    import meshio

    from dicer.io.meshes import _meshio_walk_ok

    assert not _meshio_walk_ok([648, 256, 32, 8, 324, 32, 64, 64])  # 2 x 2 x 2, all Int32
    assert _meshio_walk_ok([648, 256, 64, 8, 324, 32, 64, 64])  # offsets Int64
    for shape in [(2, 2, 2), (3, 3, 3), (2, 2, 1), (1, 7, 3), (4, 4, 4)]:
        mesh = voxel_mesh(np.ones(shape, np.uint8))
        path = tmp_path / "m.vtu"
        write_mesh(mesh, path)
        m = meshio.read(path)
        assert list(m.point_data) == ["lattice"] and list(m.cell_data) == ["material", "scaled_jacobian", "edge_ratio"]
        assert np.array_equal(m.point_data["lattice"], mesh.lattice)
        assert np.array_equal(m.cells[0].data, mesh.cells)
    head = (tmp_path / "m.vtu").read_bytes()[:3000]
    assert b'type="Int32" Name="connectivity"' in head


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000), dim=st.sampled_from([2, 3]), labels=st.sampled_from([2, 255, 256, 40_000]))
def test_stage_vtu_reads_as_meshio_reads_it(tmp_path, seed, dim, labels):
    # whatever narrow types the writer picks (and widens for meshio's reader), meshio and
    # dicer's reader get the same arrays, and dicer's the mesh written
    rng = np.random.default_rng(seed)
    shape = tuple(rng.integers(1, 6, dim))
    image = rng.integers(0, 3, shape).astype(np.int32)
    image.flat[0] = 1
    image[image > 0] = rng.integers(1, labels + 1, int(np.count_nonzero(image)))
    m = voxel_mesh(image)
    m.points[:, :dim] += rng.uniform(-0.2, 0.2, (m.n_points, dim))
    path = tmp_path / f"s{seed}_{dim}_{labels}.vtu"
    write_mesh(m, path)
    ref = meshio.read(path)
    back = read_mesh(path)
    assert meshes_io._same_mesh(m, back)
    assert np.array_equal(ref.points, m.points) and np.array_equal(ref.cells[0].data, m.cells)
    assert np.array_equal(ref.point_data["lattice"], m.lattice)
    assert np.array_equal(ref.cell_data["material"][0], m.material)
    assert list(ref.cell_data) == ["material", "scaled_jacobian", "edge_ratio"]
    assert np.array_equal(ref.cell_data["scaled_jacobian"][0], scaled_jacobian(m.points, m.cells).astype(np.float32))


def test_a_mesh_of_tens_of_thousands_of_materials_reads_back(tmp_path):
    """The field data names each material (about 100 bytes each): 12,000 of them put the data's
    start past the first MiB, where the reader stopped looking, so every stage file of such an
    atlas failed its own read-back check ('the VTU header is not dicer's')."""
    from dicer.resources import mesh_elements

    n = 20_000
    labels = np.zeros((n, 2, 1), np.int32)
    labels[:, 0, 0] = np.arange(1, n + 1)
    mesh = voxel_mesh(labels)
    mesh.names = [f"parcel_with_a_long_name_{i:07d}" for i in range(1, n + 1)]
    path = tmp_path / "atlas.vtu"
    write_mesh(mesh, path)  # read back and checked: it was refused
    assert path.read_bytes().find(b"<AppendedData") > 1 << 20
    back = read_mesh(path)
    assert back.names == mesh.names and back.n_cells == n
    assert np.array_equal(back.material, mesh.material)
    assert mesh_elements(path) == n


def _ball_mesh(dim=3):
    r = np.sqrt(((np.indices((12,) * dim) - 5.5) ** 2).sum(0))
    return voxel_mesh(np.select([r < 2.5, r < 5], [2, 1], 0).astype(np.uint8))


def _edited(field: str, value):
    def edit(m, mesh):
        if field in ("spacing", "origin", "grid_shape"):
            from dataclasses import replace

            return m, replace(mesh, **{field: np.asarray(value)})
        if field == "material":
            m.cell_data["material"] = [np.where(m.cell_data["material"][0] == 1, 1, value).astype(np.int64)]
        elif field in ("lattice", "node_class"):
            m.point_data[field] = value(m.point_data.get(field, np.zeros(len(m.points), np.int8)))
        elif field == "unused":  # one node more, at the origin, in no element
            m.points = np.vstack([m.points, np.zeros((1, 3))])
            m.point_data = {k: np.concatenate([v, v[:1] * 0]) for k, v in m.point_data.items()}
        else:  # the points
            m.points = value(m.points)
        return m, mesh
    return edit


@pytest.mark.parametrize("dim, edit, said", [
    (3, _edited("material", 2**32 + 2), r"element\(s\) have material 4294967298, past the largest material number"),
    (3, _edited("lattice", lambda a: a[:, :1]), r"'lattice' point data hold \d+ values for \d+ nodes of a 3D mesh"),
    (3, _edited("lattice", lambda a: a + 0.5), r"'lattice' point data hold values that are not whole numbers"),
    (3, _edited("spacing", [1.0, 1.0, 1.0, 1.0]), r"field data 'spacing' holds 4 value\(s\) \(1, 1, 1, 1\)"),
    (3, _edited("origin", [np.nan, 0.0, 0.0]), r"field data 'origin' holds 3 value\(s\) \(nan, 0, 0\) where a 3D mesh"),
    (3, _edited("spacing", [-1.0, 1.0, 1.0]), r"field data 'spacing' is -1, 1, 1 mm, outside 1e-07 to 1e\+06 mm"),
    (3, _edited("grid_shape", [4, 4, 4]), r"lattice indices reach 11, 11, 11, past the field data's grid_shape 4, 4, 4"),
    (3, _edited("grid_shape", [0, 12, 12]), r"field data 'grid_shape' is 0, 12, 12, not whole numbers of voxels"),
    (3, _edited("node_class", lambda n: n - 1), r"the 'node_class' point data are not one code 0\.\.7 per node"),
    (3, _edited("node_class", lambda n: np.c_[n, n]), r"the 'node_class' point data are not one code 0\.\.7 per node"),
    (3, _edited("unused", None), r"1 node\(s\) belong to no element \(e\.g\. node 823\), and would enter"),
    (2, _edited("points", lambda p: p + np.r_[0.0, 0.0, 0.5]), r"node\(s\) of the 2D mesh lie off its plane \(z up to 0\.5"),
])
def test_mesh_files_whose_data_no_stage_takes_are_refused(tmp_path, dim, edit, said):
    """A dicer mesh edited by another tool: material 2**32 + 2 read as 2 (exit 0), grid_shape
    [4, 4, 4] put 80 interior nodes into the X1 set, a spacing of -1 moved smoothed nodes by
    0.86 mm, quads off their plane were exported as CPS4, and 1-column lattices or 4-value
    spacings ended in tracebacks."""
    from dicer.io.meshes import to_meshio

    mesh = _ball_mesh(dim)
    m, grid = edit(to_meshio(mesh), mesh)
    meshio_vtu_with_grid(grid, tmp_path / "m.vtu", m)
    with pytest.raises(DicerError, match=r"m\.vtu: .*" + said + r".*the file is damaged or was edited"):
        read_mesh(tmp_path / "m.vtu")
    meshio_vtu_with_grid(mesh, tmp_path / "good.vtu")
    assert read_mesh(tmp_path / "good.vtu").n_cells == mesh.n_cells


def test_a_solver_deck_given_as_a_mesh_is_named_so(tmp_path):
    """An exported .inp, .msh or .exo was 'a mesh with no material cell data: make it with
    dicer mesh', a .feb 'cannot read mesh (ReadError)'."""
    from dicer.export.registry import EXPORT_SUFFIXES
    from dicer.io.meshes import _DECK_SUFFIXES

    assert set(_DECK_SUFFIXES) == set(EXPORT_SUFFIXES) - {".vtu"}
    for suffix in _DECK_SUFFIXES:
        (tmp_path / f"model{suffix}").write_text("anything")
        with pytest.raises(DicerError, match=rf"model\{suffix}: a solver deck \(what dicer export writes\) holds no "
                                             "mesh for dicer's stages"):
            read_mesh(tmp_path / f"model{suffix}")
