"""The one tolerance dataclass of the package (cf. trimesh ``constants.py``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tolerance:
    """Numerical tolerances, relative unless stated.

    Attributes
    ----------
    zero : float
        Absolute threshold below which a float is treated as zero.
    merge : float
        Relative (to the bounding-box diagonal) distance under which vertices are the same.
    area : float
        Relative (to diagonal squared) area under which a triangle is degenerate.
    planar : float
        Ratio of smallest to middle covariance eigenvalue below which a neighbourhood is planar.
    collinear : float
        Ratio of middle to largest covariance eigenvalue below which a neighbourhood is a line.
    volume : float
        Relative volume change accepted where an operation must preserve volume.
    contour : float
        Fraction of an edge's length within which a contour crossing is moved off the edge's
        ends when a mesh is cut along a contour (no sliver pieces).
    precision : float
        Relative (to the bounding-box diagonal) rounding that writing float64 coordinates of a
        float32 source as float32 may add; beyond it they are written as float64.
    """

    zero: float = 1e-12
    merge: float = 1e-8
    area: float = 1e-14
    planar: float = 1e-3
    collinear: float = 1e-6
    volume: float = 1e-6
    contour: float = 1e-3
    precision: float = 1e-6


tol = Tolerance()
