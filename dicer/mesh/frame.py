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
    """The direction cosines as a (3, 3) matrix, or None for the identity or a 2D mesh.

    Parameters
    ----------
    direction : sequence of float or None
        ``dim * dim`` values, row-major (ITK's ``GetDirection``); column j is the scanner
        direction of index axis j.
    dim : int
        2 or 3.
    source : str, optional
        What the values came from, for the error message.

    Returns
    -------
    (3, 3) float64 ndarray or None

    Raises
    ------
    DicerError
        The matrix is not orthonormal (a scanner frame reached by a rigid motion is what
        keeps element shapes and the quality figures the same).
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
    """Centre of voxel (0, 0, 0), the fixed point of the motion.

    Parameters
    ----------
    spacing, origin : sequence of float
        Voxel size and image origin, mm.

    Returns
    -------
    (3,) float64 ndarray
        mm.
    """
    return np.asarray(origin, np.float64) + np.asarray(spacing, np.float64) / 2


def to_scanner(points: np.ndarray, spacing, origin, direction: np.ndarray) -> np.ndarray:
    """Scanner coordinates of lattice-frame points.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Lattice-frame coordinates, mm.
    spacing, origin : sequence of float
        Voxel size and image origin, mm.
    direction : (3, 3) float64 ndarray
        Direction cosines (:func:`check_direction`).

    Returns
    -------
    (N, 3) float64 ndarray
        mm, LPS.
    """
    return _rotated(points, voxel_centre(spacing, origin), np.asarray(direction, np.float64))


def to_lattice(points: np.ndarray, spacing, origin, direction: np.ndarray) -> np.ndarray:
    """Lattice-frame coordinates of scanner points: the inverse of :func:`to_scanner`.

    Parameters
    ----------
    points : (N, 3) float64 ndarray
        Scanner coordinates, mm, LPS.
    spacing, origin, direction
        As in :func:`to_scanner`.

    Returns
    -------
    (N, 3) float64 ndarray
    """
    # the inverse, not the transpose: a header's cosines are orthonormal only to float32 precision
    return _rotated(points, voxel_centre(spacing, origin), _inverse3(np.asarray(direction, np.float64)))


def lattice_shift(spacing, origin, to_spacing, to_origin, direction) -> np.ndarray:
    """What to add to lattice-frame points of one grid to have them in the lattice frame of
    another grid of the same scan (another voxel size or origin, the same direction).

    Each grid's frame is its own motion about its own first voxel centre, so two grids apart
    by a voxel size (downsampling keeps the first voxel's corner, :func:`dicer.image.regridded_origin`)
    lie in frames a shift ``(I - D^-1) (c' - c)`` apart; zero for the identity, and exactly zero
    where the centres agree.

    Parameters
    ----------
    spacing, origin : sequence of float
        The points' grid: voxel size and origin, mm (2 or 3 values).
    to_spacing, to_origin : sequence of float
        The other grid's.
    direction : (3, 3) array_like or None
        Direction cosines of both (None: the identity, or a 2D grid).

    Returns
    -------
    (len(spacing),) float64 ndarray
        mm.
    """
    dim = len(spacing)
    if direction is None or dim != 3:
        return np.zeros(dim)
    delta = voxel_centre(to_spacing, to_origin) - voxel_centre(spacing, origin)
    inv = _inverse3(np.asarray(direction, np.float64).reshape(3, 3))
    return delta - (inv[:, 0] * delta[0] + inv[:, 1] * delta[1] + inv[:, 2] * delta[2])


def _inverse3(d: np.ndarray) -> np.ndarray:
    """The inverse of a 3 x 3 matrix by its cofactors (no LAPACK: the same bytes on every CPU)."""
    cof = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            r, q = [a for a in range(3) if a != i], [b for b in range(3) if b != j]
            cof[i, j] = (-1.0) ** (i + j) * (d[r[0], q[0]] * d[r[1], q[1]] - d[r[0], q[1]] * d[r[1], q[0]])
    return cof.T / (d[0, 0] * cof[0, 0] + d[0, 1] * cof[0, 1] + d[0, 2] * cof[0, 2])


def _rotated(points: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(N, 3): ``c + d @ (p - c)`` for each row p of ``points``, term by term: a matrix product
    would take BLAS, whose kernels the CPU picks and whose last bits differ between them."""
    points = np.asarray(points, np.float64)
    rel = [points[:, j] - c[j] for j in range(3)]
    out = np.empty((points.shape[0], 3))
    for i in range(3):
        out[:, i] = d[i, 0] * rel[0] + d[i, 1] * rel[1] + d[i, 2] * rel[2] + c[i]
    return out


def mirrored(direction: np.ndarray | None) -> bool:
    """Whether the direction holds a reflection (a left-handed affine, det < 0).

    Parameters
    ----------
    direction : (3, 3) float64 ndarray or None

    Returns
    -------
    bool
    """
    return direction is not None and bool(np.linalg.det(direction) < 0)


def image_affine(spacing, origin, direction=None) -> np.ndarray:
    """The affine from continuous voxel index to scanner coordinates, as ITK's
    ``TransformContinuousIndexToPhysicalPoint``.

    The centre of voxel (0, 0, 0) is index 0. The NIfTI (RAS) affine of the same image is
    ``diag(-1, -1, 1, 1) @ image_affine(...)``.

    Parameters
    ----------
    spacing, origin : sequence of float
        Voxel size and image origin, mm.
    direction : sequence of 9 float or (3, 3) ndarray, optional
        Direction cosines; None for the identity.

    Returns
    -------
    (4, 4) float64 ndarray
        To mm, LPS.
    """
    d = np.eye(3) if direction is None else np.asarray(direction, np.float64).reshape(3, 3)
    a = np.eye(4)
    a[:3, :3] = d * np.asarray(spacing, np.float64)[None, :]
    a[:3, 3] = voxel_centre(spacing, origin)
    return a
