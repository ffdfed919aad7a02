"""Scanner coordinates: where the lattice frame the stages work in sits in the scanner.

Every stage works in the *lattice frame*: the voxel mesh's node of lattice index
``(i, j, k)`` lies at ``origin + spacing * (i, j, k)``, axes along the image's index
axes, so merging, coarsening, smoothing and the bounding-plane sets can rely on
axis-aligned voxels. ``origin`` is ``Volume.origin``: the header's position of the
centre of voxel (0, 0, 0) minus half a voxel along each index axis.

The *scanner frame* is ITK's physical space, the patient coordinates of DICOM (LPS:
x towards the patient's left, y posterior, z superior) in mm, which is where
SimpleITK's ``TransformContinuousIndexToPhysicalPoint`` puts a voxel: a node at voxel
corner ``(i, j, k)`` (continuous index ``(i, j, k) - 1/2``) lies at
``c + D @ (spacing * ((i, j, k) - 1/2))`` with ``c`` the centre of voxel (0, 0, 0) and
``D`` the image's direction cosines. In lattice terms that is one rigid motion
(a rotation, or a rotation and a reflection) about ``c``::

    scanner = c + D @ (lattice_frame - c),    c = origin + spacing / 2

It moves smoothed nodes exactly as it moves voxel corners, so it is applied once,
where coordinates leave the program (the exports). A reflection (det D < 0) would
turn every element inside out: the corners are then put in their mirrored order.
"""

from __future__ import annotations

import numpy as np

from dicer.errors import DicerError


def check_direction(direction, dim: int, source: str | None = None) -> np.ndarray | None:
    """The direction cosines as a (3, 3) float64 matrix, or None for the identity or a 2D mesh.

    direction : None or ``dim * dim`` values, row-major (ITK's ``GetDirection``); column j
        is the scanner direction of index axis j.
    Raises DicerError for a matrix that is not orthonormal (a scanner frame reached by a
    rigid motion is what keeps element shapes and the quality figures the same).
    """
    if direction is None or dim != 3:
        return None  # a 2D image has no 3D placement dicer could honour
    d = np.asarray(direction, dtype=np.float64).reshape(3, 3)
    if np.array_equal(d, np.eye(3)):
        return None
    err = float(np.abs(d.T @ d - np.eye(3)).max()) if np.all(np.isfinite(d)) else np.inf
    if not err <= 1e-4:  # header cosines are rounded (DICOM: a few decimals), not sheared
        raise DicerError(
            f"{source + ': ' if source else ''}the image's direction cosines are not orthonormal (largest "
            f"error of D^T D - I: {err:.3g}), so "
            "no rigid motion puts the mesh in scanner coordinates; fix the image header's orientation, or set "
            "mesh.coordinates: index to mesh in the image's index axes"
        )
    return d


def voxel_centre(spacing, origin) -> np.ndarray:
    """(3,) float64: centre of voxel (0, 0, 0) in mm, the fixed point of the motion."""
    return np.asarray(origin, np.float64) + np.asarray(spacing, np.float64) / 2


def to_scanner(points: np.ndarray, spacing, origin, direction: np.ndarray) -> np.ndarray:
    """(N, 3) float64 scanner coordinates (mm, LPS) of lattice-frame ``points`` (N, 3)."""
    c = voxel_centre(spacing, origin)
    out = np.subtract(points, c)
    out = out @ np.asarray(direction, np.float64).T
    out += c
    return out


def to_lattice(points: np.ndarray, spacing, origin, direction: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_scanner`."""
    c = voxel_centre(spacing, origin)
    out = np.subtract(points, c)
    # the inverse, not the transpose: a header's cosines are orthonormal only to float32 precision
    out = out @ np.linalg.inv(np.asarray(direction, np.float64)).T
    out += c
    return out


def mirrored(direction: np.ndarray | None) -> bool:
    """Whether the direction holds a reflection (a left-handed affine, det < 0)."""
    return direction is not None and bool(np.linalg.det(direction) < 0)


def image_affine(spacing, origin, direction=None) -> np.ndarray:
    """(4, 4) float64 affine from continuous voxel index (centre of voxel (0, 0, 0) at 0) to
    scanner coordinates (mm, LPS), as ITK's ``TransformContinuousIndexToPhysicalPoint``.

    The NIfTI (RAS) affine of the same image is ``diag(-1, -1, 1, 1) @ image_affine(...)``.
    """
    d = np.eye(3) if direction is None else np.asarray(direction, np.float64).reshape(3, 3)
    a = np.eye(4)
    a[:3, :3] = d * np.asarray(spacing, np.float64)[None, :]
    a[:3, 3] = voxel_centre(spacing, origin)
    return a
