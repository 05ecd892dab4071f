"""A grid's far field made the exact distance to its own zero level.

A fitted field (``recon fit-sdf``'s network) is a distance near the surface it was fitted to
and an extrapolation away from it. :func:`redistance` keeps the grid's values within a band
of its zero level (so its marching-cubes surface stays the same to the bit) and replaces them
beyond it by the signed distance to that surface: the triangles marching cubes makes of the
grid, exact point-to-triangle distances, the sign the grid's own.
"""

from __future__ import annotations

import math

import numpy as np

#: the grids of up to this many samples get the exact distance at every sample; a larger one
#: exactly within :func:`redistance`'s band and a stride of its lattice, trilinear in between
EXACT_SAMPLES = 1 << 24
# the fine samples beyond which a larger grid's far values are interpolated, in strides
_FINE_STRIDES = 2


def redistance(
    values: np.ndarray,
    origin: np.ndarray,
    voxel_size: float,
    keep: float = 2.0,
    blend: float = 1.0,
) -> tuple[np.ndarray, dict]:
    """The grid with its far values the signed distance to its zero level.

    Parameters
    ----------
    values : (nx, ny, nz) float
        The field, negative inside, finite; sample ``[i, j, k]`` at ``origin + (i, j, k) h``.
    origin : (3,) float
        World position of sample ``[0, 0, 0]``.
    voxel_size : float
        ``h``, the samples' spacing (world units).
    keep : float
        Samples within this many ``h`` of the zero level keep their value. At 1 or more the
        ends of every edge the surface crosses keep theirs, so marching cubes (and its
        asymptotic decider) gives the same surface; at 2 the samples next to them too (the
        central differences of the surface's normals).
    blend : float
        Over the next ``blend`` ``h`` the value goes linearly from the grid's to the distance.

    Returns
    -------
    out : (nx, ny, nz) ndarray of ``values``' dtype
        ``values`` within the band, the signed distance (world units) beyond it.
    info : dict
        ``redistanced`` (samples whose value changed) and ``exact`` (False when the grid has
        more than :data:`EXACT_SAMPLES` samples: the distance is then exact within
        ``2 * stride + keep + blend`` samples of the surface and on every ``stride``-th
        sample, trilinear between those).

    References
    ----------
    Lorensen, W. E. & Cline, H. E. (1987). Marching cubes: a high resolution 3D surface
    construction algorithm. SIGGRAPH (the zero level's triangles).
    """
    from recon_cli.mesh.distance import distance_grid
    from recon_cli.stages.mcubes import marching_cubes

    s = np.asarray(values)
    h = float(voxel_size)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    v, f, _ = marching_cubes(s, 0.0, h, (float(origin[0]), float(origin[1]), float(origin[2])))
    if len(f) == 0:  # no surface: nothing to measure from
        return s, {"redistanced": 0, "exact": True}
    stride = max(1, math.ceil((s.size / EXACT_SAMPLES) ** (1.0 / 3.0)))
    if stride == 1:
        dist, _ = distance_grid(v, f, origin, h, s.shape)
    else:
        dist = _banded_distance(v, f, origin, h, s.shape, stride, keep + blend)
    ds = np.where(s < 0, -dist, dist)
    del dist
    w = np.clip((np.abs(ds) - keep * h) / (blend * h), 0.0, 1.0)
    changed = w > 0
    # where w is 0 the sum is the grid's value to the bit
    out = (s + w * (ds - s)).astype(s.dtype)
    return out, {"redistanced": int(changed.sum()), "exact": stride == 1}


def _banded_distance(v, f, origin, h, shape, stride: int, band: float) -> np.ndarray:
    """Exact within ``2 stride + band`` samples and on the ``stride`` lattice, trilinear between.

    Returns (nx, ny, nz) float64 distances (world units).
    """
    from scipy.ndimage import map_coordinates

    from recon_cli.mesh.distance import distance_grid

    reach = (_FINE_STRIDES * stride + band) * h
    near, _ = distance_grid(v, f, origin, h, shape, band=reach)
    cshape = tuple(-(-(n - 1) // stride) + 1 for n in shape)  # the lattice covers the grid
    coarse, _ = distance_grid(v, f, origin, stride * h, cshape)
    yz = np.indices(shape[1:], dtype=np.float32).reshape(2, -1) / stride
    for i in range(shape[0]):  # a plane at a time: the coordinates of one plane at most
        far = near[i] >= reach
        if not far.any():
            continue
        idx = np.vstack([np.full(yz.shape[1], i / stride, np.float32), yz])
        plane = map_coordinates(coarse, idx, order=1, mode="nearest").reshape(shape[1:])
        near[i][far] = plane[far]
    return near
