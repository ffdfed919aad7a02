"""Pictures of a segmentation and of a model: orthogonal slices with the label overlay,
the threshold criterion curves, the scaled-Jacobian histogram per material, the node-class
counts, and the model itself (its exterior coloured by material, and a cut through it).
PNG files, rendered off-screen with matplotlib's Agg canvas (no display, GPU or VTK),
written atomically and byte-for-byte reproducible (no time stamp or software tag in the
file, fixed size and dpi).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from dicer.arrays import nonzero, norm
from dicer.errors import DicerError
from dicer.image import Volume
from dicer.io.atomic import atomic_path
from dicer.mesh.frame import mirrored, to_scanner
from dicer.mesh.topology import HEX_FACES

__all__ = ["legend_materials", "save_jacobian_histogram", "save_model_picture", "save_node_class_chart",
           "save_overlay_png", "save_threshold_plot", "slice_centre", "visible_faces", "worst_materials", "zbuffer"]

# background transparent, then one colour per class (cycled); the first six are those of
# the few classes a scan's segmentation has, the rest tell an atlas's neighbours apart
_COLOURS = ["#e6550d", "#fdd835", "#31a354", "#3182bd", "#9e4ac0", "#e377c2",
            "#8c564b", "#17becf", "#bcbd22", "#7f7f7f", "#ff9896", "#98df8a", "#aec7e8", "#c5b0d5",
            "#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#fdae6b"]
_DPI = 100
_LEGEND_ENTRIES = 8  # materials a legend names; an atlas's others are counted


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
        views = [((slice(None), slice(None)), (0, 1), "i-j")]
    else:
        cx, cy, cz = centre
        # the image's index axes i, j, k (the scanner's x, y, z only for an unturned scan)
        views = [((slice(None), slice(None), cz), (0, 1), f"i-j at k={cz}"),
                 ((slice(None), cy, slice(None)), (0, 2), f"i-k at j={cy}"),
                 ((cx, slice(None), slice(None)), (1, 2), f"j-k at i={cx}")]
    fig = Figure(figsize=(4.2 * len(views), 4.6))
    for i, (sl, (a0, a1), label) in enumerate(views):
        ax = fig.add_subplot(1, len(views), i + 1)
        extent = (0, img.shape[a0] * sp[a0], 0, img.shape[a1] * sp[a1])
        ax.imshow(img[sl].T, cmap="gray", vmin=vmin, vmax=vmax, origin="lower", extent=extent,
                  interpolation="nearest")
        ax.imshow(lab[sl].T, cmap=cmap, vmin=-0.5, vmax=k + 0.5, alpha=0.45, origin="lower",
                  extent=extent, interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("ijk"[a0] + " (mm from voxel 0's corner)", fontsize=8)
        ax.set_ylabel("ijk"[a1] + " (mm from voxel 0's corner)", fontsize=8)
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


def legend_materials(material: np.ndarray, limit: int = _LEGEND_ENTRIES) -> tuple[np.ndarray, int]:
    """The materials a legend names: all of them, or an atlas's ``limit`` largest.

    material : (M,) int label per element. Returns the labels named, ascending, and how
    many others there are.
    """
    labels, sizes = np.unique(np.asarray(material), return_counts=True)
    if labels.size <= limit:
        return labels, 0
    return np.sort(labels[np.argsort(-sizes, kind="stable")[:limit]]), int(labels.size - limit)


def worst_materials(sj: np.ndarray, material: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` materials whose lowest scaled Jacobian is lowest, worst first (ties: lower label).

    sj : (M,) float scaled Jacobian per element; material : (M,) int label per element.
    """
    material = np.asarray(material, np.int64)
    labels = np.unique(material)
    worst = np.full(int(labels.max(initial=0)) + 1, np.inf)
    np.minimum.at(worst, material, np.asarray(sj, np.float64))
    return labels[np.argsort(worst[labels], kind="stable")[:count]]


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
    labels = np.unique(material)
    if labels.size > _LEGEND_ENTRIES:
        # an atlas: every element in one outline, and the materials with the worst elements
        counts, _ = np.histogram(np.clip(sj, lo, 1.0), bins=edges)
        ax.stairs(counts, edges, color="#252525", lw=1.6,
                  label=f"all {labels.size} materials ({sj.size} elements, min {sj.min():.3f})")
        labels = worst_materials(sj, material, _LEGEND_ENTRIES - 2)
        ax.set_title(f"Scaled Jacobian: all elements and the {labels.size} materials with the lowest", fontsize=10)
    else:
        ax.set_title("Scaled Jacobian per material", fontsize=10)
    for label in labels.tolist():
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


# the camera: looking from azimuth -60 deg, elevation 20 deg (scanner z up); its sines by the C
# library (math), as numpy's own vector code on AVX-512 CPUs may differ in the last bit
_AZIM, _ELEV = math.radians(-60.0), math.radians(20.0)


def _camera() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(towards the viewer, screen right, screen up), unit vectors."""
    ca, sa, ce, se = math.cos(_AZIM), math.sin(_AZIM), math.cos(_ELEV), math.sin(_ELEV)
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
    across = np.where(neighbours >= 0, keep[np.maximum(neighbours, 0)], False)
    e_idx, f_idx = nonzero(keep[:, None] & ~across)
    quads = cells[e_idx[:, None], HEX_FACES[f_idx]]
    p = points[quads]  # (F, 4, 3)
    normal = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
    if flip:
        normal = -normal
    length = norm(normal, axis=1)
    facing = normal @ towards
    front = facing > 1e-12 * np.maximum(length, 1e-300)
    e_idx, quads, p = e_idx[front], quads[front], p[front]
    _, right, up = _camera()
    light = towards + 0.6 * right + 0.4 * up
    lambert = (normal[front] @ (light / norm(light))) / length[front]
    depth = p.mean(axis=1) @ towards
    order = np.argsort(depth, kind="stable")
    return e_idx[order], quads[order], lambert[order]


def _shaded(labels: np.ndarray, lambert: np.ndarray) -> np.ndarray:
    from matplotlib.colors import to_rgb

    table = np.array([to_rgb(material_colour(k)) if k > 0 else (0.5, 0.5, 0.5)
                      for k in range(int(labels.max(initial=0)) + 1)])
    shade = 0.35 + 0.65 * np.clip(lambert, 0.0, 1.0)
    return np.clip(table[labels] * shade[:, None], 0.0, 1.0)


def zbuffer(xy: np.ndarray, depth: np.ndarray, shape: tuple[int, int], chunk: int = 1 << 21) -> np.ndarray:
    """Which quad is nearest the eye at each pixel centre: a z-buffer, in blocks of candidates.

    Each quad is split into the triangles (0, 1, 2) and (0, 2, 3); every pixel centre in a
    triangle's bounding box is tested (barycentric coordinates, edges inclusive, so quads
    sharing an edge leave no gap), its depth interpolated, and the nearest kept. A quad
    smaller than a pixel covers the pixel centres it holds, or none.

    xy : (F, 4, 2) quad corners in pixel units: column c's centre at x = c, row r's at y = r
        (row 0 at the bottom); depth : (F, 4) distance from the eye (smaller is nearer);
    shape : (H, W) pixels; chunk : candidate pixels tested at once (bounds the memory).
    Returns (H, W) int64, the quad seen at each pixel, -1 where none (equal depths: the
    lower index).
    """
    h, w = shape
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    txy = np.asarray(xy, np.float64)[:, tri].reshape(-1, 3, 2)  # (T, 3, 2), T = 2F
    tz = np.asarray(depth, np.float64)[:, tri].reshape(-1, 3)
    a = txy[:, 0]
    e1, e2 = txy[:, 1] - a, txy[:, 2] - a
    den = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    lo = np.ceil(txy.min(axis=1)).astype(np.int64)
    hi = np.floor(txy.max(axis=1)).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [w - 1, h - 1])
    span = np.maximum(hi - lo + 1, 0)
    count = np.where(np.abs(den) > 1e-12, span[:, 0] * span[:, 1], 0)
    end = np.cumsum(count)
    zbuf = np.full(h * w, np.inf)
    face = np.full(h * w, -1, np.int64)
    # blocks of whole triangles holding about ``chunk`` candidates each
    cuts = np.unique(np.concatenate([[0], np.searchsorted(end, np.arange(chunk, int(end[-1]) if end.size else 0,
                                                                          chunk), side="right"), [count.size]]))
    for t0, t1 in zip(cuts[:-1].tolist(), cuts[1:].tolist()):
        n = count[t0:t1]
        total = int(n.sum())
        if total == 0:
            continue
        t = np.repeat(np.arange(t0, t1), n)
        local = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
        col = lo[t, 0] + local % span[t, 0]
        row = lo[t, 1] + local // span[t, 0]
        px, py = col - a[t, 0], row - a[t, 1]
        u = (px * e2[t, 1] - py * e2[t, 0]) / den[t]
        v = (py * e1[t, 0] - px * e1[t, 1]) / den[t]
        inside = (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1.0 + 1e-9)
        t, u, v = t[inside], u[inside], v[inside]
        z = tz[t, 0] + u * (tz[t, 1] - tz[t, 0]) + v * (tz[t, 2] - tz[t, 0])
        pix = (row[inside] * w + col[inside])
        order = np.lexsort((t, z, pix))  # per pixel: nearest first, then the lower quad
        pix, z, t = pix[order], z[order], t[order]
        first = np.ones(pix.size, bool)
        first[1:] = pix[1:] != pix[:-1]
        pix, z, t = pix[first], z[first], t[first]
        better = z < zbuf[pix]
        zbuf[pix[better]] = z[better]
        face[pix[better]] = t[better] // 2
    return face.reshape(h, w)


def _edge_pixels(face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pixel wide outlines of the quads seen, face : (H, W) from :func:`zbuffer`.

    Returns two (H, W) bool masks of covered pixels: ``shared``, where the quad seen changes
    to the right or above (an edge two drawn quads share), and ``rim``, next to an empty pixel
    (the outline of the picture and its holes)."""
    seen = face >= 0
    shared = np.zeros(face.shape, bool)
    shared[:, :-1] |= (face[:, :-1] != face[:, 1:]) & seen[:, 1:]
    shared[:-1, :] |= (face[:-1, :] != face[1:, :]) & seen[1:, :]
    rim = np.zeros(face.shape, bool)
    rim[:, 1:] |= ~seen[:, :-1]
    rim[:, :-1] |= ~seen[:, 1:]
    rim[1:, :] |= ~seen[:-1, :]
    rim[:-1, :] |= ~seen[1:, :]
    return shared & seen, rim & seen


def _draw_faces(ax, xy: np.ndarray, depth: np.ndarray, colours: np.ndarray, edges: bool) -> None:
    """Rasterise the quads into ``ax`` at its size in pixels (the figure laid out already).

    xy : (F, 4, 2) corners in the picture plane (mm); depth : (F, 4) distance from the eye;
    colours : (F, 3) RGB in 0..1; edges : outline every quad (dark, translucent).
    """
    lo, hi = xy.reshape(-1, 2).min(axis=0), xy.reshape(-1, 2).max(axis=0)
    pad = 0.03 * float((hi - lo).max() or 1.0)
    x0, x1, y0, y1 = lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.apply_aspect()
    box = ax.get_window_extent()
    w, h = max(int(round(box.width)), 1), max(int(round(box.height)), 1)
    pixel = (xy - [x0, y0]) / [(x1 - x0) / w, (y1 - y0) / h] - 0.5
    face = zbuffer(pixel, depth, (h, w))
    image = np.zeros((h, w, 4))
    seen = face >= 0
    image[seen, :3] = colours[face[seen]]
    image[seen, 3] = 1.0
    if edges:
        shared, rim = _edge_pixels(face)  # a shared edge was drawn by both its quads
        for mask, alpha in ((shared, 1.0 - 0.65 ** 2), (rim & ~shared, 0.35)):
            image[mask, :3] = (1.0 - alpha) * image[mask, :3] + alpha * 0.1
    ax.imshow(image, origin="lower", extent=(x0, x1, y0, y1), interpolation="nearest", aspect="equal")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)


def save_model_picture(mesh, names: dict, path, max_edges: int = 20000, neighbours: np.ndarray | None = None) -> Path:
    """Picture of the model: its exterior coloured by material, and the same view cut open.

    3D: the boundary quads seen from azimuth -60 deg, elevation 20 deg in scanner coordinates
    (z up), rasterised with a z-buffer at the picture's pixel size and shaded by the angle to
    the eye; the cut removes the elements whose centre lies beyond the mid-plane of x, showing
    every material on the cut face. 2D: the quads from above. Element edges are drawn while at
    most ``max_edges`` faces are visible (beyond that they would blacken the picture).
    neighbours : (M, 6) element across each face (:func:`dicer.quality.element_neighbours`),
    computed when not given.
    """
    from matplotlib.patches import Patch

    from dicer.quality import element_neighbours

    material = np.asarray(mesh.material, np.int64)
    shown, more = legend_materials(material)
    legend = [Patch(color=material_colour(k), label=_name(names, k)) for k in shown.tolist()]
    if more:
        legend.append(Patch(color="none", label=f"and {more} more materials"))
    if mesh.dim == 2 or mesh.n_cells == 0:
        fig = Figure(figsize=(5.0, 5.0), dpi=_DPI)
        ax = fig.add_subplot()
        ax.set_title("model", fontsize=9)
        xy = mesh.points[mesh.cells][:, :, :2] if mesh.n_cells else np.zeros((1, 4, 2))
        colours = _shaded(material, np.ones(material.size)) if mesh.n_cells else np.ones((1, 3))
        panels = [(ax, xy, np.zeros(xy.shape[:2]), colours, mesh.n_cells <= max_edges)]
    else:
        points = mesh.points
        flip = False
        if mesh.direction is not None:
            points = to_scanner(points, mesh.spacing, mesh.origin, mesh.direction)
            flip = mirrored(mesh.direction)
        towards, right, up = _camera()
        if neighbours is None:
            neighbours = element_neighbours(mesh)
        x = points[:, 0]
        cells = mesh.cells
        centre_x = x[cells[:, 0]].copy()
        for k in range(1, cells.shape[1]):  # the 8 corners, not the elements
            centre_x += x[cells[:, k]]
        centre_x /= cells.shape[1]
        mid = 0.5 * (x.min() + x.max())
        if not (centre_x <= mid).any():  # a model one element thick along x: its centres lie past the middle
            mid = float(np.median(centre_x))
        fig = Figure(figsize=(10.0, 5.0), dpi=_DPI)
        panels = []
        views = [("exterior", np.ones(mesh.n_cells, bool)), (f"cut at x = {mid:.1f} mm", centre_x <= mid)]
        for i, (title, keep) in enumerate(views):
            ax = fig.add_subplot(1, 2, i + 1)
            e_idx, quads, lambert = visible_faces(points, cells, neighbours, keep, towards, flip)
            p = points[quads]
            xy = np.stack([p @ right, p @ up], axis=-1)
            panels.append((ax, xy, -(p @ towards), _shaded(material[e_idx], lambert), quads.shape[0] <= max_edges))
            ax.set_title(title, fontsize=9)
    rows = -(-len(legend) // 6)
    fig.legend(handles=legend, loc="lower center", ncol=min(len(legend), 6), fontsize=8, frameon=False)
    FigureCanvasAgg(fig)
    for ax, xy, depth, colours, edges in panels:  # the limits first: they set the layout
        corners = xy.reshape(-1, 2) if xy.size else np.zeros((1, 2))  # (a panel with no face: empty)
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        pad = 0.03 * float((hi - lo).max() or 1.0)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.set_axis_off()
    fig.tight_layout(rect=(0, 0.06 * rows, 1, 1))
    for ax, xy, depth, colours, edges in panels:
        if xy.size:
            _draw_faces(ax, xy, depth, colours, edges)
    _save(fig, path)
    return Path(path)
