"""Boundary and interior smoothing (DICER Box 3 and section 2.6) with a quality guard.

1. **Boundary solve.** For every boundary node n (see ``dicer.mesh.boundary``)::

       x_n - (k_n / R_n) * sum_{j in N_b(n)} x_j = (1 - k_n) * x_n^0

   with R_n its boundary-edge count, N_b(n) its boundary neighbours and k_n the
   coefficient of its node class. Multiplying row n by R_n / k_n gives the symmetric,
   strictly diagonally dominant (so positive definite) system
   ``(R_n/k_n) x_n - sum x_j = R_n (1/k_n - 1) x_n^0``, solved for the three coordinates
   at once by Jacobi-preconditioned conjugate gradients (on displacements, in single
   precision). Nodes with k_n = 0 stay put. Nodes on a bounding plane of the image keep
   that coordinate (a Dirichlet value). With ``shrink_compensation`` the solve S is
   applied twice, x = (2S - S^2) x0 ("twicing"): the stair steps go, the shrinkage of
   curved surfaces does not.
2. **Interior solve.** With boundary nodes fixed, the displacement u of interior nodes
   solves the graph Laplace equation u_n = mean of u over its edge neighbours; on the
   unmerged lattice that is exactly "every interior node at the centroid of its
   neighbours' final positions" (paper 2.6), and on a plane-merged mesh it keeps the
   graded spacing. The solve is restricted to the interior nodes within ``interior_band``
   edges of the boundary (u = 0 beyond; 0 = all interior nodes).
3. **Quality guard.** No element may end with a scaled Jacobian below
   ``min_scaled_jacobian`` (and never <= 0). Where one would, the coefficients of the
   boundary nodes of the offending elements (widening to their neighbours when those
   already stay put) are multiplied by ``backoff_factor``, or set to 0 in the last
   rounds, and both solves rerun. A mesh that still fails raises DicerError naming the
   worst element.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy.linalg.blas import get_blas_funcs as _blas

from dicer.errors import DicerError
from dicer.mesh.boundary import NODE_CLASSES, boundary_graph, class_counts
from dicer.mesh.metrics import element_volumes, scaled_jacobian
from dicer.mesh.model import Mesh

__all__ = ["DEFAULTS", "smooth_mesh", "smoothing_settings"]

DEFAULTS = {
    "coefficient": None,
    "coefficients": {"A": 0.85, "B": 0.85, "C": 0.9, "D": 0.95, "E": 0.9, "F": 0.9},
    "keep_bounding_planes": True,
    "interior": True,
    "shrink_compensation": True,
    "interior_band": 3,
    "min_scaled_jacobian": 0.2,
    "backoff_factor": 0.5,
    "max_backoff_rounds": 8,
    "tolerance": 1e-4,
}
_CLASS_LETTERS = ("A", "B", "C", "D", "E", "F")


def smoothing_settings(section: dict | None) -> dict:
    """The ``smooth:`` config section with defaults filled in and values checked."""
    s = {k: (dict(v) if isinstance(v, dict) else v) for k, v in DEFAULTS.items()}
    for key, value in (section or {}).items():
        if key not in s:
            raise DicerError(f"smooth.{key}: unknown setting; use one of {', '.join(sorted(s))}")
        if key == "coefficients":
            if not isinstance(value, dict):
                raise DicerError("smooth.coefficients: give a mapping of node classes A-F to values in [0, 1)")
            for cls, k in value.items():
                if cls not in _CLASS_LETTERS:
                    raise DicerError(f"smooth.coefficients.{cls}: unknown node class; use A, B, C, D, E or F")
                s["coefficients"][cls] = k
        else:
            s[key] = value

    def coef(name, k):
        if isinstance(k, bool) or not isinstance(k, (int, float)) or not (0.0 <= float(k) < 1.0):
            raise DicerError(f"{name} = {k!r} is outside [0, 1); 0 keeps nodes still, values near 1 flatten the surface")
        return float(k)

    if s["coefficient"] is not None:
        k = coef("smooth.coefficient", s["coefficient"])
        s["coefficients"] = {c: k for c in _CLASS_LETTERS}
    s["coefficients"] = {c: coef(f"smooth.coefficients.{c}", s["coefficients"][c]) for c in _CLASS_LETTERS}
    msj = s["min_scaled_jacobian"]
    if isinstance(msj, bool) or not isinstance(msj, (int, float)) or not (0.0 <= msj < 1.0):
        raise DicerError(f"smooth.min_scaled_jacobian = {msj!r} must lie in [0, 1)")
    bf = s["backoff_factor"]
    if isinstance(bf, bool) or not isinstance(bf, (int, float)) or not (0.0 <= bf < 1.0):
        raise DicerError(f"smooth.backoff_factor = {bf!r} must lie in [0, 1)")
    for key in ("interior_band", "max_backoff_rounds"):
        v = s[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise DicerError(f"smooth.{key} = {v!r} must be a whole number >= 0")
    tol = s["tolerance"]
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (0 < tol < 1):
        raise DicerError(f"smooth.tolerance = {tol!r} must lie in (0, 1)")
    for key in ("keep_bounding_planes", "interior", "shrink_compensation"):
        if not isinstance(s[key], bool):
            raise DicerError(f"smooth.{key} = {s[key]!r} must be true or false")
    return s


# --- solvers -------------------------------------------------------------------------------


def _pcg(apply, rhs: np.ndarray, inv_diag: np.ndarray | None, tol: float, maxiter: int) -> tuple[np.ndarray, int]:
    """Conjugate gradients on the block-diagonal system of the columns of ``rhs``.

    The columns share one operator; CG runs on them stacked as one vector (the block
    system is symmetric positive definite when each block is), preconditioned by
    ``inv_diag`` (None: none), until ||r|| <= tol * ||rhs||. Vector updates are in place.
    """
    shape = rhs.shape
    b = np.ascontiguousarray(rhs).ravel()
    bnorm = float(np.sqrt(b @ b))
    x = np.zeros_like(b)
    if bnorm == 0:
        return x.reshape(shape), 0
    d = None if inv_diag is None else np.repeat(inv_diag, shape[1]).astype(b.dtype)
    axpy = _blas("axpy", (b,))

    def op(v):
        return np.ascontiguousarray(apply(v.reshape(shape))).ravel()

    r = b.copy()
    z = r if d is None else r * d
    p = z.copy()
    rz = float(r @ z)
    target = tol * bnorm
    for it in range(1, maxiter + 1):
        q = op(p)
        pq = float(p @ q)
        if pq <= 0:
            return x.reshape(shape), it
        alpha = rz / pq
        axpy(p, x, a=alpha)
        axpy(q, r, a=-alpha)
        if np.sqrt(r @ r) <= target:
            return x.reshape(shape), it
        if d is None:
            z = r
        else:
            np.multiply(r, d, out=z)
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x.reshape(shape), maxiter


def _smoothing_step(adj: sp.csr_matrix, degree: np.ndarray, k: np.ndarray, y: np.ndarray,
                    fixed: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
    """The displacement S(y) - y of the boundary system applied to positions ``y``.

    With x = y + delta, the system (R/k) x_n - sum x_j = R (1/k - 1) y_n becomes
    (R/k) delta_n - sum delta_j = sum_j (y_j - y_n): the right-hand side is the graph
    Laplacian of y (small numbers), so single precision and a relative residual of
    ``tol`` are ample. Fixed coordinates (and nodes with k = 0) get delta = 0.
    """
    fixed = fixed | (k <= 0)[:, None] | (degree == 0)[:, None]
    free = ~fixed
    kk = np.where(k > 0, k, 1.0)
    diag = (degree / kk).astype(np.float32)
    lap = adj @ y - degree[:, None] * y  # float64: positions are large, differences small
    rhs = np.where(free, lap, 0.0).astype(np.float32)
    inv_diag = np.where(diag > 0, 1.0 / np.where(diag > 0, diag, 1.0), 1.0).astype(np.float32)
    adj32 = adj.astype(np.float32)
    free32 = free

    def apply(v):
        out = adj32 @ v
        np.subtract(diag[:, None] * v, out, out=out)
        out[~free32] = v[~free32]
        return out

    delta, it = _pcg(apply, rhs, inv_diag, tol, 2000)
    return np.where(fixed, 0.0, delta.astype(np.float64)), it


_HEX_NEIGHBOURS = np.array([[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]])
_QUAD_NEIGHBOURS = np.array([[1, 3], [2, 0], [3, 1], [0, 2]])


def _touching(cells: np.ndarray, mark: np.ndarray) -> np.ndarray:
    """Indices of the elements with at least one node marked in ``mark`` (N,) bool."""
    return np.flatnonzero(mark[cells].any(axis=1))


def _corner_slots(cells: np.ndarray, n_points: int) -> np.ndarray:
    """(corners, N) int32: the element in which each node is corner c (-1: none).

    In a conforming mesh of lattice-aligned elements in VTK order (voxel and plane-merged
    meshes), a node is corner c of at most one element: the one in the matching octant.
    """
    per = cells.shape[1]
    if cells.shape[0] >= 2**31 - 1 or n_points >= 2**31 - 1:
        raise DicerError("the mesh is too large for smoothing (2^31 nodes or elements)")
    slots = np.full((per, n_points), -1, np.int32)
    ids = np.arange(cells.shape[0], dtype=np.int32)
    for c in range(per):
        slots[c][cells[:, c]] = ids
    if int(np.count_nonzero(slots >= 0)) != cells.size:
        raise DicerError("the elements are not lattice-aligned with VTK corner order (a node is the same "
                         "corner of two elements); remesh from the labels with 'dicer mesh'")
    return slots


def _cells_of(slots: np.ndarray, nodes: np.ndarray, n_cells: int) -> np.ndarray:
    """Sorted unique elements holding any of ``nodes``."""
    cand = slots[:, nodes].ravel()
    mark = np.zeros(n_cells, bool)
    mark[cand[cand >= 0]] = True
    return np.flatnonzero(mark)


def _band(cells: np.ndarray, slots: np.ndarray, boundary: np.ndarray, boundary_cells: np.ndarray, width: int):
    """Interior nodes within ``width`` element layers of the boundary (all interior nodes
    if 0) and the elements holding a boundary or band node."""
    if width == 0:
        return np.flatnonzero(~boundary), np.arange(cells.shape[0])
    n, m = boundary.size, cells.shape[0]
    seen = boundary.copy()
    in_cells = np.zeros(m, bool)
    in_cells[boundary_cells] = True
    layer_cells = boundary_cells
    for _ in range(width):
        mark = np.zeros(n, bool)
        mark[cells[layer_cells].ravel()] = True
        mark &= ~seen
        nodes = np.flatnonzero(mark)
        if nodes.size == 0:
            break
        seen[nodes] = True
        layer_cells = _cells_of(slots, nodes, m)
        in_cells[layer_cells] = True
    return np.flatnonzero(seen & ~boundary), np.flatnonzero(in_cells)


# the corner a node is in its +++ element (0) and in its --- element (6), and the corners
# of those elements next to it: +x, +y, +z and -x, -y, -z (2D: corners 0 and 2)
_FORWARD = {8: (0, (1, 3, 4)), 4: (0, (1, 3))}
_BACKWARD = {8: (6, (7, 5, 2)), 4: (2, (3, 1))}


class _Interior:
    """The interior Laplace system on a band of interior nodes, assembled once.

    An interior node has a full unit block, so its 2*dim edge neighbours are the
    neighbouring corners in its +++ and --- elements.
    """

    def __init__(self, cells: np.ndarray, slots: np.ndarray, band_nodes: np.ndarray, boundary: np.ndarray):
        n = boundary.size
        per = cells.shape[1]
        m = band_nodes.size
        self.nodes = band_nodes
        if m == 0:
            return
        parts = []
        for corner, nbrs in (_FORWARD[per], _BACKWARD[per]):
            owner = slots[corner][band_nodes]
            if np.any(owner < 0):
                raise DicerError("an interior node lacks a full unit block of elements; the mesh is not conforming")
            parts.append(cells[owner][:, list(nbrs)])
        nb = np.concatenate(parts, axis=1)  # (m, 2*dim)
        n_nb = nb.shape[1]
        pos = np.full(n, -1, np.int32 if n < 2**31 else np.int64)
        pos[band_nodes] = np.arange(m)
        cols = nb.ravel()
        indptr = np.arange(0, m * n_nb + 1, n_nb, dtype=np.int64)
        # fixed-length rows: neighbours of another kind stay in place with a zero weight
        pb = pos[cols]
        in_band = pb >= 0
        self.m_bb = sp.csr_matrix((in_band.astype(np.float32), np.where(in_band, pb, 0), indptr), shape=(m, m))
        bnodes = np.flatnonzero(boundary)
        pos[:] = -1
        pos[bnodes] = np.arange(bnodes.size)
        pB = pos[cols]
        on_bnd = pB >= 0
        self.m_bB = sp.csr_matrix((on_bnd.astype(np.float64), np.where(on_bnd, pB, 0), indptr),
                                  shape=(m, bnodes.size))
        self.deg = float(n_nb)

    def solve(self, u_boundary: np.ndarray, tol: float) -> tuple[np.ndarray, int]:
        """Displacements of the band nodes given those of the boundary nodes (B, 3)."""
        if self.nodes.size == 0:
            return np.zeros((0, 3)), 0
        rhs = (self.m_bB @ u_boundary).astype(np.float32)
        deg, m_bb = np.float32(self.deg), self.m_bb

        def apply(v):
            out = m_bb @ v
            np.subtract(deg * v, out, out=out)
            return out

        u, it = _pcg(apply, rhs, None, tol, 5000)
        return u.astype(np.float64), it


# --- the stage -----------------------------------------------------------------------------


def _lattice_volumes(mesh: Mesh) -> np.ndarray:
    """Per element, the volume (2D: area) of its lattice box: exact before smoothing."""
    far = 6 if mesh.dim == 3 else 2
    lo, hi = mesh.cells[:, 0], mesh.cells[:, far]
    out = np.ones(mesh.n_cells)
    for d in range(mesh.dim):
        col = np.ascontiguousarray(mesh.lattice[:, d])
        out *= np.abs(col[hi] - col[lo]) * float(mesh.spacing[d])
    return out


def _plane_fixed(mesh: Mesh, nodes: np.ndarray) -> np.ndarray:
    """(len(nodes), 3) bool: the coordinate lies on a bounding plane of the image."""
    pts = mesh.points[nodes]
    lo = np.asarray(mesh.origin, float)
    hi = lo + np.asarray(mesh.grid_shape, float) * np.asarray(mesh.spacing, float)
    tol = 1e-6 * np.asarray(mesh.spacing, float)
    out = (np.abs(pts - lo) <= tol) | (np.abs(pts - hi) <= tol)
    if mesh.dim == 2:
        out[:, 2] = True
    return out


def _check_input(mesh: Mesh) -> None:
    if mesh.n_cells == 0 or mesh.n_points == 0:
        raise DicerError("the mesh is empty (no elements); mesh a label volume with material voxels first")
    if mesh.lattice is None or np.asarray(mesh.lattice).shape != (mesh.n_points, 3):
        raise DicerError("the mesh has no 'lattice' point data (not made by 'dicer mesh'); "
                         "remesh from the labels with 'dicer mesh'")
    if not np.all(np.isfinite(mesh.points)):
        raise DicerError("the mesh has non-finite node coordinates; remesh from the labels")


def smooth_mesh(mesh: Mesh, config_section: dict | None = None) -> tuple[Mesh, dict]:
    """Smooth ``mesh`` (boundary solve per node class, interior Laplace, quality guard).

    ``config_section`` is the ``smooth:`` config section (missing keys take DEFAULTS).
    Returns the smoothed mesh (same topology, with point data ``node_class``) and a report
    dict. Raises DicerError on bad settings, an empty mesh, a mesh without lattice data,
    or a mesh the guard cannot bring above ``min_scaled_jacobian``.
    """
    s = smoothing_settings(config_section)
    _check_input(mesh)
    t0 = time.perf_counter()
    timings = {}
    x0 = np.asarray(mesh.points, float)
    g = boundary_graph(mesh, x0)
    timings["classify"] = time.perf_counter() - t0

    bnodes = np.flatnonzero(g.boundary)
    adj = g.adjacency(bnodes)
    degree = g.degree[bnodes].astype(float)
    cls = g.node_class[bnodes]
    coef_by_code = np.zeros(len(NODE_CLASSES))
    for code, name in enumerate(NODE_CLASSES):
        if name in s["coefficients"]:
            coef_by_code[code] = s["coefficients"][name]
    coef_by_code[7] = min(s["coefficients"].values())  # irregular nodes: the most cautious value
    k = coef_by_code[cls]
    if mesh.dim == 2:
        fixed = np.zeros((bnodes.size, 3), bool)
        fixed[:, 2] = True
        if s["keep_bounding_planes"]:
            fixed |= _plane_fixed(mesh, bnodes)
    else:
        fixed = _plane_fixed(mesh, bnodes) if s["keep_bounding_planes"] else np.zeros((bnodes.size, 3), bool)
    xb0 = x0[bnodes]

    t1 = time.perf_counter()
    if s["interior"]:
        slots = _corner_slots(mesh.cells, mesh.n_points)
        band_nodes, touched = _band(mesh.cells, slots, g.boundary, g.boundary_cells, s["interior_band"])
        interior = _Interior(mesh.cells, slots, band_nodes, g.boundary)
        del slots
    else:
        band_nodes = np.zeros(0, np.int64)
        touched = g.boundary_cells
        interior = None
    timings["assemble"] = time.perf_counter() - t1

    floor = float(s["min_scaled_jacobian"])
    sj_before = scaled_jacobian(x0, mesh.cells[touched])
    backed = np.zeros(bnodes.size, bool)
    bpos = np.full(mesh.n_points, -1, np.int64)
    bpos[bnodes] = np.arange(bnodes.size)
    rounds = 0
    x = None
    t_solve = t_guard = 0.0
    it_b = it_i = 0
    while True:
        ts = time.perf_counter()
        d1, itb = _smoothing_step(adj, degree, k, xb0, fixed, s["tolerance"])
        it_b += itb
        if s["shrink_compensation"]:
            # twicing: x = (2S - S^2) x0 = x0 - (S(d1) - d1) with d1 = S(x0) - x0; the
            # low-frequency part of the displacement (the shrinkage) is taken back
            d2, itb = _smoothing_step(adj, degree, k, d1, fixed, s["tolerance"])
            it_b += itb
            xb = xb0 - d2
        else:
            xb = xb0 + d1
        if x is None:
            x = x0.copy()
        x[bnodes] = xb
        if interior is not None and band_nodes.size:
            u, iti = interior.solve(xb - xb0, s["tolerance"])
            it_i += iti
            x[band_nodes] = x0[band_nodes] + u
        tg = time.perf_counter()
        t_solve += tg - ts
        sj = scaled_jacobian(x, mesh.cells[touched])
        bad = (sj < floor) | (sj <= 0)
        # elements that were already below the floor before smoothing only fail if they got worse
        bad &= ~((sj_before < floor) & (sj >= sj_before - 1e-12) & (sj_before > 0))
        t_guard += time.perf_counter() - tg
        if not bad.any():
            break
        if rounds >= s["max_backoff_rounds"]:
            worst = int(np.argmin(np.where(bad, sj, np.inf)))
            e = int(touched[worst])
            centre = x[mesh.cells[e]].mean(axis=0)
            raise DicerError(
                f"smoothing cannot keep element {e + 1} (material {int(mesh.material[e])}, centre "
                f"{', '.join(f'{c:.2f}' for c in centre[: mesh.dim])} mm) at a scaled Jacobian of at least "
                f"{floor:g} (it reaches {sj[worst]:.3f}, {int(bad.sum())} element(s) fail); "
                "lower smooth.coefficient or smooth.min_scaled_jacobian")
        rounds += 1
        last = rounds >= max(1, s["max_backoff_rounds"] - 2)
        nodes = np.unique(mesh.cells[touched[bad]].ravel())
        for _ in range(4):
            sel = bpos[nodes]
            sel = sel[(sel >= 0)]
            sel = sel[k[sel] > 0]
            if sel.size:
                break
            mark = np.zeros(mesh.n_points, bool)
            mark[nodes] = True
            nodes = np.unique(mesh.cells[_touching(mesh.cells, mark)].ravel())
        if sel.size == 0:
            rounds = s["max_backoff_rounds"]  # nothing left to back off: report on the next pass
            continue
        k[sel] = 0.0 if last else k[sel] * s["backoff_factor"]
        k[sel[k[sel] < 0.02]] = 0.0
        backed[sel] = True

    # the smoothed mesh shares the input's topology arrays (cells, material, lattice)
    point_data = dict(mesh.point_data)
    point_data["node_class"] = g.node_class
    out = Mesh(x, mesh.cells, mesh.material, mesh.lattice, mesh.spacing.copy(), mesh.origin.copy(),
               mesh.grid_shape.copy(), point_data, dict(mesh.cell_data))
    # the volume a mesh (and each material) encloses depends on its boundary nodes only:
    # measure it on the elements holding a boundary node, with only those nodes moved
    bc = g.boundary_cells
    xb_only = x0.copy()
    xb_only[bnodes] = x[bnodes]
    dv = element_volumes(xb_only, mesh.cells[bc]) - element_volumes(x0, mesh.cells[bc])
    del xb_only
    base = np.bincount(mesh.material, weights=_lattice_volumes(mesh))
    change = np.bincount(mesh.material[bc], weights=dv, minlength=base.size)
    volume_change = {str(kind): float(change[kind] / base[kind]) for kind in np.flatnonzero(base)}
    moved = np.concatenate([bnodes, band_nodes])
    disp = np.linalg.norm(x[moved] - x0[moved], axis=1)
    bdisp = disp[: bnodes.size]
    report = {
        "nodes": mesh.n_points,
        "elements": mesh.n_cells,
        "boundary_nodes": int(bnodes.size),
        "boundary_edges": int(g.edges.shape[0]),
        "node_classes": class_counts(g.node_class),
        "coefficients": dict(s["coefficients"]),
        "interior_nodes_solved": int(band_nodes.size),
        "interior_band": s["interior_band"],
        "boundary_iterations": int(it_b),
        "interior_iterations": int(it_i),
        "backoff_rounds": rounds,
        "backed_off_nodes": int(backed.sum()),
        "min_scaled_jacobian": float(sj.min()) if sj.size else 1.0,
        "checked_elements": int(touched.size),
        "inverted_elements": int(np.count_nonzero(sj <= 0)),
        "volume_change": float(dv.sum() / base.sum()),
        "volume_change_by_material": volume_change,
        "max_displacement_mm": float(disp.max()) if disp.size else 0.0,
        "mean_boundary_displacement_mm": float(bdisp.mean()) if bdisp.size else 0.0,
        "seconds": {**{k_: round(v, 3) for k_, v in timings.items()}, "solve": round(t_solve, 3),
                    "guard": round(t_guard, 3), "total": round(time.perf_counter() - t0, 3)},
    }
    return out, report
