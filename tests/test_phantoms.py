"""Synthetic phantoms: determinism, geometry, and the label volumes they stand for."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.images import read_image, write_image
from dicer.phantoms import (
    DEFAULT_SIZE,
    PHANTOMS,
    SPHERE_OFFSET,
    block_labels,
    head_labels,
    long_bone_labels,
    make_phantom,
    phantom_labels,
    shell_labels,
    sphere_labels,
)

FULL = np.ones((3, 3, 3), bool)  # 26-connectivity
SMALL = {"head": 40, "long_bone": 40, "shell": 24, "sphere": 16, "block": 16}


def _threshold(hu):
    # the default manual thresholds of the configuration
    return (hu >= -140).astype(np.uint8) + (hu >= 226)


def test_registry_lists_every_phantom():
    assert set(PHANTOMS) == {"head", "long_bone", "shell", "sphere", "block"}
    assert set(DEFAULT_SIZE) == set(PHANTOMS)


@pytest.mark.parametrize("name", sorted(PHANTOMS))
def test_deterministic_for_a_seed(name):
    a = make_phantom(name, size=SMALL[name], seed=3)
    b = make_phantom(name, size=SMALL[name], seed=3)
    c = make_phantom(name, size=SMALL[name], seed=4)
    assert a.array.dtype == np.float32
    assert a.array.tobytes() == b.array.tobytes() and a.spacing == b.spacing
    assert not np.array_equal(a.array, c.array)
    np.testing.assert_array_equal(a.array, np.rint(a.array))  # whole HU, like a scanner


@pytest.mark.parametrize("name", sorted(PHANTOMS))
def test_noise_free_thresholds_recover_labels(name):
    image = make_phantom(name, size=SMALL[name], noise=0)
    labels = phantom_labels(name, size=SMALL[name])
    assert labels.array.dtype == np.uint8 and labels.array.shape == image.array.shape
    assert labels.spacing == image.spacing
    wrong = _threshold(image.array) != labels.array
    if name == "head":
        # only the headrest differs: bright enough to pass the bone threshold, background in the labels
        assert np.all(image.array[wrong] == 300) and np.all(labels.array[wrong] == 0)
        assert wrong.sum() > 0
    else:
        assert wrong.sum() == 0


@pytest.mark.parametrize("name", sorted(PHANTOMS))
def test_noise_level(name):
    clean = make_phantom(name, size=SMALL[name], noise=0).array
    noisy = make_phantom(name, size=SMALL[name], noise=25, seed=1).array
    assert np.std(noisy - clean) == pytest.approx(25, rel=0.05)


def test_default_noise_keeps_thresholds_clean(head_small):
    image, labels = head_small
    headrest = make_phantom("head", size=48, noise=0).array == 300
    wrong = (_threshold(image.array) != labels.array) & ~headrest
    assert wrong.sum() <= 5  # thresholds sit > 5 sigma from every tissue at 30 HU noise


def test_head_label_fractions_resemble_a_head_ct():
    labels = head_labels().array
    fractions = np.bincount(labels.ravel(), minlength=3) / labels.size
    assert labels.shape[1] == 96 and max(labels.shape) == 96
    assert 0.15 < fractions[1] < 0.40  # the real cranium CT: about 0.33 - 0.07
    assert 0.04 < fractions[2] < 0.10  # about 0.067
    assert fractions.sum() == pytest.approx(1.0)


def test_head_skull_has_thin_regions_and_is_closed():
    labels = head_labels().array
    bone = labels == 2
    nx, ny, nz = labels.shape
    # bone runs along the x ray through the centre: the temporal bone is 2-3 voxels thick
    row = bone[:, ny // 2, nz // 2].astype(np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], row, [0]])))
    runs = edges[1::2] - edges[::2]
    assert len(runs) == 2 and np.all((runs >= 2) & (runs <= 3))
    # and thicker elsewhere: the vertex along z
    col = bone[nx // 2, ny // 2, :]
    assert col.sum() >= 6
    # the skull seals the brain off from the scalp, even with 26-neighbours
    _, n_soft = ndimage.label(labels == 1, FULL)
    assert n_soft == 2
    # the sinus is an air cavity inside the head
    _, n_air = ndimage.label(labels == 0)
    assert n_air == 2
    assert head_labels(sinus=False).array.min() == 0
    assert ndimage.label(head_labels(sinus=False).array == 0)[1] == 1


def test_headrest_is_separate_from_the_head():
    image = make_phantom("head", noise=0)
    labels = phantom_labels("head")
    bright, n = ndimage.label(image.array >= 226, FULL)
    assert n == 2  # skull and headrest
    sizes = np.bincount(bright.ravel())[1:]
    headrest = bright == 1 + np.argmin(sizes)
    assert np.all(labels.array[headrest] == 0)
    # more than one voxel diagonal away from every head voxel
    s = np.array(image.spacing)
    dist = ndimage.distance_transform_edt(labels.array == 0, sampling=s)
    assert dist[headrest].min() > np.linalg.norm(s)
    # it lies behind the head (low y)
    ys = np.nonzero(headrest)[1]
    head_ys = np.nonzero(labels.array)[1]
    assert ys.mean() < head_ys.min() + 0.5 * (head_ys.max() - head_ys.min())


def test_shell_volume_against_the_ball_formula():
    n = 64
    labels = shell_labels(n).array
    counts = np.bincount(labels.ravel(), minlength=3)
    outer = 4 / 3 * np.pi * (0.45 * n) ** 3
    inner = 4 / 3 * np.pi * (0.30 * n) ** 3
    assert counts[1] + counts[2] == pytest.approx(outer, rel=0.02)
    assert counts[2] == pytest.approx(inner, rel=0.02)
    # centred on the volume centre: symmetric under every axis flip
    for ax in range(3):
        np.testing.assert_array_equal(labels, np.flip(labels, ax))


def test_shell_benchmark_size():
    vol = shell_labels()  # n = 256
    assert vol.array.shape == (256, 256, 256) and vol.array.dtype == np.uint8
    assert vol.spacing == (1.0, 1.0, 1.0)
    count = np.count_nonzero(vol.array)
    assert count == pytest.approx(6.4e6, rel=0.002)
    assert count == pytest.approx(4 / 3 * np.pi * 115.2**3, rel=0.001)


@settings(max_examples=10, deadline=None)
@given(n=st.integers(20, 60))
def test_sphere_volume_and_centre(n):
    labels = sphere_labels(n).array
    assert set(np.unique(labels)) == {0, 2}
    assert np.count_nonzero(labels) == pytest.approx(4 / 3 * np.pi * (0.3 * n) ** 3, rel=0.05)
    centre = np.array(ndimage.center_of_mass(labels > 0)) + 0.5  # voxel centres at i + 0.5
    np.testing.assert_allclose(centre, n / 2 + np.array(SPHERE_OFFSET), atol=0.08)


def test_sphere_is_off_lattice():
    labels = sphere_labels(48).array
    assert not np.array_equal(labels, np.flip(labels, 0))
    assert sphere_labels(48, label=1).array.max() == 1


def test_block():
    vol = block_labels(32)
    assert vol.array.shape == (32, 24, 16)
    assert np.count_nonzero(vol.array) == (32 - 8) * (24 - 8) * (16 - 8)
    assert np.all(block_labels(16, margin=0).array == 2)


def test_long_bone_structure():
    labels = long_bone_labels().array
    nx, ny, nz = labels.shape
    assert nz == 96 and nx == ny == 48
    # muscle reaches both end planes (cut planes); the bone does not
    assert np.all(labels[:, :, 0][labels[:, :, 0] > 0] == 1) and labels[:, :, -1].max() == 1
    assert labels[:, :, 0].max() == 1 and (labels[:, :, :2] == 2).sum() == 0
    bone = labels == 2
    assert ndimage.label(bone, FULL)[1] == 1
    # marrow is a second soft-tissue component, sealed inside the cortex
    _, n_soft = ndimage.label(labels == 1, FULL)
    assert n_soft == 2
    # the shaft is a tube: a mid slice holds bone around marrow
    mid = labels[:, :, nz // 2]
    filled = ndimage.binary_fill_holes(mid == 2)
    assert np.count_nonzero(filled & (mid == 1)) > 0


def test_phantom_round_trip_as_int16(tmp_path):
    image = make_phantom("head", size=40, seed=5)
    write_image(image, tmp_path / "head.nii.gz")
    back = read_image(tmp_path / "head.nii.gz")
    np.testing.assert_array_equal(back.array, image.array)
    assert back.spacing == image.spacing == (5.6, 5.6, 7.0)  # short decimals survive float32


def test_errors():
    with pytest.raises(DicerError, match="unknown"):
        make_phantom("torso")
    with pytest.raises(DicerError, match="unknown"):
        phantom_labels("torso")
    with pytest.raises(DicerError, match="too small"):
        make_phantom("head", size=8)
    with pytest.raises(DicerError, match="noise"):
        make_phantom("shell", size=16, noise=-1)


def test_fixtures_are_read_only(shell_small, head_small):
    assert isinstance(shell_small, Volume) and shell_small.array.shape == (24, 24, 24)
    with pytest.raises(ValueError):
        shell_small.array[0, 0, 0] = 1
    image, labels = head_small
    assert image.array.shape == labels.array.shape
