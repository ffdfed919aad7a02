"""The labels' staircase relaxed to its smoothest surface within the voxels (a constrained surface net).

A label image says, for each voxel centre, which kind lies there; the surface between two
kinds passes somewhere between the centres. Each vertex of the staircase between two kinds
(a lattice corner of the voxels' faces between them) may therefore move within its dual
cell, half a voxel along each axis, and the staircase is relaxed to the surface whose
curvature varies least there (a fair surface): with L the umbrella operator of the
staircase's quad mesh (x_v less the mean of x over v's neighbours along its edges, about
the curvature normal at v), the vertices x minimise

    |L L x|^2 + lam |x - x0|^2

within their cells (lam a small pull to the corner, so that every vertex has one
minimiser). Constant curvature costs nothing, so a digitised circle or sphere relaxes to a
circle or sphere within its cells. The umbrella energy |L x|^2 (the staircase's bending),
used until late on 6 December 2026, is least for the longest, flattest curve the cells allow: it
straightened the flat runs of a circle's staircase at its poles, so the Kirsch plate's hole
read 8 % low from labels (docs/validation.md §4). The three axes are independent problems
(a cell is a box), each solved by projected gradient steps with Nesterov's momentum (FISTA),
a fixed number of them, so the result depends on the labels only.

Without a scan's places, each connected sheet of the relaxed staircase is then moved along its
normals to sweep no volume from the corners (:func:`_volume_kept`): the fairing draws small
parts in. A vertex where three or more kinds meet stays on its corner, and a vertex on the
image's edge stays in that plane. The relaxed vertices, with their normals (the faces around them)
and areas, are the samples ``dicer.mesh.labelsurface`` fits its quadrics to instead of the
faces' centres (``smooth.label_samples: relaxed``): on a circle of radius 7 voxels the
curvature of the relaxed staircase spreads 0.08 / a about its mean against 0.75 / a for the
quadrics fitted to the faces (docs/smoothing.md §3c).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

from dicer.arrays import nonzero, norm
from dicer.parallel import MAX_WORKERS, cores

__all__ = ["RELAXATION_STEPS", "faces_between", "relaxed_staircase", "staircase_vertices"]

RELAXATION_STEPS = 1000  # FISTA steps: within 0.024 voxel of 4000 steps' vertices on the Lamé tube at a = 7 (0.005 on the Kirsch plate)
_LAM = 1e-4  # pull towards the corner, against the bending energy's flat directions
_FOLD_PAD = 2  # voxels of reflected labels beyond a mirror plane: every vertex within has its neighbours' neighbours
_ROWS_PER_CORE = 20000  # vertices for another core to pay its threads' hand-overs, 4 an iteration
_PLACED = 0.1  # the pull of a face to where the scan placed it, against the fairing


def faces_between(lab: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """The faces between voxels of two kinds, axis by axis, each axis's in C order of the lower
    voxel: the one order every reader of the staircase takes (its samples in
    ``dicer.mesh.labelsurface.label_image_samples``, the placements :func:`relaxed_staircase`
    takes).

    Parameters
    ----------
    lab : (nx, ny[, nz]) integer ndarray
        Labels.

    Returns
    -------
    list of (d, idx, a, b)
        Per axis d: (F, dim) int64 indices of the voxel below each face along d, and (F,) int64
        the labels of that voxel and of the one above it.
    """
    out = []
    for d in range(lab.ndim):
        lo = lab[(slice(None),) * d + (slice(None, -1),)]
        hi = lab[(slice(None),) * d + (slice(1, None),)]
        idx = np.column_stack(nonzero(lo != hi)).astype(np.int64).reshape(-1, lab.ndim)
        out.append((d, idx, lo[tuple(idx.T)].astype(np.int64), hi[tuple(idx.T)].astype(np.int64)))
    return out


def _staircase(lab: np.ndarray):
    """The faces between two kinds: (F, 2^(dim-1)) corner keys in cyclic order, (F,) pair codes
    and (F, dim) unit normals into the higher kind, and the corner grid's shape."""
    dim = lab.ndim
    shape = np.array(lab.shape) + 1
    strides = np.cumprod(np.r_[1, shape[::-1][:-1]])[::-1].astype(np.int64)
    top = int(lab.max(initial=0)) + 1
    keys, pairs, normals = [], [], []
    for d, idx, a, b in faces_between(lab):
        base = idx.copy()
        base[:, d] += 1  # the face between voxels i and i + 1 lies on corner plane i + 1
        unit = np.eye(dim, dtype=np.int64)[[e for e in range(dim) if e != d]]
        offsets = [0 * unit[0], unit[0]] if dim == 2 else [0 * unit[0], unit[0], unit[0] + unit[1], unit[1]]
        keys.append(np.stack([(base + o) @ strides for o in offsets], axis=1))
        pairs.append(np.minimum(a, b) * top + np.maximum(a, b))
        n = np.zeros((idx.shape[0], dim))
        n[:, d] = np.where(b > a, 1.0, -1.0)
        normals.append(n)
    return np.concatenate(keys), np.concatenate(pairs), np.concatenate(normals), shape, top


def staircase_vertices(lab: np.ndarray):
    """The staircase's vertices: one per pair of kinds at each lattice corner of a face between them.

    Returns
    -------
    corner : (V, dim) float64 ndarray
        Lattice corner (voxels from the corner of voxel 0), in the order
        :func:`relaxed_staircase` returns its vertices in (without ``mirror``).
    pair : (V,) int64 ndarray
        lower kind * top + higher kind.
    junction : (V,) bool ndarray
        Corners in more than one pair (they stay put).
    faces : (F, 2^(dim-1)) int64 ndarray
        Each face's vertices in cyclic order.
    face_normals : (F, dim) float64 ndarray
    shape : (dim,) int64 ndarray
        The corner grid's shape.
    top : int
        One more than the largest label.
    """
    keys, pair, face_normal, shape, top = _staircase(np.asarray(lab))
    size = np.int64(np.prod(shape))
    code = np.repeat(pair, keys.shape[1]) * size + keys.ravel()
    uniq, inv = np.unique(code, return_inverse=True)
    vpair, vkey = uniq // size, uniq % size
    corner = np.stack(np.unravel_index(vkey, tuple(shape)), axis=1).astype(float).reshape(-1, len(shape))
    keys_sorted, counts = np.unique(vkey, return_counts=True)
    junction = counts[np.searchsorted(keys_sorted, vkey)] > 1
    return corner, vpair, junction, inv.reshape(keys.shape), face_normal, shape, top


class _Fold:
    """A staircase cut by mirrors: the image's edges, each axis's two planes facing mirrors,
    so that the cut staircase stands for the endless one they reflect (a cut model relaxes as
    the whole one, to rounding). The labels are reflected ``_FOLD_PAD`` voxels beyond each
    edge, so every vertex within the mirrors has its whole neighbourhood two edges deep; each
    vertex beyond them is the mirror image of one within (``rep``): its coordinates ``sign``
    times that vertex's plus ``shift``, in the padded voxels.

    Attributes
    ----------
    inside : (V,) bool ndarray
        The vertices within the mirrors (on them too).
    ghosts : (G,) int64 ndarray
        The vertices beyond the mirrors.
    rep : (V,) int64 ndarray
        For each vertex, the number among those inside of the vertex it images.
    sign, shift : (V, dim) float64 ndarray
    share : (n,) float64 ndarray
        For each vertex inside, 1/2 per mirror plane it lies on: the part of it one copy holds.
    """

    def __init__(self, corner: np.ndarray, vpair: np.ndarray, shape: np.ndarray, extent: np.ndarray, pad: int):
        c = corner - pad  # voxels from the image's corner
        period = 2.0 * extent
        r = np.mod(c, period)
        back = r > extent
        folded = np.where(back, period - r, r)
        self.sign = np.where(back, -1.0, 1.0)
        self.shift = (c - self.sign * folded) + pad * (1.0 - self.sign)  # in the padded voxels
        self.inside = np.all((c >= 0) & (c <= extent), axis=1)
        self.ghosts = np.flatnonzero(~self.inside)
        size = np.int64(np.prod(shape))
        strides = np.cumprod(np.r_[1, shape[::-1][:-1]])[::-1].astype(np.int64)
        code = lambda p, q: q * size + np.rint(p + pad).astype(np.int64) @ strides  # noqa: E731
        own = code(c[self.inside], vpair[self.inside])
        order = np.argsort(own)
        want = code(folded, vpair)
        at = np.clip(np.searchsorted(own[order], want), 0, own.size - 1)
        if own.size == 0 or not np.array_equal(own[order][at], want):
            raise AssertionError("a vertex beyond a mirror has no image within it")  # the pad is symmetric
        self.rep = order[at]
        on_planes = np.count_nonzero((c[self.inside] == 0) | (c[self.inside] == extent), axis=1)
        self.share = 0.5 ** on_planes

    def ghost_values(self, x: np.ndarray, shifted: bool) -> np.ndarray:
        """(G, dim) the coordinates of the vertices beyond the mirrors (``ghosts``), as :meth:`unfold`."""
        g = self.ghosts
        out = self.sign[g] * x[self.rep[g]]
        if shifted:
            out += self.shift[g]
        return out

    def unfold(self, x: np.ndarray, shifted: bool) -> np.ndarray:
        """(V, dim) every vertex's coordinates (``shifted``: positions; else the differences
        the operators make, which mirror without the shift) from those inside (n, dim)."""
        out = self.sign * x[self.rep]
        if shifted:
            out += self.shift
        return out


def _fista(L: sp.csr_matrix, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
           data: tuple[sp.csr_matrix, np.ndarray, np.ndarray] | None = None, fold: _Fold | None = None
           ) -> np.ndarray:
    """argmin |L L x|^2 + _LAM |x - x0|^2 (+ sum W (A x - Y)^2) over lo <= x <= hi, each
    column on its own; (n, k). ``data``: A (F, n), Y and W (F, k). With ``fold`` the n
    unknowns are the vertices within the mirrors and L and A act on all the staircase's
    vertices, the others being mirror images of them (:class:`_Fold`): the sums of an endless
    mirrored staircase, on one copy of it."""
    # the vertices beyond the mirrors apart (few: two voxels deep), so the products over those
    # within take the unknowns as they are
    ghost = (lambda v, shifted: None) if fold is None else fold.ghost_values  # noqa: E731
    inside = slice(None) if fold is None else fold.inside

    def split(m: sp.csr_matrix) -> tuple[sp.csr_matrix, sp.csr_matrix | None]:
        return m[:, inside].tocsr(), None if fold is None else m[:, fold.ghosts].tocsr()
    Lt = L[:, inside].T.tocsr()
    # the gradient's Lipschitz constant 2 (|L|^4 + lam (+ |W| |A|^2)), |L|_2^2 <= |L|_1 |L|_inf;
    # L applied twice costs less than the product's denser matrix. Folded: the columns of the
    # vertices within the mirrors hold every column's sum, and the rows are theirs
    def norm2(m: sp.csr_matrix, rows=slice(None)) -> float:
        return float(abs(m[:, inside]).sum(axis=0).max()) * float(abs(m[rows]).sum(axis=1).max())

    lip = 2.0 * (norm2(L, inside) ** 2 + _LAM)
    L = L[inside].tocsr()
    if data is not None:
        A, Y, W = data
        At = A[:, inside].T.tocsr()
        lip += 2.0 * float(W.max(initial=0.0)) * norm2(A)
    step = 1.0 / lip
    # the rows in blocks, one per core: a row's sums are the same in any block, so the
    # result is the same bytes on any number of cores
    parts = min(cores(), MAX_WORKERS) if x0.shape[0] >= _ROWS_PER_CORE else 1
    cut = np.linspace(0, x0.shape[0], parts + 1).astype(np.int64)
    rows = [slice(int(cut[i]), int(cut[i + 1])) for i in range(parts)]
    L_rows, Lt_rows = [split(L[r]) for r in rows], [split(Lt[r]) for r in rows]
    if data is not None:
        fcut = np.linspace(0, A.shape[0], parts + 1).astype(np.int64)
        frows = [slice(int(fcut[i]), int(fcut[i + 1])) for i in range(parts)]
        A_rows, At_rows = [split(A[r]) for r in frows], [At[r] for r in rows]
    x = x0.copy()
    y = x0.copy()
    nxt = np.empty_like(x0)
    u, v, w, pull = (np.empty_like(x0) for _ in range(4))
    misfit = None if data is None else np.empty_like(Y)
    t = 1.0

    def times(m: tuple, vec: np.ndarray, beyond: np.ndarray | None) -> np.ndarray:
        within, mirrored = m
        out = within @ vec
        if beyond is not None:
            out += mirrored @ beyond
        return out

    def product(m_rows, vec, out, shifted=False):
        beyond = ghost(vec, shifted)

        def one(i):
            out[rows[i]] = times(m_rows[i], vec, beyond)
        return one

    def descend(i, momentum):
        # y - step grad, clipped, and nxt + momentum (nxt - x), in place (the same operations
        # in the same order: a fresh array of this size costs its pages again each time)
        r = rows[i]
        grad = times(Lt_rows[i], w, w_beyond)
        grad *= 2.0
        np.subtract(y[r], x0[r], out=pull[r])
        pull[r] *= 2.0 * _LAM
        grad += pull[r]
        if data is not None:
            grad += 2.0 * (At_rows[i] @ misfit)
        grad *= step
        np.subtract(y[r], grad, out=grad)
        np.clip(grad, lo[r], hi[r], out=nxt[r])
        np.subtract(nxt[r], x[r], out=grad)
        grad *= momentum
        np.add(nxt[r], grad, out=y[r])

    def misfits(i):
        f = frows[i]
        misfit[f] = W[f] * (times(A_rows[i], y, y_beyond) - Y[f])

    with ThreadPoolExecutor(parts) as pool:
        def each(fn):  # every block done before the next product reads them
            if parts == 1:
                fn(0)
            else:
                for _ in pool.map(fn, range(parts)):
                    pass

        for _ in range(RELAXATION_STEPS):
            y_beyond = ghost(y, True)
            each(product(L_rows, y, u, True))
            if data is not None:
                each(misfits)
            each(product(L_rows, u, v))
            each(product(Lt_rows, v, w))
            t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
            momentum = (t - 1.0) / t_next
            w_beyond = ghost(w, False)
            each(lambda i: descend(i, momentum))
            x, nxt = nxt, x
            t = t_next
    return x


def _face_keys(axis: np.ndarray, twice: np.ndarray, shape2: np.ndarray) -> np.ndarray:
    """One int64 per face: its axis and its centre's doubled lattice coordinates."""
    return axis.astype(np.int64) + twice.astype(np.int64) @ np.cumprod(np.r_[len(shape2), shape2[:-1]]).astype(np.int64)


def _placed_targets(lab: np.ndarray, corner: np.ndarray, inv: np.ndarray, face_normal: np.ndarray, pad: int,
                    placed: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """The relaxed faces' pull to where a scan placed them: A (F, V) averaging each face's
    vertices, Y (F, dim) the placed coordinate along the face's axis, W (F, dim) _PLACED where
    the face was placed, along its axis (a padded face takes its mirror image's placement)."""
    dim = lab.ndim
    ext2 = 2 * (np.asarray(lab.shape, np.int64) - 2 * pad)
    shape2 = ext2 + 1
    # the placements, keyed by face, in label_image_samples' order (unpadded labels)
    inner = lab[tuple(slice(pad, lab.shape[e] - pad) for e in range(dim))]
    keys = []
    for d, idx, _, _ in faces_between(inner):
        twice = 2 * idx + 1
        twice[:, d] += 1
        keys.append(_face_keys(np.full(idx.shape[0], d), twice, shape2))
    keys = np.concatenate(keys)
    if keys.size == 0:  # no face to place
        return sp.csr_matrix((0, corner.shape[0])), np.zeros((0, dim)), np.zeros((0, dim))
    order = np.argsort(keys)
    keys, offs = keys[order], placed[order]
    # every relaxed face's centre, folded back into the image across the mirrors
    k = inv.shape[1]
    axis = np.argmax(np.abs(face_normal), axis=1)
    twice = np.rint(2.0 * corner[inv].mean(axis=1)).astype(np.int64) - 2 * pad
    flips = np.zeros(inv.shape[0], bool)
    for e in range(dim):
        for _ in range(4):  # a pad wider than the image reflects again
            low, high = twice[:, e] < 0, twice[:, e] > ext2[e]
            twice[low, e] = -twice[low, e]
            twice[high, e] = 2 * ext2[e] - twice[high, e]
            flips ^= (low | high) & (axis == e)
    key = _face_keys(axis, twice, shape2)
    pos = np.clip(np.searchsorted(keys, key), 0, keys.size - 1)
    off = np.where(keys[pos] == key, offs[pos], np.nan)  # a staircase has faces here: the placed ones
    off = np.where(flips, -off, off)
    rows = np.flatnonzero(np.isfinite(off))
    V = corner.shape[0]
    A = sp.csr_matrix((np.full(rows.size * k, 1.0 / k), (np.repeat(np.arange(rows.size), k), inv[rows].ravel())),
                      shape=(rows.size, V))
    Y = np.zeros((rows.size, dim))
    W = np.zeros((rows.size, dim))
    Y[np.arange(rows.size), axis[rows]] = corner[inv[rows]].mean(axis=1)[np.arange(rows.size), axis[rows]] + off[rows]
    W[np.arange(rows.size), axis[rows]] = _PLACED
    return A, Y, W


def _vertex_normals(x: np.ndarray, inv: np.ndarray, face_normal: np.ndarray, spacing: np.ndarray, n: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(n, dim) unit normals into the higher kind and (n,) areas (mm^2; 2D: mm, on voxels of
    ``spacing`` mm) of the faces ``inv`` (F, k) of the vertices ``x`` (n, dim) in voxels, summed
    at their vertices."""
    dim, k = x.shape[1], inv.shape[1]
    if dim == 2:
        tangent = x[inv[:, 1]] - x[inv[:, 0]]
        area = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1) * spacing[::-1]
    else:
        area = 0.5 * np.cross((x[inv[:, 2]] - x[inv[:, 0]]) * spacing, (x[inv[:, 3]] - x[inv[:, 1]]) * spacing)
    area *= np.sign(np.einsum("ij,ij->i", area, face_normal))[:, None]
    at = inv.ravel()  # each face's area shared among its k vertices
    summed = np.stack([np.bincount(at, weights=np.repeat(area[:, c] / k, k), minlength=n) for c in range(dim)],
                      axis=1)
    size = norm(summed, axis=1)
    return summed / np.maximum(size, 1e-300)[:, None], size


def _volume_kept(x: np.ndarray, corner: np.ndarray, lo: np.ndarray, hi: np.ndarray, adj: sp.csr_matrix,
                 normals: np.ndarray, area: np.ndarray) -> np.ndarray:
    """The relaxed vertices ``x`` (voxels) moved along their normals (``normals``, ``area``:
    in voxels, so that every axis stays its own problem on any voxel size), one distance per
    connected sheet of the staircase, so that each sheet sweeps no volume from its corners
    (sum of area times the move along the normal), within their cells (``lo``, ``hi``).

    The fairing's energy |L L x|^2 is not zero on a circle of few vertices but falls with its
    radius, so a part two or three voxels across relaxed to a fraction of its section (a rod
    2 x 2 voxels: a quarter); on large parts the sheets sweep next to nothing (the head CT's
    materials: under 0.1 % of their volume either way)."""
    from scipy.sparse.csgraph import connected_components

    sheets, sheet = connected_components(adj, directed=False)
    for _ in range(3):  # the cells clip some moves: again with what is left
        swept = np.einsum("ij,ij->i", x - corner, normals) * area
        lost = np.bincount(sheet, weights=swept, minlength=sheets)
        free = np.bincount(sheet, weights=area, minlength=sheets)
        move = -np.divide(lost, free, out=np.zeros(sheets), where=free > 0)[sheet]
        x = np.clip(x + move[:, None] * normals, lo, hi)
    return x


def relaxed_staircase(lab: np.ndarray, spacing, origin, mirror: bool = False, placed: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The staircase's vertices between two kinds, relaxed within their voxels.

    Parameters
    ----------
    lab : (nx, ny[, nz]) integer ndarray
        Labels, 0 background.
    spacing, origin : sequence of float
        mm per voxel and the corner of voxel 0, per axis.
    mirror : bool, optional
        The image's edges are mirrors (``bounding_planes: mirror``): the staircase is relaxed as
        the endless one they reflect (:class:`_Fold`), so a cut model relaxes as the whole one,
        to rounding; a vertex on a mirror stands for itself and its images, so its weight is
        halved per mirror it lies on (the fit's mirrored samples count it once per image).
        Else a vertex on an edge stays in its plane.
    placed : (S,) float64 ndarray, optional
        Where a scan placed each face between two kinds (``dicer.mesh.labelsurface.scan_crossings``):
        its move along the face's axis, in voxels towards higher indices, NaN where the scan
        did not place it; the faces in the order ``label_image_samples`` gives them (per axis,
        C order of the lower voxel). Each placed face's vertices are pulled, on average, to
        that place (weight ``_PLACED`` against the fairing), so the relaxed staircase is a fair
        surface through the scan's placements: their noise averaged along it.

    Returns
    -------
    points : (V, dim) float64 ndarray
        mm; a corner between several pairs of kinds gives one vertex per pair.
    normals : (V, dim) float64 ndarray
        Unit normals into the higher kind, of the relaxed faces around each vertex.
    kinds : (V, 2) int64 ndarray
        The lower and the higher kind.
    weights : (V,) float64 ndarray
        The area (2D: length) each vertex stands for, mm^2 (mm).
    """
    lab = np.asarray(lab)
    dim = lab.ndim
    spacing = np.asarray(spacing, float)[:dim]
    origin = np.asarray(origin, float)[:dim]
    extent = np.asarray(lab.shape, float)
    pad = _FOLD_PAD if mirror else 0
    if pad:
        lab = np.pad(lab, pad, mode="symmetric")
    corner, vpair, junction, inv, face_normal, shape, top = staircase_vertices(lab)
    n, k = corner.shape[0], inv.shape[1]
    if n == 0:
        return np.zeros((0, dim)), np.zeros((0, dim)), np.zeros((0, 2), np.int64), np.zeros(0)
    # the staircase's edges: consecutive corners of each face
    a, b = inv.ravel(), np.roll(inv, -1, axis=1).ravel()
    adj = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)).tocsr()
    adj = ((adj + adj.T) > 0).astype(float)
    degree = np.asarray(adj.sum(axis=1)).ravel()
    L = (sp.identity(n, format="csr") - sp.diags(1.0 / degree) @ adj).tocsr()
    half = np.where(junction, 0.0, 0.5)[:, None] * np.ones((1, dim))
    # on the image's edge (a mirror: on a plane of symmetry, as its images are): stays in that plane
    edge = (corner == pad) | (corner == shape[:dim] - 1 - pad)
    half[edge] = 0.0
    data = None if placed is None else _placed_targets(lab, corner, inv, face_normal, pad, np.asarray(placed, float))
    lo, hi = corner - half, corner + half
    fold = _Fold(corner, vpair, shape[:dim], extent, pad) if pad else None
    inside = slice(None) if fold is None else fold.inside
    share = 1.0 if fold is None else fold.share
    x = _fista(L, corner[inside], lo[inside], hi[inside], data, fold)
    positions = (lambda x: x) if fold is None else (lambda x: fold.unfold(x, True))  # noqa: E731
    if data is None:  # the labels' volume kept: without a scan's places the fairing alone draws small parts in
        towards, area = _vertex_normals(positions(x), inv, face_normal, np.ones(dim), n)
        sheets = adj if fold is None else (adj[fold.inside] @ sp.csr_matrix(
            (np.ones(n), (np.arange(n), fold.rep)), shape=(n, x.shape[0]))).tocsr()
        x = _volume_kept(x, corner[inside], lo[inside], hi[inside], sheets, towards[inside], area[inside] * share)
    normals, size = _vertex_normals(positions(x), inv, face_normal, spacing, n)
    kinds = np.stack([vpair // top, vpair % top], axis=1)
    x = x - pad
    return origin + x * spacing, normals[inside], kinds[inside], size[inside] * share
