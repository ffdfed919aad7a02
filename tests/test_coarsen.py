"""Graded coarsening by transition templates (merge.method=templates)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from dicer.config import preset_settings
from dicer.connectivity import fix_connectivity
from dicer.errors import DicerError
from dicer.mesh.coarsen import coarsen_labels, coarsen_mesh
from dicer.mesh.templates import BLOCK_TEMPLATES, COARSE, FINE, INVALID, TEMPLATES_2D
from dicer.mesh.merge import merge_mesh
from dicer.mesh.metrics import corner_scaled_jacobians, element_volumes
from dicer.mesh.model import LEVEL_DATA
from dicer.mesh.smooth import smooth_mesh
from dicer.mesh.topology import HEX_FACES, QUAD_EDGES
from dicer.mesh.voxel import voxel_mesh


def faces_of(mesh):
    """(F, k) node ids of every element face (quad edges in 2D), in the element's winding,
    and the element each belongs to."""
    table = HEX_FACES if mesh.dim == 3 else QUAD_EDGES
    faces = mesh.cells[:, table].reshape(-1, table.shape[1])
    owner = np.repeat(np.arange(mesh.n_cells), table.shape[0])
    return faces, owner


def _face_rows(points, faces, *columns):
    """One sorted row per face: its corner positions (rounded, sorted) and ``columns``."""
    pts = np.round(points[faces], 6)
    k = pts.shape[1]
    if len(faces) == 0:
        return np.zeros((0, 3 * k + len(columns)))
    pts = np.sort(pts.view([("", pts.dtype)] * pts.shape[2]).reshape(-1, k), axis=1)
    rows = np.concatenate([pts.view(float).reshape(len(faces), -1)] + [np.asarray(c, float)[:, None] for c in columns],
                          axis=1)
    return rows[np.lexsort(rows.T[::-1])]


def face_census(mesh):
    """Boundary faces (corner positions, material) and interface faces (corner positions,
    both materials) as sorted arrays, after checking that every face is used once or twice,
    twice in opposite orientation."""
    faces, owner = faces_of(mesh)
    key = np.sort(faces, axis=1)
    _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    assert count.max() <= 2, "a face is shared by three or more elements"
    once = count[inverse] == 1
    boundary = _face_rows(mesh.points, faces[once], mesh.material[owner[once]])
    # faces used twice: opposite windings, and interfaces recorded with both materials
    twice = np.flatnonzero(count == 2)
    order = np.argsort(inverse, kind="stable")
    starts = np.searchsorted(inverse[order], twice)
    a, b = order[starts], order[starts + 1]
    if mesh.dim == 3:
        # the same cyclic order read backwards: face b is a rotation of face a reversed
        fa, fb = faces[a], faces[b][:, ::-1]
        same = np.zeros(a.size, bool)
        for shift in range(4):
            same |= np.all(fa == np.roll(fb, shift, axis=1), axis=1)
        assert same.all(), "an interior face is seen in the same orientation from both sides"
    else:
        assert np.all(faces[a][:, 0] == faces[b][:, 1]), "an interior edge is seen in the same direction from both sides"
    ma, mb = mesh.material[owner[a]], mesh.material[owner[b]]
    d = ma != mb
    interface = _face_rows(mesh.points, faces[a[d]], np.minimum(ma, mb)[d], np.maximum(ma, mb)[d])
    return boundary, interface


def same_census(one, other):
    return all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(one, other))


def check_graded(voxel, graded):
    """The invariants of a graded mesh against the voxel mesh it came from."""
    per = 8 if voxel.dim == 3 else 4
    assert graded.cells.shape[1] == per
    assert corner_scaled_jacobians(graded.points, graded.cells).min() > 0.2
    vol_v = np.bincount(voxel.material, weights=element_volumes(voxel.points, voxel.cells))
    vol_g = np.bincount(graded.material, weights=element_volumes(graded.points, graded.cells),
                        minlength=vol_v.size)
    np.testing.assert_allclose(vol_g, vol_v, rtol=0, atol=1e-9 * max(1.0, vol_v.sum()))
    assert same_census(face_census(graded), face_census(voxel))
    # nodes of coarse elements are never on a boundary or interface
    level = graded.cell_data[LEVEL_DATA]
    assert level.shape == (graded.n_cells,)
    faces, owner = faces_of(graded)
    on_boundary = np.zeros(graded.n_points, bool)
    key = np.sort(faces, axis=1)
    _, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    single = count[inverse.ravel()] == 1
    on_boundary[faces[single].ravel()] = True
    assert not on_boundary[graded.cells[level > 0]].any()


def _jacobians_and_volume(cells, scale=(1.0, 1.0, 1.0)):
    x = np.asarray(cells, float) * np.asarray(scale)[: np.asarray(cells).shape[-1]]
    dim = x.shape[-1]
    pts = np.zeros((x.shape[0] * x.shape[1], 3))
    pts[:, :dim] = x.reshape(-1, dim)
    conn = np.arange(pts.shape[0]).reshape(x.shape[0], x.shape[1])
    return corner_scaled_jacobians(pts, conn).min(), element_volumes(pts, conn).sum()


def test_template_tables_cover_every_corner_pattern():
    pattern, table = TEMPLATES_2D
    assert pattern.shape == (16,) and pattern[0] == COARSE and pattern[-1] == FINE
    assert not np.any(pattern == INVALID)  # 2D: no cell is ever refined for its pattern alone
    for mask, cells in table.items():
        sj, volume = _jacobians_and_volume(cells)
        assert sj >= 0.29, mask
        assert volume == pytest.approx(9.0, abs=1e-9)
    # 3D one-axis blocks (2 x 2 cells of 3 x 1 x 1 cells of the step below): every pattern
    # but two marks on a diagonal has a template, good in every cell shape the steps give
    # (the step below's cells are 1 x 1 x 1, 3 x 1 x 1 or 3 x 3 x 1)
    pattern, table = BLOCK_TEMPLATES
    assert pattern.shape == (16,) and pattern[0] == COARSE and pattern[-1] == FINE
    assert sorted(np.flatnonzero(pattern == INVALID)) == [5, 10]
    assert sorted(table) == [m for m in range(16) if m not in (5, 10)]
    for mask, cells in table.items():
        for scale in ((1, 1, 1), (1, 3, 1), (1, 1, 3), (1, 3, 3)):
            sj, volume = _jacobians_and_volume(cells, scale)
            assert sj >= 0.22, (mask, scale)
            assert volume == pytest.approx(12.0 * scale[1] * scale[2], abs=1e-9)


def _face_quads(cells, axis, value):
    """The template faces lying on the box face ``axis = value``, as a set of frozensets of
    rounded points (the two other coordinates, in increasing axis order)."""
    other = [d for d in range(3) if d != axis]
    out = set()
    for hexa in np.asarray(cells, float):
        for face in HEX_FACES:
            pts = hexa[face]
            if np.all(np.abs(pts[:, axis] - value) < 1e-9):
                out.add(frozenset(tuple(np.round(p[other], 9)) for p in pts))
    return out


def test_block_templates_put_one_pattern_on_each_kind_of_face():
    # a block face's quads depend only on which of its two corners along the refined axis
    # are marked, whatever template and orientation produced them: so neighbours always
    # match; the ends across the refined axis are always the four cells' faces
    _, table = BLOCK_TEMPLATES
    corners = np.array([[0, 0], [2, 0], [2, 2], [0, 2]])
    seen = {}
    for mask, cells in table.items():
        marked = {tuple(c) for i, c in enumerate(corners) if mask >> i & 1}
        for end in (0, 3):
            assert len(_face_quads(cells, 0, end)) == 4
        for axis, value in itertools.product((1, 2), (0, 2)):
            edges = [c for c in corners if c[axis - 1] == value]
            key = (axis, frozenset(tuple(c) for c in edges if tuple(c) in marked))
            quads = _face_quads(cells, axis, value)
            seen.setdefault(key, quads)
            assert seen[key] == quads, (mask, axis, value)
            assert len(quads) == {0: 2, 1: 5, 2: 6}[len(key[1])]
    # per axis across: no mark, and on either face one of its two corners (2 ways) or both
    assert len(seen) == 14


def ball_labels(shape, radii, centre=None):
    grid = np.indices(shape).astype(float)
    centre = np.array(shape, float) / 2 if centre is None else np.asarray(centre, float)
    r = np.sqrt(sum((g + 0.5 - c) ** 2 for g, c in zip(grid, centre)))
    labels = np.zeros(shape, np.int32)
    for k, radius in enumerate(radii, start=1):
        labels[r < radius] = k
    return labels


def test_2d_disc_coarsens_and_keeps_every_boundary():
    labels = ball_labels((120, 120), (55, 25))
    voxel = voxel_mesh(labels)
    graded, report = coarsen_mesh(voxel, levels=2, min_distance=1, keep_fine=())
    check_graded(voxel, graded)
    assert voxel.n_cells == 9500
    assert report["element_ratio"] >= 2.5
    assert set(report["elements_by_level"]) == {"0", "1", "2"}
    for k in ("1", "2"):
        assert report["volume"][k]["change_percent"] == 0.0
    # more levels never give more elements
    one, _ = coarsen_mesh(voxel, levels=1, min_distance=1, keep_fine=())
    assert graded.n_cells <= one.n_cells < voxel.n_cells


def test_levels_zero_and_keep_fine_leave_voxels():
    labels = ball_labels((60, 60), (28, 12))
    voxel = voxel_mesh(labels)
    same, _ = coarsen_mesh(voxel, levels=0, min_distance=1, keep_fine=())
    assert same.n_cells == voxel.n_cells
    np.testing.assert_array_equal(same.points, voxel.points)
    kept, report = coarsen_mesh(voxel, levels=2, keep_fine=[1, 2], min_distance=1)
    assert kept.n_cells == voxel.n_cells
    part, report = coarsen_mesh(voxel, levels=2, keep_fine=[2], min_distance=1)
    assert report["elements_by_material"]["2"]["after"] == report["elements_by_material"]["2"]["before"]
    assert report["elements_by_material"]["1"]["after"] < report["elements_by_material"]["1"]["before"]


def test_keep_fine_naming_no_material_of_the_mesh_is_warned_of(caplog):
    """keep_fine: [3] written for bone's 2 kept nothing fine and said nothing."""
    labels = ball_labels((60, 60), (28, 12))
    voxel = voxel_mesh(labels)
    voxel.names = ["soft_tissue", "bone"]
    coarsened, report = coarsen_mesh(voxel, levels=2, keep_fine=[3, 2], min_distance=1)
    assert report["elements_by_material"]["2"]["after"] == report["elements_by_material"]["2"]["before"]
    assert caplog.text.count("keep_fine") == 1
    assert ("merge.templates.keep_fine names label(s) 3 that no material of the mesh has (its materials: "
            "1 soft_tissue, 2 bone), so they keep nothing at voxel size") in caplog.text
    caplog.clear()
    coarsen_mesh(voxel, levels=2, keep_fine=[1, 2], min_distance=1)
    merge_mesh(voxel, {"method": "templates", "templates": {"keep_fine": [2]}})
    assert "keep_fine" not in caplog.text
    merge_mesh(voxel, {"method": "templates", "templates": {"keep_fine": [7, 9]}})
    assert "keep_fine names label(s) 7, 9 that no material" in caplog.text


def test_min_distance_keeps_thin_parts_fine():
    labels = np.zeros((60, 60), np.int32)
    labels[5:55, 5:55] = 1
    labels[5:55, 28:32] = 2  # a 4-voxel band
    voxel = voxel_mesh(labels)
    graded, report = coarsen_mesh(voxel, levels=1, min_distance=1, keep_fine=())
    assert report["elements_by_material"]["2"]["after"] == 200
    far, report_far = coarsen_mesh(voxel, levels=1, min_distance=4, keep_fine=())
    assert far.n_cells > graded.n_cells
    check_graded(voxel, far)


def test_graded_2d_mesh_smooths_like_the_voxel_mesh():
    labels = ball_labels((90, 90), (40, 18))
    voxel = voxel_mesh(labels)
    graded, _ = coarsen_mesh(voxel, levels=2, min_distance=1, keep_fine=())
    # the per-class smoothing, without the pillow layer over it (the preset explicit-dynamics)
    without_the_layer = preset_settings("explicit-dynamics")["smooth"]
    smooth_v, rep_v = smooth_mesh(voxel, without_the_layer)
    smooth_g, rep_g = smooth_mesh(graded, without_the_layer)
    assert rep_g["inverted_elements"] == 0
    assert rep_g["min_scaled_jacobian"] >= 0.2
    assert {k: v for k, v in rep_g["node_classes"].items() if k != "interior"} == \
        {k: v for k, v in rep_v["node_classes"].items() if k != "interior"}
    # boundary nodes land where they land on the voxel mesh
    lat_v = {tuple(p): i for i, p in enumerate(voxel.lattice)}
    boundary = np.flatnonzero(np.asarray(smooth_g.point_data["node_class"]) > 0)
    rows = np.array([lat_v[tuple(p)] for p in graded.lattice[boundary]])
    assert np.abs(smooth_g.points[boundary] - smooth_v.points[rows]).max() < 1e-4


def test_templates_refuse_a_merged_mesh():
    labels = ball_labels((30, 30, 30), (12,))
    merged, _ = merge_mesh(voxel_mesh(labels), {"passes": [1, 0, 0]})
    with pytest.raises(DicerError, match="voxel mesh"):
        coarsen_mesh(merged, levels=1, min_distance=1, keep_fine=())
    # one voxel's corners turned about its axis: still a box, no longer in VTK order
    turned = voxel_mesh(labels)
    turned.cells[7] = turned.cells[7][[1, 2, 3, 0, 5, 6, 7, 4]]
    with pytest.raises(DicerError, match="voxel mesh"):
        coarsen_mesh(turned, levels=1, min_distance=1, keep_fine=())
    with pytest.raises(DicerError, match="min_distance"):
        coarsen_mesh(voxel_mesh(labels), levels=1, min_distance=0, keep_fine=())


def test_merge_stage_grades_3d_meshes():
    voxel = voxel_mesh(ball_labels((64, 64, 64), (30, 14)))
    graded, report = merge_mesh(voxel, {"method": "templates"})
    check_graded(voxel, graded)
    assert report["element_ratio"] > 1.4  # 1.44: at this size the transitions are most of the ball
    smoothed, sreport = smooth_mesh(graded, {})
    assert sreport["inverted_elements"] == 0


def test_merge_stage_dispatches_to_templates():
    labels = ball_labels((60, 60), (28,))
    voxel = voxel_mesh(labels)
    graded, report = merge_mesh(voxel, {"method": "templates", "templates": {"levels": 1}})
    assert report["method"] == "templates" and report["levels"] == 1
    assert graded.n_cells < voxel.n_cells
    with pytest.raises(DicerError, match="merge.templates.level"):
        merge_mesh(voxel, {"method": "templates", "templates": {"level": 1}})


def test_templates_on_long_voxels_are_reported_and_warned(tmp_path, caplog):
    # the templates' bound holds on the lattice: on cubic voxels it holds in mm too, on
    # voxels six times longer along z their slopes flatten
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    labels = ball_labels((30, 30, 30), (13,))
    _, cubic = merge_mesh(voxel_mesh(labels), {"method": "templates"})
    assert cubic["min_scaled_jacobian"] >= 0.229
    path = tmp_path / "long.vtu"
    write_mesh(voxel_mesh(labels, spacing=(0.5, 0.5, 3.0)), path)
    caplog.set_level("WARNING", logger="dicer")
    assert main(["merge", str(path), "-o", str(tmp_path / "graded.vtu"), "--set", "merge.method=templates",
                 "--report", str(tmp_path / "merge.json")]) == 0
    import json

    report = json.loads((tmp_path / "merge.json").read_text())
    assert report["min_scaled_jacobian"] < 0.2
    said = [r.getMessage() for r in caplog.records if "transition templates" in r.getMessage()]
    assert len(said) == 1 and "0.5 x 0.5 x 3 mm" in said[0] and f"{report['min_scaled_jacobian']:.3f}" in said[0]
    caplog.clear()
    write_mesh(voxel_mesh(labels), path)
    assert main(["merge", str(path), "-o", str(tmp_path / "graded.vtu"), "--set", "merge.method=templates"]) == 0
    assert not [r for r in caplog.records if "transition templates" in r.getMessage()]


def test_templates_that_make_no_fewer_elements_are_warned_of(tmp_path, caplog):
    # an 8^3 block: 48 cubes became transitions (min scaled Jacobian 1.0 -> 0.30), 512 -> 512
    from dicer.cli import main
    from dicer.io.meshes import write_mesh

    path = tmp_path / "block.vtu"
    caplog.set_level("WARNING", logger="dicer")
    for size, warned in ((8, True), (30, False)):
        caplog.clear()
        write_mesh(voxel_mesh(np.ones((size,) * 3, np.uint8)), path)
        assert main(["merge", str(path), "-o", str(tmp_path / "graded.vtu"), "--set", "merge.method=templates",
                     "--report", str(tmp_path / "merge.json")]) == 0
        import json

        report = json.loads((tmp_path / "merge.json").read_text())
        said = [r.getMessage() for r in caplog.records if "made no fewer elements" in r.getMessage()]
        assert len(said) == int(warned)
        if warned:
            assert report["elements_after"] == report["elements_before"] == 512
            assert said[0].startswith("merge: the transition templates made no fewer elements (512 -> 512; min "
                                      f"scaled Jacobian {report['min_scaled_jacobian']:.3f})")
        else:
            assert report["elements_after"] < 0.7 * report["elements_before"]  # 27,000 -> 17,880
    # the 30^3 block again, kept fine by the settings: said by the setting that kept it
    caplog.set_level("INFO", logger="dicer")
    for sets, said_part in ((["merge.templates.keep_fine=[1]"], "merge.templates.keep_fine lists every material"),
                            (["merge.templates.min_distance=20"], "merge.templates.min_distance=20 voxels"),
                            (["merge.templates.levels=0"], "merge.templates.levels is 0: the voxel mesh is kept")):
        caplog.clear()
        assert main(["merge", str(path), "-o", str(tmp_path / "graded.vtu"), "--set", "merge.method=templates",
                     *[a for s in sets for a in ("--set", s)]]) == 0
        said = [r for r in caplog.records if said_part in r.getMessage()]
        assert len(said) == 1 and said[0].levelname == ("INFO" if "levels is 0" in said_part else "WARNING")
    # a whole number written as 2.0 is 2
    assert main(["merge", str(path), "-o", str(tmp_path / "graded2.vtu"), "--set", "merge.method=templates",
                 "--set", "merge.templates.levels=2.0"]) == 0
    assert main(["merge", str(path), "-o", str(tmp_path / "graded_int.vtu"), "--set", "merge.method=templates",
                 "--set", "merge.templates.levels=2"]) == 0
    assert (tmp_path / "graded2.vtu").read_bytes() == (tmp_path / "graded_int.vtu").read_bytes()
    with pytest.raises(DicerError, match="merge.templates.levels=2.5"):
        coarsen_mesh(voxel_mesh(np.ones((4, 4, 4), np.uint8)), levels=2.5, min_distance=1, keep_fine=[])


@st.composite
def label_volumes(draw, dim):
    shape = tuple(draw(st.integers(12, 40 if dim == 2 else 16)) for _ in range(dim))
    classes = draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    field = ndimage.gaussian_filter(rng.random(shape), draw(st.floats(2.0, 6.0)))
    edges = np.quantile(field, np.linspace(0, 1, classes + 2)[1:-1])
    labels = np.digitize(field, edges).astype(np.int32)
    if draw(st.booleans()):
        labels[labels == 0] = 1  # a volume filling the whole image, touching every plane
    fixed, _ = fix_connectivity(labels)
    return fixed


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(labels=label_volumes(2), levels=st.integers(1, 3), distance=st.integers(1, 3))
def test_random_2d_volumes_keep_every_invariant(labels, levels, distance):
    if not labels.any():
        return
    voxel = voxel_mesh(labels)
    graded, _ = coarsen_mesh(voxel, levels=levels, min_distance=distance, keep_fine=())
    check_graded(voxel, graded)
    smoothed, report = smooth_mesh(graded, {})
    assert report["inverted_elements"] == 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(labels=label_volumes(3), levels=st.integers(1, 2))
def test_random_3d_volumes_keep_every_invariant(labels, levels):
    if not labels.any():
        return
    voxel = voxel_mesh(labels)
    graded, _ = coarsen_mesh(voxel, levels=levels, min_distance=1, keep_fine=())
    check_graded(voxel, graded)
    smoothed, report = smooth_mesh(graded, {})  # never raises: the templates keep their floor
    assert report["inverted_elements"] == 0 and report["min_scaled_jacobian"] >= 0.2


def _overlapping_balls(n, seed):
    rng = np.random.default_rng(seed)
    grid = np.indices((n, n, n)).astype(float)
    labels = np.zeros((n, n, n), np.int32)
    for _ in range(rng.integers(2, 6)):
        centre, radius = rng.uniform(0, n, 3), rng.uniform(n / 6, n / 2)
        labels[((grid - centre[:, None, None, None]) ** 2).sum(axis=0) < radius ** 2] = rng.integers(1, 4)
    return labels


@pytest.mark.parametrize("seed", [1, 2, 5, 6])
def test_3d_volumes_large_enough_for_every_step(seed):
    # 56 voxels a side, seeds whose x, y and z steps all hold coarse cells next to the
    # templates and refined cells of the steps below
    labels, _ = fix_connectivity(_overlapping_balls(56, seed))
    steps = coarsen_labels(labels, levels=2, min_distance=1, keep_fine=())["steps"]
    coarse = {(s["level"], s["frame"][0]): int((s["cell_plain"] & s["open"]).sum()) for s in steps}
    assert min(coarse.get((1, axis), 0) for axis in range(3)) > 0, coarse
    voxel = voxel_mesh(labels)
    graded, report = coarsen_mesh(voxel, levels=2, min_distance=1, keep_fine=())
    check_graded(voxel, graded)
    assert report["elements_after"] < 0.9 * report["elements_before"]
    _, smoothed = smooth_mesh(graded, {})
    assert smoothed["inverted_elements"] == 0 and smoothed["min_scaled_jacobian"] >= 0.2


def test_fine_template_is_the_unit_grid():
    for dim, (pattern, table) in ((2, TEMPLATES_2D),):
        fine = table[len(pattern) - 1]
        expected = sorted(tuple(map(tuple, np.asarray(c) + (
            np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
            if dim == 3 else np.array([[0, 0], [1, 0], [1, 1], [0, 1]]))))
            for c in itertools.product(range(3), repeat=dim))
        assert sorted(tuple(map(tuple, c.astype(int))) for c in fine) == expected


def test_node_lookup_by_table_and_by_search_agree():
    """Template corners find their nodes in a dense table, or by a sorted search when the
    image's grid is far larger than the mesh: both give the same node, and -1 for none."""
    from dicer.mesh.coarsen import _node_lookup

    rng = np.random.default_rng(3)
    n_grid = 1000
    key = rng.permutation(n_grid)[:300]  # nodes on 300 of 1000 lattice points, any order
    wanted = rng.integers(0, n_grid, 5000)
    dense = _node_lookup(key, n_grid)(wanted)
    search = _node_lookup(key, 10**12)(wanted)  # far larger than the mesh: the search
    expect = np.full(n_grid, -1)
    expect[key] = np.arange(key.size)
    assert np.array_equal(dense, expect[wanted]) and np.array_equal(search, expect[wanted])
    assert np.count_nonzero(dense < 0) > 1000


@settings(max_examples=200, deadline=None)
@given(dim=st.integers(1, 3), radius=st.integers(1, 5), seed=st.integers(0, 2**31 - 1),
       dtype=st.sampled_from([np.uint8, np.uint16, np.int32, np.int64]))
def test_window_min_max_is_ndimage_min_max_filter(dim, radius, seed, dtype):
    """The neighbourhood test's sweeps give ndimage's cube min/max filters (mode constant,
    cval 0) exactly, at every size, also windows wider than the image and signed labels."""
    from dicer.mesh.coarsen import _window_min_max

    rng = np.random.default_rng(seed)
    shape = tuple(int(s) for s in rng.integers(1, 10, dim))
    labels = rng.integers(-2 if np.issubdtype(dtype, np.signedinteger) else 0, 4, shape).astype(dtype)
    lo, hi = _window_min_max(labels, radius)
    size = 2 * radius + 1
    expect_lo = ndimage.minimum_filter(labels, size=size, mode="constant", cval=0)
    expect_hi = ndimage.maximum_filter(labels, size=size, mode="constant", cval=0)
    assert lo.dtype == labels.dtype and np.array_equal(lo, expect_lo) and np.array_equal(hi, expect_hi)


def test_templates_refuse_elements_outside_the_image():
    """An element whose first corner lies on a far plane of the point grid (its corners'
    keys still one voxel apart) is outside the image; with a material <= 0 as well, the
    lattice is named first."""
    labels = np.zeros((8, 6, 5), np.int32)
    labels[:-3] = 1
    voxel = voxel_mesh(labels)
    grid = tuple(int(s) + 1 for s in voxel.grid_shape)
    key = np.ravel_multi_index(tuple(voxel.lattice.T), grid) + 1  # every node one step along z
    voxel.lattice[:] = np.stack(np.unravel_index(key, grid), axis=1)
    with pytest.raises(DicerError, match="element lattice indices lie outside"):
        coarsen_mesh(voxel, levels=1, min_distance=1, keep_fine=())
    voxel.material[0] = 0
    with pytest.raises(DicerError, match="element lattice indices lie outside"):
        coarsen_mesh(voxel, levels=1, min_distance=1, keep_fine=())


def test_templates_under_the_smoothing_floor_are_said_as_the_templates_shapes(tmp_path, caplog):
    """A two-material ball on 1 x 1 x 1.5 mm voxels, graded: transition templates reach 0.286
    (under the floor 0.3) on the elongated lattice, and the smooth stage said to set
    merge.min_scaled_jacobian, plane merging's floor, which graded coarsening does not read."""
    from dicer.cli import main
    from dicer.image import Volume
    from dicer.io.images import write_image

    g = np.indices((40, 40, 30)).astype(float)
    c = np.array([19.5, 19.5, 14.5])[:, None, None, None]
    r = np.sqrt((((g - c) * np.array([1.0, 1.0, 1.5])[:, None, None, None]) ** 2).sum(0))
    write_image(Volume((r < 17).astype(np.uint8) + (r < 8).astype(np.uint8), (1.0, 1.0, 1.5)),
                tmp_path / "ball.nii.gz")
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert main(["run", "--labels", str(tmp_path / "ball.nii.gz"), "-o", str(tmp_path / "out"), "-q",
                     "--set", "merge.method=templates"]) == 0
    said = [r.getMessage() for r in caplog.records if "smallest scaled Jacobian" in r.getMessage()]
    assert len(said) == 1 and "transition templates of graded coarsening" in said[0]
    assert "merge.min_scaled_jacobian" not in said[0]
