"""Sub-voxel surfaces from the labels: boundary nodes moved onto a local quadric fit of the staircase.

A label image places a surface only to within a voxel, but its staircase holds more: the
element faces between two kinds scatter about the surface they were cut from by up to half
a voxel along its normal, evenly over a few voxels of surface. After the boundary solve of
``dicer.mesh.smooth`` (``smooth.surface_from_labels``), every boundary node between exactly
two kinds (a material and the background, or two materials) moves along its normal onto a
quadric fitted by weighted least squares to those faces near it (moving least squares):

1. **Samples**: every element face between two kinds, not on a bounding plane, at the
   unsmoothed positions, cut into its lattice steps (a merged face of 1 x 4 voxels gives four
   samples), each with the face's unit normal into the higher kind and its area. With
   ``bounding_planes: mirror`` the samples near a bounding plane are mirrored across it (the
   two planes of an axis as two facing mirrors), so a cut model is fitted as the whole one is.
2. **Neighbours**: the samples within the radius r (``label_surface_radius`` voxels of the
   finest axis) of the node, of the node's pair of kinds, facing its side (the far side of a
   thin plate faces the other way; faces within 6 degrees of edge-on count less) and within two
   voxels of its tangent plane (bent by r).
3. **Fit**: in the node's frame (normal n from its elements, as the image pull takes it;
   tangents t1, t2) the height h = c0 + c1 u + c2 v + c3 u^2 + c4 uv + c5 v^2 (2D:
   c0 + c1 u + c2 u^2), weights area (1 - d^2 / r^2)^2 with d the tangential distance; then
   once more without the samples a voxel or more off the first fit (another sheet). The
   quadric takes the surface's curvature, so a curved body is not shrunk as blurring the
   labels would shrink it.
4. The node moves by c0 along n, at most the voxel's extent along n. A node with fewer than
   three samples per coefficient stays where the labels' smoothing put it.

With the scan the labels came from (``smooth.fit_to_scan``) each face sample is first placed
where the scan crosses its threshold within its voxel pair (:func:`scan_crossings`); blurring
moves such an iso-surface towards its centres of curvature by s^2 H (s^2 the edge's variance
in the smoothed scan, :func:`edge_variance`; H the mean curvature, at most a sphere's of the
window's radius), so the node moves by c0 - s^2 (c3 + c5) (2D: c0 - s^2 c2), as the pull onto
the scan takes the shift back.

The fitted surface does not depend on the smoothing coefficients, so it is fitted once per
stage; the quality guard then backs the move off as it backs off the pull onto a scan.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy import special
from scipy.spatial import cKDTree

from dicer.arrays import nonzero, norm
from dicer.errors import DicerError
from dicer.mesh.boundary import plane_bits
from dicer.mesh.faces import neighbour_materials
from dicer.mesh.labelnet import RELAXATION_STEPS, faces_between, relaxed_staircase
from dicer.mesh.model import Mesh
from dicer.mesh.subvoxel import normal_density
from dicer.mesh.topology import HEX_FACES, QUAD_EDGES
from dicer.parallel import ordered_map

__all__ = ["LabelSurface", "check_labels_for_mesh", "edge_variance", "label_image_samples", "scan_crossings",
           "staircase_samples"]

log = logging.getLogger("dicer")

_FACING = 0.1  # the cosine between a face's and the node's normals from which a face counts fully
_SHEET = 2.0  # voxels off the tangent plane (besides the bend over r) where another sheet begins
_OUTLIER = 1.0  # voxels off the first fit: dropped from the second
_LEAN = 0.3  # the fit's slope at its node (about 17 degrees) from which it is fitted again along its own normal
_PER_COEFFICIENT = 3  # samples needed per coefficient of the fit
_CHUNK = 2048  # nodes fitted at a time: (chunk, k) temporaries, some 10 of them, k 180 or more
_GROUPS = 4  # a chunk's nodes fitted in this many groups of like sample counts
_FAR = 2.5  # voxels either side of a face where the scan's contrast across its edge is read
_CHECKED = 200_000  # elements checked against a label volume at most (evenly spread)
_AGREE = 0.999  # the share of them that must lie on voxels of their own material (measured: all of them
# on the meshes of their own labels; 97.4 % on a head's labels flipped left to right, 90.4 % on its labels before
# the fix: 0.9 until 6 December 2026 let both through)
_GIVE = ("give the label volume the mesh was made from (labels_fixed.nii.gz of dicer run, or what dicer fix "
         "wrote)")


def staircase_samples(mesh: Mesh, mirror_reach: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The faces between two kinds, cut into lattice steps.

    Parameters
    ----------
    mesh : Mesh
        Voxel, plane-merged or graded, unsmoothed (its ``points`` on the lattice).
    mirror_reach : float, optional
        Mirror the samples within this distance (mm) of each bounding plane across it, the
        mirror images too (so a corner of two or three planes is mirrored into each of its
        quadrants or octants, and a slab thinner than the distance into an endless prism);
        0: none.

    Returns
    -------
    points : (S, dim) float64 ndarray
        Sample positions, mm.
    normals : (S, dim) float64 ndarray
        Unit normals into the higher kind.
    kinds : (S, 2) int64 ndarray
        The lower and the higher kind (0: background).
    weights : (S,) float64 ndarray
        The area (2D: length) each sample stands for, mm^2 (mm).
    """
    dim = mesh.dim
    x0 = np.asarray(mesh.points, float)
    table = HEX_FACES if dim == 3 else QUAD_EDGES
    across = neighbour_materials(mesh)
    own = np.asarray(mesh.material)
    # a face between two materials once, from its lower material's element
    elem, face = nonzero((across != own[:, None]) & ((across == 0) | (across > own[:, None])))
    corner = np.asarray(mesh.cells)[elem[:, None], table[face]]  # (F, 4 | 2)
    # the image's edge is no surface between two kinds: a face whose corners share a bounding plane
    keep = np.bitwise_and.reduce(plane_bits(mesh, x0)[corner], axis=1) == 0
    elem, face, corner = elem[keep], face[keep], corner[keep]
    a, b = own[elem].astype(np.int64), across[elem, face].astype(np.int64)
    kinds = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    p = x0[corner][..., :dim]  # (F, 4 | 2, dim)
    if dim == 3:
        nrm = np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 1])
        area = 0.5 * norm(nrm, axis=1)
    else:
        e = p[:, 1] - p[:, 0]
        nrm = np.stack([e[:, 1], -e[:, 0]], axis=1)
        area = norm(nrm, axis=1)
    nrm /= np.maximum(norm(nrm, axis=1), 1e-30)[:, None]
    inward = x0[np.asarray(mesh.cells)[elem]][..., :dim].mean(axis=1) - p.mean(axis=1)  # into the face's element
    towards_own = np.sign(np.einsum("ij,ij->i", nrm, inward))
    nrm *= (np.where(a == kinds[:, 1], 1.0, -1.0) * towards_own)[:, None]
    # lattice steps along the face's two edges from corner 0
    lat = np.asarray(mesh.lattice)[corner][..., :dim]
    steps_u = np.maximum(np.abs(lat[:, 1] - lat[:, 0]).max(axis=1), 1)
    steps_v = np.maximum(np.abs(lat[:, -1] - lat[:, 0]).max(axis=1), 1) if dim == 3 else np.ones_like(steps_u)
    code = steps_u * (int(steps_v.max(initial=1)) + 1) + steps_v
    parts = []
    for c in np.unique(code):  # a few face sizes
        sel = np.flatnonzero(code == c)
        nu, nv = int(steps_u[sel[0]]), int(steps_v[sel[0]])
        su, sv = (np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv
        if dim == 3:
            uu, vv = (g.ravel() for g in np.meshgrid(su, sv, indexing="ij"))
            shape = np.stack([(1 - uu) * (1 - vv), uu * (1 - vv), uu * vv, (1 - uu) * vv], axis=1)  # bilinear
        else:
            shape = np.stack([1 - su, su], axis=1)
        pts = np.einsum("sc,fcd->fsd", shape, p[sel])  # (f, steps, dim)
        k = shape.shape[0]
        parts.append((pts.reshape(-1, dim), np.repeat(nrm[sel], k, axis=0), np.repeat(kinds[sel], k, axis=0),
                      np.repeat(area[sel] / k, k)))
    if not parts:
        return np.zeros((0, dim)), np.zeros((0, dim)), np.zeros((0, 2), np.int64), np.zeros(0)
    points, normals, kinds, weights = (np.concatenate(x) for x in zip(*parts))
    return _mirrored(mesh, (points, normals, kinds, weights), mirror_reach)


def label_image_samples(labels, mesh: Mesh, mirror_reach: float = 0.0
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The faces between two kinds of a label volume: the staircase its voxel mesh has.

    The samples :func:`staircase_samples` gives for ``voxel_mesh(labels)``, in another order,
    without making that mesh; for a plane-merged or graded mesh of these labels, the
    staircase before merging (a merge's chamfers and filled notches add volume at the surface).

    Parameters
    ----------
    labels : dicer.image.Volume
        (nx, ny[, nz]) integer labels, 0 background, on ``mesh``'s lattice
        (:func:`check_labels_for_mesh`).
    mesh : Mesh
        The mesh of the labels: its origin, spacing and bounding planes.
    mirror_reach : float, optional
        As in :func:`staircase_samples`.

    Returns
    -------
    points, normals, kinds, weights
        As :func:`staircase_samples`.
    """
    lab = np.asarray(labels.array)
    dim = lab.ndim
    spacing = np.asarray(mesh.spacing, float)[:dim]
    origin = np.asarray(mesh.origin, float)[:dim]
    parts = []
    for d, index, a, b in faces_between(lab):  # the faces between voxels i and i + 1 along d
        centre = index.astype(float) + 0.5
        centre[:, d] += 0.5
        normal = np.zeros((a.size, dim))
        normal[:, d] = np.where(b > a, 1.0, -1.0)  # into the higher kind
        parts.append((origin + centre * spacing, normal, np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1),
                      np.full(a.size, float(np.prod(np.delete(spacing, d))))))
    samples = tuple(np.concatenate(x) for x in zip(*parts))
    return _mirrored(mesh, samples, mirror_reach)


def _thresholds_of(kinds: np.ndarray, scan) -> np.ndarray:
    """(S,) the scan's threshold of each sample's pair: the higher kind's lower bound."""
    return np.asarray(scan.thresholds, float)[np.clip(kinds[:, 1] - 1, 0, len(scan.thresholds) - 1)]


def scan_crossings(points: np.ndarray, normals: np.ndarray, kinds: np.ndarray, step: np.ndarray, scan) -> np.ndarray:
    """Face samples moved to where the scan crosses their threshold between the voxels' centres.

    A face between a voxel of the lower kind and one of the higher lies half a voxel from
    each centre; where an edge of the (smoothed) scan passes there (it rises across the higher
    kind's threshold between the two centres, or past a centre that the smoothing tipped over
    it while the scan crosses it further out that way), the sample moves to where the edge
    crosses the threshold, at most half a voxel: the crossing of the edge fitted through the
    two centres' values as a blurred step (the normal distribution's integral between the
    values 2.5 voxels either side, where those rise and bracket the centres'; else the straight
    line between the centres), or the nearer centre where the threshold lies beyond it.
    Elsewhere (the segmentation's clean-up, noise across the threshold) the sample stays on
    the face: the surface follows the labels, placed within the voxel by the scan.

    Parameters
    ----------
    points, normals : (S, dim) float64 ndarray
        Face centres (mm) and unit normals into the higher kind.
    kinds : (S, 2) int64 ndarray
        Lower and higher kind (0: background).
    step : (S,) float64 ndarray
        The voxel's extent along each normal, mm.
    scan : dicer.mesh.subvoxel.ImageSurface
        Its ``thresholds`` (lower bound of each material) and ``sample``.

    Returns
    -------
    (S, dim) float64 ndarray
    """
    t = _thresholds_of(kinds, scan)
    at = lambda f: scan.sample(points + (f * step)[:, None] * normals).astype(float)  # noqa: E731
    below, above = at(-0.5), at(0.5)
    low = at(-_FAR)
    contrast = at(_FAR) - low
    # an edge through the threshold here: the scan rises across it between the centres, or past
    # a centre that the smoothing tipped over it while the scan crosses it further out that way
    # (where both sides lie above it, the segmentation's clean-up or the fix made the face, and
    # noise alone would move it)
    edge = (above > below) & (((below < t) & (t <= above)) | ((below >= t) & (low < t))
                              | ((above < t) & (low + contrast >= t)))
    f = np.where(edge, np.clip((t - below) / np.where(edge, above - below, 1.0), 0.0, 1.0), 0.5)
    # a blurred edge rises as the normal distribution's integral: interpolated on its scale
    # (probit of the level within the edge's contrast) the crossing is that of the edge itself,
    # where the straight line between the centres leans towards the middle; only where the far
    # values bracket the centres' (a plate of a few voxels: its far side spoils them)
    rises = edge & (contrast > 0)  # the far values: a scale only where the higher side's is higher
    level = lambda v: (v - low) / np.where(rises, contrast, 1.0)  # noqa: E731
    q_below, q_above = level(below), level(above)
    bracketed = rises & (q_below > 0.01) & (q_above < 0.99)
    z_below, z_above = special.ndtri(np.clip(q_below, 0.01, 0.99)), special.ndtri(np.clip(q_above, 0.01, 0.99))
    z_t = special.ndtri(np.clip(level(t), 0.01, 0.99))
    f = np.where(bracketed, np.clip((z_t - z_below) / np.where(bracketed, z_above - z_below, 1.0), 0.0, 1.0), f)
    return points + ((f - 0.5) * step)[:, None] * normals


def edge_variance(points: np.ndarray, kinds: np.ndarray, scan) -> dict:
    """Each pair of kinds' edge width in the smoothed scan, as a Gaussian's variance.

    Blurring moves the iso-surface of a curved body towards its centres of curvature by
    this variance times the mean curvature, which the fit takes back. An edge of contrast
    D blurred by a Gaussian of standard deviation s has, at its level q, the gradient
    D phi(Phi^-1(q)) / s: measured at each sample the scan placed (central differences
    over half a voxel along each axis, the contrast 2.5 voxels either side along the
    gradient) and the median taken per pair. An edge wider than a voxel's width squared plus
    the scan's own smoothing squared is no blurred step (a thin part's far side spoils D; an
    MR image's shading rises over many voxels): 0 there, no shift taken back.

    Parameters
    ----------
    points : (S, dim) float64 ndarray
        Samples placed on the scan's crossings by :func:`scan_crossings`, mm.
    kinds : (S, 2) int64 ndarray
        Lower and higher kind.
    scan : dicer.mesh.subvoxel.ImageSurface

    Returns
    -------
    dict
        ``(lower, higher) -> variance`` in mm^2, for the pairs with samples.
    """
    dim = points.shape[1]
    spacing = np.asarray(scan.spacing, float)[:dim]
    t = _thresholds_of(kinds, scan)
    grad = np.empty_like(points)
    for d in range(dim):
        h = np.zeros(dim)
        h[d] = 0.25 * spacing[d]
        grad[:, d] = (scan.sample(points + h) - scan.sample(points - h)).astype(float) / (2 * h[d])
    slope = norm(grad, axis=1)
    up = grad / np.maximum(slope, 1e-30)[:, None]
    far = _FAR * float(np.max(spacing))
    low = scan.sample(points - far * up).astype(float)
    contrast = scan.sample(points + far * up).astype(float) - low
    level = np.clip((t - low) / np.where(contrast > 0, contrast, 1.0), 0.05, 0.95)
    density = normal_density(special.ndtri(level))
    good = (slope > 0) & (contrast > 0)
    # the interpolated scan's gradient is a chord between voxel centres: to first order a box
    # of a voxel along u more blur, whose variance (sum u_d^2 h_d^2 / 12) is taken off
    chord = (up * up * (spacing * spacing)).sum(axis=1) / 12.0  # not a BLAS product: the same bytes on every CPU
    var = np.maximum((contrast * density / np.where(good, slope, 1.0)) ** 2 - chord, 0.0)
    cap = float(np.max(spacing)) ** 2 + (scan.sigma * float(np.min(spacing))) ** 2
    # medians per pair, by one sort (an atlas has thousands of pairs)
    codes = np.unique(kinds[good], axis=0)  # in the order of their codes below
    out = {}
    if codes.size:
        key = kinds[good, 0].astype(np.int64) * (int(kinds[:, 1].max()) + 1) + kinds[good, 1]
        order = np.argsort(key, kind="stable")
        groups = np.split(var[good][order], np.flatnonzero(np.diff(key[order])) + 1)
        for (a, b), values in zip(codes, groups):
            median = float(np.median(values))
            out[(int(a), int(b))] = median if median <= cap else 0.0
    return out


def check_labels_for_mesh(labels, mesh: Mesh, source: str) -> None:
    """Raise unless ``labels`` is a label volume ``mesh`` can have been made from.

    Its dimensions, voxel count per axis, voxel size, origin and
    direction cosines (when both have them) must be the mesh's, and of the elements (at most
    ``_CHECKED``, evenly spread) all but a thousandth must hold a voxel of their own material
    at a corner (inside the element; every one does on its own labels, a merge's chamfers and
    filled notches included, while labels flipped or taken before the fix miss on a few per
    cent).

    Parameters
    ----------
    labels : dicer.image.Volume
    mesh : Mesh
    source : str
        The labels' name in messages.

    Raises
    ------
    DicerError
    """
    lab = np.asarray(labels.array)
    dim = mesh.dim
    if lab.ndim != dim:
        raise DicerError(f"{source}: a {lab.ndim}D label volume for a {dim}D mesh; {_GIVE}")
    grid = tuple(int(v) for v in np.asarray(mesh.grid_shape)[:dim])
    if lab.shape != grid:
        raise DicerError(f"{source}: {'x'.join(map(str, lab.shape))} voxels, but the mesh was made from "
                         f"{'x'.join(map(str, grid))}; {_GIVE}")
    if mesh.direction is not None and labels.direction is not None and not np.allclose(
            np.asarray(labels.direction, float).reshape(dim, dim), np.asarray(mesh.direction, float)[:dim, :dim],
            atol=1e-5):
        raise DicerError(f"{source}: the labels' direction cosines differ from the mesh's (their axes are turned or "
                         f"flipped); {_GIVE}")
    for what, mine, theirs in (("voxel size", labels.spacing, mesh.spacing), ("origin", labels.origin, mesh.origin)):
        mine, theirs = np.asarray(mine, float)[:dim], np.asarray(theirs, float)[:dim]
        if not np.allclose(mine, theirs, rtol=1e-6, atol=1e-6 * float(np.max(np.asarray(mesh.spacing)[:dim]))):
            raise DicerError(f"{source}: {what} {' x '.join(f'{v:g}' for v in mine)} mm, the mesh's "
                             f"{' x '.join(f'{v:g}' for v in theirs)} mm; {_GIVE}")
    n = mesh.n_cells
    rows = np.arange(0, n, max(1, -(-n // _CHECKED)))
    # the voxel inside each element at each of its corners: a merged box's are all its own, a
    # chamfer's or a filled notch's unmoved corners hold the voxel it was made from
    corners = np.asarray(mesh.lattice)[np.asarray(mesh.cells)[rows]][..., :dim]
    # a pillow layer's elements (a smoothed mesh's) sit on no voxel of theirs: their copies keep
    # the lattice points of the face under them (flat, or on a merged mesh's sloped face)
    spans = np.all(corners.max(axis=1) > corners.min(axis=1), axis=1)
    key = np.sort(np.ravel_multi_index(tuple(np.moveaxis(corners + 1, -1, 0)), tuple(np.array(grid) + 3)), axis=1)
    spans &= np.all(key[:, 1:] != key[:, :-1], axis=1)  # no two corners on one lattice point
    rows, corners = rows[spans], corners[spans]
    voxel = corners - (corners > corners.mean(axis=1, keepdims=True))
    np.clip(voxel, 0, np.array(grid) - 1, out=voxel)
    own = np.any(lab[tuple(np.moveaxis(voxel, -1, 0))] == np.asarray(mesh.material)[rows, None], axis=1)
    if rows.size and np.count_nonzero(own) < _AGREE * rows.size:
        raise DicerError(f"{source}: {rows.size - np.count_nonzero(own)} of {rows.size} elements of the mesh hold no "
                         f"voxel of their material in these labels, so it was not made from them; {_GIVE}")


def _mirrored(mesh: Mesh, samples: tuple, mirror_reach: float) -> tuple:
    """The samples with their mirror images across the bounding planes within ``mirror_reach``
    (mm) of the model (none for 0)."""
    points, normals, kinds, weights = samples
    dim = points.shape[1]
    if mirror_reach > 0:
        lo = np.asarray(mesh.origin, float)[:dim]
        hi = lo + np.asarray(mesh.grid_shape, float)[:dim] * np.asarray(mesh.spacing, float)[:dim]
        for d in range(dim):
            # the two planes of an axis are two mirrors: their images repeat with period twice
            # the model's width (a slab thinner than the reach is an endless prism), each image
            # x + 2 k T (k != 0) or 2 lo - x + 2 k T, within the reach of the model
            width = hi[d] - lo[d]
            turns = int(np.ceil(mirror_reach / (2 * width))) + 1
            copies = [(points, normals, kinds, weights)]
            for k in range(-turns, turns + 1):
                for flip in (False, True):
                    if k == 0 and not flip:
                        continue
                    c = (2 * lo[d] - points[:, d] if flip else points[:, d]) + 2 * k * width
                    near = np.flatnonzero((c > lo[d] - mirror_reach) & (c < hi[d] + mirror_reach))
                    mp, mn = points[near], normals[near]
                    mp[:, d] = c[near]
                    if flip:
                        mn[:, d] = -mn[:, d]
                    copies.append((mp, mn, kinds[near], weights[near]))
            points, normals, kinds, weights = (np.concatenate(x) for x in zip(*copies))
    return points, normals, kinds, weights


def _cosines(near: np.ndarray, n: np.ndarray, dim: int) -> np.ndarray:
    """(P, k) cosines between the gathered samples' normals ``near[..., dim:]`` and ``n`` (P, dim),
    summed over the axes in numpy's order, term by term (a mirrored model sums alike)."""
    cos = near[..., dim] * n[:, None, 0]
    for a in range(1, dim):
        cos += near[..., dim + a] * n[:, None, a]
    return cos


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` scaled to length 1 (a zero row stays zero)."""
    length = norm(v, axis=1)
    return v / np.where(length > 0, length, 1.0)[:, None]


def _along(rel: list[np.ndarray], n: np.ndarray) -> np.ndarray:
    """(P, k): the vectors whose components are the arrays ``rel`` (each (P, k)) dotted with
    ``n`` (P, len(rel)), term by term.

    Elementwise products and sums, not a matrix product: BLAS picks its kernels by the CPU,
    and their last bits differ between them (the fit then gave other bytes on another machine)."""
    out = rel[0] * n[:, None, 0]
    for a in range(1, len(rel)):
        out += rel[a] * n[:, None, a]
    return out


def _weighted_fit(basis: list[np.ndarray], w: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(P, m) least-squares coefficients of ``h`` (P, k) in the m functions ``basis`` (each
    (P, k), the first the constant 1) with weights ``w`` (P, k); a relative 1e-9 on the
    diagonal keeps a degenerate row solvable.

    The normal equations are summed and solved (Cholesky) element by element, not by BLAS or
    LAPACK, whose kernels the CPU picks: the same bytes on every machine."""
    m = len(basis)
    wb = [w] + [b * w for b in basis[1:]]  # the constant's products are the others' own
    a = np.empty((w.shape[0], m, m))
    for i in range(m):
        a[:, i, 0] = a[:, 0, i] = np.sum(wb[i], axis=1)
        for j in range(1, i + 1):
            a[:, i, j] = a[:, j, i] = np.sum(wb[i] * basis[j], axis=1)
    rhs = np.stack([np.sum(wb[i] * h, axis=1) for i in range(m)], axis=1)
    trace = a[:, 0, 0].copy()
    for i in range(1, m):
        trace += a[:, i, i]
    for i in range(m):
        a[:, i, i] += 1e-9 * np.maximum(trace, 1e-30)
    # Cholesky, a = l l^T, then the two triangular solves
    low = np.zeros_like(a)
    for j in range(m):
        d = a[:, j, j].copy()
        for q in range(j):
            d -= low[:, j, q] * low[:, j, q]
        low[:, j, j] = np.sqrt(np.maximum(d, 1e-300))
        for i in range(j + 1, m):
            e = a[:, i, j].copy()
            for q in range(j):
                e -= low[:, i, q] * low[:, j, q]
            low[:, i, j] = e / low[:, j, j]
    y = np.empty_like(rhs)
    for i in range(m):
        e = rhs[:, i].copy()
        for q in range(i):
            e -= low[:, i, q] * y[:, q]
        y[:, i] = e / low[:, i, i]
    coef = np.empty_like(rhs)
    for i in reversed(range(m)):
        e = y[:, i].copy()
        for q in range(i + 1, m):
            e -= low[:, q, i] * coef[:, q]
        coef[:, i] = e / low[:, i, i]
    return coef


class LabelSurface:
    """The labels' staircase near a mesh, and the fit of its boundary nodes onto it.

    Parameters
    ----------
    mesh : Mesh
        The mesh to be smoothed (unsmoothed: on its lattice).
    radius : float
        The fit's radius, voxels of the finest axis.
    mirror : bool
        ``bounding_planes: mirror``: samples mirrored across the bounding planes.
    labels : dicer.image.Volume, optional
        The label volume the mesh was made from (checked by :func:`check_labels_for_mesh`):
        the staircase is taken from it instead of from the mesh's faces, so a plane-merged or
        graded mesh is fitted to the labels' surface, not to its chamfers.
    scan : dicer.mesh.subvoxel.ImageSurface, optional
        With ``labels``: the scan they were segmented from, which places each face sample
        within its voxel pair (:func:`scan_crossings`).
    relaxed : bool, optional
        With ``labels`` (and no ``scan``): the samples are the staircase's vertices relaxed to
        its smoothest surface within their voxels (:func:`dicer.mesh.labelnet.relaxed_staircase`,
        ``smooth.label_samples: relaxed``), not the faces' centres.
    """

    def __init__(self, mesh: Mesh, radius: float, mirror: bool, labels=None, scan=None, relaxed: bool = False):
        dim = mesh.dim
        self.dim = dim
        spacing = np.asarray(mesh.spacing, float)[:dim]
        self.mesh_spacing = spacing
        self.voxel = float(spacing.max())
        # the fit works in units of the finest voxel, so a volume whose voxels are micrometres or
        # metres fits as one of 1 mm voxels (the least-squares damping is relative to its terms)
        self.unit = float(spacing.min())
        self.radius = float(radius) * self.unit
        reach = self.radius if mirror else 0.0
        self.placed = self.placed_share = None
        self.top = int(np.max(mesh.material, initial=0)) + 1
        blur = {}  # (lower, higher) -> the scan's edge variance, mm^2: the blur's shift taken back
        self.relaxed = bool(relaxed and labels is not None)
        if labels is None:
            samples = staircase_samples(mesh, reach)
        else:
            points, normals, kinds, weights = label_image_samples(labels, mesh)
            if scan is not None:  # placed before mirroring, so the mirror images are placed alike
                step = (np.abs(normals) * spacing).sum(axis=1)
                placed = scan_crossings(points, normals, kinds, step, scan)
                moved = np.any(placed != points, axis=1)
                self.placed = int(np.count_nonzero(moved))
                # of the labels' faces, before mirroring (none: a crop within one material)
                self.placed_share = self.placed / points.shape[0] if points.shape[0] else None
                # the edge's width where the scan crosses between the centres: a sample sent to a
                # centre lies off the edge (a part the labels or their downsampling made larger
                # than the scan's), where the gradient is flatter and would widen it
                between = moved & (np.abs(np.einsum("ij,ij->i", placed - points, normals)) < 0.5 * step * (1 - 1e-9))
                blur = edge_variance(placed[between], kinds[between], scan)
                points, unplaced = placed, points
            if relaxed:  # the staircase's vertices at its fairest surface within their voxels
                moves = None
                if scan is not None:  # through the scan's placements, voxels along each face's axis
                    # (a face the scan leaves where it is counts there, as its sample does)
                    moves = ((points - unplaced) / spacing).sum(axis=1)
                # progress: the relaxation takes tens of seconds on a head, before the fit says anything
                t = time.perf_counter()
                log.info("smooth: relaxing the labels' staircase within its voxels (%d faces, %d steps; "
                         "smooth.label_samples)", points.shape[0], RELAXATION_STEPS)
                samples = _mirrored(mesh, relaxed_staircase(np.asarray(labels.array), mesh.spacing[:dim],
                                                            mesh.origin[:dim], mirror=mirror, placed=moves), reach)
                log.info("smooth: relaxed in %.1f s", time.perf_counter() - t)
            else:
                samples = _mirrored(mesh, (points, normals, kinds, weights), reach)
        self.points, self.normals, kinds, self.weights = samples
        self._points_normals = np.c_[self.points, self.normals]  # gathered together by the fit
        # the mesh's faces off the lattice's axes: merging's slopes (chamfers), off the labels' surface
        self.sloped = 0 if labels is not None else int(np.count_nonzero(np.abs(self.normals).max(axis=1) < 1 - 1e-9))
        # thresholds for NodeSides: one per material (the labels have no image values)
        self.thresholds = np.arange(1, self.top, dtype=float)
        # each pair of kinds in a space of its own: a fourth coordinate, the pair's rank times
        # more than the radius, so a query finds its own pair's samples only (an atlas's
        # thousands of pairs would otherwise crowd each other's neighbourhoods)
        self.pairs, rank = np.unique(kinds[:, 0] * self.top + kinds[:, 1], return_inverse=True)
        self.blur = blur
        self._pair_blur = np.array([blur.get((int(c) // self.top, int(c) % self.top), 0.0) for c in self.pairs])
        self._apart = 4.0 * self.radius
        self.tree = cKDTree(np.c_[self.points, rank * self._apart]) if self.points.shape[0] else None
        # the samples a disc of the radius holds on a staircase (sqrt 3 its area), and more (a thin
        # part's far side): most nodes' all in one query
        r = float(radius)
        self.k = int(np.ceil(3.0 * np.pi * r * r if dim == 3 else 6.0 * r)) + 8

    def offsets(self, y: np.ndarray, normal: np.ndarray, pair: np.ndarray, fixed: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fitted surface's height above each node along its normal.

        Parameters
        ----------
        y : (P, 3) float64 ndarray
            Node positions, mm.
        normal : (P, 3) float64 ndarray
            Unit normals into the higher kind.
        pair : (P,) int64 ndarray
            Each node's kinds, lower * ``top`` + higher.
        fixed : (P, 3) bool ndarray, optional
            Coordinates the nodes keep (a plane's axis): the fit's normal has none along them.

        Returns
        -------
        height : (P,) float64 ndarray
            mm along ``direction``, 0 where no fit.
        fitted : (P,) bool ndarray
            Nodes with enough samples for the fit.
        direction : (P, 3) float64 ndarray
            Unit normals the heights lie along: ``normal``, or where the fit along it leaned, its
            own normal, or where it failed, the staircase's mean normal about the node.
        """
        height = np.zeros(y.shape[0])
        fitted = np.zeros(y.shape[0], bool)
        direction = np.array(normal, float, copy=True)
        if self.tree is None or y.shape[0] == 0:
            return height, fitted, direction
        free = np.ones((y.shape[0], self.dim)) if fixed is None else (~fixed[:, :self.dim]).astype(float)

        def fit(part: slice) -> None:
            height[part], fitted[part], direction[part, :self.dim] = self._fit(
                y[part, :self.dim], direction[part, :self.dim], pair[part], free[part])

        for _ in ordered_map(fit, [slice(s, s + _CHUNK) for s in range(0, y.shape[0], _CHUNK)]):
            pass
        return height, fitted, direction

    def _neighbours(self, p: np.ndarray, pair: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every sample of the pair within the radius of each point: (P, k) distances (inf: none)
        and indices.

        The k nearest are asked for, and again with twice k where all k lie within the radius,
        so no sample within it is left out (leaving some out would break ties by numbering and
        a mirrored model would not fit alike)."""
        rank = np.searchsorted(self.pairs, pair)
        known = (rank < self.pairs.size) & (self.pairs[np.minimum(rank, self.pairs.size - 1)] == pair)
        p = np.c_[p, np.where(known, rank, -1) * self._apart]  # a pair without samples: none near
        k = min(self.k, self.points.shape[0])
        dist, idx = self.tree.query(p, k=k, distance_upper_bound=self.radius)
        full = np.isfinite(dist[:, -1])
        while full.any() and k < self.points.shape[0]:
            k = min(2 * k, self.points.shape[0])
            rows = np.flatnonzero(full)
            d2, i2 = self.tree.query(p[rows], k=k, distance_upper_bound=self.radius)
            wide_d = np.full((p.shape[0], k), np.inf)
            wide_i = np.full((p.shape[0], k), self.points.shape[0], np.int64)
            wide_d[:, :dist.shape[1]], wide_i[:, :idx.shape[1]] = dist, idx
            wide_d[rows], wide_i[rows] = d2, i2
            dist, idx = wide_d, wide_i
            full = np.zeros(p.shape[0], bool)
            full[rows] = np.isfinite(d2[:, -1])
        # sorted by distance, the misses last: as wide as the fullest row (the doubling widens
        # every row for a few, and the fit's temporaries are this wide)
        width = max(int(np.count_nonzero(np.isfinite(dist), axis=1).max(initial=0)), 1)
        return dist[:, :width], idx[:, :width]

    def _fit(self, p: np.ndarray, n: np.ndarray, pair: np.ndarray, free: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(P,) heights, fitted flags and (P, dim) normals of the fit of the points ``p`` (P, dim)
        with normals ``n`` (P, dim); ``free`` (P, dim): 1 where a normal may have a component."""
        dist, idx = self._neighbours(p, pair)
        rank = np.minimum(np.searchsorted(self.pairs, pair), max(self.pairs.size - 1, 0))
        blur = np.where(self.pairs[rank] == pair, self._pair_blur[rank], 0.0) if self.pairs.size else np.zeros(p.shape[0])
        # in groups of like sample counts, each as wide as its fullest row: the counts vary
        # twofold (a thin plate's both sides), and the temporaries are that wide
        count = np.count_nonzero(np.isfinite(dist), axis=1)
        order = np.argsort(count, kind="stable")
        height, fitted, direction = np.zeros(p.shape[0]), np.zeros(p.shape[0], bool), n.copy()
        for g in np.array_split(order, _GROUPS):
            if g.size:
                width = max(int(count[g].max()), 1)
                height[g], fitted[g], direction[g] = self._fit_samples(p[g], n[g], dist[g, :width], idx[g, :width],
                                                                       blur[g], free[g])
        return height, fitted, direction

    def _fit_samples(self, p: np.ndarray, n: np.ndarray, dist: np.ndarray, idx: np.ndarray, blur: np.ndarray,
                     free: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fit of points ``p`` (P, dim) with normals ``n`` to their samples (``dist``, ``idx``:
        (P, k), inf where none); ``blur`` (P,): the scan's edge variance (mm^2) whose shift of a
        curved iso-surface (towards its centres of curvature, by the variance times the mean
        curvature) is taken back, 0 for the labels; ``free`` (P, dim): 1 where the normal may
        have a component. Returns heights, fitted flags and the normals they lie along.

        The smoothed mesh's normal ``n`` can miss the surface's by 25 degrees and more in the middle
        of a flat run of the staircase (its elements there stand square): the fit along it then
        leans, or facing too few samples fails and the node would keep the labels' smoothing. A
        leaning node is fitted again along the first fit's own normal, a failed one along the
        staircase's mean normal about it."""
        ok = np.isfinite(dist)
        idx[~ok] = 0
        near = np.take(self._points_normals, idx, axis=0)  # (np.take gathers rows several times faster)
        weights = np.take(self.weights, idx)
        height, fitted, slope, _ = self._fit_in_frame(p, n, near, ok, weights, blur)
        n = n.copy()
        # leaning: fitted again along the fit's own normal at the node, kept where the surface
        # found is no more curved than the blur's shift allows (a part smaller than the window,
        # fitted beyond its equator, reads otherwise in every frame)
        lean = np.flatnonzero(fitted & (np.einsum("ij,ij->i", slope, slope) > _LEAN * _LEAN))
        if lean.size:
            own = _unit((n[lean] - slope[lean]) * free[lean])
            h2, f2, _, mild = self._fit_in_frame(p[lean], own, near[lean], ok[lean], weights[lean], blur[lean])
            take = f2 & mild
            height[lean[take]], n[lean[take]] = h2[take], own[take]
        lost = np.flatnonzero(~fitted)
        if not lost.size:
            return height, fitted, n
        # failed: the faces on the node's side (edge-on ones too), nearer ones more
        r, dim = self.radius, self.dim
        q = np.where(ok[lost], dist[lost] * dist[lost] / (r * r), 1.0)
        w = np.where(_cosines(near[lost], n[lost], dim) > -_FACING, (1.0 - np.minimum(q, 1.0)) ** 2 * weights[lost], 0.0)
        mean = np.stack([np.einsum("ij,ij->i", w, near[lost, :, dim + a]) for a in range(dim)], axis=1) * free[lost]
        some = norm(mean, axis=1) > 1e-9 * w.sum(axis=1)  # relative: the weights are areas, mm^2
        lost, mean = lost[some], _unit(mean[some])
        h2, f2, _, _ = self._fit_in_frame(p[lost], mean, near[lost], ok[lost], weights[lost], blur[lost])
        take = lost[f2]
        height[take], fitted[take], n[take] = h2[f2], True, mean[f2]
        return height, fitted, n

    def _fit_in_frame(self, p: np.ndarray, n: np.ndarray, near: np.ndarray, ok: np.ndarray, weights: np.ndarray,
                      blur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The quadric fit of ``p`` (P, dim) along ``n`` (P, dim) to the gathered samples ``near``
        (P, k, 2 dim: positions and normals; ``ok`` (P, k), ``weights`` (P, k)): heights, fitted
        flags, (P, dim) the fitted surface's slope at the node (its normal is n - slope, not
        scaled) and whether its curvature lies within the blur's limit."""
        dim, unit = self.dim, self.unit
        r, voxel = self.radius / unit, self.voxel / unit  # lengths below in units of the finest voxel
        # facing the node's side: a weight rising from 0 (edge-on) to 1 at _FACING, continuous so
        # that faces edge-on to the node (an axis-aligned normal) count alike in a mirrored model
        facing = np.clip(_cosines(near, n, dim) / _FACING, 0.0, 1.0)
        rel = [(near[..., a] - p[:, None, a]) / unit for a in range(dim)]  # (P, k) each: rows run on
        h = _along(rel, n)  # (P, k)
        if dim == 2:
            u = rel[0] * -n[:, None, 1] + rel[1] * n[:, None, 0]
            d2 = u * u
            basis = [np.ones_like(u), u, u * u]
        else:
            helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
            t1 = np.cross(n, helper)
            t1 /= norm(t1, axis=1)[:, None]
            t2 = np.cross(n, t1)
            u = _along(rel, t1)
            v = _along(rel, t2)
            d2 = u * u + v * v
            basis = [np.ones_like(u), u, v, u * u, u * v, v * v]
        q = d2 / (r * r)
        ok = ok & (q < 1.0) & (np.abs(h) < voxel * _SHEET + 0.5 * d2 / r)
        w = np.where(ok, (1.0 - q) ** 2 * facing * weights, 0.0)
        m = len(basis)
        coef = _weighted_fit(basis, w, h)
        # once more without the samples far off the first fit, for the nodes that had such
        residual = h - _along(basis, coef)
        kept = np.where(np.abs(residual) < _OUTLIER * voxel, w, 0.0)
        again = np.flatnonzero(np.any(kept != w, axis=1))
        if again.size:
            coef[again] = _weighted_fit([b[again] for b in basis], kept[again], h[again])
        fitted = np.count_nonzero(kept, axis=1) >= _PER_COEFFICIENT * m
        # the mean curvature towards n: c2 (2D), c3 + c5 (3D); the blurred iso-surface lies that
        # times the variance further along n than the surface. At most a circle's (sphere's) of
        # the window's radius: a part smaller than the window gives the fit samples from beyond
        # its equator, which read it more curved than it is (a CT-like ball of radius 3.5 voxels
        # came out +20 % in volume, +2.8 % with the limit)
        limit = (0.5 if dim == 2 else 1.0) / r
        curvature = coef[:, 2] if dim == 2 else coef[:, 3] + coef[:, 5]
        bend = np.clip(curvature, -limit, limit)
        if dim == 2:
            slope = coef[:, 1, None] * np.stack([-n[:, 1], n[:, 0]], axis=1)
        else:
            slope = coef[:, 1, None] * t1 + coef[:, 2, None] * t2
        # back to mm: the height times the unit, the curvature (1/unit) over it
        return (np.where(fitted, unit * coef[:, 0] - blur * (bend / unit), 0.0), fitted,
                np.where(fitted[:, None], slope, 0.0), np.abs(curvature) < limit)

    def project(self, sides, x: np.ndarray, bnodes: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, dict]:
        """The boundary positions moved onto the fitted surface (before ``subvoxel.lift``).

        Parameters
        ----------
        sides : dicer.mesh.subvoxel.NodeSides
        x : (N, 3) float64 ndarray
            Positions of all nodes, mm (the boundary nodes' are replaced by ``xb``).
        bnodes : (B,) int64 ndarray
        xb : (B, 3) float64 ndarray
            The boundary nodes' positions from the labels' smoothing, mm.

        Returns
        -------
        positions : (B, 3) float64 ndarray
        report : dict
        """
        xs = x.copy()
        xs[bnodes] = xb
        normal, defined = sides.normals(xs, xb)
        sel = np.flatnonzero(defined)
        lo, hi = sides.pair[sel] // sides.top, sides.pair[sel] % sides.top
        height, fitted, normal = self.offsets(xb[sel], normal[sel], lo * self.top + hi, sides.fixed[sel])
        limit = (np.abs(normal[:, :self.dim]) * self.mesh_spacing).sum(axis=1)
        height = np.clip(height, -limit, limit)
        y = xb.copy()
        y[sel] += height[:, None] * normal
        return y, {"nodes_moved": int(np.count_nonzero(fitted)), "nodes_between_two_kinds": int(sides.usable.sum()),
                   "label_surface_radius": self.radius / float(self.mesh_spacing.min()),
                   "samples": int(self.points.shape[0]), "samples_on_sloped_faces": self.sloped,
                   **({} if self.placed is None else {"samples_placed_by_the_scan": self.placed,
                                                      **({} if self.placed_share is None else
                                                         {"share_of_faces_placed_by_the_scan":
                                                          round(self.placed_share, 4)}),
                                                      "edge_variance_mm2": {f"{a}|{b}": round(v, 6) for (a, b), v
                                                                            in sorted(self.blur.items())}}),
                   **({"samples_relaxed": True} if self.relaxed else {})}
