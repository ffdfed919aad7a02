"""Closed-form stresses of the validation cases (linear elasticity)."""

from __future__ import annotations

import numpy as np


def kirsch_hoop(theta: np.ndarray) -> np.ndarray:
    """Hoop stress on the rim of a round hole in an infinite plate under uniaxial tension,
    over the applied stress: 1 - 2 cos(2 theta); 3 at theta = 90 degrees.

    Parameters
    ----------
    theta : ndarray
        Angle from the load axis (x), radians.

    Returns
    -------
    ndarray
        sigma_theta / sigma_0, the shape of ``theta``.
    """
    return 1.0 - 2.0 * np.cos(2.0 * np.asarray(theta, float))


def lame_hoop(r: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """Hoop stress in a thick-walled cylinder under internal pressure p, over p:
    a^2 (1 + b^2 / r^2) / (b^2 - a^2); at the bore (b^2 + a^2) / (b^2 - a^2).

    Parameters
    ----------
    r : ndarray
        Radius, between ``inner`` and ``outer``.
    inner, outer : float
        Radii a < b.

    Returns
    -------
    ndarray
        sigma_theta / p, the shape of ``r``.
    """
    a2, b2 = inner**2, outer**2
    return a2 * (1.0 + b2 / np.asarray(r, float) ** 2) / (b2 - a2)
