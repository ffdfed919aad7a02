"""Transition templates of graded coarsening: element corners of each template, per pattern
of marked corners, in the cell's own coordinates (``docs/coarsening.md`` draws them).

2D cells are refined by three along both axes at once (``TEMPLATES_2D``): a cell is a
square of side 3 (in cells of the level below) with its four corners marked or not.

3D cells are refined by three along one axis at a time: a cell is a box of 3 x 1 x 1
cells of the step below, (s, u, v) with s along the axis being refined, and its faces
across s are never subdivided. Templates sit on blocks of 2 x 2 such cells across the
axis (``BLOCK_TEMPLATES``), by the marked corners of the block's (u, v) cross-section (a
marked corner is an edge along s split in three). A block face along s shows, by the marks
of its two corners: one quad per cell (neither), three per cell (both), or the 2D edge
template beside the marked corner and one quad (one) -- so two blocks sharing a face
agree on it whatever templates they hold.
"""

from __future__ import annotations

import itertools

import numpy as np

from dicer.mesh.topology import HEX_REVERSED, QUAD_CORNERS, QUAD_REVERSED

COARSE, EDGE, FACE, FINE, INVALID, CORNER, THREE = 0, 1, 2, 3, 4, 5, 6
"""Patterns of a cell's marked corners."""

# 2D edge template (split edge y = 0, cell 0..3): three quads on the split edge, two nodes
# at 2/3 height, one quad up to the coarse edge
_Q = [[(0, 0), (1, 0), (1, 2), (0, 3)], [(1, 0), (2, 0), (2, 2), (1, 2)],
      [(2, 0), (3, 0), (3, 3), (2, 2)], [(1, 2), (2, 2), (3, 3), (0, 3)]]

# 2D corner template (split edges y = 0 and x = 0): a unit square in the corner, two quads
# along the split edges meeting on the diagonal, two up to the coarse edges
_L = [[(0, 0), (1, 0), (1, 1), (0, 1)], [(1, 0), (2, 0), (2, 2), (1, 1)], [(0, 1), (1, 1), (2, 2), (0, 2)],
      [(2, 0), (3, 0), (3, 3), (2, 2)], [(0, 2), (2, 2), (3, 3), (0, 3)]]

# 3D edge template (split edge along x at y = z = 0, cell 0..3): the 2D edge template on
# both faces that hold the edge, joined through the inner face (1,2,2) (2,2,2) (3,3,3) (0,3,3)
_E = [[(0, 0, 0), (1, 0, 0), (1, 2, 0), (0, 3, 0), (0, 0, 3), (1, 0, 2), (1, 2, 2), (0, 3, 3)],
      [(1, 0, 0), (2, 0, 0), (2, 2, 0), (1, 2, 0), (1, 0, 2), (2, 0, 2), (2, 2, 2), (1, 2, 2)],
      [(2, 0, 0), (3, 0, 0), (3, 3, 0), (2, 2, 0), (2, 0, 2), (3, 0, 3), (3, 3, 3), (2, 2, 2)],
      [(1, 2, 0), (2, 2, 0), (3, 3, 0), (0, 3, 0), (1, 2, 2), (2, 2, 2), (3, 3, 3), (0, 3, 3)],
      [(1, 0, 2), (2, 0, 2), (3, 0, 3), (0, 0, 3), (1, 2, 2), (2, 2, 2), (3, 3, 3), (0, 3, 3)]]


def oriented(cells: np.ndarray) -> np.ndarray:
    """Template elements with corners reordered where a reflection turned them inside out.

    Parameters
    ----------
    cells : (n, corners, dim) ndarray
        Corner positions of each template element.

    Returns
    -------
    (n, corners, dim) ndarray
        VTK order: positive volume.
    """
    x = np.asarray(cells, float)
    if x.shape[-1] == 3:
        a, b, c = x[:, 1] - x[:, 0], x[:, 3] - x[:, 0], x[:, 4] - x[:, 0]
        flip = np.einsum("ij,ij->i", a, np.cross(b, c)) < 0
        order = HEX_REVERSED
    else:
        a, b = x[:, 1] - x[:, 0], x[:, 3] - x[:, 0]
        flip = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] < 0
        order = QUAD_REVERSED
    out = x.copy()
    out[flip] = x[flip][:, order]
    return out


def completion(pattern: np.ndarray) -> np.ndarray:
    """For every corner mask, the valid mask that adds the fewest marks to it.

    Ties go to the smallest mask, so a cell in an invalid pattern gains as few marks as it
    must.

    Parameters
    ----------
    pattern : ndarray
        Per corner mask, the template it selects (``INVALID`` for none).

    Returns
    -------
    int ndarray
        The completed mask per corner mask.
    """
    n = pattern.size
    valid = np.flatnonzero(pattern != INVALID)
    out = np.arange(n)
    for mask in np.flatnonzero(pattern == INVALID):
        supersets = valid[(valid & mask) == mask]
        added = np.array([bin(int(v)).count("1") for v in supersets])
        out[mask] = supersets[np.argmin(added)]  # supersets ascend: ties take the smallest
    return out


# ---- 2D: both axes at once ------------------------------------------------------------

def _table_2d() -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Per corner mask of a square cell (bit c: QUAD_CORNERS[c] marked): its pattern, and
    the quads of every template in thirds of the cell, (n, 4, 2) float64."""
    corners = QUAD_CORNERS[:, :2] * 3
    fine = np.array([[c + o for o in corners // 3] for c in itertools.product(range(3), repeat=2)], float)
    pattern = np.full(16, INVALID, np.int8)
    pattern[0], pattern[15] = COARSE, FINE
    table = {15: fine}
    index = {tuple(c): i for i, c in enumerate(corners)}
    for kind, marks, cells in ((EDGE, [(0, 0), (3, 0)], _Q), (CORNER, [(0, 0), (3, 0), (0, 3)], _L)):
        cells = np.asarray(cells, float)
        for perm in itertools.permutations(range(2)):
            for flips in itertools.product((0, 1), repeat=2):
                def move(p, perm=perm, flips=flips):
                    q = np.asarray(p, float)[..., list(perm)]
                    return np.where(np.array(flips, bool), 3 - q, q)
                mask = sum(1 << index[tuple(int(v) for v in move(m))] for m in marks)
                if mask not in table:
                    table[mask] = oriented(move(cells))
                    pattern[mask] = kind
    # marked corners with no split edge (two on a diagonal, one alone): no face is split
    edges = [(a, (a + 1) % 4) for a in range(4)]
    for mask in range(16):
        if pattern[mask] == INVALID and not any(mask >> a & 1 and mask >> b & 1 for a, b in edges):
            pattern[mask] = COARSE
    return pattern, table


TEMPLATES_2D = _table_2d()
"""(pattern per corner mask, quads per mask) of 2D cells."""

# ---- 3D: one axis at a time -----------------------------------------------------------

SECTION = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])
"""Corner offsets of a cell's cross-section on its grid of corners (block corners: BLOCK / 2)."""

# one marked corner (0, 0): the 3D edge template squeezed to one cell across
_AXIS_EDGE = [[(s, u / 3, v / 3) for s, u, v in hexa] for hexa in _E]

# corners (0, 0) and (1, 0) marked (face v = 0 split): the 2D edge template in (s, v)
# through the cell along u
_AXIS_FACE = [[(s, u, h / 3) for u in (0, 1) for s, h in quad] for quad in _Q]

_BOX = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))


def _pixel(cells, u: int, v: int) -> list:
    """Template elements of one pixel (s, u..u+1, v..v+1) of a block."""
    return [[(s, u + a, v + b) for s, a, b in hexa] for hexa in cells]


def _coarse_pixel(u: int, v: int) -> list:
    return [[(3 * s, u + a, v + b) for s, a, b in _BOX]]


def _fine_pixel(u: int, v: int) -> list:
    return [[(k + s, u + a, v + b) for s, a, b in _BOX] for k in range(3)]


_C = 2 / 3
"""Inner nodes of the three-corner template: P_k = (k, 2/3, 2/3), k = 1, 2 (smallest scaled
Jacobian 0.30, 0.23 and 0.35 in the step shapes 1 x 1, 3 x 1 and 3 x 3 across)."""


def _block_three() -> list:
    """The three-corner template: block corners (0, 0), (2, 0), (0, 2) marked (faces u = 0
    and v = 0 split), the centre and far corner not. The split faces' columns run in through
    the three marked pixels to the inner nodes P_k; two hexahedra across the whole cell
    (through the far faces' edge-template nodes f_k, g_k) carry the turned layer round the
    unsplit centre edge; the fourth pixel stays one hexahedron: 12 hexahedra."""
    p = {k: (k, _C, _C) for k in (1, 2)}
    f = {k: (k, 2, 2 / 3) for k in (1, 2)}  # edge template nodes on the far face u = 2
    g = {k: (k, 2 / 3, 2) for k in (1, 2)}  # and on v = 2
    out = [[(1, 0, 0), (1, 1, 0), p[1], (1, 0, 1), (2, 0, 0), (2, 1, 0), p[2], (2, 0, 1)],
           [(1, 1, 0), (1, 2, 0), f[1], p[1], (2, 1, 0), (2, 2, 0), f[2], p[2]],
           [(1, 0, 1), p[1], g[1], (1, 0, 2), (2, 0, 1), p[2], g[2], (2, 0, 2)],
           [(0, 1, 1), (0, 2, 1), (0, 2, 2), (0, 1, 2), (3, 1, 1), (3, 2, 1), (3, 2, 2), (3, 1, 2)],
           [p[1], f[1], (0, 2, 1), (0, 1, 1), p[2], f[2], (3, 2, 1), (3, 1, 1)],
           [p[1], g[1], (0, 1, 2), (0, 1, 1), p[2], g[2], (3, 1, 2), (3, 1, 1)]]
    # the two ends: from the end face's four squares in to the nearer inner plane
    for end, k in ((0, 1), (3, 2)):
        out += [[(end, 0, 0), (end, 1, 0), (end, 1, 1), (end, 0, 1), (k, 0, 0), (k, 1, 0), p[k], (k, 0, 1)],
                [(end, 1, 0), (end, 2, 0), (end, 2, 1), (end, 1, 1), (k, 1, 0), (k, 2, 0), f[k], p[k]],
                [(end, 0, 1), (end, 1, 1), (end, 1, 2), (end, 0, 2), (k, 0, 1), p[k], g[k], (k, 0, 2)]]
    return out


BLOCK = np.array([[0, 0], [2, 0], [2, 2], [0, 2]])
"""The (u, v) corners of a block's cross-section (2 x 2 one-axis cells), bit c of a mask
for corner c."""


def _table_blocks() -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Per block mask: its pattern and the hexahedra of its template in (s, u, v) (s in
    0..3, u and v in 0..2 cells of the step below), (n, 8, 3) float64. A block face along s
    holds two cell faces: one quad each (no mark), three each (both marks), or the 2D edge
    template beside the marked corner and one quad (one mark)."""
    coarse = [h for u in (0, 1) for v in (0, 1) for h in _coarse_pixel(u, v)]
    canonical = [
        (EDGE, [(0, 0)], _pixel(_AXIS_EDGE, 0, 0) + [h for u, v in ((1, 0), (0, 1), (1, 1))
                                                      for h in _coarse_pixel(u, v)]),
        (FACE, [(0, 0), (2, 0)], _pixel(_AXIS_FACE, 0, 0) + _pixel(_AXIS_FACE, 1, 0)
         + _coarse_pixel(0, 1) + _coarse_pixel(1, 1)),
        (THREE, [(0, 0), (2, 0), (0, 2)], _block_three()),
    ]
    pattern = np.full(16, INVALID, np.int8)
    pattern[0], pattern[15] = COARSE, FINE
    table = {0: np.array(coarse, float),
             15: np.array([h for u in (0, 1) for v in (0, 1) for h in _fine_pixel(u, v)], float)}
    index = {tuple(c): i for i, c in enumerate(BLOCK)}
    for kind, marks, cells in canonical:
        cells = np.asarray(cells, float)
        for swap, fu, fv in itertools.product((0, 1), repeat=3):
            def move(p, swap=swap, fu=fu, fv=fv):
                q = np.asarray(p, float)
                u, v = (q[..., 2], q[..., 1]) if swap else (q[..., 1], q[..., 2])
                u = 2 - u if fu else u
                v = 2 - v if fv else v
                return np.stack([q[..., 0], u, v], axis=-1)
            mask = sum(1 << index[tuple(int(round(c)) for c in move((0, *m))[1:])] for m in marks)
            if mask not in table:
                table[mask] = oriented(move(cells))
                pattern[mask] = kind
    return pattern, table


BLOCK_TEMPLATES = _table_blocks()
"""(pattern per block mask, hexahedra per mask) of 3D one-axis blocks; two marks on a
diagonal are INVALID (completed to three)."""

COMPLETION_2D = completion(TEMPLATES_2D[0])
COMPLETION_BLOCK = completion(BLOCK_TEMPLATES[0])
