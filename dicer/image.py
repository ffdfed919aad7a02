"""The in-memory image: a voxel array with its physical voxel size."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_LABEL = 65535
"""The largest material label: label volumes are written as uint16 (NIfTI)."""


@dataclass
class Volume:
    """A 2D or 3D image or label volume.

    array : (nx, ny[, nz]) array indexed [x, y, z]; intensities (float32, HU for CT)
        or labels (integer, 0 = background, 1..K = material class).
    spacing : per-axis voxel size in mm, one value per array axis.
    origin : position of voxel (0, 0, 0)'s corner in mm, one value per array axis.
    """

    array: np.ndarray
    spacing: tuple[float, ...]
    origin: tuple[float, ...] | None = None

    def __post_init__(self):
        self.spacing = tuple(float(s) for s in self.spacing)
        if self.origin is None:
            self.origin = (0.0,) * self.array.ndim
        self.origin = tuple(float(o) for o in self.origin)

    @property
    def ndim(self) -> int:
        return self.array.ndim
