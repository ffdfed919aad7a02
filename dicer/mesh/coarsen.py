"""Graded all-hexahedral (2D: all-quad) meshes by 3-refinement transition templates.

A voxel mesh keeps one element per voxel everywhere. Here the elements stay one voxel
wherever a material boundary or interface is near and grow by a factor of three per
level away from it (3 x 3 x 3 voxels at level 1, 9 x 9 x 9 at level 2, ...), joined by
conforming transition templates: no hanging node, every interior face shared by exactly
two elements, every node on an integer voxel corner. ``docs/coarsening.md`` gives the
construction and the quality bound of each template.

Cells of level l are cubes of 3**l voxels aligned with the image's first voxel. Corners
of the level-l cell grid are *marked* when a cell that must stay refined holds them.
An edge of a cell is *split* (into three) when both its ends are marked; a face's
pattern follows from its split edges, so two cells sharing a face agree on it. A cell
that may coarsen takes, by its marked corners:

* no split edge: one element (a coarse cell);
* one split edge: the edge template (5 hexahedra; 2D: 4 quads);
* the four edges of one face split: the face template (13 hexahedra; 3D only);
* every corner marked: refinement into its 27 (2D: 9) cells of the level below;
* anything else: every corner is marked too, and the marking repeats until no cell is
  left in another pattern (node marking to valid patterns, as in Schneiders' method).

A cell may coarsen at level 1 when its voxels and every voxel within ``min_distance``
of it (inside the image) hold one material; at level l > 1 when none of the level-(l-1)
corners in it, its boundary included, is marked. So elements touching a boundary or
interface node are always voxels, and the node classes and smoothing apply unchanged.
"""

from __future__ import annotations

import itertools
import logging
import time

import numpy as np
from scipy import ndimage

from dicer.errors import DicerError
from dicer.mesh.merge import _lattice_boxes
from dicer.mesh.metrics import element_volumes
from dicer.mesh.model import LEVEL_DATA, Mesh
from dicer.mesh.topology import HEX_CORNERS, HEX_REVERSED, QUAD_CORNERS, QUAD_REVERSED

__all__ = ["coarsen_mesh", "coarsen_labels", "TEMPLATES", "LEVEL_DATA"]

log = logging.getLogger("dicer")

COARSE, EDGE, FACE, FINE, INVALID, CORNER, TWO_FACES = 0, 1, 2, 3, 4, 5, 6
"""Patterns of a cell's marked corners."""

# canonical templates in thirds of the cell (coordinates 0..3), corners in VTK order

# 2D edge template (split edge y = 0): three quads on the split edge, two nodes at 2/3
# height, one quad up to the coarse edge
_Q = [[(0, 0), (1, 0), (1, 2), (0, 3)], [(1, 0), (2, 0), (2, 2), (1, 2)],
      [(2, 0), (3, 0), (3, 3), (2, 2)], [(1, 2), (2, 2), (3, 3), (0, 3)]]

# 3D edge template (split edge along x at y = z = 0): the 2D edge template on both faces
# that hold the edge, joined through the inner face (1,2,2) (2,2,2) (3,3,3) (0,3,3)
_E = [[(0, 0, 0), (1, 0, 0), (1, 2, 0), (0, 3, 0), (0, 0, 3), (1, 0, 2), (1, 2, 2), (0, 3, 3)],
      [(1, 0, 0), (2, 0, 0), (2, 2, 0), (1, 2, 0), (1, 0, 2), (2, 0, 2), (2, 2, 2), (1, 2, 2)],
      [(2, 0, 0), (3, 0, 0), (3, 3, 0), (2, 2, 0), (2, 0, 2), (3, 0, 3), (3, 3, 3), (2, 2, 2)],
      [(1, 2, 0), (2, 2, 0), (3, 3, 0), (0, 3, 0), (1, 2, 2), (2, 2, 2), (3, 3, 3), (0, 3, 3)],
      [(1, 0, 2), (2, 0, 2), (3, 0, 3), (0, 0, 3), (1, 2, 2), (2, 2, 2), (3, 3, 3), (0, 3, 3)]]


def _face_template() -> list:
    """The 3D face template (refined face z = 0): the 2D edge template in (y, z), each of
    its three lower quads swept along x through the 2D edge template in (x, height), the
    top quad swept straight (3 x 4 + 1 = 13 hexahedra)."""
    # each lower quad of the (y, z) template at the sweep's side s (0, 1) and level
    # (0: on the refined face, "m": the template's middle nodes, 1: its top edge)
    quads = [{(0, 0): (0, 0), (1, 0): (1, 0), (0, "m"): (0, 2), (1, "m"): (1, 1), (0, 1): (0, 3), (1, 1): (1, 2)},
             {(0, 0): (1, 0), (1, 0): (2, 0), (0, "m"): (1, 1), (1, "m"): (2, 1), (0, 1): (1, 2), (1, 1): (2, 2)},
             {(0, 0): (2, 0), (1, 0): (3, 0), (0, "m"): (2, 1), (1, "m"): (3, 2), (0, 1): (2, 2), (1, 1): (3, 3)}]
    # the 2D edge template in (x, level)
    sweep = [[(0, 0), (1, 0), (1, "m"), (0, 1)], [(1, 0), (2, 0), (2, "m"), (1, "m")],
             [(2, 0), (3, 0), (3, 1), (2, "m")], [(1, "m"), (2, "m"), (3, 1), (0, 1)]]
    out = [[(x, *quad[(s, level)]) for s in (0, 1) for x, level in cell] for quad in quads for cell in sweep]
    out.append([(0, 1, 2), (0, 2, 2), (0, 3, 3), (0, 0, 3), (3, 1, 2), (3, 2, 2), (3, 3, 3), (3, 0, 3)])
    return out


# The 3D faces with two split edges at a corner (faces of the two-face template) carry
# this pattern: nine quads, mirror-symmetric about the diagonal through the refined corner
# (0, 0), so both cells sharing such a face see the same quads. Its quad count is odd,
# as a three-face template (27 + 3 x 9 boundary quads) needs. From each node of the split
# edges a rung runs inward: from the corner diagonally to D, from (1, 0) to R1, from (2, 0)
# to R2, from (3, 0) along the whole coarse edge to (3, 3); three quads around M fill the
# middle. The positions maximise the smallest scaled Jacobian of the two-face template.
_D, _R1, _R2, _M = (7 / 6, 7 / 6), (4 / 3, 13 / 12), (5 / 3, 7 / 6), (5 / 4, 5 / 4)
_S1, _S2 = _R1[::-1], _R2[::-1]
_L_RUNGS_U = [((0, 0), (1, 0), _R1, _D), ((1, 0), (2, 0), _R2, _R1), ((2, 0), (3, 0), (3, 3), _R2)]
_L_RUNGS_T = [((0, 1), (0, 0), _D, _S1), ((0, 2), (0, 1), _S1, _S2), ((0, 3), (0, 2), _S2, (3, 3))]
_L_MIDDLE = [(_D, _R1, _R2, _M), (_M, _R2, (3, 3), _S2), (_D, _M, _S2, _S1)]


def _two_face_template() -> list:
    """The 3D two-face template (refined faces x = 0 and z = 0): the nine-quad corner
    pattern in (x, z) swept along y. A quad with an edge on the refined faces becomes the
    2D edge template in (y, rung): four hexahedra whose middle nodes sit 2/3 along its
    rungs; a middle quad becomes one hexahedron (6 x 4 + 3 = 27)."""
    def at(p, y):
        return (p[0], y, p[1])

    out = []
    for p0, p1, q1, q0 in _L_RUNGS_U + _L_RUNGS_T:
        for cell in _Q:
            out.append([at(tuple(a + (b - a) * t / 3 for a, b in zip(*side)), y)
                        for side in ((p0, q0), (p1, q1)) for y, t in cell])
    for quad in _L_MIDDLE:
        out.append([at(p, y) for y in (0, 3) for p in quad])
    return out


def _oriented(cells: np.ndarray, dim: int) -> np.ndarray:
    """Template elements (n, corners, dim) with corners reordered where a reflection
    turned them inside out."""
    x = np.asarray(cells, float)
    if dim == 3:
        a, b, c = x[:, 1] - x[:, 0], x[:, 3] - x[:, 0], x[:, 4] - x[:, 0]
        flip = np.einsum("ij,ij->i", a, np.cross(b, c)) < 0
        order = HEX_REVERSED
    else:
        a, b = x[:, 1] - x[:, 0], x[:, 3] - x[:, 0]
        flip = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] < 0
        order = QUAD_REVERSED
    out = cells.copy()
    out[flip] = cells[flip][:, order]
    return out


_L = [[(0, 0), (1, 0), (1, 1), (0, 1)], [(1, 0), (2, 0), (2, 2), (1, 1)], [(0, 1), (1, 1), (2, 2), (0, 2)],
      [(2, 0), (3, 0), (3, 3), (2, 2)], [(0, 2), (2, 2), (3, 3), (0, 3)]]
"""2D corner template (split edges y = 0 and x = 0): a unit square in the corner, two quads
along the split edges meeting on the diagonal, two up to the coarse edges."""


def _canonical(dim: int) -> list:
    """(pattern, marked corners in thirds, elements) of every template of dimension ``dim``."""
    if dim == 2:
        return [(EDGE, [(0, 0), (3, 0)], _Q), (CORNER, [(0, 0), (3, 0), (0, 3)], _L)]
    corners = [tuple(c) for c in itertools.product((0, 3), repeat=3)]
    return [(EDGE, [(0, 0, 0), (3, 0, 0)], _E),
            (FACE, [c for c in corners if c[2] == 0], _face_template()),
            (TWO_FACES, [c for c in corners if c[0] == 0 or c[2] == 0], _two_face_template())]


def _template_table(dim: int) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Per corner-mask (bit c: corner c marked): its pattern, and the elements of every
    template, in thirds of the cell, (n, corners, dim) float64."""
    corners = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim] * 3
    n_corners = len(corners)
    fine = np.array([[c + o for o in corners // 3] for c in itertools.product(range(3), repeat=dim)], float)
    pattern = np.full(1 << n_corners, INVALID, np.int8)
    pattern[0] = COARSE
    pattern[(1 << n_corners) - 1] = FINE
    table = {(1 << n_corners) - 1: fine}
    index = {tuple(c): i for i, c in enumerate(corners)}
    for kind, marks, cells in _canonical(dim):
        cells = np.asarray(cells, float)
        for perm in itertools.permutations(range(dim)):
            for flips in itertools.product((0, 1), repeat=dim):
                def move(p, perm=perm, flips=flips):
                    q = np.asarray(p, float)[..., list(perm)]
                    return np.where(np.array(flips, bool), 3 - q, q)
                mask = 0
                for m in marks:
                    mask |= 1 << index[tuple(int(v) for v in move(m))]
                if mask not in table:
                    table[mask] = _oriented(move(cells), dim)
                    pattern[mask] = kind
    # a cell with marked corners but no split edge stays coarse: no face of it is split
    edges = [(a, b) for a in range(n_corners) for b in range(a + 1, n_corners)
             if np.abs(corners[a] - corners[b]).sum() == 3]
    for mask in range(1 << n_corners):
        if pattern[mask] == INVALID and not any(mask >> a & 1 and mask >> b & 1 for a, b in edges):
            pattern[mask] = COARSE
    return pattern, table


TEMPLATES = {3: _template_table(3), 2: _template_table(2)}
"""dim -> (pattern per corner mask, elements per mask)."""



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


def _corner_slices(dim: int, shape: tuple) -> list:
    """Per corner c (VTK order): the slice of the (n + 1)-point node grid of cells ``shape``
    that holds corner c of every cell."""
    corners = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim]
    return [tuple(slice(o, o + n) for o, n in zip(c, shape)) for c in corners]


def _completion(pattern: np.ndarray) -> np.ndarray:
    """Per corner mask: the valid mask that adds the fewest marks to it (ties: the smallest
    mask), so an invalid cell gains as few marks as it must."""
    n = pattern.size
    valid = np.flatnonzero(pattern != INVALID)
    out = np.arange(n)
    for mask in np.flatnonzero(pattern == INVALID):
        supersets = valid[(valid & mask) == mask]
        added = np.array([bin(int(v)).count("1") for v in supersets])
        out[mask] = supersets[np.argmin(added)]  # supersets ascend: ties take the smallest
    return out


def _close(candidate: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Mark the corners of every refined cell, then add the fewest marks that bring each
    cell left in an invalid pattern to a valid one, until none is left. Returns the node
    marks and each cell's corner mask."""
    pattern, _ = TEMPLATES[dim]
    complete = COMPLETION[dim]
    shape = candidate.shape
    slices = _corner_slices(dim, shape)
    marked = np.zeros(tuple(n + 1 for n in shape), bool)
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


COMPLETION = {dim: _completion(TEMPLATES[dim][0]) for dim in (2, 3)}
"""dim -> per corner mask, the valid mask an invalid cell is completed to."""


def _level_one(labels: np.ndarray, dim: int, min_distance: int, keep_fine) -> tuple[np.ndarray, np.ndarray]:
    """Candidates and materials of the level-1 cells: one material in the cell and within
    ``min_distance`` voxels of it, inside the image, not a material kept fine."""
    n = tuple(-(-s // 3) for s in labels.shape)
    size = 3 + 2 * min_distance
    lo = ndimage.minimum_filter(labels, size=size, mode="constant", cval=0)
    hi = ndimage.maximum_filter(labels, size=size, mode="constant", cval=0)
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
    """Candidates and materials of the next level's cells: 27 (2D: 9) candidate children of
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


def coarsen_labels(labels: np.ndarray, levels: int = 1, min_distance: int = 1, keep_fine=()) -> dict:
    """The graded decomposition of a label volume: which cells of which level are elements.

    labels : (nx, ny, nz) or (nx, ny) integer array, 0 = background.
    levels : coarsening levels (0: every voxel its own element).
    min_distance : voxels (>= 1) of one material around a level-1 cell before it may coarsen.
    keep_fine : material labels kept at voxel size.
    Returns {"levels": [per level l = 1..: {"mask": corner masks (cells), "state": pattern
    per cell, "material": (cells) int64, "open": (cells) bool, cells that are elements or
    refined (no coarser ancestor)}], "voxels": (nx, ny, nz) bool, voxels that are elements}.
    """
    dim = labels.ndim
    pattern, _ = TEMPLATES[dim]
    per_level = []
    candidate = material = marked = None
    for level in range(1, levels + 1):
        if level == 1:
            candidate, material = _level_one(labels, dim, min_distance, keep_fine)
        else:
            candidate, material = _next_level(marked, candidate, material, dim)
        marked, mask = _close(candidate, dim)
        state = np.where(candidate, pattern[mask], FINE)
        per_level.append({"mask": mask, "state": state, "material": material})
        if not candidate.any():
            break
    # open cells, top down: every top-level cell, then the children of refined open cells
    open_ = None
    for entry in reversed(per_level):
        shape = entry["state"].shape
        if open_ is None:
            entry["open"] = np.ones(shape, bool)
        else:
            entry["open"] = _children(open_, shape)
        open_ = entry["open"] & (entry["state"] == FINE)
    if open_ is None:
        voxels = labels != 0
    else:
        voxels = _children(open_, labels.shape) & (labels != 0)
    return {"levels": per_level, "voxels": voxels}


def _children(parent: np.ndarray, shape: tuple) -> np.ndarray:
    """(shape) bool: cells of the level below whose parent is set in ``parent``."""
    out = parent
    for axis in range(parent.ndim):
        out = np.repeat(out, 3, axis=axis)
    return out[tuple(slice(0, s) for s in shape)]


_ROWS = 1 << 20
"""Elements per block of the passes over all elements (a block's temporaries stay small)."""


def _lattice_keys(lattice: np.ndarray, shape: tuple) -> np.ndarray:
    """(N,) int64: C-order index of each lattice point in the (shape + 1) point grid."""
    grid = [s + 1 for s in shape]
    stride = np.array([int(np.prod(grid[d + 1:])) for d in range(len(shape))], np.int64)
    return np.asarray(lattice, np.int64)[:, : len(shape)] @ stride, stride


def _voxels_of(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The label volume (grid_shape; 2D: (nx, ny)) of a voxel mesh and each element's
    voxel (M, dim); DicerError for any other mesh."""
    dim = mesh.dim
    if mesh.n_cells == 0:
        raise DicerError("the mesh has no elements; nothing to coarsen")
    shape = tuple(int(s) for s in mesh.grid_shape[:dim])
    lattice = np.asarray(mesh.lattice, np.int64)
    if lattice.shape != (mesh.n_points, 3) or lattice.min() < 0 or np.any(lattice[:, :dim].max(axis=0) > shape):
        raise DicerError("node lattice indices lie outside the image grid; remesh from the labels with 'dicer mesh'")
    # every element a lattice box (the test plane merging uses) of one voxel
    box, size = _lattice_boxes(mesh.cells, lattice, dim)
    if not (box.all() and np.all(size == 1)):
        raise DicerError("merge.method=templates needs a voxel mesh (one element per voxel, as 'dicer mesh' "
                         "writes it); this mesh was merged or edited already")
    first = lattice[mesh.cells[:, 0], :dim]
    if np.any(first >= np.asarray(shape)):
        raise DicerError("element lattice indices lie outside the image grid; remesh from the labels with 'dicer mesh'")
    if int(mesh.material.min()) <= 0:
        raise DicerError("the mesh has material labels <= 0; materials are numbered 1..K")
    labels = np.zeros(shape, np.int64)
    labels[tuple(first.T)] = mesh.material
    return labels, first


def _new_elements(decomposition: dict, dim: int):
    """The coarse and template elements: corners (M, corners, dim) float64 in voxel units,
    materials and levels."""
    _, table = TEMPLATES[dim]
    corners = (HEX_CORNERS if dim == 3 else QUAD_CORNERS)[:, :dim]
    per = corners.shape[0]
    parts, materials, levels = [np.zeros((0, per, dim))], [np.zeros(0, np.int64)], [np.zeros(0, np.int8)]
    for level, entry in enumerate(decomposition["levels"], start=1):
        size = 3 ** level
        state, mask, open_ = entry["state"], entry["mask"], entry["open"]
        emit = open_ & (state != FINE)
        if not emit.any():
            continue
        # one coarse element for a cell without split edge, else its template
        kind_mask = np.where(state == COARSE, 0, mask)
        for m in np.unique(kind_mask[emit]):
            rows = emit & (kind_mask == m)
            origin = np.argwhere(rows) * size
            shape = corners[None] * 3.0 if m == 0 else table[int(m)]  # thirds of the cell
            cells = origin[:, None, None, :] + shape[None] * (size / 3)
            parts.append(cells.reshape(-1, per, dim))
            mat = entry["material"][rows]
            materials.append(np.repeat(mat, shape.shape[0]))
            levels.append(np.full(mat.size * shape.shape[0], level, np.int8))
    return np.concatenate(parts), np.concatenate(materials), np.concatenate(levels)


def coarsen_mesh(mesh: Mesh, levels: int = 1, min_distance: int = 1, keep_fine=()) -> tuple[Mesh, dict]:
    """A graded mesh of the voxel mesh ``mesh`` (see the module notes).

    mesh : voxel mesh from ``voxel_mesh`` (hexahedra or quads).
    levels : coarsening levels; elements grow to 3**levels voxels at most (0: unchanged).
    min_distance : voxels (>= 1) of one material around a cell before it coarsens.
    keep_fine : material labels kept at voxel size.
    Returns the graded mesh and a report (elements before and after, per material and
    level; volumes). The graded mesh keeps the voxel mesh's remaining voxels and nodes (in
    their order), adds the coarse and template elements after them and any template node
    between voxel corners after the nodes (lattice -1); cell data ``coarsening_level``.
    Each material's volume and boundary faces are those of the voxel mesh.
    """
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 0:
        raise DicerError(f"merge.templates.levels={levels!r}: give a whole number >= 0")
    if isinstance(min_distance, bool) or not isinstance(min_distance, (int, np.integer)) or min_distance < 1:
        raise DicerError(f"merge.templates.min_distance={min_distance!r}: give a whole number of voxels >= 1")
    t0 = time.perf_counter()
    labels, first = _voxels_of(mesh)
    decomposition = coarsen_labels(labels, int(levels), int(min_distance), keep_fine)
    keep = decomposition["voxels"][tuple(first.T)]
    corner_points, material, level = _new_elements(decomposition, mesh.dim)
    out = _assemble(mesh, keep, corner_points, material.astype(np.int32), level)
    report = _report(mesh, out, keep, level, time.perf_counter() - t0, int(levels), int(min_distance), keep_fine)
    log.info("merge: templates, %d levels: %d -> %d elements (%.1f s)", levels, mesh.n_cells, out.n_cells,
             report["seconds"])
    return out, report


_KEY = float(1 << 20)
"""Template nodes between voxel corners are matched on a grid of 2**-20 voxel (they are
rationals with small denominators; the same node computed from two templates agrees to
far better than that)."""


def _assemble(mesh: Mesh, keep: np.ndarray, corner_points: np.ndarray, material: np.ndarray,
              level: np.ndarray) -> Mesh:
    """The graded mesh: the kept voxel elements of ``mesh`` and the new elements given by
    their corners (voxel units). A new corner on a voxel corner is the voxel mesh's node
    there (every such corner lies inside a solid cell, so the node exists); the others are
    new nodes, shared by position."""
    dim = mesh.dim
    n_new, per = corner_points.shape[:2]
    shape = tuple(int(s) for s in mesh.grid_shape[:dim])
    key, stride = _lattice_keys(mesh.lattice, shape)
    order = None if np.all(key[1:] > key[:-1]) else np.argsort(key, kind="stable")
    sorted_key = key if order is None else key[order]
    flat = corner_points.reshape(-1, dim)
    whole = np.all(flat == np.round(flat), axis=1)
    ids = np.empty(flat.shape[0], np.int64)
    wanted = np.round(flat[whole]).astype(np.int64) @ stride
    pos = np.searchsorted(sorted_key, wanted)
    if np.any(pos >= sorted_key.size) or np.any(sorted_key[np.minimum(pos, sorted_key.size - 1)] != wanted):
        raise DicerError("a coarse element's corner has no node in the voxel mesh; the mesh is not a full voxel mesh")
    ids[whole] = pos if order is None else order[pos]
    off, inverse = np.unique(np.round(flat[~whole] * _KEY).astype(np.int64), axis=0, return_inverse=True)
    ids[~whole] = mesh.n_points + inverse.ravel()
    cells = np.concatenate([np.compress(keep, mesh.cells, axis=0), ids.reshape(n_new, per)])
    # nodes still used, in the voxel mesh's order, then the new ones
    used = np.zeros(mesh.n_points + off.shape[0], bool)
    for start in range(0, cells.shape[0], _ROWS):
        used[cells[start : start + _ROWS]] = True
    number = np.cumsum(used) - 1
    cells = number[cells]
    n_old = int(used[: mesh.n_points].sum())
    n_off = off.shape[0]
    points = np.empty((n_old + n_off, 3))
    points[:n_old] = np.compress(used[: mesh.n_points], mesh.points, axis=0)
    lattice = np.full((n_old + n_off, 3), -1, np.int64)
    lattice[:n_old] = np.compress(used[: mesh.n_points], mesh.lattice, axis=0)
    lattice[n_old:, dim:] = 0
    position = np.zeros((n_off, 3))
    position[:, :dim] = off / _KEY
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
    vol = np.bincount(out.material[coarse], weights=element_volumes(out.points, out.cells[coarse]),
                      minlength=top).astype(float)
    vol += np.bincount(mesh.material[keep], minlength=top) * voxel
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
        "seconds": round(seconds, 3),
    }
