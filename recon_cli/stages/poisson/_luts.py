"""Tables of the screened Poisson solver: the trilinear (Q1) element matrices."""

from __future__ import annotations

import numpy as np

# 1D linear element on [0, 1]: mass and stiffness between the hats at its two ends
_MASS_1D = np.array([[1.0 / 3.0, 1.0 / 6.0], [1.0 / 6.0, 1.0 / 3.0]])
_STIFF_1D = np.array([[1.0, -1.0], [-1.0, 1.0]])


def _element_stiffness() -> np.ndarray:
    """Int grad(phi_a) . grad(phi_b) over the unit cube, corners ordered bit i = axis i."""
    ke = np.zeros((8, 8))
    for a in range(8):
        for b in range(8):
            ia = [(a >> k) & 1 for k in range(3)]
            ib = [(b >> k) & 1 for k in range(3)]
            s = 0.0
            for axis in range(3):
                t = 1.0
                for k in range(3):
                    m = _STIFF_1D if k == axis else _MASS_1D
                    t *= m[ia[k], ib[k]]
                s += t
            ke[a, b] = s
    return ke


# on a cube of side h the element stiffness is h * UNIT_STIFFNESS (3D: h^3 volume / h^2 gradients)
UNIT_STIFFNESS = _element_stiffness()
# the solver's diagonal is a table by incident-cell count (stiffness_diag_table): exact only
# because every corner has the same diagonal entry, bit for bit
if not np.all(np.diag(UNIT_STIFFNESS) == UNIT_STIFFNESS[0, 0]):
    raise RuntimeError(
        "element stiffness: corner diagonal entries differ; the solver's diagonal table needs "
        "them equal"
    )

# mean over plane offsets of sum_k B2(t - k)^2: a plane of sigma samples per unit area gives a
# kernel density of about 0.55 * sigma * h^2 at level spacing h
B2_PLANE_DENSITY = 0.55

# Degree 2: the centred quadratic B-spline B2 (support [-1.5, 1.5]); between the functions of
# two cells t = -2..2 apart (cell units): mass int B2(u) B2(u - t) du (the quintic B-spline at
# t) and stiffness int B2'(u) B2'(u - t) du (minus its second derivative)
B2_MASS = np.array([1.0 / 120.0, 13.0 / 60.0, 11.0 / 20.0, 13.0 / 60.0, 1.0 / 120.0])
B2_STIFFNESS = np.array([-1.0 / 6.0, -1.0 / 3.0, 1.0, -1.0 / 3.0, -1.0 / 6.0])
