"""dicer.arrays: numpy's nonzero and argwhere, by the flat indices."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

from dicer.arrays import all_per_row, any_per_row, argwhere, nonzero, norm


@settings(max_examples=200, deadline=None)
@given(arrays(st.sampled_from([np.bool_, np.int8, np.float64]), array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=6)),
       st.booleans())
def test_the_same_arrays_as_numpys(mask, transposed):
    if transposed:
        mask = mask.T  # a view out of C order: its logical order counts
    assert np.array_equal(argwhere(mask), np.argwhere(mask)) and argwhere(mask).dtype == np.argwhere(mask).dtype
    if mask.ndim:
        ours, theirs = nonzero(mask), np.nonzero(mask)
        assert len(ours) == len(theirs)
        for a, b in zip(ours, theirs):
            assert a.dtype == b.dtype and np.array_equal(a, b)


def test_a_large_sparse_mask():
    mask = np.zeros((60, 50, 40), bool)
    mask.ravel()[np.random.default_rng(0).choice(mask.size, 300, replace=False)] = True
    for a, b in zip(nonzero(mask), np.nonzero(mask)):
        assert np.array_equal(a, b)
    assert argwhere(mask).shape == (300, 3)


@settings(max_examples=300, deadline=None)
@given(arrays(st.sampled_from([np.float32, np.float64]), array_shapes(min_dims=1, max_dims=3, min_side=1, max_side=9),
              elements=st.floats(allow_nan=True, allow_infinity=True, width=32)),
       st.integers(-3, 2), st.booleans(), st.booleans())
def test_norm_gives_numpys_bytes(v, axis, keepdims, transposed):
    if transposed:
        v = v.T
    axis = axis % v.ndim
    with np.errstate(over="ignore", invalid="ignore"):  # squares of huge values overflow, alike in both
        ours, theirs = norm(v, axis=axis, keepdims=keepdims), np.linalg.norm(v, axis=axis, keepdims=keepdims)
    assert ours.dtype == theirs.dtype and ours.shape == theirs.shape
    assert np.array_equal(ours, theirs, equal_nan=True)


def test_norm_of_vectors_of_mixed_magnitudes_on_a_large_array():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(5000, 4, 3)) * 10.0 ** rng.uniform(-200, 200, size=(5000, 4, 1))
    with np.errstate(over="ignore"):  # squares above 1e308 are inf in both
        for axis in (0, 1, 2, -1):
            assert np.array_equal(norm(v, axis=axis), np.linalg.norm(v, axis=axis))
    assert np.array_equal(norm(np.arange(12).reshape(4, 3), axis=1), np.linalg.norm(np.arange(12).reshape(4, 3), axis=1))


@settings(max_examples=200, deadline=None)
@given(arrays(st.sampled_from([np.bool_, np.int8, np.float64]), st.tuples(st.integers(0, 40), st.integers(1, 9))),
       st.booleans())
def test_per_row_any_and_all_are_numpys(mask, transposed):
    if transposed and mask.shape[0] == mask.shape[1]:
        mask = mask.T  # a view out of C order
    assert np.array_equal(any_per_row(mask), mask.any(axis=1)) and any_per_row(mask).dtype == bool
    assert np.array_equal(all_per_row(mask), mask.all(axis=1)) and all_per_row(mask).dtype == bool
