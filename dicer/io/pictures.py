"""Pictures of a segmentation and of a model: orthogonal slices with the label overlay,
the threshold criterion curves, the scaled-Jacobian histogram per material, the node-class
counts, and the model itself (its exterior coloured by material, and a cut through it).
PNG files, rendered off-screen with matplotlib's Agg canvas (no display, GPU or VTK),
written atomically and byte-for-byte reproducible (no time stamp or software tag in the
file, fixed size and dpi).
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

__all__ = ["save_jacobian_histogram", "save_model_picture", "save_node_class_chart", "save_overlay_png",
           "save_threshold_plot", "slice_centre", "visible_faces"]

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


def material_colour(label: int) -> str:
    """The colour of material ``label`` (1..K) in every picture (the overlay's too)."""
    return _COLOURS[(int(label) - 1) % len(_COLOURS)]


def _name(names: dict, label: int) -> str:
    return names.get(int(label), f"material_{int(label)}")


def save_jacobian_histogram(sj: np.ndarray, material: np.ndarray, names: dict, path, poor: float | None = None) -> Path:
    """Histogram of the elements' scaled Jacobian, one outline per material (log count axis).

    sj : (M,) scaled Jacobian per element; material : (M,) label per element;
    names : label -> material name; poor : the poor-element threshold, drawn as a line.
    """
    sj = np.asarray(sj, np.float64)
    material = np.asarray(material)
    lo = min(0.0, float(np.floor(sj.min() * 20) / 20)) if sj.size else 0.0
    edges = np.linspace(lo, 1.0, int(round((1.0 - lo) / 0.025)) + 1)
    fig = Figure(figsize=(6.4, 3.6))
    ax = fig.add_subplot()
    for label in np.unique(material).tolist():
        values = sj[material == label]
        counts, _ = np.histogram(np.clip(values, lo, 1.0), bins=edges)
        ax.stairs(counts, edges, color=material_colour(label), lw=1.6,
                  label=f"{_name(names, label)} ({values.size} elements, min {values.min():.3f})")
    if poor is not None:
        ax.axvline(poor, color="#555555", lw=1.0, ls="--", label=f"poor below {poor:g}")
    ax.set_yscale("log")
    ax.set_ylim(bottom=0.8)
    ax.set_xlim(lo, 1.0)
    ax.set_xlabel("scaled Jacobian (1: a perfect box; 0 or less: inverted)", fontsize=8)
    ax.set_ylabel("elements", fontsize=8)
    ax.set_title("Scaled Jacobian per material", fontsize=10)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", frameon=False)
    fig.tight_layout()
    _save(fig, path)
    return Path(path)


def save_node_class_chart(node_classes: dict, path) -> Path:
    """Bar chart of the boundary node classes A..F (paper Fig. 5); the interior count in the title."""
    classes = [c for c in "ABCDEF" if c in node_classes]
    counts = [int(node_classes[c]) for c in classes]
    fig = Figure(figsize=(5.2, 3.2))
    ax = fig.add_subplot()
    bars = ax.bar(classes, counts, color="#3182bd")
    ax.bar_label(bars, labels=[str(c) for c in counts], fontsize=7)
    ax.set_ylim(0, max(counts + [1]) * 1.15)
    ax.set_xlabel("boundary node class (A 3 boundary edges, B/D 4, C 5, E/F 6)", fontsize=8)
    ax.set_ylabel("nodes", fontsize=8)
    interior = node_classes.get("interior")
    ax.set_title("Node classes" + (f" ({interior} interior nodes)" if interior is not None else ""), fontsize=10)
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    _save(fig, path)
    return Path(path)


# the camera: looking from azimuth -60 deg, elevation 20 deg (scanner z up)
_AZIM, _ELEV = np.radians(-60.0), np.radians(20.0)


def _camera() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(towards the viewer, screen right, screen up), unit vectors."""
    ca, sa, ce, se = np.cos(_AZIM), np.sin(_AZIM), np.cos(_ELEV), np.sin(_ELEV)
    return (np.array([ce * ca, ce * sa, se]), np.array([-sa, ca, 0.0]), np.array([-se * ca, -se * sa, ce]))


def visible_faces(points: np.ndarray, cells: np.ndarray, neighbours: np.ndarray, keep: np.ndarray,
                  towards: np.ndarray, flip: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boundary faces of the kept elements that face the viewer, far to near.

    points : (N, 3) node coordinates; cells : (M, 8) hexahedra; neighbours : (M, 6) element
    across each face (Abaqus S1..S6), -1 for none; keep : (M,) bool, the elements drawn (the
    rest is cut away); towards : (3,) unit vector to the viewer; flip : the points went through
    a reflection (normals reversed).
    Returns (element (F,), quad node indices (F, 4) running outward, lambert factor (F,) for a
    light from over the viewer's right shoulder), sorted by depth, farthest first (the painter's order).
    """
    from dicer.export.stl import OUTWARD_FACES

    across = np.where(neighbours >= 0, keep[np.maximum(neighbours, 0)], False)
    e_idx, f_idx = np.nonzero(keep[:, None] & ~across)
    quads = cells[e_idx[:, None], OUTWARD_FACES[f_idx]]
    p = points[quads]  # (F, 4, 3)
    normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
    if flip:
        normal = -normal
    length = np.linalg.norm(normal, axis=1)
    facing = normal @ towards
    front = facing > 1e-12 * np.maximum(length, 1e-300)
    e_idx, quads, p = e_idx[front], quads[front], p[front]
    _, right, up = _camera()
    light = towards + 0.6 * right + 0.4 * up
    lambert = (normal[front] @ (light / np.linalg.norm(light))) / length[front]
    depth = p.mean(axis=1) @ towards
    order = np.argsort(depth, kind="stable")
    return e_idx[order], quads[order], lambert[order]


def _shaded(labels: np.ndarray, lambert: np.ndarray) -> np.ndarray:
    from matplotlib.colors import to_rgb

    table = np.array([to_rgb(material_colour(k)) if k > 0 else (0.5, 0.5, 0.5)
                      for k in range(int(labels.max(initial=0)) + 1)])
    shade = 0.35 + 0.65 * np.clip(lambert, 0.0, 1.0)
    return np.clip(table[labels] * shade[:, None], 0.0, 1.0)


def _draw_faces(ax, xy: np.ndarray, colours: np.ndarray, edges: bool) -> None:
    from matplotlib.collections import PolyCollection

    coll = PolyCollection(xy, facecolors=colours, edgecolors=(0.1, 0.1, 0.1, 0.35) if edges else "face",
                          linewidths=0.15 if edges else 0.0, antialiaseds=False)
    ax.add_collection(coll)
    lo, hi = xy.reshape(-1, 2).min(axis=0), xy.reshape(-1, 2).max(axis=0)
    pad = 0.03 * float((hi - lo).max() or 1.0)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_axis_off()


def save_model_picture(mesh, names: dict, path, max_edges: int = 20000) -> Path:
    """Picture of the model: its exterior coloured by material, and the same view cut open.

    3D: the boundary quads seen from azimuth -60 deg, elevation 20 deg in scanner coordinates
    (z up), drawn far to near (painter's algorithm) and shaded by the angle to the eye; the cut
    removes the elements whose centre lies beyond the mid-plane of x, showing every material on
    the cut face. 2D: the quads from above. Element edges are drawn while at most ``max_edges``
    faces are visible (beyond that they would blacken the picture).
    """
    from matplotlib.patches import Patch

    from dicer.mesh.frame import mirrored, to_scanner
    from dicer.quality import element_neighbours

    material = np.asarray(mesh.material, np.int64)
    labels = np.unique(material).tolist()
    legend = [Patch(color=material_colour(k), label=_name(names, k)) for k in labels]
    if mesh.dim == 2 or mesh.n_cells == 0:
        fig = Figure(figsize=(5.0, 5.0))
        ax = fig.add_subplot()
        xy = mesh.points[mesh.cells][:, :, :2] if mesh.n_cells else np.zeros((1, 4, 2))
        _draw_faces(ax, xy, _shaded(material, np.ones(material.size)), mesh.n_cells <= max_edges)
        ax.set_title("model", fontsize=9)
    else:
        points = mesh.points
        flip = False
        if mesh.direction is not None:
            points = to_scanner(points, mesh.spacing, mesh.origin, mesh.direction)
            flip = mirrored(mesh.direction)
        towards, right, up = _camera()
        neighbours = element_neighbours(mesh)
        centre = points[mesh.cells].mean(axis=1)
        mid = 0.5 * (points[:, 0].min() + points[:, 0].max())
        fig = Figure(figsize=(10.0, 5.0))
        views = [("exterior", np.ones(mesh.n_cells, bool)), (f"cut at x = {mid:.1f} mm", centre[:, 0] <= mid)]
        for i, (title, keep) in enumerate(views):
            ax = fig.add_subplot(1, 2, i + 1)
            e_idx, quads, lambert = visible_faces(points, mesh.cells, neighbours, keep, towards, flip)
            p = points[quads]
            xy = np.stack([p @ right, p @ up], axis=-1)
            _draw_faces(ax, xy, _shaded(material[e_idx], lambert), quads.shape[0] <= max_edges)
            ax.set_title(title, fontsize=9)
    fig.legend(handles=legend, loc="lower center", ncol=len(legend), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    _save(fig, path)
    return Path(path)
