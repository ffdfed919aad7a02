"""Shared fixtures: small phantoms (read-only arrays; copy before changing them)."""

import pytest

from dicer.phantoms import make_phantom, phantom_labels, shell_labels


def _frozen(volume):
    volume.array.setflags(write=False)
    return volume


@pytest.fixture(scope="session")
def shell_small():
    """Two-material shell labels, 24^3 voxels of 1 mm (uint8: 0, 1, 2)."""
    return _frozen(shell_labels(24))


@pytest.fixture(scope="session")
def head_small():
    """(image, labels) of the head phantom at 48 voxels along y: float32 HU and uint8 labels."""
    return _frozen(make_phantom("head", size=48, seed=0)), _frozen(phantom_labels("head", size=48))


@pytest.fixture(autouse=True)
def _warnings_said_afresh():
    """Each test a fresh process as far as the once-a-run image warnings go."""
    from dicer.io import images

    images._said.clear()
    yield
