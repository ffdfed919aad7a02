"""The validation cases end to end: label image -> dicer's stages -> CalculiX -> stresses.

Kirsch: a plate with a round hole (radius ``a`` voxels, 1 mm voxels) under a uniform
tension sigma_0 = 1 MPa along x, plane stress (CPS4 / CPS8). The quarter plate lies on
rollers on its symmetry lines (X0: u_x = 0, Y0: u_y = 0) and is pulled on X1; the full
plate is pulled on X0 and X1 and held at two nodes only (the mid-points of X0 and X1),
which take no load. Each deck is solved a second time with Kirsch's displacements on the
plate's outer edges (:func:`kirsch_edges`), whose exact answer is Kirsch's 3.0; the finite
plate's is 3.095. Read on the hole's rim: the hoop stress at every rim node.

Lamé: a tube (radii a < b voxels) under internal pressure p = 1 MPa, a slice of a long
cylinder in plane strain (u_z = 0 on Z0 and Z1; the quarter on rollers on X0, Y0).
Read at the bore: the hoop stress at every bore node.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dicer.validation import analytic, geometry
from dicer.validation.calculix import read_frd_stress, run_ccx
from dicer.validation.models import Deck, build, dload, write_moved
from dicer.validation.reference import kirsch_displacement


def hoop(points: np.ndarray, stress: np.ndarray, centre) -> tuple[np.ndarray, np.ndarray]:
    """Hoop stress at nodes about an axis along z.

    Parameters
    ----------
    points : (N, >=2) float ndarray
    stress : (N, 6) float ndarray
        xx, yy, zz, xy, yz, zx.
    centre : sequence of float
        (x, y) of the axis.

    Returns
    -------
    theta : (N,) float64 ndarray
        Radians in (-pi, pi].
    hoop : (N,) float64 ndarray
    """
    theta = np.arctan2(points[:, 1] - centre[1], points[:, 0] - centre[0])
    s, c = np.sin(theta), np.cos(theta)
    return theta, stress[:, 0] * s * s + stress[:, 1] * c * c - 2.0 * stress[:, 3] * s * c


def _nodal_stress(frd: Path, n_points: int) -> np.ndarray:
    ids, stress = read_frd_stress(frd)
    out = np.full((n_points, 6), np.nan)
    out[ids - 1] = stress
    return out


def _solve_kirsch(deck_path: Path, part: str, centre, radius: float, edges: str = "tension") -> dict:
    """Solve one Kirsch deck and read its rim; ``edges``: ``tension`` (uniform sigma_0 on the
    loaded ends, the finite plate) or ``kirsch`` (Kirsch's displacements on the outer edges,
    whose exact answer is Kirsch's own: 3.0 at 90 degrees)."""
    deck = Deck.read(deck_path)
    x = deck.points[:, 0]
    x1 = deck.plane_faces(0, 1)
    if edges == "kirsch":
        step = kirsch_edges(deck, part, centre, radius)
    elif part == "quarter":
        step = "*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\n"
    else:  # two nodes on the x mid-line, on X0 and X1: a statically determinate hold
        mid = deck.points[:, 1] - centre[1]
        low = np.flatnonzero(x == x.min())
        high = np.flatnonzero(x == x.max())
        a, b = low[np.argmin(np.abs(mid[low]))], high[np.argmin(np.abs(mid[high]))]
        step = f"*NSET, NSET=HOLD_A\n{a + 1}\n*NSET, NSET=HOLD_B\n{b + 1}\n*BOUNDARY\nHOLD_A, 1, 2, 0\nHOLD_B, 2, 2, 0\n"
    if edges == "tension":
        loaded = x1 if part == "quarter" else x1 | deck.plane_faces(0, 0)
        step += "*STEP\n*STATIC\n" + dload(deck.face_elements[loaded], deck.face_numbers[loaded], -1.0)
    step += "*EL FILE\nS\n*END STEP\n"
    job = f"kirsch_{deck_path.stem}" + ("" if edges == "tension" else f"_{edges}")
    frd = run_ccx(deck_path.parent, f"*INCLUDE, INPUT={deck_path.name}\n{step}", job=job)
    return _read_rim(deck, _nodal_stress(frd, len(deck.points)), centre, radius)


def kirsch_edges(deck: Deck, part: str, centre, radius: float) -> str:
    """The step that gives a Kirsch deck Kirsch's own displacements on its outer edges.

    On a finite plate under uniform tension the stress at the hole is not Kirsch's 3.0: the
    square plate of the cases, L = 20 a, reads 3.095 at 90 degrees on a converged mesh
    (:func:`dicer.validation.reference.kirsch_square`). With the infinite plate's
    displacements (:func:`~dicer.validation.reference.kirsch_displacement`) prescribed at every
    node of the plate's outer edges (the quarter: X1 and Y1, rollers on X0 and Y0; the full
    plate: all four edges), Kirsch's field is the exact solution of the model, so its
    reading is the mesh's own error against 3.0, as in the reference O-grid.

    Parameters
    ----------
    deck : Deck
    part : {"quarter", "full"}
    centre : sequence of float
        The hole's centre (x, y), mm.
    radius : float
        The hole's radius, mm.

    Returns
    -------
    str
        Input lines from the model's boundary conditions to the step's loads.
    """
    x, y = deck.points[:, 0], deck.points[:, 1]
    outer = (np.abs(x - x.max()) < 1e-9) | (np.abs(y - y.max()) < 1e-9)
    if part != "quarter":
        outer |= (np.abs(x - x.min()) < 1e-9) | (np.abs(y - y.min()) < 1e-9)
    nodes = np.flatnonzero(outer)
    ux, uy = kirsch_displacement(x[nodes] - centre[0], y[nodes] - centre[1], radius)
    rows = "".join(f"{k + 1}, 1, 1, {u:.12e}\n{k + 1}, 2, 2, {v:.12e}\n" for k, u, v in zip(nodes, ux, uy))
    held = "*BOUNDARY\nX0, 1, 1, 0\nY0, 2, 2, 0\n" if part == "quarter" else ""
    return f"{held}*STEP\n*STATIC\n*BOUNDARY\n{rows}"


def _read_rim(deck: Deck, stress: np.ndarray, centre, radius: float) -> dict:
    """The Kirsch readings of the rim (see :func:`kirsch`) from the nodal stresses."""
    free = deck.free_faces()
    rim = np.unique(deck.face_nodes()[free])
    rim = rim[np.hypot(*(deck.points[rim, :2] - centre).T) < 2 * radius]
    theta, s_hoop = hoop(deck.points[rim], stress[rim], centre)
    order = np.argsort(theta, kind="stable")
    theta, s_hoop, s_xx = theta[order], s_hoop[order], stress[rim[order], 0]
    at_90 = [float(np.interp(t, theta, s_xx)) for t in (np.pi / 2, -np.pi / 2) if theta[0] <= t <= theta[-1]]
    top = int(np.argmax(s_hoop))
    rim_r = np.hypot(*(deck.points[rim[order], :2] - centre).T)
    # the field about the hole apart from the rim's local kinks: Kirsch's form at the rim,
    # A + B cos 2 theta (exact 1 - 2 cos 2 theta), fitted by least squares to every rim node
    # and evaluated at 90 deg; the residual is the nodes' scatter about it
    form = np.column_stack([np.ones(theta.size), np.cos(2.0 * theta)])
    coef, *_ = np.linalg.lstsq(form, s_hoop, rcond=None)
    scatter = float(np.sqrt(np.mean((s_hoop - form @ coef) ** 2)))
    return {
        "elements": int(deck.cells.shape[0]),
        "nodes": int(deck.points.shape[0]),
        "sigma_x_90": float(np.mean(at_90)),
        "sigma_x_90_each": at_90,
        "peak": float(s_hoop[top]),
        "peak_angle_deg": float(np.degrees(np.arccos(abs(np.cos(theta[top]))))),  # folded into [0, 90]
        "rim_fit_90": float(coef[0] - coef[1]),
        "rim_fit_scatter": scatter,
        "rim_radius_90": float(np.interp(np.pi / 2, theta, rim_r)),
        # the rim's geometry: its nodes' distance from the hole's circle (voxels)
        "rim_radius_error_mean": float(np.abs(rim_r - radius).mean()),
        "rim_radius_error_max": float(np.abs(rim_r - radius).max()),
        "rim_theta_deg": np.degrees(theta).tolist(),
        "rim_radius": rim_r.tolist(),
        "rim_hoop": s_hoop.tolist(),
    }


def rim_on_circle(deck_path: Path, centre, radius: float) -> Path:
    """A copy of a Kirsch deck with its rim on the exact circle: what the same elements read
    when the rim's position is no error at all.

    The rim's corner nodes move radially onto r = ``radius``; a quadratic deck's mid-edge
    rim nodes go to the midpoints of their moved ends (as ``dicer export`` places them).
    Nothing else moves, so the elements at the staircase's convex corners (three rim nodes)
    get a corner angle above 180 degrees there.

    Parameters
    ----------
    deck_path : Path
        A deck :func:`kirsch` solved.
    centre : sequence of float
        The hole's centre (x, y).
    radius : float

    Returns
    -------
    Path
        ``<deck>_circle.inp`` beside it.
    """
    deck = Deck.read(deck_path)
    points = deck.points.copy()
    free = deck.free_faces()
    sides = deck.face_nodes()[free]
    ends = np.unique(sides[:, :2])
    ends = ends[np.hypot(*(points[ends, :2] - centre).T) < 2 * radius]
    d = points[ends, :2] - centre
    points[ends, :2] = centre + d * (radius / np.hypot(*d.T))[:, None]
    if sides.shape[1] == 3:
        points[sides[:, 2]] = 0.5 * (points[sides[:, 0]] + points[sides[:, 1]])
    return write_moved(deck_path, points, deck_path.with_name(f"{deck_path.stem}_circle.inp"))


def kirsch(folder: str | os.PathLike, part: str = "quarter", sets: list[str] = (), radius: float = 7.0,
           width: int = 140, orders=(1, 2), offset=(0.0, 0.0), scan: bool = False, noise: float = 30.0,
           on_circle: bool = False, seed: int = 0) -> dict:
    """The Kirsch plate (:func:`~dicer.validation.geometry.kirsch_plate`) meshed and solved at
    each element order.

    Parameters
    ----------
    folder : str or os.PathLike
        Where the models and solver runs go.
    part : {"quarter", "full"}, optional
    sets : list of str, optional
        ``--set`` overrides.
    radius : float, optional
        Hole radius, voxels.
    width : int, optional
        Plate width, voxels.
    orders : sequence of int, optional
        Element orders.
    offset : sequence of float, optional
        The full plate's hole centre off the image centre (voxels).
    scan : bool, optional
        Model the plate from a CT-like grey-value image
        (:func:`~dicer.validation.geometry.kirsch_scan`) by ``dicer run`` on the image (manual
        threshold, the smoothing pulled onto the image's iso-line) instead of from labels.
    noise : float, optional
        With ``scan``: the image's noise (standard deviation, of a contrast of 1000).
    seed : int, optional
        With ``scan``: the noise's draw (the quarter's noise is the full plate's of the same seed).
    on_circle : bool, optional
        Also solve each deck with its rim moved onto the exact circle (:func:`rim_on_circle`),
        as ``"<order> on circle"``.

    Returns
    -------
    dict
        ``{"min_sj", "inverted", "backed_off", order: {...}}`` where each order gives
        sigma_x / sigma_0 at theta = 90 degrees (the mean over the points at +-90 degrees
        the part holds), the largest rim hoop stress and its angle from the load axis
        (degrees, folded into [0, 90]), the rim fit (Kirsch's form A + B cos 2 theta fitted
        to the rim nodes' hoop stresses, at 90 degrees, and the nodes' rms scatter about
        it), the rim node radius at 90 degrees, the rim nodes' distance from the circle
        (mean and largest |r - a|) and the rim's hoop stresses and radii by angle; its
        ``kirsch_edges`` the same stress readings with Kirsch's displacements on the plate's
        outer edges instead of the uniform tension (:func:`kirsch_edges`: exact 3.0).
    """
    if scan and any(offset):
        raise ValueError("the grey-value plate has its hole about the image centre; no offset")
    image = (geometry.kirsch_scan(radius, width, part, noise=noise, seed=seed) if scan
             else geometry.kirsch_plate(radius, width, part, offset))
    centre = np.zeros(2) if part == "quarter" else np.full(2, width / 2) + offset
    built = build(image, folder, sets, orders, scan=scan)
    out = {"min_sj": built["quality"]["scaled_jacobian"]["min"], "inverted": built["quality"]["inverted_elements"],
           "backed_off": built["smooth"]["backed_off_nodes"]}
    for order, path in built["decks"].items():
        out[order] = _solve_kirsch(path, part, centre, radius)
        exact = _solve_kirsch(path, part, centre, radius, edges="kirsch")
        out[order]["kirsch_edges"] = {k: exact[k] for k in _EDGE_READINGS}
        if on_circle:
            out[f"{order} on circle"] = _solve_kirsch(rim_on_circle(path, centre, radius), part, centre, radius)
    return out


_EDGE_READINGS = ("sigma_x_90", "sigma_x_90_each", "peak", "peak_angle_deg", "rim_fit_90", "rim_fit_scatter")


def _solve_lame(deck_path: Path, part: str, centre, inner: float, outer: float) -> dict:
    deck = Deck.read(deck_path)
    free = deck.free_faces()
    nodes = deck.face_nodes()
    r = np.hypot(*(deck.points[:, :2] - centre).T)
    bore_faces = free & np.all(r[nodes] < 0.5 * (inner + outer), axis=1)
    step = "*BOUNDARY\nZ0, 3, 3, 0\nZ1, 3, 3, 0\n"
    if part == "quarter":
        step += "X0, 1, 1, 0\nY0, 2, 2, 0\n"
    else:  # rigid motions in the plane: two nodes on the bore's x axis, on either side
        on_x = np.flatnonzero((np.abs(deck.points[:, 1] - centre[1]) < 1e-9) & (deck.points[:, 2] == 0))
        a, b = on_x[np.argmin(deck.points[on_x, 0])], on_x[np.argmax(deck.points[on_x, 0])]
        step += f"*NSET, NSET=HOLD_A\n{a + 1}\n*NSET, NSET=HOLD_B\n{b + 1}\n*BOUNDARY\nHOLD_A, 1, 2, 0\nHOLD_B, 2, 2, 0\n"
    step += ("*STEP\n*STATIC\n" + dload(deck.face_elements[bore_faces], deck.face_numbers[bore_faces], 1.0)
             + "*EL FILE\nS\n*END STEP\n")
    frd = run_ccx(deck_path.parent, f"*INCLUDE, INPUT={deck_path.name}\n{step}", job=f"lame_{deck_path.stem}")
    stress = _nodal_stress(frd, len(deck.points))
    bore = np.unique(nodes[bore_faces])
    _, s_hoop = hoop(deck.points[bore], stress[bore], centre)
    exact = float(analytic.lame_hoop(inner, inner, outer))
    # the field inside the wall: least squares of A + B / r^2 (Lamé's form) through the nodes
    # more than 1.5 voxels from either surface, evaluated at the bore
    wall = np.flatnonzero((r >= inner + 1.5) & (r <= outer - 1.5) & np.isfinite(stress[:, 0]))
    _, s_wall = hoop(deck.points[wall], stress[wall], centre)
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(wall.size), r[wall] ** -2.0]), s_wall, rcond=None)
    fit = float(coef[0] + coef[1] / inner**2)
    return {
        "elements": int(deck.cells.shape[0]),
        "nodes": int(deck.points.shape[0]),
        "bore_nodes": int(bore.size),
        "exact": exact,
        "mean": float(s_hoop.mean()),
        "min": float(s_hoop.min()),
        "max": float(s_hoop.max()),
        "error_mean": float(s_hoop.mean() / exact - 1.0),
        "error_worst": float(s_hoop[np.argmax(np.abs(s_hoop - exact))] / exact - 1.0),
        "bore_radius_mean": float(r[bore].mean()),
        "wall_fit": fit,
        "error_wall_fit": fit / exact - 1.0,
    }


def lame(folder: str | os.PathLike, part: str = "quarter", sets: list[str] = (), inner: float = 7.0,
         outer: float = 14.0, length: int = 2, orders=(1, 2), scan: bool = False) -> dict:
    """The Lamé cylinder (:func:`~dicer.validation.geometry.lame_cylinder`) meshed and solved at
    each element order.

    Parameters
    ----------
    folder, part, sets
        As in :func:`kirsch`.
    inner, outer : float, optional
        Radii, voxels.
    length : int, optional
        Voxels along z.
    orders : sequence of int, optional
        Element orders.
    scan : bool, optional
        From a CT-like grey-value image (:func:`~dicer.validation.geometry.lame_scan`), as in
        :func:`kirsch`.

    Returns
    -------
    dict
        ``{"min_sj", "inverted", order: {...}}`` where each order gives the bore hoop
        stress / p (mean, min, max over the bore nodes), the exact value, the relative
        errors of the mean and of the worst node, and the wall fit: Lamé's form
        A + B / r^2 fitted to the hoop stress at the nodes inside the wall, at r = a.
    """
    image = (geometry.lame_scan if scan else geometry.lame_cylinder)(inner, outer, length, part)
    half = image.shape[0] / 2
    centre = np.zeros(2) if part == "quarter" else np.full(2, half)
    built = build(image, folder, sets, orders, scan=scan)
    out = {"min_sj": built["quality"]["scaled_jacobian"]["min"], "inverted": built["quality"]["inverted_elements"],
           "backed_off": built["smooth"]["backed_off_nodes"]}
    for order, path in built["decks"].items():
        out[order] = _solve_lame(path, part, centre, inner, outer)
    return out
