"""Adapters to PyMeshLab (reference backend)."""

from __future__ import annotations

from typing import Any

import numpy as np

from recon_cli.backends import record, require
from recon_cli.geometry import PointCloud, TriangleMesh


def meshset(obj: PointCloud | TriangleMesh):
    """A ``pymeshlab.MeshSet`` holding ``obj``."""
    ml = require("pymeshlab")
    kwargs = {}
    if obj.normals is not None:
        kwargs["v_normals_matrix"] = np.asarray(obj.normals, dtype=np.float64)
    if isinstance(obj, TriangleMesh):
        m = ml.Mesh(
            vertex_matrix=np.asarray(obj.vertices, dtype=np.float64),
            face_matrix=np.asarray(obj.faces, dtype=np.int32),
            **kwargs,
        )
    else:
        m = ml.Mesh(vertex_matrix=np.asarray(obj.points, dtype=np.float64), **kwargs)
    ms = ml.MeshSet()
    ms.add_mesh(m)
    return ms


def current_mesh(ms, history: list[str] | None = None) -> TriangleMesh:
    """The current mesh of MeshSet ``ms`` as a :class:`~recon_cli.geometry.TriangleMesh`."""
    m = ms.current_mesh()
    return TriangleMesh(
        vertices=np.asarray(m.vertex_matrix(), dtype=np.float64),
        faces=np.asarray(m.face_matrix(), dtype=np.int64),
        normals=np.asarray(m.vertex_normal_matrix(), dtype=np.float64),
        history=list(history or []),
    )


def estimate_normals(cloud: PointCloud, knn: int = 10, viewpoint=None) -> np.ndarray:
    """PyMeshLab ``compute_normal_for_point_clouds``: (n, 3) normals of ``cloud``."""
    ms = meshset(PointCloud(points=cloud.points))
    kwargs: dict[str, Any] = {"k": knn}
    if viewpoint is not None:
        kwargs["viewpos"] = np.asarray(viewpoint, dtype=np.float64)
    record(
        "pymeshlab.compute_normal_for_point_clouds",
        k=knn,
        viewpos=None if viewpoint is None else [float(x) for x in kwargs["viewpos"]],
    )
    ms.compute_normal_for_point_clouds(**kwargs)
    return np.asarray(ms.current_mesh().vertex_normal_matrix(), dtype=np.float64)


def poisson(
    cloud: PointCloud,
    depth: int = 8,
    scale: float = 1.1,
    samples_per_node: float = 1.5,
    point_weight: float = 4.0,
) -> TriangleMesh:
    """PyMeshLab ``generate_surface_reconstruction_screened_poisson`` of an oriented ``cloud``."""
    ms = meshset(cloud)
    record(
        "pymeshlab.generate_surface_reconstruction_screened_poisson",
        depth=depth,
        scale=scale,
        samplespernode=samples_per_node,
        pointweight=point_weight,
        preclean=False,
    )
    ms.generate_surface_reconstruction_screened_poisson(
        depth=depth,
        scale=scale,
        samplespernode=samples_per_node,
        pointweight=point_weight,
        preclean=False,
    )
    return current_mesh(ms, cloud.history)


def ball_pivoting(
    cloud: PointCloud,
    radius: float | None = None,
    clustering: float = 20.0,
    creasethr: float = 90.0,
) -> TriangleMesh:
    """PyMeshLab ball pivoting; ``radius`` None = its automatic radius."""
    ml = require("pymeshlab")
    ms = meshset(cloud)
    kwargs = {"clustering": clustering, "creasethr": creasethr}
    if radius is not None:
        kwargs["ballradius"] = ml.PureValue(float(radius))
    record(
        "pymeshlab.generate_surface_reconstruction_ball_pivoting",
        ballradius=radius,
        clustering=clustering,
        creasethr=creasethr,
    )
    ms.generate_surface_reconstruction_ball_pivoting(**kwargs)
    return current_mesh(ms, cloud.history)


def topological_measures(mesh: TriangleMesh) -> dict:
    """PyMeshLab ``get_topological_measures`` of ``mesh``."""
    ms = meshset(mesh)
    return dict(ms.get_topological_measures())


def hausdorff(sampled: TriangleMesh, target: TriangleMesh, samples: int) -> dict:
    """PyMeshLab ``get_hausdorff_distance`` from ``sampled`` to ``target``."""
    ml = require("pymeshlab")
    ms = ml.MeshSet()
    for m in (sampled, target):
        ms.add_mesh(
            ml.Mesh(
                vertex_matrix=np.asarray(m.vertices, dtype=np.float64),
                face_matrix=np.asarray(m.faces, dtype=np.int32),
            )
        )
    return dict(
        ms.get_hausdorff_distance(
            sampledmesh=0, targetmesh=1, samplenum=int(samples), samplevert=False, sampleface=True
        )
    )


def hausdorff_points(points: np.ndarray, target: TriangleMesh) -> dict:
    """PyMeshLab ``get_hausdorff_distance`` from every one of ``points`` ((k, 3)) to ``target``.

    The points are passed as a vertex-only mesh and all of them are used (vertex sampling),
    so the result is comparable sample for sample with ours; ``maxdist`` is set beyond
    both bounding boxes so that no sample is discarded.
    """
    ml = require("pymeshlab")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    allpts = np.vstack([pts, np.asarray(target.vertices, dtype=np.float64)])
    reach = float(np.linalg.norm(allpts.max(axis=0) - allpts.min(axis=0))) * 2.0 + 1.0
    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(vertex_matrix=pts))
    ms.add_mesh(
        ml.Mesh(
            vertex_matrix=np.asarray(target.vertices, dtype=np.float64),
            face_matrix=np.asarray(target.faces, dtype=np.int32),
        )
    )
    return dict(
        ms.get_hausdorff_distance(
            sampledmesh=0,
            targetmesh=1,
            samplenum=len(pts),
            samplevert=True,
            sampleface=False,
            maxdist=ml.PureValue(reach),
        )
    )


def repair(mesh: TriangleMesh, fill_holes: int = 0) -> TriangleMesh:
    """PyMeshLab's cleaning chain matching ``recon repair``'s steps.

    Merge duplicate vertices, remove null and duplicate faces and unreferenced vertices, repair
    non-manifold edges (remove faces) and vertices (split), re-orient coherently, optionally close
    holes.
    """
    record(
        "pymeshlab cleaning chain: meshing_remove_duplicate_vertices, _null_faces, "
        "_duplicate_faces, _unreferenced_vertices, "
        "meshing_repair_non_manifold_edges(method='Remove Faces'), _vertices, "
        "meshing_re_orient_faces_coherently, meshing_close_holes",
        maxholesize=int(fill_holes) if fill_holes else None,
    )
    ms = meshset(TriangleMesh(vertices=mesh.vertices, faces=mesh.faces))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_unreferenced_vertices()
    ms.meshing_repair_non_manifold_edges(method="Remove Faces")
    ms.meshing_repair_non_manifold_vertices()
    ms.meshing_re_orient_faces_coherently()
    if fill_holes:
        ms.meshing_close_holes(maxholesize=int(fill_holes))
    return current_mesh(ms, mesh.history)


def ball_pivoting_radii(
    cloud: PointCloud, radii: list[float], clustering: float = 20.0, creasethr: float = 90.0
) -> TriangleMesh:
    """PyMeshLab ball pivoting applied once per radius (increasing), keeping earlier faces."""
    ml = require("pymeshlab")
    ms = meshset(cloud)
    record(
        "pymeshlab.generate_surface_reconstruction_ball_pivoting "
        "(once per radius, deletefaces=False)",
        ballradius=[float(r) for r in radii],
        clustering=clustering,
        creasethr=creasethr,
    )
    for r in radii:
        ms.generate_surface_reconstruction_ball_pivoting(
            ballradius=ml.PureValue(float(r)),
            clustering=clustering,
            creasethr=creasethr,
            deletefaces=False,
        )
    return current_mesh(ms, cloud.history)


def _local(mesh: TriangleMesh):
    """A MeshSet of ``mesh`` about its bounding-box centre, and that centre."""
    from recon_cli.geometry import local_origin

    v = np.asarray(mesh.vertices, dtype=np.float64)
    centre = local_origin(v)
    return meshset(TriangleMesh(v - centre, mesh.faces)), centre


def simplify_quadric(mesh: TriangleMesh, faces: int) -> TriangleMesh:
    """PyMeshLab ``meshing_decimation_quadric_edge_collapse`` to ``faces`` triangles.

    Its topology and normal preservation are on (the guarantees ``recon simplify`` gives).
    """
    ms, centre = _local(mesh)
    kwargs = {"targetfacenum": int(faces), "preservetopology": True, "preservenormal": True}
    record("pymeshlab.meshing_decimation_quadric_edge_collapse", **kwargs)
    ms.meshing_decimation_quadric_edge_collapse(**kwargs)
    out = current_mesh(ms, mesh.history)
    out.vertices = out.vertices + centre
    return out


def smooth_taubin(mesh: TriangleMesh, iterations: int, lam: float, mu: float) -> TriangleMesh:
    """PyMeshLab ``apply_coord_taubin_smoothing`` (about a local origin)."""
    ms, centre = _local(mesh)
    kwargs = {"lambda_": lam, "mu": mu, "stepsmoothnum": int(iterations)}
    record("pymeshlab.apply_coord_taubin_smoothing", **kwargs)
    ms.apply_coord_taubin_smoothing(**kwargs)
    out = current_mesh(ms, mesh.history)
    out.vertices = out.vertices + centre
    return out
