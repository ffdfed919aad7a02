"""The element tables of dicer.mesh.topology agree with one another and with the unit cube."""

import numpy as np

from dicer.mesh import topology as t


def edge_set(table):
    return {frozenset(map(int, e)) for e in table}


def test_edges_join_corners_one_lattice_step_apart_along_their_axis():
    for corners, edges, axes in ((t.HEX_CORNERS, t.HEX_EDGES, t.HEX_EDGE_AXES),
                                 (t.QUAD_CORNERS, t.QUAD_EDGES, t.QUAD_EDGE_AXES)):
        step = corners[edges[:, 1]] - corners[edges[:, 0]]
        assert np.array_equal(np.abs(step), np.eye(3, dtype=int)[axes])
        assert len(edge_set(edges)) == len(edges)
    # every pair of corners one step apart is an edge
    d = np.abs(t.HEX_CORNERS[:, None] - t.HEX_CORNERS[None]).sum(axis=2)
    assert edge_set(np.argwhere(np.triu(d == 1))) == edge_set(t.HEX_EDGES)


def test_hex_faces_run_along_hex_edges_and_each_edge_bounds_two_faces():
    uses = {e: 0 for e in edge_set(t.HEX_EDGES)}
    for f, face in enumerate(t.HEX_FACES):
        rim = [frozenset((int(face[j]), int(face[(j + 1) % 4]))) for j in range(4)]
        assert set(rim) <= set(uses)
        assert [frozenset(map(int, t.HEX_EDGES[e])) for e in t.HEX_FACE_EDGES[f]] == rim
        for e in rim:
            uses[e] += 1
    assert set(uses.values()) == {2}


def test_hex_faces_point_outward_on_the_unit_cube():
    x = t.HEX_CORNERS.astype(float)
    centre = x.mean(axis=0)
    for face, (axis, side) in zip(t.HEX_FACES, t.HEX_FACE_PLANES):
        p = x[face]
        normal = np.cross(p[2] - p[0], p[3] - p[1])
        assert np.dot(normal, p.mean(axis=0) - centre) > 0
        assert np.all(p[:, axis] == side)  # the face lies in its plane
        expected = np.zeros(3)
        expected[axis] = 1 if side else -1
        assert np.allclose(normal / np.linalg.norm(normal), expected)


def test_quad_sides_run_counter_clockwise_and_lie_in_their_planes():
    x = t.QUAD_CORNERS.astype(float)
    centre = x.mean(axis=0)
    for edge, (axis, side) in zip(t.QUAD_EDGES, t.QUAD_SIDE_PLANES):
        a, b = x[edge]
        outward = np.array([b[1] - a[1], a[0] - b[0], 0.0])  # the edge turned clockwise
        assert np.dot(outward, (a + b) / 2 - centre) > 0
        assert a[axis] == b[axis] == side
    assert np.array_equal(t.QUAD_EDGES[t.QUAD_SIDE_EDGES[:, 0]], t.QUAD_EDGES)


def test_quadratic_face_tables_follow_their_edges():
    for f in range(6):
        mids = t.HEX20_FACES[f, 4:] - 8
        corners = t.HEX20_FACES[f, :4]
        for j in range(4):
            assert set(t.HEX_EDGES[mids[j]]) == {corners[j], corners[(j + 1) % 4]}
    assert np.array_equal(t.QUAD8_SIDES[:, :2], t.QUAD_EDGES)
    assert np.array_equal(t.QUAD8_SIDES[:, 2], 4 + np.arange(4))
    assert sorted(t.HEX20_EXODUS) == list(range(20))


def test_corner_tables_agree_with_the_edges_and_axes():
    for neighbours, edges in ((t.HEX_CORNER_NEIGHBOURS, t.HEX_EDGES), (t.QUAD_CORNER_NEIGHBOURS, t.QUAD_EDGES)):
        pairs = {frozenset((c, int(n))) for c, row in enumerate(neighbours) for n in row}
        assert pairs == edge_set(edges)
    x = t.HEX_CORNERS.astype(float)
    for c, row in enumerate(t.HEX_CORNER_NEIGHBOURS):  # right-handed: positive triple product
        e = x[row] - x[c]
        assert np.linalg.det(e) > 0
    for corners, table in ((t.HEX_CORNERS, t.HEX_AXIS_CORNERS), (t.QUAD_CORNERS, t.QUAD_AXIS_CORNERS)):
        for axis, (low, high) in table.items():
            step = corners[high] - corners[low]
            assert np.array_equal(step, np.tile(np.eye(3, dtype=int)[axis], (len(low), 1)))


def test_corner_permutations_turn_reflected_elements_right_side_out():
    x = t.HEX_CORNERS.astype(float)
    for flip, perm in ((np.diag([1.0, 1.0, -1.0]), t.HEX_MIRROR), (np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, 1]]),
                                                                  t.HEX_REVERSED)):
        y = (x @ flip)[perm]
        for c, row in enumerate(t.HEX_CORNER_NEIGHBOURS):
            assert np.linalg.det(y[row] - y[c]) > 0
    # the mirrored faces: face S(k) of the mirrored element holds the corners of face S(HEX_FACE_MIRROR[k])
    for f in range(6):
        g = t.HEX_FACE_MIRROR[f + 1] - 1
        assert set(t.HEX_MIRROR[t.HEX_FACES[g]]) == set(t.HEX_FACES[f])
    assert np.array_equal(t.HEX20_MIRROR[:8], t.HEX_MIRROR)
    q = t.QUAD_CORNERS[:, :2].astype(float)[:, ::-1][t.QUAD_REVERSED]  # reflected through x = y
    for c, (i, j) in enumerate(t.QUAD_CORNER_NEIGHBOURS):
        assert np.linalg.det(np.stack([q[i] - q[c], q[j] - q[c]])) > 0


def test_meshio_names():
    assert t.MESHIO_TYPES == {(3, 1): "hexahedron", (3, 2): "hexahedron20", (2, 1): "quad", (2, 2): "quad8"}
