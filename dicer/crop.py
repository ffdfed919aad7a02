"""Crop an image or label volume to a region of interest before meshing (``image.crop``).

The cropped volume keeps its place in the scanner: its first voxel is voxel ``start`` of
the input, so the origin moves by ``D (spacing * start)`` (D the direction cosines) and
spacing and direction stay; label files written from it overlay the input scan, and the
model sits where the uncropped one would (docs/coordinates.md).
"""

from __future__ import annotations

import numpy as np

from dicer.errors import DicerError
from dicer.image import Volume


def _direction(volume: Volume) -> np.ndarray:
    n = volume.ndim
    return np.eye(n) if volume.direction is None else np.asarray(volume.direction, float).reshape(n, n)


def crop_box(volume: Volume, crop: dict, source: str) -> tuple[np.ndarray, np.ndarray]:
    """The voxel index box of a crop setting on a volume.

    unit voxels: min and max are those indices (max exclusive, like a Python slice), and
    must lie in the image. unit mm: min and max are opposite corners of a box in scanner
    coordinates (LPS, mm, the exported model's frame); the region is the smallest index box
    holding every voxel whose centre lies in the box (exactly those voxels unless the image
    is oblique; then found row by row), clipped to the image.

    Parameters
    ----------
    volume : Volume
    crop : dict
        The ``image.crop`` setting: ``unit``, ``min``, ``max``.
    source : str
        File named in error messages.

    Returns
    -------
    start, stop : (ndim,) int64 ndarray
        The voxels ``start[i] <= index[i] < stop[i]``.
    """
    shape = np.array(volume.array.shape, np.int64)
    n = volume.ndim
    lo, hi = np.asarray(crop["min"], float), np.asarray(crop["max"], float)
    if lo.size != n or hi.size != n:
        raise DicerError(f"{source}: image.crop gives {lo.size} and {hi.size} values for a {n}D image of "
                         f"{'x'.join(map(str, shape))} voxels; give {n} values in min and in max")
    if crop["unit"] == "voxels":
        if np.any(lo != np.round(lo)) or np.any(hi != np.round(hi)):
            raise DicerError(f"{source}: image.crop in voxels needs whole voxel indices, got min {lo.tolist()} "
                             f"max {hi.tolist()}; round them or give unit: mm")
        start, stop = lo.astype(np.int64), hi.astype(np.int64)
        if np.any(start < 0) or np.any(stop > shape) or np.any(stop <= start):
            raise DicerError(f"{source}: image.crop min {start.tolist()} max {stop.tolist()} (voxels, max "
                             f"exclusive) is not a box inside the image's {'x'.join(map(str, shape))} voxels; "
                             f"give 0 <= min < max <= {shape.tolist()}")
        return start, stop
    # mm: the box's corners in continuous voxel index (0 at the centre of voxel 0)
    spacing = np.asarray(volume.spacing, float)
    d = _direction(volume)
    # Volume.origin is ITK's origin (centre of voxel 0) minus half a voxel along each index axis
    centre0 = np.asarray(volume.origin, float) + spacing / 2
    corners = np.array(np.meshgrid(*[[a, b] for a, b in zip(lo, hi)], indexing="ij")).reshape(n, -1)
    index = np.linalg.solve(d, corners - centre0[:, None]) / spacing[:, None]
    eps = 1e-9  # a box edge through a voxel centre keeps that voxel
    start = np.maximum(np.ceil(index.min(axis=1) - eps), 0).astype(np.int64)
    stop = np.minimum(np.floor(index.max(axis=1) + eps) + 1, shape).astype(np.int64)
    if np.all(stop > start) and not np.allclose(np.abs(d), np.round(np.abs(d)), atol=1e-6):
        start, stop = _centres_in_box(start, stop, d, centre0, spacing, lo, hi, eps)
    if np.any(stop <= start):
        raise DicerError(f"{source}: the image.crop box min {lo.tolist()} max {hi.tolist()} (mm, scanner "
                         "coordinates) holds no voxel centre of the image; check the box against the "
                         "scan's extent (or give unit: voxels)")
    return start, stop


def _centres_in_box(start, stop, d, centre0, spacing, lo, hi, eps):
    """The smallest index box holding the voxel centres of ``start:stop`` that lie in the mm box
    ``lo``..``hi`` (an oblique scan: the corners' index box holds more); (start, start) when none
    does. Along each row of the last index axis the centres inside form one interval, found in
    closed form from the box's faces, for every row at once."""
    n = len(start)
    low, high = np.minimum(lo, hi) - eps, np.maximum(lo, hi) + eps
    grids = np.meshgrid(*[np.arange(a, b) for a, b in zip(start[:-1], stop[:-1])], indexing="ij")
    rows = np.stack([g.ravel() for g in grids]).astype(float)  # (n - 1, R): the other axes' indices
    base = centre0[:, None] + d[:, :-1] @ (rows * spacing[:-1, None])  # (n, R): centre at last index 0
    step = d[:, -1] * spacing[-1]  # (n,): the move of one voxel along the last axis
    first = np.full(rows.shape[1], float(start[-1]))
    last = np.full(rows.shape[1], float(stop[-1] - 1))
    for a in range(n):  # low <= base + k step <= high, per scanner axis
        if abs(step[a]) < 1e-12:
            outside = (base[a] < low[a]) | (base[a] > high[a])
            last[outside] = -1.0
            continue
        k1, k2 = (low[a] - base[a]) / step[a], (high[a] - base[a]) / step[a]
        first = np.maximum(first, np.ceil(np.minimum(k1, k2)))
        last = np.minimum(last, np.floor(np.maximum(k1, k2)))
    some = first <= last
    if not some.any():
        return start, start
    kept = rows[:, some].astype(np.int64)
    return (np.append(kept.min(axis=1), int(first[some].min())),
            np.append(kept.max(axis=1), int(last[some].max())) + 1)


def crop_volume(volume: Volume, crop: dict | None, source: str) -> tuple[Volume, dict | None]:
    """A volume cut to the ``image.crop`` setting.

    Parameters
    ----------
    volume : Volume
    crop : dict or None
        The ``image.crop`` setting (:func:`crop_box`); None leaves the volume unchanged.
    source : str
        File named in error messages.

    Returns
    -------
    cropped : Volume
    summary : dict or None
        Start, stop, shape before and after; None when nothing was cut.
    """
    if crop is None:
        return volume, None
    start, stop = crop_box(volume, crop, source)
    thin = [(axis, int(b - a)) for axis, (a, b) in enumerate(zip(start.tolist(), stop.tolist())) if b - a < 2]
    if len(thin) > 1 or (thin and volume.array.ndim == 2):
        # one voxel thick along one axis of a 3D image is a 2D model; less is nothing to mesh
        axes = ", ".join(f"{n} voxel along {'xyz'[a]}" for a, n in thin)
        raise DicerError(f"{source}: image.crop keeps {axes}; every stage needs 2 voxels or more along each axis (one "
                         "axis of a 3D image may keep one: a 2D model): widen the crop box")
    spacing = np.asarray(volume.spacing, float)
    origin = np.asarray(volume.origin, float) + _direction(volume) @ (spacing * start)
    array = np.ascontiguousarray(volume.array[tuple(slice(a, b) for a, b in zip(start.tolist(), stop.tolist()))])
    info = {"start": start.tolist(), "stop": stop.tolist(), "shape_before": list(volume.array.shape),
            "shape": list(array.shape)}
    return Volume(array, volume.spacing, tuple(origin.tolist()), volume.direction, volume.modality), info
