"""Connectivity fixes (DICER Box 1): make every class of a label volume well connected.

Three poorly connected arrangements are repaired (paper section 2.2, Fig. 3):

* **Type A** - in a 2x2 block of any axis-aligned plane, a class occupies exactly one
  diagonal (the two voxels touch only along an edge).
* **Type B** - in a 2x2x2 block, a class occupies exactly the two voxels of a body
  diagonal, or exactly the six voxels that leave a body diagonal to others (the central
  node is exposed).
* **Type C** - a voxel holds two class-A boundary nodes joined by a boundary edge
  (an element hanging on by two adjacent faces, or its complement).

Every class, background (0) included, is treated. A Type A/B fix never lowers a
voxel's class: label values order the classes (background lowest, the highest label
wins), and every fix sets a voxel to a class of higher value than it had, so the
sweeps reach a fixed point with no Type A or B arrangement left. Type C first applies
the paper's rule (the majority class of the neighbours) for a few rounds, keeping the
state with the fewest sites; that rule lowers classes, so it can undo itself and it
eats one-voxel plates away. The remaining sites are then repaired by raising only:
notches are filled and one-voxel-thick features made two voxels thick. That phase is
monotone too, so it ends, and where it ends no Type A, B or C arrangement is left.
``docs/smoothing.md`` gives the exact rules.

Arrays are indexed ``[x, y, z]`` (``[x, y]`` in 2D). Voxels outside the image count
as background for node classification (Type C) and are never changed.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from dicer.arrays import argwhere, nonzero
from dicer.config import takes_settings, unknown_materials
from dicer.errors import DicerError
from dicer.image import count_labels

__all__ = ["fix_connectivity", "fix_stage", "connectivity_defects", "boundary_edge_counts", "remove_islands",
           "joined_parts", "faces_reached", "priority_order", "check_priority"]


# --- helpers -----------------------------------------------------------------------------


def _sl(ndim: int, axis: int, s: slice) -> tuple:
    out = [slice(None)] * ndim
    out[axis] = s
    return tuple(out)


_LO, _HI = slice(None, -1), slice(1, None)


def _corner_views(a: np.ndarray, axes: tuple[int, ...]) -> list[tuple]:
    """Slices selecting, for every 2^len(axes) block along ``axes``, one of its corners.

    Corner index bit b (in ``axes`` order) set means the high side along ``axes[b]``.
    """
    out = []
    for code in range(1 << len(axes)):
        s = [slice(None)] * a.ndim
        for b, ax in enumerate(axes):
            s[ax] = _HI if (code >> b) & 1 else _LO
        out.append(tuple(s))
    return out


def _as_work(labels: np.ndarray) -> np.ndarray:
    if labels.size == 0:
        raise DicerError(f"labels have shape {labels.shape}; an image with at least one voxel is needed")
    top = int(labels.max())
    if int(labels.min()) < 0:
        raise DicerError("labels contain negative values; use 0 for background and 1..K for materials")
    dtype = np.uint8 if top < 256 else (np.uint16 if top < 65536 else np.int64)
    return np.ascontiguousarray(labels, dtype=dtype)


def _mixed_blocks(w: np.ndarray, axes: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """Index arrays of the low corner of every 2^len(axes) block along ``axes`` that holds
    more than one class: only those can be poorly connected. The blocks' maxima and minima
    come axis by axis (three passes each in 3D, not seven); a scan is mostly uniform
    blocks, so the rules then run on a few per cent of the volume."""
    hi = lo = w
    for ax in axes:
        s_lo, s_hi = _sl(w.ndim, ax, _LO), _sl(w.ndim, ax, _HI)
        hi = np.maximum(hi[s_lo], hi[s_hi])
        lo = np.minimum(lo[s_lo], lo[s_hi])
    return nonzero(hi != lo)


def _corners(origins: tuple[np.ndarray, ...], axes: tuple[int, ...]) -> list[tuple[np.ndarray, ...]]:
    """Index arrays of each corner of the blocks at ``origins``, in :func:`_corner_views` order."""
    out = []
    for code in range(1 << len(axes)):
        index = list(origins)
        for b, ax in enumerate(axes):
            if (code >> b) & 1:
                index[ax] = index[ax] + 1
        out.append(tuple(index))
    return out


def _raise_to(prop: np.ndarray, index: tuple[np.ndarray, ...], mask: np.ndarray, value: np.ndarray) -> None:
    """``prop`` at ``index[mask]`` raised to ``value[mask]`` (a voxel at most once per call)."""
    if mask.any():
        at = tuple(i[mask] for i in index)
        prop[at] = np.maximum(prop[at], value[mask])


# --- Type A ------------------------------------------------------------------------------


def _type_a_pass(w: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    """One simultaneous Type A sweep over the 2x2 blocks spanning ``axes``; returns proposals.

    Corners a (0,0), b (1,0), c (0,1), d (1,1). For a checkerboard diagonal P of class p
    with the other diagonal Q: if p is above the lower Q class, that Q voxel (the first
    on ties) becomes p (the connecting voxel); otherwise the first P voxel becomes the
    higher Q class. Returns the array of proposed classes (>= w everywhere).
    """
    ia, ib, ic, id_ = _corners(_mixed_blocks(w, axes), axes)
    a, b, c, d = w[ia], w[ib], w[ic], w[id_]
    prop = w.copy()
    for (p1, p2, q1, q2, s_p1, s_q1, s_q2) in ((a, d, b, c, ia, ib, ic), (b, c, a, d, ib, ia, id_)):
        bad = (p1 == p2) & (q1 != p1) & (q2 != p1)
        if not bad.any():
            continue
        grow = bad & (p1 > np.minimum(q1, q2))
        # p above the lower Q class: the lower Q voxel (q1 on ties) becomes p
        _raise_to(prop, s_q1, grow & (q1 <= q2), p1)
        _raise_to(prop, s_q2, grow & (q1 > q2), p1)
        # p below both Q classes: the first P voxel takes the higher Q class
        _raise_to(prop, s_p1, bad & ~grow, np.maximum(q1, q2))
    return prop


def _type_a_defects(w: np.ndarray, axes: tuple[int, int]) -> int:
    """Number of Type A blocks spanning ``axes``."""
    a, b, c, d = (w[i] for i in _corners(_mixed_blocks(w, axes), axes))
    return int(np.count_nonzero(((a == d) & (b != a) & (c != a)) | ((b == c) & (a != b) & (d != b))))


# --- Type B ------------------------------------------------------------------------------

# corner codes: bit 0 = x, bit 1 = y, bit 2 = z; the body-diagonal partner of p is p ^ 7
_DIAG = (0, 1, 2, 3)


def _type_b_masks(v: list[np.ndarray], p: int):
    """(pair, six) masks for the body diagonal (p, p^7): pair = the two share a class no
    other corner has; six = the other six share a class neither diagonal voxel has."""
    q = p ^ 7
    rest = [v[r] for r in range(8) if r not in (p, q)]
    vp, vq = v[p], v[q]
    pair = vp == vq
    for r in rest:
        pair &= r != vp
    six = np.ones_like(pair)
    r0 = rest[0]
    for r in rest[1:]:
        six &= r == r0
    six &= (vp != r0) & (vq != r0)
    return pair, six, rest


def _type_b_pass(w: np.ndarray) -> np.ndarray:
    """One simultaneous Type B sweep over all 2x2x2 blocks; returns proposals (>= w)."""
    index = _corners(_mixed_blocks(w, (0, 1, 2)), (0, 1, 2))
    v = [w[i] for i in index]
    prop = w.copy()
    for p in _DIAG:
        q = p ^ 7
        pair, six, rest = _type_b_masks(v, p)
        vp, vq = v[p], v[q]
        if six.any():
            c = rest[0]
            # the six-class fills each diagonal voxel it is above (the paper's fill) ...
            _raise_to(prop, index[p], six & (c > vp), c)
            _raise_to(prop, index[q], six & (c > vq), c)
            # ... and where it is below both, one of its voxels next to the higher diagonal
            # voxel takes that voxel's class
            low = six & (c < vp) & (c < vq)
            hi_p = vp >= vq
            _raise_to(prop, index[p ^ 1], low & hi_p, vp)
            _raise_to(prop, index[q ^ 1], low & ~hi_p, vq)
        if pair.any():
            rmax = rest[0]
            for r in rest[1:]:
                rmax = np.maximum(rmax, r)
            # the pair's class is above all others: join the pair by a face path p, p^1, p^3, q
            top = pair & (vp > rmax)
            _raise_to(prop, index[p ^ 1], top, vp)
            _raise_to(prop, index[p ^ 3], top, vp)
            # otherwise the first voxel of the pair takes the highest other class
            _raise_to(prop, index[p], pair & ~top, rmax)
    return prop


def _type_b_defects(w: np.ndarray) -> int:
    """Number of Type B blocks."""
    v = [w[i] for i in _corners(_mixed_blocks(w, (0, 1, 2)), (0, 1, 2))]
    bad = np.zeros(v[0].shape, bool)
    for p in _DIAG:
        pair, six, _ = _type_b_masks(v, p)
        bad |= pair | six
    return int(np.count_nonzero(bad))


# --- node classification in voxel space (Type C) ------------------------------------------


def _edge_boundary(lp: np.ndarray, axis: int) -> np.ndarray:
    """Boundary flags of the lattice edges along ``axis`` of the padded volume ``lp``.

    An edge is a boundary edge unless its four voxels hold one class; four background
    voxels mean no edge (also False). Shape: voxels along ``axis``, nodes along the others.
    """
    others = tuple(ax for ax in range(3) if ax != axis)
    core = lp[_sl(3, axis, slice(1, -1))]
    v = [core[s] for s in _corner_views(core, others)]
    same = (v[0] == v[1]) & (v[1] == v[2]) & (v[2] == v[3])
    return ~same


def _padded(w: np.ndarray) -> np.ndarray:
    return np.pad(w, 1, mode="constant", constant_values=0)


def boundary_edge_counts(labels: np.ndarray) -> np.ndarray:
    """Boundary edges at every voxel corner of a 3D label volume.

    Voxels outside the image count as background.

    Parameters
    ----------
    labels : (nx, ny, nz) int ndarray
        0 background.

    Returns
    -------
    (nx+1, ny+1, nz+1) int8 ndarray
        0 for interior nodes (eight voxels of one material) and for corners of background
        only.
    """
    w = _as_work(np.asarray(labels))
    if w.ndim != 3:
        raise DicerError("boundary_edge_counts needs a 3D label volume")
    lp = _padded(w)
    cnt = np.zeros(tuple(n + 1 for n in w.shape), np.int8)
    for axis in range(3):
        e = _edge_boundary(lp, axis).astype(np.int8)
        cnt[_sl(3, axis, _LO)] += e  # edge towards +axis
        cnt[_sl(3, axis, _HI)] += e  # edge towards -axis
    return cnt


def _type_c_edges(w: np.ndarray):
    """Type C sites: for each axis, the (voxels-along-axis, nodes, nodes) mask of boundary
    edges whose two end nodes both have three boundary edges (class A), leaving out the
    edges that lie on the image's bounding surface (their outside voxels are no class)."""
    lp = _padded(w)
    cnt = np.zeros(tuple(n + 1 for n in w.shape), np.int8)
    edges = []
    for axis in range(3):
        e = _edge_boundary(lp, axis)
        edges.append(e)
        cnt[_sl(3, axis, _LO)] += e
        cnt[_sl(3, axis, _HI)] += e
    a_node = cnt == 3
    out = []
    for axis in range(3):
        site = edges[axis] & a_node[_sl(3, axis, _LO)] & a_node[_sl(3, axis, _HI)]
        for ax in range(3):
            if ax != axis:  # edges on the image's bounding surface are cut faces: not sites
                site[_sl(3, ax, slice(0, 1))] = False
                site[_sl(3, ax, slice(-1, None))] = False
        out.append(site)
    return lp, out


def _edge_voxels(lp: np.ndarray, sites: list[np.ndarray]):
    """For each axis with Type C sites: (axis, the four voxels around each site edge as
    image coordinate tuples, their classes (n, 4)). Sites lie off the image's bounding
    surface, so all four voxels are inside the image."""
    for axis in range(3):
        if not sites[axis].any():  # far cheaper than nonzero on an empty mask
            continue
        idx = nonzero(sites[axis])
        others = [ax for ax in range(3) if ax != axis]
        vox = []
        for code in range(4):
            coord = [None, None, None]
            coord[axis] = idx[axis]
            for b, ax in enumerate(others):
                coord[ax] = idx[ax] - 1 + ((code >> b) & 1)  # padded node index - 1 + side
            vox.append(tuple(coord))
        yield axis, vox, np.stack([lp[tuple(c + 1 for c in coord)] for coord in vox], axis=1)


def _face_neighbours(w: np.ndarray, coords) -> tuple[np.ndarray, np.ndarray]:
    """Classes (n, 6) int64 of the six face neighbours of the voxels at ``coords`` (0
    outside the image) and whether each neighbour is inside the image."""
    vals, inside = [], []
    for axis in range(3):
        for step in (-1, 1):
            nb = list(coords)
            nb[axis] = nb[axis] + step
            ok = (nb[axis] >= 0) & (nb[axis] < w.shape[axis])
            nb[axis] = np.where(ok, nb[axis], 0)
            vals.append(np.where(ok, w[tuple(nb)], 0))
            inside.append(ok)
    return np.stack(vals, axis=1).astype(np.int64), np.stack(inside, axis=1)


def _type_c_proposals(w: np.ndarray, thicken: bool = True) -> tuple[np.ndarray, int]:
    """One Type C sweep: proposed classes (>= w everywhere) and the number of sites seen.

    At every A-A boundary edge the four voxels around it are looked at. When one of them
    holds a class above the other three, it is the thin corner of a feature one voxel
    thick along the edge, and a seed for ``_fatten``: the thin voxels of its class
    26-connected to it each take a 2x2x2 block of their class. Otherwise the voxels
    around the edge below its highest class take that class (a notch is filled). Only
    raising keeps the fix monotone, so the rounds end. A seed may raise nothing (already
    fat, or no higher neighbour to rise to); with ``thicken=False`` every site is filled
    instead, which always raises a voxel (the caller's fallback when a sweep proposes
    no change).
    """
    lp, sites = _type_c_edges(w)
    prop = w.copy()
    all_seeds = None
    for _, vox, vals in _edge_voxels(lp, sites):
        top = vals.max(axis=1)
        lone = ((vals == top[:, None]).sum(axis=1) == 1) & thicken
        seeds = np.zeros(w.shape, dtype=bool)
        for code in range(4):
            coord = vox[code]
            v = vals[:, code]
            fill = ~lone & (v < top)
            np.maximum.at(prop, tuple(c[fill] for c in coord), top[fill].astype(w.dtype))
            seed = lone & (v == top)
            seeds[tuple(c[seed] for c in coord)] = True
        all_seeds = seeds if all_seeds is None else all_seeds | seeds
    if all_seeds is not None and all_seeds.any():
        _fatten(w, prop, all_seeds)
    return prop, sum(int(np.count_nonzero(e)) for e in sites)


def _type_c_voxels(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Flat indices of the in-image voxels to reclassify, the class each gets, and the
    number of Type C sites.

    For every A-A boundary edge, the voxel among the four around it whose class differs
    from the other three (if the four split otherwise, all four) takes the majority class
    of its six face neighbours (outside the image: background); ties go to the class of
    the other voxels around the edge, then to the higher class.
    """
    lp, sites = _type_c_edges(w)
    n_sites = sum(int(np.count_nonzero(e)) for e in sites)
    cand, hint = [], []
    for _, vox, vals in _edge_voxels(lp, sites):
        n_same = (vals[:, :, None] == vals[:, None, :]).sum(axis=2)  # voxels sharing each one's class
        odd = (n_same == 1) & (n_same.sum(axis=1, keepdims=True) == 1 + 3 * 3)
        general = ~odd.any(axis=1)
        for code in range(4):
            take = odd[:, code] | general
            cand.append(np.ravel_multi_index(tuple(c[take] for c in vox[code]), w.shape))
            hint.append(_row_mode(np.delete(vals[take], code, axis=1)))  # the other voxels' class
    if not cand:
        return np.zeros(0, np.int64), np.zeros(0, w.dtype), n_sites
    flat, first = np.unique(np.concatenate(cand), return_index=True)
    hint = np.concatenate(hint)[first]
    neighbours, _ = _face_neighbours(w, np.unravel_index(flat, w.shape))
    # score: twice the neighbour count, plus one for the hint; ties go to the higher class
    score = 2 * (neighbours[:, :, None] == neighbours[:, None, :]).sum(axis=2)
    score += neighbours == hint.astype(np.int64)[:, None]
    new = _best_value(neighbours, score).astype(w.dtype)
    change = new != w.ravel()[flat]
    return flat[change], new[change], n_sites


def _best_value(vals: np.ndarray, score: np.ndarray) -> np.ndarray:
    """Per row, the value with the highest score (ties: the highest value); vals >= 0."""
    top = score == score.max(axis=1, keepdims=True)
    return np.where(top, vals, -1).max(axis=1)


def _row_mode(vals: np.ndarray) -> np.ndarray:
    """Most frequent value of each row (ties: the higher value)."""
    vals = vals.astype(np.int64)
    return _best_value(vals, (vals[:, :, None] == vals[:, None, :]).sum(axis=2))


def _fat(w: np.ndarray) -> np.ndarray:
    """(shape) bool: voxels lying in a 2x2x2 block of their own class."""
    views = _corner_views(w, (0, 1, 2))
    full = np.ones(w[views[0]].shape, dtype=bool)
    for s in views[1:]:
        full &= w[s] == w[views[0]]
    fat = np.zeros(w.shape, dtype=bool)
    for s in views:
        fat[s] |= full
    return fat


_FORWARD_26 = [off for off in itertools.product((-1, 0, 1), repeat=3) if off > (0, 0, 0)]
"""Half of the 26 neighbour offsets: with their opposites, every neighbour pair once."""


def _joined_to_seeds(w: np.ndarray, mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """(shape) bool: the voxels of ``mask`` 26-connected to a seed in ``mask`` through voxels of
    ``mask`` of the seed's class.

    The components of all classes at once, from the graph of neighbouring mask voxels of
    equal class: the work does not grow with the number of classes.
    """
    out = np.zeros(w.shape, dtype=bool)
    if not (mask & seeds).any():
        return out
    nodes = np.flatnonzero(mask)
    strides = np.array([int(np.prod(w.shape[d + 1 :])) for d in range(3)], np.int64)
    first, second = [], []
    for off in _FORWARD_26:
        src = tuple(slice(max(0, -o), n - max(0, o)) for o, n in zip(off, w.shape))
        dst = tuple(slice(max(0, o), n - max(0, -o)) for o, n in zip(off, w.shape))
        linked = mask[src] & mask[dst] & (w[src] == w[dst])
        where = nonzero(linked)
        flat = sum((c + s.start) * st for c, s, st in zip(where, src, strides))
        first.append(np.searchsorted(nodes, flat))
        second.append(np.searchsorted(nodes, flat + int(np.dot(off, strides))))
    a, b = np.concatenate(first), np.concatenate(second)
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(nodes.size, nodes.size))
    _, comp = connected_components(graph, directed=False)
    chosen = np.zeros(int(comp.max()) + 1, dtype=bool)
    chosen[comp[np.searchsorted(nodes, np.flatnonzero(mask & seeds))]] = True
    out.ravel()[nodes[chosen[comp]]] = True
    return out


def _fatten(w: np.ndarray, prop: np.ndarray, seeds: np.ndarray) -> None:
    """Propose classes that put every thin voxel joined to ``seeds`` into a 2x2x2 block.

    A voxel is thin when no 2x2x2 block of its class holds it. The thin voxels of a
    seed's class that are 26-connected to it (through thin voxels of that class) each
    take the block around them with the most voxels of their class and none of a higher
    one, and raise that block's other voxels to their class; a thin voxel with no such
    block rises to the lowest higher class among its face neighbours.
    """
    thin = ~_fat(w)
    pts = argwhere(_joined_to_seeds(w, thin, seeds))
    if not pts.size:
        return
    v = w[tuple(pts.T)]
    shape = np.array(w.shape)
    offsets = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])
    best_score = np.full(pts.shape[0], -1, dtype=np.int64)
    best_lo = np.zeros_like(pts)
    for o in offsets:
        lo = pts - o  # the block's lowest corner
        valid = np.all((lo >= 0) & (lo + 1 < shape), axis=1)
        cells = np.clip(lo[:, None, :] + offsets[None, :, :], 0, shape - 1)  # (N, 8, 3)
        vals = w[cells[..., 0], cells[..., 1], cells[..., 2]]
        score = np.where(valid & np.all(vals <= v[:, None], axis=1), (vals == v[:, None]).sum(axis=1), -1)
        better = score > best_score
        best_score[better] = score[better]
        best_lo[better] = lo[better]
    ok = best_score >= 0
    cells = (best_lo[ok][:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    np.maximum.at(prop, tuple(cells.T), np.repeat(v[ok], 8).astype(w.dtype))
    stuck = pts[~ok]
    if stuck.size:
        nb, inside = _face_neighbours(w, tuple(stuck.T))
        higher = inside & (nb > v[~ok].astype(np.int64)[:, None])
        rise = np.where(higher, nb, np.iinfo(np.int64).max).min(axis=1)
        up = higher.any(axis=1)
        np.maximum.at(prop, tuple(stuck[up].T), rise[up].astype(w.dtype))


# --- public API ----------------------------------------------------------------------------


_TILE = 16  # edge of the tiles that later sweeps revisit (voxels)


def _sweep(w: np.ndarray, counts: dict, box: tuple) -> np.ndarray:
    """One Type A (all plane orientations) then Type B sweep over ``w[box]``, applied in
    place. Returns the tiles (rows of tile indices) holding voxels it changed."""
    sub = w[box]
    planes = [(0, 1)] if w.ndim == 2 else [(1, 2), (0, 2), (0, 1)]
    passes = [lambda a=axes: _type_a_pass(sub, a) for axes in planes]
    if w.ndim == 3:
        passes.append(lambda: _type_b_pass(sub))
    changed = None
    for kind, run in zip("A" * len(planes) + "B", passes):
        prop = run()
        diff = prop != sub
        if diff.any():
            _tally(counts[kind], prop[diff])
            sub[diff] = prop[diff]
            changed = diff if changed is None else changed | diff
    if changed is None:
        return np.zeros((0, w.ndim), dtype=np.int64)
    start = np.array([b.start or 0 for b in box])
    return (argwhere(changed) + start) // _TILE


def _tile_boxes(tiles: np.ndarray, shape: tuple) -> list[tuple]:
    """Boxes covering every block (2x2 or 2x2x2) that holds a voxel of ``tiles``: each
    tile grown by one voxel on every side, in tile order."""
    tiles = np.unique(tiles, axis=0)
    return [tuple(slice(max(int(t) * _TILE - 1, 0), min((int(t) + 1) * _TILE + 1, n))
                  for t, n in zip(tile, shape)) for tile in tiles]


def _ab_to_fixed_point(w: np.ndarray, max_iterations: int, counts: dict,
                       changed: np.ndarray | None = None) -> tuple[int, bool]:
    """Run Type A then Type B sweeps until nothing changes. Returns (iterations, converged).

    The first sweep covers the whole volume, or with ``changed`` (voxels changed since
    ``w`` was last at a fixed point) only the blocks around those; every later sweep
    revisits only the tiles around the voxels the previous sweep changed, since a block
    none of whose voxels changed cannot have become a defect.
    """
    if changed is None:
        boxes = [tuple(slice(None) for _ in range(w.ndim))]
    else:
        boxes = _tile_boxes(argwhere(changed) // _TILE, w.shape)
    for it in range(1, max_iterations + 1):
        tiles = [_sweep(w, counts, box) for box in boxes]
        tiles = np.concatenate(tiles) if tiles else np.zeros((0, w.ndim), dtype=np.int64)
        if tiles.shape[0] == 0:
            return it, True
        boxes = _tile_boxes(tiles, w.shape)
    return max_iterations, False


def _tally(table: dict, new_values: np.ndarray) -> None:
    vals, n = np.unique(new_values, return_counts=True)
    for v, c in zip(vals.tolist(), n.tolist()):
        table[int(v)] = table.get(int(v), 0) + int(c)


@takes_settings("fix")
def fix_connectivity(labels: np.ndarray, *, max_iterations: int, type_c: bool, max_type_c_rounds: int,
                     majority_rounds: int) -> tuple[np.ndarray, dict]:
    """Repair Type A, B and C connectivity in a 2D or 3D label volume.

    Type A and B sweeps repeat until nothing changes (at most ``max_iterations``
    sweeps). In 3D, Type C follows in two phases, each round followed by A/B to their
    fixed point again:

    1. the paper's rule, for at most ``majority_rounds`` rounds: each offending voxel
       takes the majority class of its face neighbours; of the states reached, the one
       with the fewest sites is kept (the rule can undo itself or eat a thin plate);
    2. raising only, until no site is left (at most ``max_type_c_rounds`` rounds): a
       notch is filled, a one-voxel-thick corner has its feature made two voxels thick.
       Every change raises a class, so this phase ends, and when it ends no Type A, B
       or C arrangement is left.

    The settings are those of the ``fix:`` section, keyword-only with no defaults here;
    settings left out take the schema's defaults (:func:`dicer.config.takes_settings`).

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        0 background.
    max_iterations : int
        A/B sweeps per round at most.
    type_c : bool
        Repair Type C too (3D).
    max_type_c_rounds : int
        Rounds of the raising phase at most.
    majority_rounds : int
        Rounds of the majority phase at most.

    Returns
    -------
    fixed : ndarray
        Same dtype and shape as ``labels``.
    report : dict
        ``{"changed_voxels": n, "type_a": {class: voxels set to it}, "type_b": {...},
        "type_c": {...}, "iterations": [A/B sweeps per round], "majority_rounds": r1,
        "type_c_rounds": r2, "type_c_sites": [sites before each round kept],
        "converged": bool (no cap was hit), "remaining": connectivity_defects(fixed)}``.

    Raises
    ------
    DicerError
        Input that is not a 2D/3D non-negative integer volume.
    """
    labels = np.asarray(labels)
    if labels.ndim not in (2, 3):
        raise DicerError(f"labels have {labels.ndim} dimensions; a 2D or 3D label image is needed")
    if not np.issubdtype(labels.dtype, np.integer):
        raise DicerError(f"labels have dtype {labels.dtype}; an integer label image is needed")
    if max_iterations < 1 or max_type_c_rounds < 0 or majority_rounds < 0:
        raise DicerError("fix: max_iterations must be >= 1, max_type_c_rounds and majority_rounds >= 0")
    w = _as_work(labels).copy()
    before = w.copy()
    counts = {"A": {}, "B": {}, "C": {}}
    it, converged = _ab_to_fixed_point(w, max_iterations, counts)
    iterations = [it]
    site_counts = []
    kept_majority = rounds = 0
    left = None  # Type C sites after the majority phase, when it ran
    if w.ndim == 3 and type_c and converged and majority_rounds:
        w, counts, iterations, site_counts, kept_majority, left = _majority_phase(
            w, counts, iterations, max_iterations, majority_rounds)
    if w.ndim == 3 and type_c and converged and left != 0:
        while True:
            prop, sites = _type_c_proposals(w)
            if sites == 0:
                break
            site_counts.append(sites)
            if rounds == max_type_c_rounds:
                converged = False
                break
            diff = prop != w
            if not diff.any():  # thickening could raise nothing: fill instead
                prop, _ = _type_c_proposals(w, thicken=False)
                diff = prop != w
            rounds += 1
            _tally(counts["C"], prop[diff])
            w[diff] = prop[diff]
            it, converged = _ab_to_fixed_point(w, max_iterations, counts, changed=diff)
            iterations.append(it)
            if not converged:
                break
    remaining = connectivity_defects(w, type_c=type_c)
    report = {
        "changed_voxels": int(np.count_nonzero(w != before)),
        "type_a": {str(k): v for k, v in sorted(counts["A"].items())},
        "type_b": {str(k): v for k, v in sorted(counts["B"].items())},
        "type_c": {str(k): v for k, v in sorted(counts["C"].items())},
        "iterations": iterations,
        "majority_rounds": kept_majority,
        "type_c_rounds": rounds,
        "type_c_sites": site_counts,
        "converged": bool(converged),
        "remaining": remaining,
    }
    return w.astype(labels.dtype, copy=False), report


def _majority_phase(w, counts, iterations, max_iterations, max_rounds):
    """The paper's Type C rule, round by round on a copy; returns the state with the
    fewest sites (the earliest on ties): (labels, counts, iterations, site counts of
    the rounds kept, rounds kept, sites left)."""
    trial = w  # copied before the first change
    t_counts = {k: dict(v) for k, v in counts.items()}
    t_its, t_sites = list(iterations), []
    best = None
    r = 0
    while True:
        flat, new, sites = _type_c_voxels(trial)
        if best is None:
            best = (sites, w, counts, iterations, [], 0)
        elif sites < best[0]:
            best = (sites, trial.copy(), {k: dict(v) for k, v in t_counts.items()}, list(t_its), list(t_sites), r)
        if sites == 0 or flat.size == 0 or r == max_rounds:
            break
        r += 1
        if trial is w:
            trial = w.copy()
        t_sites.append(sites)
        _tally(t_counts["C"], new)
        changed = np.zeros(trial.shape, dtype=bool)
        changed.ravel()[flat] = True
        trial.ravel()[flat] = new
        it, ok = _ab_to_fixed_point(trial, max_iterations, t_counts, changed=changed)
        t_its.append(it)
        if not ok:
            break
    return best[1], best[2], best[3], best[4], best[5], best[0]


def connectivity_defects(labels: np.ndarray, type_c: bool = True) -> dict:
    """Count the poorly connected arrangements left in a label volume.

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        0 background.
    type_c : bool, optional
        Count Type C sites too.

    Returns
    -------
    dict
        ``type_a``: planar 2x2 blocks (all three orientations) where a class holds exactly
        one diagonal; ``type_b``: 2x2x2 blocks where a class holds exactly a body diagonal
        or exactly the six voxels off one; ``type_c``: boundary edges joining two class-A
        nodes.
    """
    w = _as_work(np.asarray(labels))
    planes = [(0, 1)] if w.ndim == 2 else [(1, 2), (0, 2), (0, 1)]
    out = {"type_a": sum(_type_a_defects(w, p) for p in planes),
           "type_b": 0, "type_c": 0}
    if w.ndim == 3:
        out["type_b"] = _type_b_defects(w)
        if type_c:
            out["type_c"] = _type_c_sites(w)
    return out


def _type_c_sites(w: np.ndarray) -> int:
    """Number of Type C sites: A-A boundary edges off the image's bounding surface."""
    _, sites = _type_c_edges(w)
    return int(sum(np.count_nonzero(s) for s in sites))


def remove_islands(labels: np.ndarray, min_voxels: int, joined_by: str = "faces") -> tuple[np.ndarray, dict]:
    """Set to background every part of the model smaller than ``min_voxels`` voxels.

    A part is a connected component of the non-background voxels through shared faces
    (the elements of a mesh hold together only through faces): a part that small floats
    free of the main body, and one floating element makes a static solve singular.
    Before the connectivity fixes, which join voxels touching at an edge or a corner,
    parts are counted through those too (``joined_by="corners"``): a structure one voxel
    thick across the voxels' diagonal is a row of parts of a voxel each until then.

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        0 background.
    min_voxels : int
    joined_by : {"faces", "corners"}
        Voxels of one part share a face, or a face, an edge or a corner.

    Returns
    -------
    labels : ndarray
        A copy when anything changed.
    report : dict
        The parts found, the parts removed and their voxels, per material.
    """
    from scipy import ndimage

    solid = labels != 0
    parts, n = ndimage.label(solid, structure=np.ones((3,) * labels.ndim, bool) if joined_by == "corners" else None)
    report = {"parts": int(n), "removed_parts": 0, "removed_voxels": 0, "removed_by_material": {}}
    if n == 0 or min_voxels <= 1:
        return labels, report
    size = np.bincount(parts.ravel(), minlength=n + 1)
    small = size < min_voxels
    small[0] = False
    if not small.any():
        return labels, report
    drop = small[parts]
    kinds, counts = np.unique(labels[drop], return_counts=True)
    out = labels.copy()
    out[drop] = 0
    report.update(removed_parts=int(small.sum()), removed_voxels=int(drop.sum()),
                  removed_by_material={str(int(k)): int(c) for k, c in zip(kinds, counts)})
    return out, report


@takes_settings("fix")
def fix_stage(labels: np.ndarray, *, names: dict[str, str], min_component_voxels: int, max_iterations: int,
              type_c: bool, max_type_c_rounds: int, majority_rounds: int, priority: list[str] | None
              ) -> tuple[np.ndarray, dict]:
    """The fix stage: floating parts removed, the connectivity fixes, floating parts again.

    The command line passes ``dicer.config.stage_kwargs(config, "fix")``; a library call
    may give a configuration as the second argument instead, or leave settings out (the
    schema's defaults fill them, :func:`dicer.config.takes_settings`).

    Parameters
    ----------
    labels : (nx, ny[, nz]) integer ndarray
        Label volume, 0 = background.
    names : dict of str to str
        Material name per label value (as a string); the report names materials by them.
    min_component_voxels, max_iterations, type_c, max_type_c_rounds, majority_rounds, priority
        The ``fix:`` config section (see the schema). With ``priority`` the fixes run on
        the labels renumbered in that order (:func:`priority_order`) and the result is
        numbered back: every fix compares classes only by their order.

    Returns
    -------
    fixed : ndarray
        The repaired labels, same shape and dtype.
    report : dict
        ``fix_connectivity``'s report with voxel changes per named material, an
        ``islands`` entry (floating parts removed before and after the fixes) and
        ``lost_materials``: the materials of the input that have no voxel left.
    """
    values, ranked = None, labels
    if priority is not None:
        values, ranked = priority_order(labels, names, priority)
    # floating parts go first (the fixes need not work on them; parts touching at an edge or
    # a corner are not floating, the fixes join them) and again after the fixes (which can
    # cut a thin bridge)
    array, islands = remove_islands(ranked, min_component_voxels, joined_by="corners")
    fixed, report = fix_connectivity.__wrapped__(array, max_iterations=max_iterations, type_c=type_c,
                                     max_type_c_rounds=max_type_c_rounds, majority_rounds=majority_rounds)
    fixed, after = remove_islands(fixed, min_component_voxels)
    if values is not None:  # numbered back: the report's classes too
        back = values.astype(labels.dtype)  # a table: no (voxels,) int64 temporaries
        fixed, array = back[fixed], labels if array is ranked else back[array]
        for part in (report, islands, after):
            for kind in ("type_a", "type_b", "type_c", "removed_by_material"):
                if kind in part:
                    part[kind] = {str(int(values[int(k)])): v for k, v in part[kind].items()}
    removed: dict[str, int] = {}
    for part in (islands, after):
        for k, v in part["removed_by_material"].items():
            removed[names.get(k, k)] = removed.get(names.get(k, k), 0) + v
    report["islands"] = {"min_component_voxels": min_component_voxels, "parts": after["parts"],
                         "removed_parts": islands["removed_parts"] + after["removed_parts"],
                         "removed_voxels": islands["removed_voxels"] + after["removed_voxels"],
                         "removed_by_material": removed}
    named = names | {"0": "background"}
    for kind in ("type_a", "type_b", "type_c"):
        report[kind] = {named.get(k, k): v for k, v in report[kind].items()}
    gone = np.setdiff1d(_present(labels), _present(fixed))
    report["lost_materials"] = [names.get(str(int(k)), str(int(k))) for k in gone[gone > 0]]
    report["joined_parts"] = joined_parts(array, fixed, after["parts"] - after["removed_parts"])
    # against the labels less their floating specks (removed and reported as such)
    report["solid_voxels"] = {"before": int(np.count_nonzero(array)), "after": int(np.count_nonzero(fixed))}
    report["faces_reached"] = faces_reached(array, fixed)
    return fixed, report


def check_priority(materials: list[str], priority: list[str]) -> None:
    """Refuse a ``fix.priority`` that names anything but materials.

    Parameters
    ----------
    materials : list of str
        The material names, label 1 first.
    priority : list of str
        ``fix.priority``: material names, the first the highest class.

    Returns
    -------
    None

    Raises
    ------
    DicerError
        Naming the unknown names and the materials.
    """
    said = unknown_materials(materials, priority, "fix.priority")
    if said:
        raise DicerError(said)


def priority_order(labels: np.ndarray, names: dict[str, str], priority: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The labels renumbered so that the fixes' order of classes is ``priority``'s.

    Parameters
    ----------
    labels : (nx, ny[, nz]) int ndarray
        0 background.
    names : dict of str to str
        Material name per label value (as a string).
    priority : list of str
        Material names, the first the highest class; the others follow below them in
        label order, the background lowest.

    Returns
    -------
    values : (K,) ndarray
        The label value of each new number (``values[renumbered]`` gives the labels back).
    renumbered : ndarray
        Same shape, 0 .. K - 1, background 0.

    Raises
    ------
    DicerError
        A name that is no material.
    """
    if not np.issubdtype(labels.dtype, np.integer):
        raise DicerError(f"labels of type {labels.dtype}: the fixes take integer labels")
    by_name: dict[str, list[int]] = {}
    for v, n in names.items():
        if int(v) != 0:
            by_name.setdefault(n, []).append(int(v))
    check_priority(list(by_name), priority)
    present = _present(labels)
    # a name of several labels: the highest of them first, as without a priority
    listed = [v for n in priority for v in sorted(by_name[n], reverse=True)]
    rest = [int(v) for v in present if v != 0 and int(v) not in listed]
    values = np.array([0] + rest + listed[::-1], dtype=np.int64)
    small = np.min_scalar_type(max(values.size - 1, 1))
    if present.size and 0 <= int(present[0]) and int(present[-1]) < 1 << 20:  # a table by value
        table = np.zeros(int(max(values.max(), present[-1])) + 1, small)
        table[values] = np.arange(values.size, dtype=small)
        return values, table[labels]
    order = np.argsort(values)
    index = np.searchsorted(values[order], labels)  # every value of labels is in ``values`` or listed
    return values, order[index].astype(small)


def joined_parts(before: np.ndarray, after: np.ndarray, parts_after: int | None = None) -> int:
    """How many separate parts of ``before`` the fixes joined into others in ``after``.

    A part is a component of the non-background voxels touching at faces (an element mesh
    holds together only through them), as in :func:`remove_islands`. The count is the parts
    of ``before`` that keep a voxel less the parts of ``after``: two parts touching only at
    an edge or a corner (which the fixes connect) or a gap one voxel wide filled between
    them (a slot the type C rounds fill) make it positive. A part split in two by the fixes
    offsets a join, so the count is a lower bound.

    Parameters
    ----------
    before, after : (nx, ny[, nz]) int ndarray
        Label volumes, 0 background, the same shape.
    parts_after : int, optional
        The parts of ``after`` when already counted.

    Returns
    -------
    int
        0 or more.
    """
    from scipy import ndimage

    comp, n = ndimage.label(before != 0, output=np.int32)
    if n < 2:
        return 0
    kept = int(np.count_nonzero(np.bincount(comp[after != 0], minlength=n + 1)[1:]))
    if parts_after is None:
        parts_after = ndimage.label(after != 0, output=np.int32)[1]
    return max(kept - int(parts_after), 0)


def faces_reached(before: np.ndarray, after: np.ndarray) -> list[str]:
    """The image's faces that material reaches in ``after`` and did not in ``before``.

    Parameters
    ----------
    before, after : (nx, ny[, nz]) int ndarray
        Label volumes, 0 background, the same shape.

    Returns
    -------
    list of str
        ``X0``, ``X1``, ``Y0``, ... (the deck's plane sets of those names), in that order.
    """
    out = []
    for axis in range(before.ndim):
        for side, end in ((0, 0), (1, -1)):
            if np.take(after, end, axis=axis).any() and not np.take(before, end, axis=axis).any():
                out.append(f"{'XYZ'[axis]}{side}")
    return out


def _present(labels: np.ndarray) -> np.ndarray:
    """The distinct values of a label volume, ascending (a count per value where they are small)."""
    if labels.size and 0 <= int(labels.min()) and int(labels.max()) < 1 << 20:
        return np.flatnonzero(count_labels(labels))
    return np.unique(labels)
