"""Sub-voxel surfaces: boundary nodes moved onto the threshold iso-surface of the scan.

A label image places a surface only to within a voxel; the grey values of the scan it was
segmented from place it to a fraction of one (partial volume). After the boundary solve of
``dicer.mesh.smooth``, every boundary node between exactly two kinds (a material and the
background, or two materials a < b) is moved along its surface normal to where the lightly
smoothed image crosses the threshold between them (the lower bound of material b, the
threshold segmentation used to tell b from the kinds below it), then corrected for the
shift that blurring gives a curved iso-surface (below). The smoothing stage keeps its
quality guard: the move of a node is scaled with its backed-off coefficient.

Per node and pass (two passes, the second from the first's positions):

1. **Normal** n, pointing into the higher kind b: the sum of the unit vectors from the
   node to the centroids of its elements of kind b minus those of kind a (at the current
   positions). On a bounding plane its normal components are dropped (the node stays in
   the plane).
2. **Profile**: the image (Gaussian-smoothed, sigma ``image_sigma`` voxels of the
   image's finest axis) sampled trilinearly at 21 points along n over +-L, with L the
   mesh voxel's extent along n (sum |n_d| spacing_d), and at +-2.5 L.
3. **Crossing**: the upward crossing of the threshold nearest the node, linearly
   interpolated between samples. No crossing in the window: the node is not moved.
4. **Curvature correction**: blurring an edge by a Gaussian of variance s^2 moves the
   iso-surface of a curved body towards its centres of curvature by s^2 H (3D, H the
   mean curvature; 2D s^2 kappa / 2). s^2 is estimated per pair of kinds from the
   profiles (an error-function edge of contrast D has slope D phi(Phi^-1(q)) / s at its
   level q: the median over the pair's nodes of (D phi(Phi^-1(q)) / slope)^2, D the
   difference of the samples at +-2.5 L, at most L^2); the curvature from the moved nodes (umbrella
   operator over the boundary graph, averaged over neighbours four times). The node
   moves back by that shift, along -n where its kind-b side is convex.
5. The move from the node's smoothed position is limited to L.

Coordinates are the lattice frame (mm) of the mesh; the image is sampled at continuous
index (x - origin) / spacing - 1/2 (its origin is the corner of voxel 0), so a mesh of a
downsampled label volume samples the full-resolution scan it came from.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy import ndimage, special

from dicer.arrays import norm
from dicer.errors import DicerError
from dicer.image import Volume
from dicer.mesh.frame import lattice_shift
from dicer.mesh.model import Mesh, pieces
from dicer.mesh.topology import HEX_CORNER_NEIGHBOURS, QUAD_CORNER_NEIGHBOURS
from dicer.parallel import ordered_map

log = logging.getLogger("dicer")

__all__ = ["ImageSurface", "NodeSides", "check_thresholds_for_mesh", "lift", "normal_density", "pairs_not_helped",
           "project"]

# corners per element -> for each corner, the corners its edges run to, right-handed
_EDGE_ENDS = {8: HEX_CORNER_NEIGHBOURS, 4: QUAD_CORNER_NEIGHBOURS}
_LIFT_MARGIN = 0.02
_LIFT_ITERATIONS = 30  # at most; rounds end when every corner reaches the target
_LIFT_TOLERANCE = 1e-3  # a corner within this of its target (in scaled Jacobian) has reached it

_SAMPLES = 21  # profile samples over [-L, L]
_FAR = 2.5  # the contrast samples, in units of L
_PASSES = 2
_CURVATURE_AVERAGING = 4


def normal_density(z: np.ndarray) -> np.ndarray:
    """The standard normal density at ``z``.

    By scipy's expm1, not numpy's exp: numpy computes exp with its own vector code on CPUs
    with AVX-512 and with the C library elsewhere, which differ in the last bit, and the
    density sets where nodes go.

    Parameters
    ----------
    z : float ndarray
        Any shape.

    Returns
    -------
    float64 ndarray
        The same shape.
    """
    return (special.expm1(-0.5 * z * z) + 1.0) / np.sqrt(2.0 * np.pi)


def check_thresholds_for_mesh(thresholds, mesh: Mesh, source: str = "the thresholds") -> np.ndarray:
    """The thresholds as an array, checked against the mesh's materials.

    Parameters
    ----------
    thresholds : sequence of float
        The lower bound of each material 1..K in image units (HU for CT), strictly
        increasing, as ``dicer segment`` chooses them (``segmentation.json``).
    mesh : Mesh
    source : str, optional
        Where the thresholds came from, for error messages.

    Returns
    -------
    (K,) float64 ndarray

    Raises
    ------
    DicerError
        Thresholds that are not finite numbers, not increasing, or fewer than the mesh's
        highest material.
    """
    try:
        t = np.asarray(thresholds, dtype=float).ravel()
    except (TypeError, ValueError):
        raise DicerError(f"{source}: thresholds must be a list of numbers (one lower bound per material)") from None
    if t.size == 0 or not np.all(np.isfinite(t)):
        raise DicerError(f"{source}: thresholds must be a non-empty list of finite numbers")
    if np.any(np.diff(t) <= 0):
        raise DicerError(f"{source}: thresholds {t.tolist()} are not strictly increasing; give the lower bound "
                         "of each material in increasing order, as dicer segment writes them")
    top = int(np.max(mesh.material)) if mesh.n_cells else 0
    if mesh.names and t.size != len(mesh.names):
        raise DicerError(f"{source}: {t.size} threshold(s) for a mesh of {len(mesh.names)} materials "
                         f"({', '.join(mesh.names)}); give one threshold per material (the segmentation.json of the "
                         "scan the mesh came from)")
    if top > t.size:
        raise DicerError(f"{source}: {t.size} threshold(s) for a mesh with material {top}; give one threshold "
                         "per material (the segmentation.json of the scan the mesh came from)")
    return t


class ImageSurface:
    """The smoothed scan around a mesh, and the projection of its boundary nodes.

    Parameters
    ----------
    image : Volume
        The scan, (nx, ny[, nz]) intensities, with the spacing and origin (corner of voxel
        0, mm) of its file; its dimension must be the mesh's.
    thresholds : (K,) float
        Lower bound of each material (image units), strictly increasing.
    mesh : Mesh
        The mesh to be smoothed (lattice frame, mm).
    sigma : float
        Gaussian smoothing of the image, in voxels of its finest axis (0: none).
    source : str
        The image's file name, for error messages.

    Raises
    ------
    DicerError
        A dimension or orientation that differs from the mesh's, or an image that does not
        cover the mesh's grid.
    """

    def __init__(self, image: Volume, thresholds: np.ndarray, mesh: Mesh, sigma: float, source: str = "image"):
        dim = mesh.dim
        arr = np.asarray(image.array)
        if arr.ndim != dim:
            raise DicerError(f"{source}: a {arr.ndim}D image for a {dim}D mesh; give the scan the mesh was "
                             "segmented from")
        if mesh.direction is not None and image.direction is not None:
            d_img = np.asarray(image.direction, float).reshape(dim, dim)
            if not np.allclose(d_img, np.asarray(mesh.direction, float)[:dim, :dim], atol=1e-5):
                raise DicerError(f"{source}: the image's direction cosines differ from the mesh's; give the "
                                 "scan the mesh was segmented from")
        spacing = np.asarray(image.spacing, float)
        origin = np.asarray(image.origin, float)
        # a mesh on a coarser grid than the scan's (downsample) with turned or flipped axes lies in
        # a lattice frame of its own: this shift takes its coordinates into the scan's
        shift = lattice_shift(mesh.spacing[:dim], mesh.origin[:dim], spacing, origin, mesh.direction)
        m_lo = np.asarray(mesh.origin, float)[:dim] + shift
        m_hi = m_lo + np.asarray(mesh.grid_shape, float)[:dim] * np.asarray(mesh.spacing, float)[:dim]
        i_lo, i_hi = origin, origin + np.asarray(arr.shape, float) * spacing
        tol = 1e-3 * spacing
        # downsampling pads the grid up to a whole number of coarse voxels (less than one
        # on either side); beyond the image the nearest value is sampled
        pad = np.asarray(mesh.spacing, float)[:dim]
        if np.any(m_lo < i_lo - pad - tol) or np.any(m_hi > i_hi + pad + tol):
            fmt = lambda v: "(" + ", ".join(f"{c:g}" for c in v) + ")"  # noqa: E731
            turned = image.direction is not None and not np.allclose(
                np.asarray(image.direction, float).reshape(dim, dim), np.eye(dim), atol=1e-5)
            if turned and mesh.direction is None:  # its span in the mesh's frame is not origin + shape
                raise DicerError(f"{source}: the image's axes are turned or flipped (direction cosines "
                                 f"{fmt(np.ravel(image.direction))}) against the mesh's grid; give the scan the mesh "
                                 "was segmented from, or resample this one onto the labels' grid")
            raise DicerError(f"{source}: the image spans {fmt(i_lo)}..{fmt(i_hi)} mm, the mesh's grid "
                             f"{fmt(m_lo)}..{fmt(m_hi)} mm; give the scan the mesh was segmented from")
        self.dim = dim
        self.thresholds = np.asarray(thresholds, float)
        self.mesh_spacing = np.asarray(mesh.spacing, float)[:dim]
        self.sigma = float(sigma)
        # crop to the mesh's nodes and the reach of the profiles and the filter
        pts = np.asarray(mesh.points, float)[:, :dim] + shift
        reach = (_FAR + 1) * float(self.mesh_spacing.sum())
        sig_vox = self.sigma * float(spacing.min()) / spacing
        lo = np.floor((pts.min(axis=0) - reach - origin) / spacing - 4 * sig_vox - 2).astype(int)
        hi = np.ceil((pts.max(axis=0) + reach - origin) / spacing + 4 * sig_vox + 2).astype(int)
        lo, hi = np.maximum(lo, 0), np.minimum(hi, arr.shape)
        sub = np.asarray(arr[tuple(slice(a, b) for a, b in zip(lo, hi))], np.float32)
        if not np.all(np.isfinite(sub)):
            raise DicerError(f"{source}: the image holds non-finite values near the mesh; check the file")
        low, high = (float(sub.min()), float(sub.max())) if sub.size else (0.0, 0.0)
        outside = [t for t in self.thresholds if not low < t <= high]
        if outside:  # no iso-surface of these near the mesh: the thresholds of another scan, or of other units
            log.warning("smooth: the thresholds %s lie outside the values of %s near the mesh (%g to %g), so it has "
                        "no surface there; give this scan's thresholds (the segmentation.json of its dicer segment "
                        "--info)", ", ".join(f"{t:g}" for t in outside), source, low, high)
        if self.sigma > 0:
            sub = ndimage.gaussian_filter(sub, sig_vox, mode="nearest")
        self.array = sub
        self.spacing = spacing
        # corner of the cropped array's voxel 0, in the mesh's lattice frame
        self.origin = origin + lo * spacing - shift

    def sample(self, points: np.ndarray) -> np.ndarray:
        """Trilinear (2D: bilinear) values of the smoothed image; beyond the image, the nearest edge value.

        Parameters
        ----------
        points : (P, dim) float64 ndarray
            mm.

        Returns
        -------
        (P,) float32 ndarray
        """
        idx = (points - self.origin) / self.spacing - 0.5
        return ndimage.map_coordinates(self.array, idx.T, order=1, mode="nearest")


class NodeSides:
    """Per boundary node, the two kinds it separates and its elements on either side.

    Parameters
    ----------
    mesh : Mesh
    bnodes : (B,) int64, the boundary nodes (smoothing order).
    cells_near : (Mb,) int64, the elements holding a boundary node.
    x0 : (N, 3) float64, the unsmoothed positions (mm).
    on_plane : (B, 3) bool, the bounding-plane axes each boundary node lies on.
    fixed : (B, 3) bool, the coordinates the smoothing holds (plane axes, z in 2D).
    thresholds : (K,) float64, lower bound of each material.
    mirror : bool, the bounding planes are mirrors (``bounding_planes: mirror``).

    Attributes
    ----------
    usable : (B,) bool, nodes between exactly two kinds (a material and the background
        inside the image, or two materials), that may move.
    threshold : (B,) float64, the iso-value of each node's pair (lower bound of the higher).
    pair : (B,) int64, an id of the node's pair of kinds (a * (K + 1) + b).
    """

    def __init__(self, mesh: Mesh, bnodes: np.ndarray, cells_near: np.ndarray, x0: np.ndarray,
                 on_plane: np.ndarray, fixed: np.ndarray, thresholds: np.ndarray, mirror: bool = False):
        n = mesh.n_points
        b = bnodes.size
        dim = mesh.dim
        per = mesh.cells.shape[1]
        bpos = np.full(n, -1, np.int64)
        bpos[bnodes] = np.arange(b)
        sub = mesh.cells[cells_near]
        mat = np.asarray(mesh.material)[cells_near].astype(np.int64)
        rows = bpos[sub].ravel()  # (Mb * per,) boundary-node number of each corner, -1: none
        elem = np.repeat(np.arange(cells_near.size), per)
        keep = rows >= 0
        rows, elem = rows[keep], elem[keep]
        emat = mat[elem]
        top = int(mat.max(initial=0)) + 1
        hi = np.zeros(b, np.int64)
        np.maximum.at(hi, rows, emat)
        lo = np.full(b, top, np.int64)
        np.minimum.at(lo, rows, emat)
        count = np.bincount(rows, minlength=b)
        third = np.bincount(rows, weights=(emat != lo[rows]) & (emat != hi[rows]), minlength=b) > 0
        # an octant of the node inside the image without an element is background
        inside = 1 << (dim - on_plane[:, :dim].sum(axis=1))
        movable = ~fixed[:, :dim].all(axis=1)
        empty = count < inside
        single = lo == hi
        usable = movable & ~third & (single == empty) & (count > 0)
        lo = np.where(empty, 0, lo)
        self.usable = usable
        self.threshold = np.where(usable, thresholds[np.clip(hi - 1, 0, thresholds.size - 1)], np.nan)
        self.pair = lo * top + hi
        # corner entries of the usable nodes: +1 towards an element of the higher kind, -1 the lower
        sign = np.where(emat == hi[rows], 1.0, np.where(emat == lo[rows], -1.0, 0.0))
        take = usable[rows] & (sign != 0)
        self.rows, self.elem, self.sign = rows[take], elem[take], sign[take]
        self.cells = sub
        self.b = b
        self.fixed = fixed
        # the coordinates a mirror plane holds: the mirror images of a node's corners move them
        # the other way, so ``lift`` sizes its steps as if they were free and then drops them
        self.mirrored = on_plane & fixed if mirror else np.zeros_like(fixed)
        self.top = top
        # the corners at a usable node whose edges all end at boundary nodes: their scaled
        # Jacobian depends on boundary positions only (``lift``)
        ends = _EDGE_ENDS[per]
        node = bpos[sub]  # (Mb, per)
        other = node[:, ends]  # (Mb, per, dim)
        ok = (node >= 0) & (other >= 0).all(axis=2)
        ok[ok] = usable[node[ok]] & usable[other[ok]].all(axis=1)
        self.corner = node[ok]
        self.corner_ends = other[ok]
        self.dim = dim

    def normals(self, x: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit normals into the higher kind at the boundary nodes, where one is defined.

        Parameters
        ----------
        x : (N, 3) float64 ndarray
            Positions of all nodes, mm.
        xb : (B, 3) float64 ndarray
            Positions of the boundary nodes, mm.

        Returns
        -------
        normals : (B, 3) float64 ndarray
        defined : (B,) bool ndarray
        """
        centre = x[self.cells].mean(axis=1)
        v = centre[self.elem] - xb[self.rows]
        v /= np.maximum(norm(v, axis=1), 1e-30)[:, None]
        v *= self.sign[:, None]
        nrm = np.stack([np.bincount(self.rows, weights=v[:, d], minlength=self.b) for d in range(3)], axis=1)
        nrm[self.fixed] = 0.0  # plane nodes stay in their planes (and z in 2D)
        length = norm(nrm, axis=1)
        # a sum of unit vectors that nearly cancels has no direction; at a mirror plane the sum
        # is the mirrored model's, whose images of the node's elements add alike (2^k of them)
        whole = length * (1 << self.mirrored[:, :self.dim].sum(axis=1))
        ok = self.usable & (whole > 0.5)
        return nrm / np.where(ok, length, 1.0)[:, None], ok


_LIFT_PIECE = 1 << 17  # corners per piece of a lift round


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 3): the rows' cross products, ``np.cross(a, b)``'s bytes without its set-up."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=1)


def _corner_steps(y: np.ndarray, p: np.ndarray, ends: np.ndarray, active: np.ndarray, counted: np.ndarray,
                  free: np.ndarray, target: float, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The corners ``active`` below ``target`` and their nodes' steps (:func:`lift`): (R,) corner
    numbers and (R, 1 + dim, 3) steps, mm."""
    # np.take gathers rows several times faster than indexing
    e = np.take(y, ends[active], axis=0) - np.take(y, p[active], axis=0)[:, None, :]  # (A, dim, 3)
    length = norm(e, axis=2)
    if dim == 3:
        a, b, c = e[:, 0], e[:, 1], e[:, 2]
        bc = _cross(b, c)
        f = np.einsum("ij,ij->i", a, bc)
    else:
        a, b = e[:, 0], e[:, 1]
        f = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    scale = length[:, 0] * length[:, 1]  # np.prod's order, without its slow reduction over a short axis
    for d in range(2, dim):
        scale *= length[:, d]
    need = target * scale - f
    # the gradient of the corners below the target only: after the first rounds most active
    # corners are above it (their neighbours moved, they did not need to)
    low = np.flatnonzero(need > _LIFT_TOLERANCE * scale)
    if dim == 3:
        a, b, c, bc = a[low], b[low], c[low], bc[low]
        ca, ab = _cross(c, a), _cross(a, b)
        grad = np.stack([-(bc + ca + ab), bc, ca, ab], axis=1)
    else:
        a, b = a[low], b[low]
        zero = np.zeros(len(a))
        ga = np.stack([b[:, 1], -b[:, 0], zero], axis=1)  # df/da
        gb = np.stack([-a[:, 1], a[:, 0], zero], axis=1)  # df/db
        grad = np.stack([-(ga + gb), ga, gb], axis=1)
    grad = np.where(counted[active[low]], grad, 0.0)
    g2 = np.einsum("ijk,ijk->i", grad, grad)
    go = g2 > 0
    low = low[go]
    rows = active[low]
    return rows, np.where(free[rows], grad[go], 0.0) * (need[low] / g2[go])[:, None, None]


def lift(sides: NodeSides, y: np.ndarray, floor: float, share: np.ndarray | None = None) -> np.ndarray:
    """Boundary positions with flattened corners sharpened to the quality floor.

    A voxel at a convex corner of the staircase has up to seven boundary nodes; placed on a
    smooth surface, the corner opposite its interior node goes flat (scaled Jacobian 0).
    The triple product f = det(a, b, c) of a corner's edges a, b, c (2D: a x b) has the
    gradient (-(b x c + c x a + a x b), b x c, c x a, a x b) with respect to the corner node
    and its three edge ends (2D: (-(rot(b - a)), ...)); the components sum to zero. Each
    corner below ``floor`` + a margin moves its four nodes along that gradient (free
    coordinates only) by the least amount that reaches the target to first order: the
    corner node out, its ends in, the surface's mean position kept. A node in several such
    corners takes the mean of their moves (their sum would overshoot: each alone reaches its
    target), in rounds until every corner reaches it (at most ``_LIFT_ITERATIONS``), as the
    moves change neighbouring corners.

    Parameters
    ----------
    sides : NodeSides
    y : (B, 3) float64 ndarray
        Boundary node positions, mm.
    floor : float
        Lowest corner scaled Jacobian wanted.
    share : (B,) float64 ndarray, optional
        With mirror planes: each node's share of the mirrored model (2^-planes it lies on).
        A node on a plane has the mirror images of its corners too, whose moves in the plane
        equal its own corners' moves: they count 1 / share times in its mean.

    Returns
    -------
    (B, 3) float64 ndarray
    """
    if sides.corner.size == 0:
        return y
    target = floor + _LIFT_MARGIN
    p, ends = sides.corner, sides.corner_ends
    nodes = np.concatenate([p[:, None], ends], axis=1)  # (C, 1 + dim)
    free = ~sides.fixed[nodes]  # (C, 1 + dim, 3)
    counted = free | sides.mirrored[nodes]  # the whole mirrored model's gradient
    y = y.copy()
    active = np.arange(p.size)  # corners whose nodes moved since they were last checked
    columns = [np.ascontiguousarray(nodes[:, j]) for j in range(nodes.shape[1])]
    for _ in range(_LIFT_ITERATIONS):
        # each corner's step depends on its own nodes only: pieces of the corners side by side,
        # put together in order (the same arrays as in one piece)
        found = list(ordered_map(lambda part: _corner_steps(y, p, ends, active[part], counted, free, target,
                                                            sides.dim), pieces(active.size, _LIFT_PIECE)))
        rows = np.concatenate([r for r, _ in found]) if found else np.zeros(0, np.int64)
        if rows.size == 0:
            break
        step = np.concatenate([st for _, st in found])
        flat = np.take(nodes, rows, axis=0).ravel()
        moves = step.reshape(-1, 3)
        total = np.stack([np.bincount(flat, weights=moves[:, k], minlength=sides.b) for k in range(3)], axis=1)
        # each corner's step alone reaches its target: a node in several corners takes the mean
        # of the steps that move it (their sum overshoots, and the kinks grow), over the mirror
        # images too
        count = np.bincount(flat, weights=(moves[:, 0] != 0.0) | (moves[:, 1] != 0.0) | (moves[:, 2] != 0.0),
                            minlength=sides.b)
        if share is not None:
            total /= share[:, None]
            count /= share
        y += total / np.maximum(count, 1.0)[:, None]
        # a corner none of whose nodes moved keeps its value: it stays above the target
        moved = count > 0
        hit = moved[columns[0]]
        for c in columns[1:]:
            hit |= moved[c]
        active = np.flatnonzero(hit)
    return y


def pairs_not_helped(sides: NodeSides, moved: np.ndarray, surface: np.ndarray, lifted: np.ndarray,
                     start: np.ndarray, share: np.ndarray | None = None) -> tuple[np.ndarray, list[str]]:
    """The pairs of kinds whose nodes :func:`lift` takes farther from the surface than the labels' smoothing left them.

    Between two materials both sides' convex corners are sharpened (each side's elements keep
    the quality floor), so on an interface the lifted nodes can end up farther from the surface
    than where the labels' smoothing put them: such a pair is better left unpulled. Decided
    per pair, by the mean distance of its moved nodes from the surface.

    Parameters
    ----------
    sides : NodeSides
    moved : (B,) bool ndarray
        Nodes given a position on the surface.
    surface : (B, 3) float64 ndarray
        Those positions (the others: unused), mm.
    lifted : (B, 3) float64 ndarray
        The positions after :func:`lift`, mm.
    start : (B, 3) float64 ndarray
        The positions the labels' smoothing gave, mm.
    share : (B,) float64 ndarray, optional
        Each node's share of the mirrored model (a cut model decides as the whole one).

    Returns
    -------
    stay : (B,) bool ndarray
        The nodes of those pairs.
    pairs : list of str
        Those pairs, "lower|higher" (0: background).
    """
    if not moved.any():
        return np.zeros(sides.b, bool), []
    ids, rank = np.unique(sides.pair[moved], return_inverse=True)
    w = 1.0 if share is None else share[moved]
    lifted_off = np.bincount(rank, weights=w * norm(lifted[moved] - surface[moved], axis=1))
    start_off = np.bincount(rank, weights=w * norm(start[moved] - surface[moved], axis=1))
    worse = ids[lifted_off >= start_off]
    return np.isin(sides.pair, worse), [f"{int(p) // sides.top}|{int(p) % sides.top}" for p in worse]


def project(surface: ImageSurface, sides: NodeSides, adj: sp.csr_matrix, degree: np.ndarray, x: np.ndarray,
            bnodes: np.ndarray, xb: np.ndarray) -> tuple[np.ndarray, dict]:
    """The boundary positions moved onto the image's iso-surfaces (before :func:`lift`).

    Parameters
    ----------
    surface : ImageSurface
    sides : NodeSides
    adj : scipy.sparse.csr_matrix
        The boundary graph (with mirror copies).
    degree : ndarray
        Neighbours of each node in ``adj``.
    x : (N, 3) float64 ndarray
        Positions of all nodes, mm: the smoothed positions from the labels.
    bnodes : (B,) int64 ndarray
        The boundary nodes.
    xb : (B, 3) float64 ndarray
        Their positions, mm.

    Returns
    -------
    positions : (B, 3) float64 ndarray
        On the iso-surfaces; nodes without a crossing, or not between two kinds, unchanged.
    report : dict
        Nodes moved, edge widths per pair.
    """
    dim = surface.dim
    y = xb.copy()
    xs = x.copy()
    s_unit = np.linspace(-1.0, 1.0, _SAMPLES)
    h_unit = s_unit[1] - s_unit[0]
    steps = np.concatenate([s_unit, [-_FAR, _FAR]])
    info = {}
    for _ in range(_PASSES):
        xs[bnodes] = y
        nrm, ok = sides.normals(xs, y)
        reach = (np.abs(nrm[:, :dim]) * surface.mesh_spacing).sum(axis=1)  # L per node, mm (no BLAS: the same bytes on every CPU)
        sel = np.flatnonzero(ok)
        pts = (y[sel, None, :dim] + (steps[None, :, None] * reach[sel, None, None]) * nrm[sel, None, :dim])
        vals = surface.sample(pts.reshape(-1, dim)).reshape(sel.size, steps.size).astype(np.float64)
        vals -= sides.threshold[sel, None]
        prof = vals[:, :_SAMPLES]
        above = prof >= 0
        up = ~above[:, :-1] & above[:, 1:]
        dist = np.abs(np.arange(_SAMPLES - 1) + 0.5 - (_SAMPLES - 1) / 2)
        cand = np.where(up, dist, np.inf)
        j = np.argmin(cand, axis=1)
        r = np.arange(sel.size)
        found = np.isfinite(cand[r, j])
        a, b = prof[r, j], prof[r, j + 1]
        frac = np.where(found, a / np.where(found, a - b, 1.0), 0.0)
        off = np.where(found, (s_unit[j] + h_unit * frac), 0.0) * reach[sel]  # mm along n
        slope = np.where(found, (b - a) / (h_unit * reach[sel]), 0.0)  # image units per mm
        contrast = vals[:, -1] - vals[:, -2]
        # the edge's variance per pair of kinds (see the module docstring): an edge
        # D Phi(s / sigma) crossed at the level q has the slope D phi(Phi^-1(q)) / sigma there
        level = np.clip(-vals[:, -2] / np.where(contrast > 0, contrast, 1.0), 0.05, 0.95)
        density = normal_density(special.ndtri(level))
        pair = sides.pair[sel]
        good = found & (slope > 0) & (contrast > 0)
        var = np.zeros(sel.size)
        widths = {}
        for p in np.unique(pair[good]):
            these = good & (pair == p)
            s2 = float(np.median((contrast[these] * density[these] / slope[these]) ** 2))
            s2 = min(s2, float(np.median(reach[sel][these])) ** 2)  # at most a voxel's width
            var[pair == p] = s2
            widths[f"{int(p) // sides.top}|{int(p) % sides.top}"] = s2
        moved = np.zeros(sides.b, bool)
        moved[sel[found]] = True
        cross = y.copy()
        cross[sel] += off[:, None] * nrm[sel]
        # curvature of the surface through the crossings (umbrella operator, averaged)
        centroid = (adj @ cross) / np.maximum(degree, 1)[:, None]
        rr = np.repeat(np.arange(sides.b), np.diff(adj.indptr))
        d2 = np.einsum("ij,ij->i", cross[rr] - cross[adj.indices], cross[rr] - cross[adj.indices])
        ell2 = np.bincount(rr, weights=d2 * adj.data, minlength=sides.b) / np.maximum(degree, 1)
        curv = np.where(moved, 2.0 * np.einsum("ij,ij->i", -nrm, cross - centroid) / np.maximum(ell2, 1e-30), 0.0)
        w = moved.astype(float)
        for _ in range(_CURVATURE_AVERAGING):
            num, den = adj @ (curv * w), adj @ w
            curv = np.where(moved, 0.5 * curv + 0.5 * num / np.maximum(den, 1e-30), 0.0)
        shift = var * curv[sel] * (dim - 1) / 2.0
        total = np.clip(off - shift, -reach[sel], reach[sel])
        step = np.where(found, total, 0.0)
        y[sel] += step[:, None] * nrm[sel]
        info = {"nodes_moved": int(found.sum()), "nodes_between_two_kinds": int(sides.usable.sum()),
                "edge_variance_mm2": {k: round(v, 6) for k, v in sorted(widths.items())}}
    # the move from the smoothed position is limited to the voxel's extent along the normal
    d = y - xb
    length = norm(d, axis=1)
    limit = (np.abs(nrm[:, :dim]) * surface.mesh_spacing).sum(axis=1)
    scale = np.where(length > limit, limit / np.maximum(length, 1e-30), 1.0)
    y = xb + d * scale[:, None]
    return y, info
