"""``stages.sdf.redistance``: the far field the exact distance to the grid's zero level."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.grid import Grid
from recon_cli.stages.mcubes import marching_cubes
from recon_cli.stages.sdf import eikonal_check
from recon_cli.stages.sdf import redistance as R


def _lattice(n: int, h: float, origin: np.ndarray) -> np.ndarray:
    """The samples' world positions, (n, n, n, 3)."""
    i = np.indices((n, n, n)).transpose(1, 2, 3, 0)
    return origin + h * i


def _warped_sphere(n: int, h: float, origin: np.ndarray, r: float) -> np.ndarray:
    """A field whose zero level is the sphere of radius ``r``, its slope not 1 away from it."""
    x = _lattice(n, h, origin) - (origin + 0.5 * h * (n - 1))
    rho = np.linalg.norm(x, axis=-1)
    # the sign and the zero level of rho - r, its slope 0.6 to 1.8 and varying with direction
    slope = 1.2 + 0.6 * np.sin(3.0 * x[..., 0] / r) * np.cos(2.0 * x[..., 1] / r)
    return ((rho - r) * slope).astype(np.float32)


def _same_surface(a, b, h: float, origin: np.ndarray, normals: bool = True) -> bool:
    """Marching cubes gives the same vertices, faces and (``normals``) normals."""
    ma, mb = marching_cubes(a, 0.0, h, origin), marching_cubes(b, 0.0, h, origin)
    k = 3 if normals else 2
    return all(np.array_equal(x, y) for x, y in zip(ma[:k], mb[:k], strict=True))


def test_far_values_are_the_distance_to_the_zero_level_and_the_surface_stays():
    """Beyond the band: the distance to the sphere (to marching cubes' chords), slope 1.

    Within it the grid's values to the bit, so the same triangles and normals; 1e6 away.
    """
    n, r = 48, 0.3
    h = 1.0 / (n - 1)
    origin = np.full(3, 1e6)
    s = _warped_sphere(n, h, origin, r)
    out, info = R.redistance(s, origin, h)
    assert out.dtype == s.dtype and info["exact"] and info["redistanced"] > 0.5 * s.size
    rho = np.linalg.norm(_lattice(n, h, origin) - (origin + 0.5 * h * (n - 1)), axis=-1)
    far = np.abs(rho - r) > 3 * h
    # the triangles' chords are inside the sphere by at most h^2 / (8 r) (and float32)
    assert np.abs(out[far] - (rho - r)[far]).max() < h * h / r + 1e-5
    near = np.abs(rho - r) < 1.5 * h  # every end of a crossed edge and its neighbours
    assert np.array_equal(out[near], s[near])
    assert _same_surface(s, out, h, origin)
    # the slope beyond the band (NaN: left out by the check), 1 but at the medial axis
    away = np.abs(rho - r) > 3.5 * h

    def within(a):
        g = Grid(sdf=np.where(away, a, np.nan), origin=origin, voxel_size=h)
        return eikonal_check(g)["fraction_within_0.1"]

    before, after = within(s), within(out)
    assert before < 0.3 and after > 0.99, (before, after)


def test_a_large_grid_is_exact_near_and_close_far(monkeypatch):
    """Past EXACT_SAMPLES: exact within the band and on the stride's lattice, trilinear between."""
    n, r = 48, 0.3
    h = 1.0 / (n - 1)
    origin = np.zeros(3)
    s = _warped_sphere(n, h, origin, r)
    exact, _ = R.redistance(s, origin, h)
    monkeypatch.setattr(R, "EXACT_SAMPLES", n**3 // 20)
    banded, info = R.redistance(s, origin, h)
    assert not info["exact"]
    rho = np.linalg.norm(_lattice(n, h, origin) - 0.5 * h * (n - 1), axis=-1)
    band = np.abs(rho - r) < 6 * h
    assert np.array_equal(banded[band], exact[band])
    # outside a sphere the distance is smooth: trilinear is close; inside it peaks at the
    # centre (the medial axis), where trilinear cuts the cone's tip by up to a stride
    stride = int(np.ceil(20 ** (1 / 3)))
    outside = rho > r
    assert np.abs(banded - exact)[outside].max() < 0.15 * h
    assert np.abs(banded - exact).max() < stride * h
    assert _same_surface(s, banded, h, origin)


def test_no_zero_level_leaves_the_grid():
    """A grid of one sign has no surface to measure from: it is returned as it is."""
    s = np.ones((6, 7, 8), np.float32)
    out, info = R.redistance(s, np.zeros(3), 0.1)
    assert out is s and info == {"redistanced": 0, "exact": True}


@settings(max_examples=25, deadline=None)
@given(
    centres=st.lists(
        st.tuples(*[st.floats(0.25, 0.75)] * 3, st.floats(0.08, 0.25), st.floats(0.3, 3.0)),
        min_size=1,
        max_size=3,
    ),
    keep=st.floats(1.05, 3.0),
)
def test_the_surface_never_moves(centres, keep):
    """Any field: the same signs and marching-cubes mesh; from ``keep`` 2 the same normals.

    The ends of the crossed edges keep their values (their neighbours too from 2 cells).
    """
    n = 20
    h = 1.0 / (n - 1)
    x = _lattice(n, h, np.zeros(3))
    s = np.min(
        [(np.linalg.norm(x - c[:3], axis=-1) - c[3]) * c[4] for c in centres], axis=0
    ).astype(np.float32)
    out, _ = R.redistance(s, np.zeros(3), h, keep=keep)
    assert np.array_equal(np.sign(out), np.sign(s))
    assert _same_surface(s, out, h, np.zeros(3), normals=keep >= 2)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_is_kept(dtype):
    """Float32 in, float32 out; double in, double out."""
    n = 16
    h = 1.0 / (n - 1)
    s = _warped_sphere(n, h, np.zeros(3), 0.3).astype(dtype)
    out, _ = R.redistance(s, np.zeros(3), h)
    assert out.dtype == dtype
