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


# --- grey-value images: what a CT scanner would show of the same bodies ----------------------------

CONTRAST = 1000.0  # solid minus background, image units (HU)
THRESHOLD = 0.5 * CONTRAST  # the iso-value between them, the segmentation's manual threshold


def _ct_section(inside, n: int, supersample: int, blur: float) -> np.ndarray:
    """A noise-free CT-like image of a cross-section: the body's indicator supersampled and
    block-averaged (partial volume), then blurred by a Gaussian (sigma ``blur`` voxels).

    ``inside(x, y)`` takes sparse supersampled grids of coordinates relative to the image
    centre (a voxel corner) and returns the body's indicator; the image is (n, n).
    """
    from scipy import ndimage

    g = (np.arange(n * supersample) + 0.5) / supersample - n / 2
    x, y = np.meshgrid(g, g, indexing="ij", sparse=True)
    fraction = inside(x, y).reshape(n, supersample, n, supersample).mean(axis=(1, 3))
    # mode "nearest": the body goes on beyond the image's edge as it is there
    return ndimage.gaussian_filter(CONTRAST * fraction, blur, mode="nearest")


def kirsch_scan(radius: float = 7.0, width: int = 140, part: str = "quarter", supersample: int = 8,
                blur: float = 0.6, noise: float = 30.0, seed: int = 0) -> np.ndarray:
    """A CT-like grey-value image of the Kirsch plate (0 in the hole, ``CONTRAST`` in the solid).

    The whole plate's image is made (the hole about its centre, a voxel corner); the quarter
    is its +x +y quarter cut out, as one would cut a scan to model a quarter with symmetry,
    so the quarter's grey values are the full plate's there.

    Parameters
    ----------
    radius : float, optional
        Hole radius, voxels.
    width : int, optional
        Plate width, voxels (even).
    part : {"quarter", "full"}, optional
    supersample : int, optional
        Sub-voxels per voxel and axis for the partial volume.
    blur : float, optional
        The scanner's point spread, a Gaussian's sigma in voxels.
    noise : float, optional
        Gaussian noise, image units (of a contrast of 1000).
    seed : int, optional

    Returns
    -------
    (nx, ny) float32 ndarray
    """
    _axis(1, part)
    image = _ct_section(lambda x, y: np.hypot(x, y) >= radius, width, supersample, blur)
    image = (image + np.random.default_rng(seed).normal(0.0, noise, image.shape)).astype(np.float32)
    return image[width // 2:, width // 2:] if part == "quarter" else image


def lame_scan(inner: float = 7.0, outer: float = 14.0, length: int = 2, part: str = "quarter",
              supersample: int = 8, blur: float = 0.6, noise: float = 30.0, seed: int = 0) -> np.ndarray:
    """A CT-like grey-value image of the Lamé tube (sizes as :func:`lame_cylinder`).

    The cross-section is made as in :func:`kirsch_scan` and repeated along z (the tube is a
    prism, so block averaging and blur act in the section); the noise is drawn per voxel.

    Parameters
    ----------
    inner, outer, length
        As in :func:`lame_cylinder`.
    part : {"quarter", "full"}, optional
        quarter: the whole tube's image cut at its axis (its +x +y quarter).
    supersample, blur, noise, seed
        As in :func:`kirsch_scan`.

    Returns
    -------
    (nx, ny, length) float32 ndarray
    """
    _axis(1, part)
    half = int(np.ceil(outer)) + 1
    n = 2 * half
    section = _ct_section(lambda x, y: (np.hypot(x, y) >= inner) & (np.hypot(x, y) < outer), n, supersample, blur)
    image = section[:, :, None] + np.random.default_rng(seed).normal(0.0, noise, (n, n, length))
    image = image.astype(np.float32)
    return image[half:, half:] if part == "quarter" else image
