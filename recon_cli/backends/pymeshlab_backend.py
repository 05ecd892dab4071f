"""Adapters to PyMeshLab (reference backend)."""

from __future__ import annotations

import numpy as np

from recon_cli.backends import require
from recon_cli.geometry import PointCloud, TriangleMesh


def meshset(obj: PointCloud | TriangleMesh):
    """A ``pymeshlab.MeshSet`` holding ``obj``."""
    ml = require("pymeshlab")
    kwargs = {}
    if obj.normals is not None:
        kwargs["v_normals_matrix"] = np.asarray(obj.normals, dtype=np.float64)
    if isinstance(obj, TriangleMesh):
        m = ml.Mesh(vertex_matrix=np.asarray(obj.vertices, dtype=np.float64), face_matrix=np.asarray(obj.faces, dtype=np.int32), **kwargs)
    else:
        m = ml.Mesh(vertex_matrix=np.asarray(obj.points, dtype=np.float64), **kwargs)
    ms = ml.MeshSet()
    ms.add_mesh(m)
    return ms


def current_mesh(ms, history: list[str] | None = None) -> TriangleMesh:
    m = ms.current_mesh()
    return TriangleMesh(
        vertices=np.asarray(m.vertex_matrix(), dtype=np.float64),
        faces=np.asarray(m.face_matrix(), dtype=np.int64),
        normals=np.asarray(m.vertex_normal_matrix(), dtype=np.float64),
        history=list(history or []),
    )


def estimate_normals(cloud: PointCloud, knn: int = 10, viewpoint=None) -> np.ndarray:
    ms = meshset(PointCloud(points=cloud.points))
    kwargs = {"k": knn}
    if viewpoint is not None:
        kwargs["viewpos"] = np.asarray(viewpoint, dtype=np.float64)
    ms.compute_normal_for_point_clouds(**kwargs)
    return np.asarray(ms.current_mesh().vertex_normal_matrix(), dtype=np.float64)


def poisson(cloud: PointCloud, depth: int = 8, scale: float = 1.1, samples_per_node: float = 1.5, point_weight: float = 4.0) -> TriangleMesh:
    ms = meshset(cloud)
    ms.generate_surface_reconstruction_screened_poisson(
        depth=depth, scale=scale, samplespernode=samples_per_node, pointweight=point_weight, preclean=False
    )
    return current_mesh(ms, cloud.history)


def ball_pivoting(cloud: PointCloud, radius: float | None = None, clustering: float = 20.0, creasethr: float = 90.0) -> TriangleMesh:
    """PyMeshLab ball pivoting; ``radius`` None = its automatic radius."""
    ml = require("pymeshlab")
    ms = meshset(cloud)
    kwargs = {"clustering": clustering, "creasethr": creasethr}
    if radius is not None:
        kwargs["ballradius"] = ml.PureValue(float(radius))
    ms.generate_surface_reconstruction_ball_pivoting(**kwargs)
    return current_mesh(ms, cloud.history)


def topological_measures(mesh: TriangleMesh) -> dict:
    ms = meshset(mesh)
    return dict(ms.get_topological_measures())


def hausdorff(sampled: TriangleMesh, target: TriangleMesh, samples: int) -> dict:
    """PyMeshLab ``get_hausdorff_distance`` from ``sampled`` to ``target``."""
    ml = require("pymeshlab")
    ms = ml.MeshSet()
    for m in (sampled, target):
        ms.add_mesh(ml.Mesh(vertex_matrix=np.asarray(m.vertices, dtype=np.float64), face_matrix=np.asarray(m.faces, dtype=np.int32)))
    return dict(ms.get_hausdorff_distance(sampledmesh=0, targetmesh=1, samplenum=int(samples), samplevert=False, sampleface=True))
