"""The warm-up's inputs: tiny clouds, meshes and files that reach every kernel's variants.

:func:`make_inputs` writes them into a folder; :class:`Files` names them for the phases of
:mod:`recon_cli.cli._warmup` (``f.m64``, ``f.open``, ...) and gives each phase its own folder.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


def _sphere_cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on the unit sphere (a jittered Fibonacci spiral) and their outward normals."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5**0.5) * i
    p = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    p += np.random.default_rng(seed).normal(scale=1e-3, size=p.shape)
    nrm = p / np.linalg.norm(p, axis=1, keepdims=True)
    return p, nrm


def _sphere_mesh(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated sphere with ``n`` vertices, faces wound outward."""
    from scipy.spatial import ConvexHull

    p, _ = _sphere_cloud(n, seed=1)
    f = ConvexHull(p).simplices.astype(np.int64)
    c = p[f].mean(axis=1)
    nrm = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    flip = np.einsum("ij,ij->i", nrm, c) < 0
    f[flip] = f[flip][:, ::-1]
    return p, f


def make_inputs(root: str) -> None:
    """Write the warm-up's input files into ``root`` (names as :class:`Files` gives them)."""
    from recon_cli.geometry import PointCloud, TriangleMesh
    from recon_cli.io.ply import write_ply

    def path(name: str) -> str:
        return os.path.join(root, name)

    p, nrm = _sphere_cloud(600)
    rgb = (np.abs(nrm) * 255).astype(np.uint8)
    v, f = _sphere_mesh(300)
    for dtype in (np.float32, np.float64):
        tag = np.dtype(dtype).name
        write_ply(PointCloud(points=p.astype(dtype), point_dtype=dtype), path(f"bare_{tag}.ply"))
        write_ply(
            PointCloud(
                points=p.astype(dtype), normals=nrm.astype(dtype), colors=rgb, point_dtype=dtype
            ),
            path(f"cloud_{tag}.ply"),
        )
        write_ply(
            TriangleMesh(vertices=v.astype(dtype), faces=f, point_dtype=dtype),
            path(f"mesh_{tag}.ply"),
        )
    # an open mesh with a stray component: repair and the topology report have work to do
    keep = f[np.asarray(v)[f].mean(axis=1)[:, 2] < 0.7]
    far = np.array([[5.0, 5.0, 5.0], [5.1, 5.0, 5.0], [5.0, 5.1, 5.0]])
    write_ply(
        TriangleMesh(
            vertices=np.vstack([v, far]),
            faces=np.vstack([keep, [[len(v), len(v) + 1, len(v) + 2]]]),
        ),
        path("open.ply"),
    )
    # dense enough that Poisson's adaptive tree goes past its complete levels
    pd, nd = _sphere_cloud(20_000, seed=1)
    write_ply(
        PointCloud(
            points=pd.astype(np.float32), normals=nd.astype(np.float32), point_dtype=np.float32
        ),
        path("dense.ply"),
    )
    # an open scan (half of it): coarse leaves hold surface, so Poisson extracts at the leaves' size
    up = pd[:, 2] > 0
    write_ply(PointCloud(points=pd[up], normals=nd[up]), path("half.ply"))
    # ... with integer codes (Poisson's --attributes votes on them)
    codes = {"classification": (pd[up, 0] > 0).astype(np.uint8) + 1}
    write_ply(PointCloud(points=pd[up], normals=nd[up], attributes=codes), path("half_codes.ply"))
    # LAS-like classes and returns: filter's selections and its majority vote per voxel
    cls = np.where(np.arange(len(p)) % 3 == 0, 6, 2).astype(np.uint8)
    las: dict[str, np.ndarray] = {
        "classification": cls,
        "return_number": np.ones(len(p), np.uint8),
        "number_of_returns": np.ones(len(p), np.uint8),
        "intensity": np.arange(len(p), dtype=np.uint16),
    }
    write_ply(PointCloud(points=p, normals=nrm, colors=rgb, attributes=las), path("classified.ply"))
    # Poisson's envelope: a closed sphere around the clouds
    write_ply(TriangleMesh(vertices=1.5 * v, faces=f), path("envelope.ply"))
    # an organized depth image (NaN pixels, a VIEWPOINT): normals from its pixel grid
    hh, ww = 12, 16
    yy, xx = np.mgrid[0:hh, 0:ww].astype(np.float32)
    grid = np.stack([xx * 0.1, yy * 0.1, 2.0 + 0.01 * xx * yy], axis=-1).reshape(-1, 3)
    grid[::7] = np.nan
    with open(path("organized.pcd"), "wb") as fh:
        fh.write(
            b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            + f"WIDTH {ww}\nHEIGHT {hh}\nVIEWPOINT 0.8 0.6 0 1 0 0 0\n".encode()
            + f"POINTS {hh * ww}\nDATA binary\n".encode()
        )
        fh.write(grid.astype("<f4").tobytes())
    # repeated and collinear points: degenerate neighbourhoods borrow their normal
    line = np.column_stack([np.linspace(2, 3, 12), np.zeros(12), np.zeros(12)])
    write_ply(
        PointCloud(points=np.vstack([p, np.repeat(p[:1], 40, axis=0), line])),
        path("degenerate.ply"),
    )
    # three triangles on one edge: repair chooses which two stay together
    fin = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=np.float64)
    write_ply(
        TriangleMesh(vertices=fin, faces=np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])),
        path("fin.ply"),
    )
    # a mixed-polygon mesh (a quad among triangles): the general list reader
    with open(path("mixed.ply"), "wb") as fh:
        fh.write(
            b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n"
            b"property float y\nproperty float z\nelement face 2\n"
            b"property list uchar int vertex_indices\nend_header\n"
        )
        fh.write(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], "<f4").tobytes())
        fh.write(
            bytes([4])
            + np.array([0, 1, 2, 3], "<i4").tobytes()
            + bytes([3])
            + np.array([0, 2, 3], "<i4").tobytes()
        )


@dataclass(frozen=True)
class Files:
    """The inputs :func:`make_inputs` wrote into ``root``, and a phase's own folder.

    What a phase's steps write goes to its own folder (:meth:`out`), so that phases running at
    once never share a file.
    """

    root: str
    own: str

    def __getattr__(self, name: str) -> str:
        leaf = _INPUTS.get(name)
        if leaf is None:
            raise AttributeError(name)
        return os.path.join(self.root, leaf)

    def out(self, name: str = "out.ply") -> str:
        """A path in the phase's own folder."""
        return os.path.join(self.own, name)


# Files' attributes: the input files by short name
_INPUTS = {
    "c32": "cloud_float32.ply",  # points, normals and colours
    "c64": "cloud_float64.ply",
    "bare32": "bare_float32.ply",  # points only
    "bare64": "bare_float64.ply",
    "m32": "mesh_float32.ply",  # a closed sphere
    "m64": "mesh_float64.ply",
    "open": "open.ply",
    "dense": "dense.ply",
    "half": "half.ply",
    "half_codes": "half_codes.ply",  # the open scan with a classification property
    "classified": "classified.ply",  # LAS classes and returns, an intensity
    "envelope": "envelope.ply",  # a closed sphere around the clouds
    "organized": "organized.pcd",  # a depth image: NaN pixels, a VIEWPOINT
    "degenerate": "degenerate.ply",
    "fin": "fin.ply",
    "mixed": "mixed.ply",
}
