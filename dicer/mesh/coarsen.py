"""Graded all-hexahedral (2D: all-quad) meshes by 3-refinement transition templates.

A voxel mesh keeps one element per voxel everywhere. Here the elements stay one voxel
wherever a material boundary or interface is near and grow by a factor of three per
level away from it, joined by conforming transition templates: no hanging node, every
interior face shared by exactly two elements. ``docs/coarsening.md`` gives the
construction and the quality bound of each template (``dicer.mesh.templates``).

2D: cells of level l are squares of 3**l voxels. Corners of the level-l cell grid are
*marked* when a cell that must stay refined holds them; an edge is *split* (into three)
when both its ends are marked, so two cells sharing an edge agree on it. A cell that may
coarsen takes the template of its marked corners (one element, the edge or the corner
template, or its 9 cells of the level below); marks are added until every cell has one
(node marking to valid patterns, as in Schneiders' method).

3D: a level is three steps, along x, then y, then z. A cell of a step is three plain
cells (one coarse element each; voxels at the first step) of the step before along the
step's axis, of one material.
Cells are grouped in blocks of 2 x 2 across the axis, marked at the block corners, and
each block takes the template of its marks.

A voxel may coarsen when every voxel within ``min_distance`` of it (inside the image)
holds its material, so elements touching a boundary or interface node are always voxels
and the node classes and smoothing apply unchanged.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from dicer.brief import brief_names
from dicer.errors import DicerError
from dicer.mesh.metrics import element_volumes, scaled_jacobian
from dicer.mesh.model import LEVEL_DATA, Mesh, pieces
from dicer.mesh.templates import (BLOCK_TEMPLATES, COARSE, COMPLETION_2D, COMPLETION_BLOCK, FINE, INVALID,
                                  SECTION, TEMPLATES_2D)
from dicer.mesh.topology import HEX_CORNERS, QUAD_CORNERS

__all__ = ["coarsen_mesh", "coarsen_labels", "LEVEL_DATA", "TEMPLATE_FLOOR"]

TEMPLATE_FLOOR = 0.2
"""The corner scaled Jacobian every graded element keeps on cubic voxels (templates: 0.229)."""

log = logging.getLogger("dicer")

def _pool_any(a: np.ndarray, dim: int, n_out: tuple) -> np.ndarray:
    """For every cell I of the next level: any of a[3I : 3I + 4] (per axis), over the
    4**dim points of the closed cell; points beyond ``a`` count as True."""
    out = a
    for axis in range(dim):
        n = n_out[axis]
        pad = [(0, 0)] * out.ndim
        pad[axis] = (0, max(0, 3 * n + 1 - out.shape[axis]))
        padded = np.pad(out, pad, constant_values=True)
        take = lambda o: np.take(padded, np.arange(n) * 3 + o, axis=axis)  # noqa: E731
        out = take(0) | take(1) | take(2) | take(3)
    return out


def _close(candidate: np.ndarray, corners: np.ndarray, pattern: np.ndarray, complete: np.ndarray,
           lead: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mark the corners of every cell that may not coarsen, then add the fewest marks that
    bring each cell left in an invalid pattern to a valid one, until none is left.

    candidate : cells, bool. corners : (k, d) offsets of a cell's corners over the last d
    axes (bit c of a mask: corner c); the first ``lead`` axes carry no corners (one-axis
    steps: the refined axis). Returns the marks ((n + 1) over the last d axes) and each
    cell's corner mask.
    """
    shape = candidate.shape
    slices = [(slice(None),) * lead + tuple(slice(o, o + n) for o, n in zip(c, shape[lead:])) for c in corners]
    marked = np.zeros(shape[:lead] + tuple(n + 1 for n in shape[lead:]), bool)
    for s in slices:
        marked[s] |= ~candidate
    while True:
        mask = np.zeros(shape, np.int32)
        for c, s in enumerate(slices):
            mask |= marked[s].astype(np.int32) << c
        bad = candidate & (pattern[mask] == INVALID)
        if not bad.any():
            return marked, mask
        target = np.where(bad, complete[mask], 0)
        for c, s in enumerate(slices):
            marked[s] |= (target >> c & 1).astype(bool)


def _sweep(a: np.ndarray, axis: int, radius: int, op) -> np.ndarray:
    """``op`` (np.minimum or np.maximum) of ``a`` over a window of 2 * radius + 1 along
    ``axis``, positions beyond the image counting as 0: ndimage's min/max filter with
    mode="constant", cval=0 in slices (no sort per window)."""
    out = a.copy()
    n = a.shape[axis]

    def cut(start, stop):
        index = [slice(None)] * a.ndim
        index[axis] = slice(start, stop)
        return tuple(index)
    for s in range(1, min(radius, n - 1) + 1):
        op(out[cut(s, None)], a[cut(None, -s)], out=out[cut(s, None)])  # a[i - s]
        op(out[cut(None, -s)], a[cut(s, None)], out=out[cut(None, -s)])  # a[i + s]
    k = min(radius, n)  # windows that reach beyond the image take its 0
    if k:
        op(out[cut(None, k)], 0, out=out[cut(None, k)])
        op(out[cut(n - k, None)], 0, out=out[cut(n - k, None)])
    return out


def _window_min_max(labels: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest label within ``radius`` voxels (a cube; 0 beyond the
    image): separable sweeps along each axis."""
    lo = hi = labels
    for axis in range(labels.ndim):
        lo = _sweep(lo, axis, radius, np.minimum)
        hi = _sweep(hi, axis, radius, np.maximum)
    return lo, hi


def _coarsenable(labels: np.ndarray, min_distance: int, keep_fine) -> np.ndarray:
    """(labels.shape, labels.dtype): the material of every voxel whose neighbours within
    ``min_distance`` voxels (inside the image) all hold it, else 0; materials kept fine 0."""
    lo, hi = _window_min_max(labels, min_distance)
    material = np.where(lo == hi, lo, 0)
    if len(keep_fine):
        material[np.isin(material, np.asarray(keep_fine, np.int64))] = 0
    return material


def _level_one(labels: np.ndarray, dim: int, min_distance: int, keep_fine) -> tuple[np.ndarray, np.ndarray]:
    """Candidates and materials of the level-1 cells (2D): one material in the cell and
    within ``min_distance`` voxels of it, inside the image, not a material kept fine."""
    n = tuple(-(-s // 3) for s in labels.shape)
    lo, hi = _window_min_max(labels, 1 + min_distance)
    # a cell's window is centred on its middle voxel; cells cut by the image's far end
    # have no middle voxel and stay 0
    centre = tuple(slice(1, None, 3) for _ in n)
    lo, hi = lo[centre], hi[centre]
    material = np.zeros(n, np.int64)
    material[tuple(slice(0, s) for s in lo.shape)] = np.where(lo == hi, lo, 0)
    full = np.ones(n, bool)  # cells wholly inside the image (partial ones stay voxels)
    for axis, s in enumerate(labels.shape):
        if s % 3:
            index = [slice(None)] * dim
            index[axis] = -1
            full[tuple(index)] = False
    material = np.where(full, material, 0)
    if len(keep_fine):
        material[np.isin(material, np.asarray(keep_fine, np.int64))] = 0
    return material > 0, material


def _next_level(marked: np.ndarray, candidate: np.ndarray, material: np.ndarray, dim: int):
    """Candidates and materials of the next level's cells (2D): 9 candidate children of
    one material and no marked child corner, boundary included."""
    n = tuple(-(-s // 3) for s in candidate.shape)
    any_marked = _pool_any(marked, dim, n)
    # one material: the children's smallest and largest agree (non-candidates count as 0)
    m = np.where(candidate, material, 0)
    pad = [(0, 3 * k - s) for k, s in zip(n, m.shape)]
    m = np.pad(m, pad)
    blocks = m.reshape(tuple(x for k in n for x in (k, 3)))
    axes = tuple(range(1, 2 * dim, 2))
    lo, hi = blocks.min(axis=axes), blocks.max(axis=axes)
    ok = ~any_marked & (lo == hi) & (lo > 0)
    return ok, np.where(ok, lo, 0)


def _steps_2d(labels: np.ndarray, levels: int, min_distance: int, keep_fine) -> list:
    """The steps of 2D coarsening: one per level, both axes at once."""
    pattern, _ = TEMPLATES_2D
    steps = []
    candidate = material = marked = None
    for level in range(1, levels + 1):
        if level == 1:
            candidate, material = _level_one(labels, 2, min_distance, keep_fine)
        else:
            candidate, material = _next_level(marked, candidate, material, 2)
        marked, mask = _close(candidate, QUAD_CORNERS[:, :2], pattern, COMPLETION_2D)
        steps.append({"level": level, "frame": (0, 1), "prior": np.full(2, 3 ** (level - 1)),
                      "candidate": candidate, "mask": mask, "state": np.where(candidate, pattern[mask], FINE),
                      "material": material})
        if not candidate.any():
            break
    return steps


def _axis_step(plain: np.ndarray, material: np.ndarray, axis: int) -> dict:
    """One step of 3D coarsening along ``axis``.

    plain, material : (cells of the step below) bool, int64: cells that are one coarse
        element (voxels at the first step) and their material.
    A cell of this step is three plain cells of the step below along ``axis`` of one
    material. Nothing is asked of its neighbours: a plain cell's block had no marked
    corner, so every block next to it shows it whole faces and edges (the marks are
    shared), and its own faces across its axis are never split. Cells are taken in blocks
    of 2 x 2 across the axis, which carry the templates. Returns the step's cells'
    material ``cell_material`` and whether each is one coarse element (``cell_plain``), and
    per block its corner ``mask`` and pattern ``state``; arrays in the image's axis order.
    """
    pattern, _ = BLOCK_TEMPLATES
    # a cyclic order of the axes: the templates' frame keeps its handedness
    frame = (axis, (axis + 1) % 3, (axis + 2) % 3)
    back = np.argsort(frame)
    p = np.transpose(plain, frame)
    m = np.transpose(np.where(plain, material, 0), frame)
    n = -(-p.shape[0] // 3)
    pad = ((0, 3 * n - p.shape[0]), (0, 0), (0, 0))
    own = np.pad(p, pad).reshape(n, 3, *p.shape[1:])
    mat = np.pad(m, pad).reshape(n, 3, *p.shape[1:])
    lo, hi = mat.min(axis=1), mat.max(axis=1)
    cell = own.all(axis=1) & (lo == hi) & (lo > 0)
    cell_material = np.where(cell, lo, 0)
    # blocks of 2 x 2 cells across the axis, all four candidates of one material
    nb, nc = (-(-k // 2) for k in cell.shape[1:])
    pad2 = ((0, 0), (0, 2 * nb - cell.shape[1]), (0, 2 * nc - cell.shape[2]))
    quad = np.pad(cell_material, pad2)
    # the four cells of each block as strided views (a reduction over two axes of two
    # is slow)
    four = [quad[:, i::2, j::2] for i in (0, 1) for j in (0, 1)]
    blo = np.minimum(np.minimum(four[0], four[1]), np.minimum(four[2], four[3]))
    bhi = np.maximum(np.maximum(four[0], four[1]), np.maximum(four[2], four[3]))
    block = (blo == bhi) & (blo > 0)
    _, mask = _close(block, SECTION, pattern, COMPLETION_BLOCK, lead=1)
    state = np.where(block, pattern[mask], FINE)
    cell_plain = np.repeat(np.repeat(state == COARSE, 2, axis=1), 2, axis=2)[:, : cell.shape[1], : cell.shape[2]]
    return {"frame": frame, "mask": np.transpose(mask, back), "state": np.transpose(state, back),
            "cell_plain": np.transpose(cell_plain, back),
            "cell_material": np.transpose(np.where(cell_plain, cell_material, 0), back),
            "block_material": np.transpose(np.where(block, blo, 0), back)}


def _steps_3d(labels: np.ndarray, levels: int, min_distance: int, keep_fine) -> list:
    """The steps of 3D coarsening: per level, along x, then y, then z."""
    steps = []
    material = _coarsenable(labels, min_distance, keep_fine)
    plain = material > 0
    prior = np.ones(3, np.int64)
    for level in range(1, levels + 1):
        for axis in range(3):
            step = _axis_step(plain, material, axis)
            step.update(level=level, prior=prior.copy(), below=plain.shape)
            steps.append(step)
            if not step["cell_plain"].any():
                return steps
            plain, material = step["cell_plain"], step["cell_material"]
            prior[axis] *= 3
    return steps


def coarsen_labels(labels: np.ndarray, *, levels: int, min_distance: int, keep_fine) -> dict:
    """The graded decomposition of a label volume: which cells of which step are elements.

    Parameters
    ----------
    labels : (nx, ny, nz) or (nx, ny) int ndarray
        0 background.
    levels : int
        Coarsening levels (0: every voxel its own element).
    min_distance : int
        Voxels (>= 1) of one material around a cell before it may coarsen.
    keep_fine : sequence of int
        Material labels kept at voxel size.

    Returns
    -------
    dict
        ``"steps"``: per step, ``"level"``, ``"frame"`` (axes of the template frame, the
        refined axis first in 3D), ``"prior"`` ((dim,) cell size of the step below in
        voxels), ``"mask"`` and ``"state"`` (per 2D cell or 3D block), ``"open"`` (per
        cell: an element or refined, no coarser ancestor), ...; ``"voxels"``: bool array
        of ``labels.shape``, the voxels that are elements.
    """
    dim = labels.ndim
    if dim == 2:
        steps = _steps_2d(labels, levels, min_distance, keep_fine) if levels else []
        open_ = None
        for step in reversed(steps):
            step["open"] = np.ones(step["state"].shape, bool) if open_ is None else open_
            below = labels.shape if step["level"] == 1 else steps[step["level"] - 2]["state"].shape
            open_ = _children(step["open"] & (step["state"] == FINE), below, (0, 1), (3, 3))
        voxels = (labels != 0) if open_ is None else open_ & (labels != 0)
        return {"steps": steps, "voxels": voxels}
    steps = _steps_3d(labels, levels, min_distance, keep_fine) if levels else []
    # open cells, top down: every top cell, then the cells below refined open cells
    open_ = None
    for step in reversed(steps):
        cells = step["cell_plain"].shape
        step["open"] = np.ones(cells, bool) if open_ is None else open_
        frame = step["frame"]
        refined = _children(step["state"] == FINE, cells, frame[1:], (2, 2)) & step["open"]
        open_ = _children(refined, step["below"], frame[:1], (3,))
    voxels = (labels != 0) if open_ is None else open_ & (labels != 0)
    return {"steps": steps, "voxels": voxels}


def _children(parent: np.ndarray, shape: tuple, axes, factors) -> np.ndarray:
    """(shape) bool: the cells below each set cell of ``parent``, ``factors`` per cell along
    ``axes``, cropped to ``shape``."""
    out = parent
    for axis, k in zip(axes, factors):
        out = np.repeat(out, k, axis=axis)
    return out[tuple(slice(0, s) for s in shape)]


_ROWS = 1 << 16
"""Elements per block of the passes over all elements (a block's temporaries stay in the
cache)."""


def _lattice_keys(lattice: np.ndarray, shape: tuple) -> np.ndarray:
    """(N,) int64: C-order index of each lattice point in the (shape + 1) point grid."""
    grid = [s + 1 for s in shape]
    stride = np.array([int(np.prod(grid[d + 1:])) for d in range(len(shape))], np.int64)
    return np.asarray(lattice, np.int64)[:, : len(shape)] @ stride, stride


def _key_type(n: int):
    """The integer type of keys below ``n`` (and of -1 - key): int32 where they fit."""
    return np.int32 if n < 2**31 - 1 else np.int64


def _voxels_of(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The label volume (grid_shape; 2D: (nx, ny)) of a voxel mesh, each element's first
    corner as its key in the point grid (M,) and every node's key (N,) (both of the type
    ``_key_type`` of the point grid); DicerError for any other mesh."""
    dim = mesh.dim
    if mesh.n_cells == 0:
        raise DicerError("the mesh has no elements; nothing to coarsen")
    shape = tuple(int(s) for s in mesh.grid_shape[:dim])
    lattice = np.asarray(mesh.lattice, np.int64)
    # the largest index over all axes first (a reduction along the rows is slow)
    if lattice.shape != (mesh.n_points, 3) or lattice.min() < 0 or (
            lattice.max() > min(shape) and np.any(lattice[:, :dim].max(axis=0) > shape)):
        raise DicerError("node lattice indices lie outside the image grid; remesh from the labels with 'dicer mesh'")
    outside = "element lattice indices lie outside the image grid; remesh from the labels with 'dicer mesh'"
    # every element one voxel, corners in VTK order: each corner's key a fixed step from
    # the first corner's (keys are one-to-one on the point grid)
    grid = tuple(s + 1 for s in shape)
    kind = _key_type(int(np.prod(grid)))
    key, stride = _lattice_keys(lattice, shape)
    key = key.astype(kind)
    corners = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim].astype(np.int64)
    step = (corners @ stride).astype(kind)
    first = np.empty(mesh.n_cells, kind)
    for part in pieces(mesh.n_cells, _ROWS):
        corner = key[mesh.cells[part]]
        first[part] = corner[:, 0]
        corner -= corner[:, :1]
        if not np.array_equal(corner, np.broadcast_to(step, corner.shape)):
            raise DicerError("merge.method=templates needs a voxel mesh (one element per voxel, as 'dicer mesh' "
                             "writes it); this mesh was merged or edited already")
    if int(mesh.material.min()) <= 0:
        if np.any(lattice[mesh.cells[:, 0], :dim] >= np.asarray(shape)):
            raise DicerError(outside)
        raise DicerError("the mesh has material labels <= 0; materials are numbered 1..K")
    # the labels on the point grid, by the first corners' keys; the smallest integer type:
    # the filters of _coarsenable run on it
    on_points = np.zeros(grid, np.min_scalar_type(int(mesh.material.max())))
    on_points.reshape(-1)[first] = mesh.material
    # an element cornered on a far plane of the point grid lies outside the image (its
    # label is > 0 there)
    if any(on_points.take(-1, axis=axis).any() for axis in range(dim)):
        raise DicerError(outside)
    return np.ascontiguousarray(on_points[tuple(slice(0, s) for s in shape)]), first, key


_THIRDS = 3
"""Every template node lies on the grid of thirds of a voxel (template coordinates are
thirds of cells of at least one voxel), so corners are matched as whole numbers of
thirds."""


def _strides(grid) -> np.ndarray:
    """(dim,) int64: C-order strides of a grid of ``grid`` points."""
    return np.array([int(np.prod(grid[d + 1:])) for d in range(len(grid))], np.int64)


def _pool_pairs(a: np.ndarray, axes) -> np.ndarray:
    """any() of ``a`` over pairs of cells along each of ``axes`` (a last odd cell alone)."""
    for axis in axes:
        n = -(-a.shape[axis] // 2)
        pad = [(0, 0)] * a.ndim
        pad[axis] = (0, 2 * n - a.shape[axis])
        a = np.pad(a, pad)
        even, odd = ([slice(None)] * a.ndim for _ in range(2))
        even[axis], odd[axis] = slice(0, None, 2), slice(1, None, 2)
        a = a[tuple(even)] | a[tuple(odd)]
    return a


def _new_elements(decomposition: dict, shape: tuple):
    """The coarse and template elements: a code per corner (M, corners), the corner's key in
    the point grid where it is a voxel corner, else -1 - its key on the grid of thirds of a
    voxel (every template node lies on that grid, ``_THIRDS``); materials and levels."""
    dim = len(shape)
    corners = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim].astype(np.int64)
    per = corners.shape[0]
    _, table = TEMPLATES_2D if dim == 2 else BLOCK_TEMPLATES
    stride = _strides([s + 1 for s in shape])
    fine_stride = _strides([_THIRDS * s + 1 for s in shape])
    kind = _key_type(int(np.prod([_THIRDS * s + 1 for s in shape])))
    parts, materials, levels = [np.zeros((0, per), kind)], [np.zeros(0, np.int64)], [np.zeros(0, np.int8)]

    def emit(index, unit, offsets, material, level):
        # index (k, dim) cells of ``unit`` voxels; offsets (t, per, dim) corners in thirds
        # of a voxel from a cell's origin (a voxel corner): k * t elements
        origin = index.astype(np.int64) * unit
        on_voxel = np.all(offsets % _THIRDS == 0, axis=-1)
        code = (origin @ stride)[:, None, None] + (offsets // _THIRDS) @ stride
        if not on_voxel.all():
            off = (origin * _THIRDS @ fine_stride)[:, None, None] + offsets @ fine_stride
            code = np.where(on_voxel, code, -1 - off)
        parts.append(code.astype(kind).reshape(-1, per))
        materials.append(np.repeat(material, offsets.shape[0]))
        levels.append(np.full(origin.shape[0] * offsets.shape[0], level, np.int8))

    for step in decomposition["steps"]:
        frame, prior = list(step["frame"]), np.asarray(step["prior"], np.int64)
        cell = prior.copy()
        cell[frame[0]] *= 3
        if dim == 2:
            cell[frame[1]] *= 3
            unit, material = cell, step["material"]
            templated = step["open"] & (step["state"] != FINE)
            kinds = np.where(step["state"] == COARSE, -1, step["mask"])
        else:
            # a block is 2 x 2 cells across the axis; a coarse block's cells are emitted
            # one by one (the next step may have taken some of them)
            unit = cell.copy()
            unit[frame[1:]] *= 2
            coarse = np.flatnonzero(step["cell_plain"] & step["open"])
            if coarse.size:
                emit(np.stack(np.unravel_index(coarse, step["cell_plain"].shape), axis=1), cell,
                     (corners * cell * _THIRDS)[None], step["cell_material"].reshape(-1)[coarse], step["level"])
            any_open = _pool_pairs(step["open"], frame[1:])
            templated = any_open & (step["state"] != FINE) & (step["state"] != COARSE)
            kinds = step["mask"]
            material = step["block_material"]
        # the templated cells by kind, each kind's in C order
        rows = np.flatnonzero(templated)
        by_kind = np.argsort(kinds.reshape(-1)[rows], kind="stable")
        rows = rows[by_kind]
        kind_of = kinds.reshape(-1)[rows]
        starts = np.flatnonzero(np.diff(kind_of, prepend=kind_of[:1] - 1)) if rows.size else rows
        index = np.stack(np.unravel_index(rows, templated.shape), axis=1)
        row_material = material.reshape(-1)[rows]
        for start, stop in zip(starts, list(starts[1:]) + [rows.size]):
            m = int(kind_of[start])
            if m < 0:
                offsets = (corners * unit * _THIRDS)[None]
            else:
                local = np.rint(table[m] * _THIRDS).astype(np.int64)  # thirds of cells of the step below
                offsets = np.empty_like(local)
                offsets[..., frame] = local * prior[frame]
            emit(index[start:stop], unit, offsets, row_material[start:stop], step["level"])
    return np.concatenate(parts), np.concatenate(materials), np.concatenate(levels)


def _whole(value) -> bool:
    """An integer, or a float with a whole value (a config's 2.0): not a bool, not 2.5."""
    if isinstance(value, bool):
        return False
    return isinstance(value, (int, np.integer)) or (isinstance(value, (float, np.floating))
                                                     and float(value).is_integer())


def coarsen_mesh(mesh: Mesh, *, levels: int, min_distance: int, keep_fine) -> tuple[Mesh, dict]:
    """A graded mesh of a voxel mesh (see the module notes).

    The graded mesh keeps the voxel mesh's remaining voxels and nodes (in their order),
    adds the coarse and template elements after them and any template node between voxel
    corners after the nodes (lattice -1); cell data ``coarsening_level``. Each material's
    volume and boundary faces are those of the voxel mesh.

    Parameters
    ----------
    mesh : Mesh
        A voxel mesh from :func:`~dicer.mesh.voxel.voxel_mesh` (hexahedra or quads).
    levels : int
        Coarsening levels; elements grow to 3**levels voxels at most (0: unchanged).
    min_distance : int
        Voxels (>= 1) of one material around a cell before it coarsens.
    keep_fine : sequence of int
        Material labels kept at voxel size.

    Returns
    -------
    graded : Mesh
    report : dict
        Elements before and after, per material and level; volumes.
    """
    if not _whole(levels) or levels < 0:
        raise DicerError(f"merge.templates.levels={levels!r}: give a whole number >= 0")
    if not _whole(min_distance) or min_distance < 1:
        raise DicerError(f"merge.templates.min_distance={min_distance!r}: give a whole number of voxels >= 1")
    _check_keep_fine(mesh, keep_fine)
    t0 = time.perf_counter()
    labels, first, key = _voxels_of(mesh)
    decomposition = coarsen_labels(labels, levels=int(levels), min_distance=int(min_distance), keep_fine=keep_fine)
    # the kept voxels on the point grid, read at each element's first corner
    voxels = np.zeros(tuple(s + 1 for s in labels.shape), bool)
    voxels[tuple(slice(0, s) for s in labels.shape)] = decomposition["voxels"]
    keep = voxels.reshape(-1)[first]
    del voxels, first
    code, material, level = _new_elements(decomposition, labels.shape)
    out = _assemble(mesh, keep, code, material.astype(np.int32), level, key)
    report = _report(mesh, out, keep, level, time.perf_counter() - t0, int(levels), int(min_distance), keep_fine)
    log.info("merge: templates, %d levels: %d -> %d elements (%.1f s)", levels, mesh.n_cells, out.n_cells,
             report["seconds"])
    return out, report


def _check_keep_fine(mesh: Mesh, keep_fine) -> None:
    """Warn of ``keep_fine`` labels that no element of the mesh has: they keep nothing fine,
    and a label written for another (3 for bone's 2) lets the meant material coarsen."""
    present = np.flatnonzero(np.bincount(np.asarray(mesh.material).ravel()))  # labels are 1..K: no sort
    absent = sorted(set(int(k) for k in keep_fine) - set(present.tolist()))
    if not absent:
        return
    names = list(mesh.names or ())
    have = [f"{k} {names[k - 1]}" if 0 < k <= len(names) else str(k) for k in present.tolist()]
    log.warning("merge: merge.templates.keep_fine names label(s) %s that no material of the mesh has (its "
                "materials: %s), so they keep nothing at voxel size; give the labels of the materials to keep "
                "fine", brief_names(absent), brief_names(have))


def _node_lookup(key: np.ndarray, n_grid: int):
    """A function from lattice keys (C-order indices in the point grid) to node numbers.

    A dense table when the grid is not much larger than the mesh (one gather), else a
    sorted search; a key with no node maps to -1."""
    if n_grid <= 4 * key.size + (1 << 24):
        kind = np.int32 if key.size < 2**31 else np.int64  # half the table's memory
        table = np.full(n_grid, -1, kind)
        table[key] = np.arange(key.size, dtype=kind)
        return lambda wanted: table[wanted]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]

    def find(wanted):
        pos = np.minimum(np.searchsorted(sorted_key, wanted), max(sorted_key.size - 1, 0))
        return np.where(sorted_key[pos] == wanted, order[pos], -1)
    return find


def _compress_into(mask: np.ndarray, a: np.ndarray, out: np.ndarray) -> None:
    """out[:] = the rows of ``a`` where ``mask`` (no temporary where the types agree)."""
    if a.dtype == out.dtype:
        np.compress(mask, a, axis=0, out=out)
    else:
        out[:] = np.compress(mask, a, axis=0)


def _assemble(mesh: Mesh, keep: np.ndarray, code: np.ndarray, material: np.ndarray, level: np.ndarray,
              key: np.ndarray) -> Mesh:
    """The graded mesh: the kept voxel elements of ``mesh`` and the new elements given by
    their corners' codes (``_new_elements``); ``key``: each node's key in the point grid. A
    new corner on a voxel corner is the voxel mesh's node there (every such corner lies
    inside a solid cell, so the node exists); the others are new nodes, shared by position."""
    dim = mesh.dim
    n_new, per = code.shape
    shape = tuple(int(s) for s in mesh.grid_shape[:dim])
    flat = code.reshape(-1)
    lookup = _node_lookup(key, int(np.prod([s + 1 for s in shape])))
    rows = _ROWS * per
    n_keep = int(np.count_nonzero(keep))
    cells = np.empty((n_keep + n_new, per), np.int64)
    new = cells[n_keep:].reshape(-1)
    # the voxel mesh's nodes on the new corners (their numbers in the voxel mesh for now),
    # in blocks: the temporaries stay small
    used = np.zeros(mesh.n_points, bool)
    for part in pieces(flat.size, rows):
        block, out = flat[part], new[part]
        whole = block >= 0
        found = lookup(block[whole])
        if np.any(found < 0):
            raise DicerError("a coarse element's corner has no node in the voxel mesh; the mesh is not a full voxel "
                             "mesh")
        used[found] = True
        out[whole] = found
    # the new nodes by their keys on the grid of thirds, ascending
    off, inverse = np.unique(-1 - flat[flat < 0].astype(np.int64), return_inverse=True)
    # nodes still used, in the voxel mesh's order, then the new ones
    kept = np.compress(keep, mesh.cells, axis=0)
    used[kept] = True
    number = np.cumsum(used) - 1
    n_old = int(number[-1]) + 1
    n_off = off.shape[0]
    np.take(number, kept, out=cells[:n_keep])
    del kept
    inverse = n_old + inverse.ravel()
    done = 0
    for part in pieces(flat.size, rows):
        whole, out = flat[part] >= 0, new[part]
        out[whole] = number[out[whole]]
        k = done + whole.size - int(np.count_nonzero(whole))
        out[~whole] = inverse[done:k]
        done = k
    del number, inverse
    points = np.empty((n_old + n_off, 3))
    _compress_into(used, mesh.points, points[:n_old])
    lattice = np.full((n_old + n_off, 3), -1, np.int64)
    _compress_into(used, mesh.lattice, lattice[:n_old])
    lattice[n_old:, dim:] = 0
    position = np.zeros((n_off, 3))
    rest = off
    for d, f in enumerate(_strides([_THIRDS * s + 1 for s in shape])):
        position[:, d], rest = np.divmod(rest, int(f))
    position[:, :dim] /= _THIRDS
    points[n_old:] = mesh.origin + position * mesh.spacing
    if dim == 2:
        points[n_old:, 2] = mesh.origin[2]
    material = np.concatenate([np.compress(keep, mesh.material), material]).astype(np.int32)
    level = np.concatenate([np.zeros(int(keep.sum()), np.int8), level])
    return Mesh(points, cells, material, lattice, mesh.spacing.copy(), mesh.origin.copy(), mesh.grid_shape.copy(),
                {}, {LEVEL_DATA: level}, list(mesh.names))


def _report(mesh: Mesh, out: Mesh, keep: np.ndarray, level: np.ndarray, seconds: float, levels: int,
            min_distance: int, keep_fine) -> dict:
    top = int(mesh.material.max()) + 1
    kinds = np.flatnonzero(np.bincount(mesh.material, minlength=top))
    before = np.bincount(mesh.material, minlength=top)
    after = np.bincount(out.material, minlength=top)
    voxel = float(np.prod(mesh.spacing[: mesh.dim]))
    coarse = np.flatnonzero(out.cell_data[LEVEL_DATA] > 0)
    if coarse.size and coarse[-1] - coarse[0] == coarse.size - 1:
        coarse = slice(int(coarse[0]), int(coarse[-1]) + 1)  # the new elements follow the kept voxels: no copies
    vol = np.bincount(out.material[coarse], weights=element_volumes(out.points, out.cells[coarse]),
                      minlength=top).astype(float)
    vol += np.bincount(mesh.material[keep], minlength=top) * voxel
    # in mm: the templates' bound (TEMPLATE_FLOOR) holds on the lattice, i.e. for cubic voxels
    sj = scaled_jacobian(out.points, out.cells[coarse])
    min_sj = float(sj.min()) if sj.size else 1.0
    per_level = {}
    out_level = out.cell_data[LEVEL_DATA]
    for lv in np.unique(out_level):
        counts = np.bincount(out.material[out_level == lv], minlength=top)
        per_level[str(int(lv))] = {str(int(k)): int(counts[k]) for k in kinds if counts[k]}
    return {
        "method": "templates", "levels": levels, "min_distance": min_distance,
        "keep_fine": [int(k) for k in keep_fine],
        "elements_before": mesh.n_cells, "elements_after": out.n_cells,
        "nodes_before": mesh.n_points, "nodes_after": out.n_points,
        "element_ratio": round(mesh.n_cells / max(out.n_cells, 1), 4),
        "elements_by_material": {str(int(k)): {"before": int(before[k]), "after": int(after[k])} for k in kinds},
        "elements_by_level": per_level,
        "volume": {str(int(k)): {"before": float(before[k] * voxel), "after": float(vol[k]),
                                 "change_percent": round(100.0 * (float(vol[k]) - before[k] * voxel)
                                                         / (before[k] * voxel), 6)} for k in kinds},
        "min_scaled_jacobian": round(min_sj, 6),
        "seconds": round(seconds, 3),
    }
