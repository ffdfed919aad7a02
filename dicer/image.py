"""The in-memory image: a voxel array with its physical voxel size."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_LABEL = 65535
"""The largest material label: label volumes are written as uint16 (NIfTI)."""


@dataclass
class Volume:
    """A 2D or 3D image or label volume.

    Parameters
    ----------
    array : (nx, ny[, nz]) ndarray
        Indexed [x, y, z]; intensities (float32, HU for CT) or labels (integer,
        0 = background, 1..K = material class).
    spacing : tuple of float
        Per-axis voxel size in mm, one value per array axis.
    origin : tuple of float, optional
        ITK's origin (centre of voxel (0, 0, 0)) minus half a voxel along each index axis,
        in mm, one value per array axis: that voxel's corner when the direction is the
        identity.
    direction : tuple of float, optional
        The file's direction cosines (ITK order, row-major, ndim * ndim values), or None
        for the identity. Stages work in the index axes; label files keep them (so their
        affine), and the exports place the model in scanner coordinates with them
        (docs/coordinates.md).
    modality : str, optional
        What the scan is, as DICOM's Modality (0008,0060) names it ("CT", "MR", ...): from a
        DICOM file or series, or the BIDS sidecar (``scan.json`` beside ``scan.nii.gz``) that
        dcm2niix writes; None when the input does not say. Segmentation refuses HU defaults
        for a scan that is not a CT.
    """

    array: np.ndarray
    spacing: tuple[float, ...]
    origin: tuple[float, ...] | None = None
    direction: tuple[float, ...] | None = None
    modality: str | None = None

    def __post_init__(self):
        self.spacing = tuple(float(s) for s in self.spacing)
        if self.origin is None:
            self.origin = (0.0,) * self.array.ndim
        self.origin = tuple(float(o) for o in self.origin)
        if self.direction is not None:
            self.direction = tuple(float(d) for d in self.direction)

    @property
    def ndim(self) -> int:
        """Number of array axes, 2 or 3."""
        return self.array.ndim


def regridded_origin(volume: Volume, spacing) -> tuple[float, ...]:
    """``Volume.origin`` of the same first-voxel corner on a grid of another voxel size.

    ``origin`` is ITK's voxel-centre origin minus half a voxel along each index axis, which
    is the corner only while the direction is the identity. With a direction D the corner
    in space is ``itk_origin - D (s / 2)``, so keeping it at a new voxel size s' moves the
    origin by ``(s - s') / 2 - D (s - s') / 2`` (zero along axes D leaves as they are).

    Parameters
    ----------
    volume : Volume
    spacing : sequence of float
        The new voxel size, mm.

    Returns
    -------
    tuple of float
    """
    old = np.asarray(volume.spacing, float)
    half = (old - np.asarray(spacing, float)) / 2
    if volume.direction is None:
        return tuple(volume.origin)
    d = np.asarray(volume.direction, float).reshape(volume.ndim, volume.ndim)
    return tuple(float(v) for v in np.asarray(volume.origin, float) + half - d @ half)


def count_labels(array: np.ndarray, minlength: int = 0) -> np.ndarray:
    """Voxels per label value: ``np.bincount`` of a whole volume, in slices.

    numpy casts what it counts to 64-bit integers first: 1 GB of fresh memory for a 512³
    uint8 volume. Slices of 2 M voxels, counted on the process's cores, keep that copy
    small and in cache.

    Parameters
    ----------
    array : ndarray of non-negative int
        Any shape.
    minlength : int, optional
        At least this many counts.

    Returns
    -------
    ndarray of int64
        ``counts[v]`` voxels of value v, length ``max(array.max() + 1, minlength)``.
    """
    from dicer.parallel import ordered_map

    flat = np.asarray(array).reshape(-1)
    step = 1 << 21
    counts = np.zeros(minlength, np.int64)
    for part in ordered_map(lambda start: np.bincount(flat[start:start + step]), range(0, flat.size, step)):
        if part.size > counts.size:
            part[:counts.size] += counts
            counts = part
        else:
            counts[:part.size] += part
    return counts


def enclosed_voids(labels: np.ndarray) -> tuple[int, int]:
    """The background regions a label volume encloses: no way out of the image through
    background (6-connected; beyond the image counts as outside).

    A mesh of the volume has their walls among its free faces; the exports hold them in the
    set CAVITIES, apart from the outer surface EXTERIOR.

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        0 background.

    Returns
    -------
    (voids, wall_faces) : tuple of int
        The enclosed regions, and the voxel faces between them and the labelled voxels.
    """
    from scipy import ndimage

    solid = np.asarray(labels) != 0
    inner = (slice(1, -1),) * solid.ndim
    regions, _ = ndimage.label(np.pad(~solid, 1, constant_values=True))
    outside = regions[(0,) * solid.ndim]
    regions = regions[inner]
    enclosed = (regions != outside) & (regions > 0)
    if not enclosed.any():
        return 0, 0
    walls = 0
    for axis in range(solid.ndim):
        s, e = np.moveaxis(solid, axis, 0), np.moveaxis(enclosed, axis, 0)
        walls += int(np.count_nonzero(s[:-1] & e[1:])) + int(np.count_nonzero(e[:-1] & s[1:]))
    return int(np.unique(regions[enclosed]).size), walls
