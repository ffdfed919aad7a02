"""Closed-form stresses of the validation cases (linear elasticity)."""

from __future__ import annotations

import numpy as np


def kirsch_hoop(theta: np.ndarray) -> np.ndarray:
    """Hoop stress on the rim of a round hole in an infinite plate under uniaxial tension
    sigma_0 along x, divided by sigma_0: 1 - 2 cos(2 theta) (theta in radians from the load
    axis); 3 at theta = 90 degrees."""
    return 1.0 - 2.0 * np.cos(2.0 * np.asarray(theta, float))


def lame_hoop(r: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """Hoop stress in a thick-walled cylinder (radii inner < outer) under internal pressure p,
    divided by p: a^2 (1 + b^2 / r^2) / (b^2 - a^2); at the bore (b^2 + a^2) / (b^2 - a^2)."""
    a2, b2 = inner**2, outer**2
    return a2 * (1.0 + b2 / np.asarray(r, float) ** 2) / (b2 - a2)
