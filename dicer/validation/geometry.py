"""Label images of the validation cases, indexed [x, y(, z)], 1 mm voxels, uint8 (0 background, 1 solid).

A voxel is solid when its centre lies in the body. Lengths are in voxels.
"""

from __future__ import annotations

import numpy as np

PARTS = ("quarter", "full")


def _axis(n: int, part: str) -> np.ndarray:
    """Voxel-centre coordinates along one axis relative to the hole (or bore) axis: the image
    corner (quarter) or the image centre, a voxel corner (full)."""
    if part not in PARTS:
        raise ValueError(f"part must be one of {PARTS}, not {part!r}")
    g = np.arange(n) + 0.5
    return g if part == "quarter" else g - n / 2


def kirsch_plate(radius: float = 7.0, width: int = 140, part: str = "quarter", offset=(0.0, 0.0)) -> np.ndarray:
    """A square plate with a round hole in its middle.

    Parameters
    ----------
    radius : float, optional
        Hole radius, voxels.
    width : int, optional
        Plate width, voxels.
    part : {"quarter", "full"}, optional
        quarter: the (width/2, width/2) image of the plate's +x +y quarter, the hole about
        the corner (0, 0), so x = 0 and y = 0 are its symmetry lines; full: the
        (width, width) image, the hole about its centre.
    offset : sequence of float, optional
        Full only: the hole moved by (x, y) voxels (off the lattice, the image has no
        symmetry line through the hole).

    Returns
    -------
    (nx, ny) uint8 ndarray
    """
    if part == "quarter" and any(offset):
        raise ValueError("a quarter plate's hole is centred on its corner; offset applies to the full plate")
    n = width // 2 if part == "quarter" else width
    g = _axis(n, part)
    r = np.hypot(g[:, None] - offset[0], g[None, :] - offset[1])
    return (r >= radius).astype(np.uint8)


def lame_cylinder(inner: float = 7.0, outer: float = 14.0, length: int = 2, part: str = "quarter") -> np.ndarray:
    """A tube along z, a slice of a long cylinder: both end planes are symmetry planes.

    One voxel of background lies beyond the outer surface.

    Parameters
    ----------
    inner, outer : float, optional
        Radii, voxels, inner < outer.
    length : int, optional
        Voxels along z.
    part : {"quarter", "full"}, optional
        quarter: its +x +y quarter, the axis on the image edge x = y = 0; full: the whole
        tube about the image centre.

    Returns
    -------
    (nx, ny, length) uint8 ndarray
    """
    half = int(np.ceil(outer)) + 1
    n = half if part == "quarter" else 2 * half
    g = _axis(n, part)
    r = np.hypot(g[:, None], g[None, :])
    ring = ((r >= inner) & (r < outer)).astype(np.uint8)
    return np.repeat(ring[:, :, None], length, axis=2)
