"""Pictures of a segmentation: orthogonal slices with the label overlay, and the
threshold criterion curves. PNG files, rendered off-screen with matplotlib's Agg
canvas, written atomically and byte-for-byte reproducible (no time stamp or
software tag in the file).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.atomic import atomic_path

__all__ = ["save_overlay_png", "save_threshold_plot", "slice_centre"]

# background transparent, then one colour per class (cycled)
_COLOURS = ["#e6550d", "#fdd835", "#31a354", "#3182bd", "#9e4ac0", "#e377c2"]
_DPI = 100


def _save(fig: Figure, path) -> None:
    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=_DPI, metadata={"Software": None})


def slice_centre(labels: np.ndarray) -> tuple[int, ...]:
    """Voxel index at the centre of the bounding box of the non-background labels.

    Parameters
    ----------
    labels : (nx, ny[, nz]) ndarray of int

    Returns
    -------
    centre : tuple of int, one per axis (the array's centre when all is background)
    """
    idx = []
    for axis in range(labels.ndim):
        other = tuple(a for a in range(labels.ndim) if a != axis)
        hit = np.flatnonzero(np.any(labels != 0, axis=other))
        idx.append(int((hit[0] + hit[-1]) // 2) if hit.size else labels.shape[axis] // 2)
    return tuple(idx)


def save_overlay_png(image: Volume, labels: Volume, path, title: str = "", n_classes: int | None = None,
                     names: list[str] | None = None) -> Path:
    """Write three orthogonal slices of ``image`` with the labels overlaid (one slice in 2D).

    The slices pass through the centre of the labelled region's bounding box; axes
    are in mm, so anisotropic voxels keep their true proportions. Grey levels are
    clipped to the 1st..99th percentiles.

    Parameters
    ----------
    image : Volume
        Grey-level image, (nx, ny[, nz]).
    labels : Volume
        Labels of the same shape, 0 background (transparent), 1..K classes.
    path : str or Path
        The PNG file to write.
    title : str
        Figure title (e.g. the thresholds).
    n_classes : int, optional
        K, for a stable colour per class; default: the largest label.
    names : list of str, optional
        Class names for the legend.

    Returns
    -------
    path : Path
    """
    img = np.asarray(image.array, dtype=np.float32)
    lab = np.asarray(labels.array)
    if img.shape != lab.shape:
        raise DicerError(f"{path}: image {img.shape} and labels {lab.shape} differ in shape; "
                         "give the labels segmented from this image")
    k = int(n_classes if n_classes is not None else max(int(lab.max()), 1))
    cmap = ListedColormap(["none"] + [_COLOURS[i % len(_COLOURS)] for i in range(k)])
    finite = img[np.isfinite(img)]
    vmin, vmax = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    if vmax <= vmin:
        vmax = vmin + 1.0
    sp = image.spacing
    centre = slice_centre(lab)
    if img.ndim == 2:
        views = [((slice(None), slice(None)), (0, 1), "x-y")]
    else:
        cx, cy, cz = centre
        views = [((slice(None), slice(None), cz), (0, 1), f"x-y at z={cz}"),
                 ((slice(None), cy, slice(None)), (0, 2), f"x-z at y={cy}"),
                 ((cx, slice(None), slice(None)), (1, 2), f"y-z at x={cx}")]
    fig = Figure(figsize=(4.2 * len(views), 4.6))
    for i, (sl, (a0, a1), label) in enumerate(views):
        ax = fig.add_subplot(1, len(views), i + 1)
        extent = (0, img.shape[a0] * sp[a0], 0, img.shape[a1] * sp[a1])
        ax.imshow(img[sl].T, cmap="gray", vmin=vmin, vmax=vmax, origin="lower", extent=extent,
                  interpolation="nearest")
        ax.imshow(lab[sl].T, cmap=cmap, vmin=-0.5, vmax=k + 0.5, alpha=0.45, origin="lower",
                  extent=extent, interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("xyz"[a0] + " (mm)", fontsize=8)
        ax.set_ylabel("xyz"[a1] + " (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    if names:
        from matplotlib.patches import Patch

        handles = [Patch(color=_COLOURS[i % len(_COLOURS)], alpha=0.6, label=n) for i, n in enumerate(names[:k])]
        fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.05 if names else 0, 1, 0.95 if title else 1))
    _save(fig, path)
    return Path(path)


def save_threshold_plot(info: dict, path) -> Path:
    """Plot the shape-connectivity criterion against each class's candidate thresholds.

    Parameters
    ----------
    info : dict
        The info returned by :func:`dicer.segment.segment` with method
        ``shape_connectivity`` (keys ``criterion``, ``thresholds``, ``ranges``).
    path : str or Path
        The PNG file to write.

    Returns
    -------
    path : Path
    """
    curves = info.get("criterion")
    if not curves:
        raise DicerError(f"{path}: no criterion curve to plot (segment.method={info.get('method')}); "
                         "the threshold plot needs segment.method=shape_connectivity")
    names = list(curves)
    fig = Figure(figsize=(4.2 * len(names), 3.4))
    for i, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), i + 1)
        t = np.asarray(curves[name]["thresholds"], dtype=float)
        v = np.asarray(curves[name]["values"], dtype=float)
        ax.plot(t, v, color="#3182bd", lw=1.4)
        chosen = info["thresholds"][i]
        ax.axvline(chosen, color="#e6550d", lw=1.0, ls="--")
        ax.set_title(f"{name}: threshold {chosen:g}", fontsize=9)
        ax.set_xlabel("lower threshold of the class", fontsize=8)
        ax.set_ylabel("J = sum of class solidities", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    _save(fig, path)
    return Path(path)
