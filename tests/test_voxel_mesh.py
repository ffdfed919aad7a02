import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dicer.errors import DicerError
from dicer.mesh.metrics import element_volumes, scaled_jacobian
from dicer.mesh.model import HEX_CORNERS, QUAD_CORNERS
from dicer.mesh.voxel import voxel_mesh


def test_two_voxels_share_a_face():
    labels = np.zeros((2, 1, 1), np.uint8)
    labels[:, 0, 0] = [1, 2]
    mesh = voxel_mesh(labels, spacing=(0.5, 1.0, 2.0), origin=(10.0, 0.0, -1.0))
    assert mesh.n_cells == 2 and mesh.n_points == 12
    assert np.intersect1d(mesh.cells[0], mesh.cells[1]).size == 4
    assert mesh.material.tolist() == [1, 2]
    assert np.allclose(mesh.points.min(axis=0), [10.0, 0.0, -1.0])
    assert np.allclose(mesh.points.max(axis=0), [11.0, 1.0, 1.0])
    assert np.allclose(element_volumes(mesh.points, mesh.cells), 1.0)
    assert mesh.grid_shape.tolist() == [2, 1, 1]


def test_empty_and_bad_labels_are_errors():
    with pytest.raises(DicerError, match="no non-background"):
        voxel_mesh(np.zeros((3, 3, 3), np.uint8))
    with pytest.raises(DicerError, match="integer"):
        voxel_mesh(np.ones((3, 3, 3), np.float32))
    with pytest.raises(DicerError, match="dimensions"):
        voxel_mesh(np.ones((2, 2, 2, 2), np.uint8))


def _check(labels, spacing, origin):
    mesh = voxel_mesh(labels, spacing, origin)
    dim = labels.ndim
    corners = HEX_CORNERS if dim == 3 else QUAD_CORNERS
    solid = np.argwhere(labels != 0)
    # one element per non-background voxel, with that voxel's material, C order
    assert mesh.n_cells == len(solid)
    assert np.array_equal(mesh.material, labels[labels != 0])
    # each element's nodes are its voxel's corners
    vox = np.zeros((len(solid), 3), np.int64)
    vox[:, :dim] = solid
    assert np.array_equal(mesh.lattice[mesh.cells], vox[:, None, :] + corners[None, :, :])
    # nodes are shared: every lattice index occurs once, and every node is used
    assert len(np.unique(mesh.lattice, axis=0)) == mesh.n_points
    assert np.array_equal(np.unique(mesh.cells), np.arange(mesh.n_points))
    # coordinates are lattice * spacing + origin
    sp = np.ones(3)
    org = np.zeros(3)
    sp[:dim] = spacing
    org[:dim] = origin
    assert np.allclose(mesh.points, mesh.lattice * sp + org)
    assert np.allclose(scaled_jacobian(mesh.points, mesh.cells), 1.0)
    assert np.isclose(element_volumes(mesh.points, mesh.cells).sum(), len(solid) * np.prod(spacing))


@settings(max_examples=60, deadline=None)
@given(
    arrays(np.uint8, st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6)), elements=st.integers(0, 3)),
    st.tuples(*[st.floats(0.1, 3.0)] * 3),
    st.tuples(*[st.floats(-100, 100)] * 3),
)
def test_voxel_mesh_invariants_3d(labels, spacing, origin):
    if not labels.any():
        labels[0, 0, 0] = 1
    _check(labels, spacing, origin)


@settings(max_examples=60, deadline=None)
@given(
    arrays(np.int16, st.tuples(st.integers(1, 8), st.integers(1, 8)), elements=st.integers(0, 2)),
    st.tuples(*[st.floats(0.1, 3.0)] * 2),
)
def test_voxel_mesh_invariants_2d(labels, spacing):
    if not labels.any():
        labels[-1, -1] = 2
    _check(labels, spacing, (0.0, 0.0))
