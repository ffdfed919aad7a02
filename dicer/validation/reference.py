"""A reference mesh for the Kirsch plate: what CPS4 and CPS8 read on an ideal mesh of dicer's size.

A structured polar (O-grid) mesh of the quarter of an infinite plate about a hole of radius
a: ``n_theta`` elements along the quarter rim, the first ring ``first`` voxels deep and the
rings growing with r (elements keep the rim's aspect), out to r = ``outer`` a, where Kirsch's
exact displacements are prescribed (so the exact solution is Kirsch's: sigma_x = 3 sigma_0
at 90 degrees, no finite-width correction). Rollers on the symmetry lines. Read as the
validation cases read: ccx's nodal stress at the rim node at 90 degrees. With 11 elements
along the quarter rim and a first ring 1 voxel deep it has dicer's element size at a = 7
voxels, so the difference between its reading and 3.0 is the elements' own error there.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dicer.validation.calculix import read_frd_stress, run_ccx
from dicer.validation.models import E_MODULUS, POISSON


def kirsch_displacement(x: np.ndarray, y: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Kirsch's displacements (plane stress, unit tension along x, E and nu of the cases).

    Parameters
    ----------
    x, y : float ndarray
        Positions relative to the hole's centre, voxels (mm).
    radius : float
        Hole radius.

    Returns
    -------
    ux, uy : float64 ndarray
    """
    shear = E_MODULUS / (2.0 * (1.0 + POISSON))
    kappa = (3.0 - POISSON) / (1.0 + POISSON)
    r, t = np.hypot(x, y), np.arctan2(y, x)
    c2, s2 = np.cos(2 * t), np.sin(2 * t)
    a2 = radius * radius
    ur = (r * ((kappa - 1) / 2 + c2) + a2 / r * (1 + (1 + kappa) * c2) - a2 * a2 / r**3 * c2) / (4 * shear)
    ut = ((1 - kappa) * a2 / r - r - a2 * a2 / r**3) * s2 / (4 * shear)
    return ur * np.cos(t) - ut * np.sin(t), ur * np.sin(t) + ut * np.cos(t)


def kirsch_ogrid(folder: str | os.PathLike, order: int = 1, radius: float = 7.0, n_theta: int = 11,
                 first: float = 1.0, outer: float = 5.0) -> dict:
    """Solve the O-grid quarter plate and read sigma_x / sigma_0 at the rim node at 90 degrees.

    Parameters
    ----------
    folder : str or os.PathLike
        Where the deck and the solver run go.
    order : {1, 2}, optional
        CPS4 or CPS8 (mid-edge nodes on the polar grid: on the arcs and rays).
    radius : float, optional
        Hole radius a, voxels.
    n_theta : int, optional
        Elements along the quarter rim.
    first : float, optional
        Depth of the first ring, voxels; ring k + 1 is (r_k / a) times as deep.
    outer : float, optional
        Outer radius, in units of a.

    Returns
    -------
    dict
        ``{"elements", "sigma_x_90"}``.
    """
    r = [radius]
    while r[-1] < outer * radius:
        r.append(r[-1] + first * r[-1] / radius)
    r = np.asarray(r)
    theta = np.linspace(0.0, np.pi / 2, n_theta + 1)
    if order == 2:  # the mid-edge nodes' rings and rays
        r = np.sort(np.concatenate([r, 0.5 * (r[1:] + r[:-1])]))
        theta = np.linspace(0.0, np.pi / 2, 2 * n_theta + 1)
    rr, tt = np.meshgrid(r, theta, indexing="ij")
    x, y = rr * np.cos(tt), rr * np.sin(tt)
    ids = np.arange(rr.size).reshape(rr.shape) + 1
    s = order  # grid lines per element side
    i, j = np.meshgrid(np.arange(0, r.size - 1, s), np.arange(0, theta.size - 1, s), indexing="ij")
    i, j = i.ravel(), j.ravel()
    corners = [ids[i, j], ids[i + s, j], ids[i + s, j + s], ids[i, j + s]]  # counter-clockwise
    if order == 2:
        corners += [ids[i + 1, j], ids[i + 2, j + 1], ids[i + 1, j + 2], ids[i, j + 1]]
    cells = np.stack(corners, axis=1)
    ux, uy = kirsch_displacement(x[-1], y[-1], radius)
    etype = "CPS4" if order == 1 else "CPS8"
    node_rows = [f"{k}, {a:.12e}, {b:.12e}" for k, a, b in zip(ids.ravel(), x.ravel(), y.ravel())]
    cell_rows = [f"{e + 1}, " + ", ".join(map(str, c)) for e, c in enumerate(cells.tolist())]
    held = [f"{k}, 2, 2, 0" for k in ids[:, 0]] + [f"{k}, 1, 1, 0" for k in ids[:, -1]]
    moved = [f"{k}, 1, 1, {u:.12e}\n{k}, 2, 2, {v:.12e}" for k, u, v in zip(ids[-1], ux, uy)]
    deck = "\n".join(["*NODE", *node_rows, f"*ELEMENT, TYPE={etype}, ELSET=PLATE", *cell_rows,
                      "*MATERIAL, NAME=SOLID", "*ELASTIC", f"{E_MODULUS}, {POISSON}",
                      "*SOLID SECTION, ELSET=PLATE, MATERIAL=SOLID", "1.0", "*BOUNDARY", *held,
                      "*STEP", "*STATIC", "*BOUNDARY", *moved, "*EL FILE", "S", "*END STEP"]) + "\n"
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    frd = run_ccx(folder, deck, job=f"ogrid_{etype}")
    node, stress = read_frd_stress(frd)
    top = int(ids[0, -1])
    return {"elements": int(cells.shape[0]), "sigma_x_90": float(stress[np.flatnonzero(node == top)[0], 0])}


def kirsch_square(folder: str | os.PathLike, radius: float = 7.0, half_width: float = 70.0, n: int = 128) -> dict:
    """The finite plate of the Kirsch cases on a converged mesh: its own exact sigma_x at 90 degrees.

    The quarter of a square plate (half-width ``half_width``) about a hole of radius
    ``radius``, under the cases' uniform tension on X1 (unit traction as consistent nodal
    forces), rollers on X0 and Y0, free Y1: the problem the label and grey-value cases solve
    under ``tension``. A mapped mesh of 8-node quads: ``n`` elements along the quarter rim,
    each ray from the rim to the square's edge cut into ``n`` elements graded quadratically
    toward the hole. Measured: 3.0861, 3.0931, 3.0949 at n = 32, 64, 128 (CPS8); CPS4 at
    n = 128 3.0955; Kirsch's 3.0 belongs to the infinite plate.

    Parameters
    ----------
    folder : str or os.PathLike
        Where the deck and the solver run go.
    radius : float, optional
        Hole radius a, mm.
    half_width : float, optional
        Half the plate's width and length, mm.
    n : int, optional
        Elements along the rim and along each ray.

    Returns
    -------
    dict
        ``{"elements", "sigma_x_90"}``.
    """
    theta = np.linspace(0.0, np.pi / 2, 2 * n + 1)  # the mid-edge nodes' rays and rings too
    c, s = np.cos(theta), np.sin(theta)
    edge = half_width / np.maximum(np.maximum(c, s), 1e-300)  # where each ray meets the square
    t = np.linspace(0.0, 1.0, 2 * n + 1) ** 2
    rr = radius + (edge[None, :] - radius) * t[:, None]
    x, y = rr * c, rr * s
    x[:, -1], y[:, 0] = 0.0, 0.0
    ids = np.arange(rr.size).reshape(rr.shape) + 1
    i, j = np.meshgrid(np.arange(0, 2 * n, 2), np.arange(0, 2 * n, 2), indexing="ij")
    i, j = i.ravel(), j.ravel()
    cells = np.stack([ids[i, j], ids[i + 2, j], ids[i + 2, j + 2], ids[i, j + 2],
                      ids[i + 1, j], ids[i + 2, j + 1], ids[i + 1, j + 2], ids[i, j + 1]], axis=1)
    # X1: the outer nodes on x = half_width, by y; unit traction as Simpson's nodal forces
    on = np.flatnonzero(np.abs(x[-1] - half_width) < 1e-9 * half_width)
    on = on[np.argsort(y[-1, on])]
    force = np.zeros(on.size)
    h = y[-1, on[2::2]] - y[-1, on[:-2:2]]
    np.add.at(force, np.arange(0, on.size - 2, 2), h / 6)
    np.add.at(force, np.arange(1, on.size - 1, 2), 4 * h / 6)
    np.add.at(force, np.arange(2, on.size, 2), h / 6)
    node_rows = [f"{k}, {a:.12e}, {b:.12e}" for k, a, b in zip(ids.ravel(), x.ravel(), y.ravel())]
    cell_rows = [f"{e + 1}, " + ", ".join(map(str, row)) for e, row in enumerate(cells.tolist())]
    held = [f"{k}, 2, 2, 0" for k in ids[:, 0]] + [f"{k}, 1, 1, 0" for k in ids[:, -1]]
    loads = [f"{ids[-1, k]}, 1, {f:.12e}" for k, f in zip(on, force)]
    deck = "\n".join(["*NODE", *node_rows, "*ELEMENT, TYPE=CPS8, ELSET=PLATE", *cell_rows,
                      "*MATERIAL, NAME=SOLID", "*ELASTIC", f"{E_MODULUS}, {POISSON}",
                      "*SOLID SECTION, ELSET=PLATE, MATERIAL=SOLID", "1.0", "*BOUNDARY", *held,
                      "*STEP", "*STATIC", "*CLOAD", *loads, "*EL FILE", "S", "*END STEP"]) + "\n"
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    node, stress = read_frd_stress(run_ccx(folder, deck, job="square_CPS8"))
    top = int(ids[0, -1])
    return {"elements": int(cells.shape[0]), "sigma_x_90": float(stress[np.flatnonzero(node == top)[0], 0])}
