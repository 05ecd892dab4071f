"""Adapters to Open3D (reference backend). Conversions copy arrays; nothing is shared."""

from __future__ import annotations

import numpy as np

from recon_cli.backends import interop, record, require
from recon_cli.geometry import PointCloud, TriangleMesh


def to_o3d_cloud(cloud: PointCloud):
    """``cloud`` as an Open3D legacy point cloud (points, normals, RGB colours)."""
    return cloud.to_open3d()


def to_o3d_mesh(mesh: TriangleMesh):
    """``mesh`` as an Open3D legacy triangle mesh (vertices, triangles, vertex normals)."""
    return TriangleMesh(vertices=mesh.vertices, faces=mesh.faces, normals=mesh.normals).to_open3d()


def from_o3d_mesh(m, history: list[str] | None = None) -> TriangleMesh:
    """An Open3D triangle mesh as recon's, with ``history``."""
    a = interop.from_open3d(m)
    return TriangleMesh(
        vertices=a["points"],
        faces=a["faces"],
        normals=a["normals"],
        colors=a["colors"],
        history=list(history or []),
    )


def from_o3d_cloud(pc, history: list[str] | None = None) -> PointCloud:
    """An Open3D point cloud as recon's, with ``history``."""
    a = interop.from_open3d(pc)
    return PointCloud(
        points=a["points"], normals=a["normals"], colors=a["colors"], history=list(history or [])
    )


def estimate_normals(
    cloud: PointCloud,
    knn: int = 30,
    radius: float | None = None,
    orient_tangent_plane: int | None = None,
):
    """Open3D ``estimate_normals`` (+ ``orient_normals_consistent_tangent_plane(k)`` if given)."""
    o3d = require("open3d")
    pc = to_o3d_cloud(PointCloud(points=cloud.points))
    if radius is not None and knn:
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=knn)
    elif radius is not None:
        param = o3d.geometry.KDTreeSearchParamRadius(radius=radius)
    else:
        param = o3d.geometry.KDTreeSearchParamKNN(knn=knn)
    record(
        "open3d.geometry.PointCloud.estimate_normals",
        knn=knn,
        radius=radius,
        orient_normals_consistent_tangent_plane=orient_tangent_plane,
    )
    pc.estimate_normals(param)
    if orient_tangent_plane:
        pc.orient_normals_consistent_tangent_plane(orient_tangent_plane)
    return np.asarray(pc.normals, dtype=np.float64)


def poisson(
    cloud: PointCloud,
    depth: int = 8,
    scale: float = 1.1,
    linear_fit: bool = False,
    threads: int = 1,
):
    """Open3D screened Poisson; returns (mesh, densities).

    ``threads`` defaults to 1: Open3D 0.20's multi-threaded Poisson crashes the process now
    and then (a race, isl-org/Open3D#6828, #7229; seen here in the test suite), and a
    reference backend must not take the user's process down. ``-1`` (Open3D's default, all
    cores) is what ``make bench`` times, in a child process.
    """
    o3d = require("open3d")
    pc = to_o3d_cloud(cloud)
    record(
        "open3d.geometry.TriangleMesh.create_from_point_cloud_poisson",
        depth=depth,
        scale=scale,
        linear_fit=linear_fit,
        n_threads=threads,
    )
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pc, depth=depth, scale=scale, linear_fit=linear_fit, n_threads=threads
    )
    return from_o3d_mesh(mesh, cloud.history), np.asarray(dens, dtype=np.float64)


def ball_pivoting(cloud: PointCloud, radii: list[float]) -> TriangleMesh:
    """Open3D ``create_from_point_cloud_ball_pivoting`` with the ball ``radii``."""
    o3d = require("open3d")
    pc = to_o3d_cloud(cloud)
    record(
        "open3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting",
        radii=[float(r) for r in radii],
    )
    mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
        pc, o3d.utility.DoubleVector(list(radii))
    )
    return from_o3d_mesh(mesh, cloud.history)


def signed_distance(mesh: TriangleMesh, query: np.ndarray) -> np.ndarray:
    """Open3D ``RaycastingScene.compute_signed_distance`` at ``query`` ((k, 3))."""
    o3d = require("open3d")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    d = scene.compute_signed_distance(o3d.core.Tensor(np.asarray(query, dtype=np.float32)))
    return d.numpy().astype(np.float64)


def unsigned_distance(mesh: TriangleMesh, query: np.ndarray) -> np.ndarray:
    """Open3D ``RaycastingScene.compute_distance`` at ``query`` ((k, 3))."""
    o3d = require("open3d")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    return (
        scene.compute_distance(o3d.core.Tensor(np.asarray(query, dtype=np.float32)))
        .numpy()
        .astype(np.float64)
    )


def manifold_checks(mesh: TriangleMesh, self_intersection: bool = True) -> dict:
    """Open3D's topology predicates on ``mesh``.

    ``self_intersection=False`` skips Open3D's quadratic self-intersection test inside
    ``is_watertight`` (minutes on 50k faces): "watertight" is then edge-manifold without
    boundary and vertex-manifold, Open3D's definition minus that test.
    """
    m = to_o3d_mesh(mesh)
    if self_intersection:
        watertight = m.is_watertight()
    else:
        watertight = m.is_edge_manifold(allow_boundary_edges=False) and m.is_vertex_manifold()
    return {
        "edge_manifold": bool(m.is_edge_manifold(allow_boundary_edges=True)),
        "vertex_manifold": bool(m.is_vertex_manifold()),
        "watertight": bool(watertight),
        "orientable": bool(m.is_orientable()),
        "non_manifold_edges": int(
            len(np.asarray(m.get_non_manifold_edges(allow_boundary_edges=True)))
        ),
        "non_manifold_vertices": int(len(np.asarray(m.get_non_manifold_vertices()))),
    }


def statistical_outlier_indices(points: np.ndarray, k: int, std_ratio: float) -> np.ndarray:
    """Open3D ``remove_statistical_outlier(k, std_ratio)``: the kept indices (int64, ascending)."""
    require("open3d")
    pc = to_o3d_cloud(PointCloud(points=points))
    record(
        "open3d.geometry.PointCloud.remove_statistical_outlier",
        nb_neighbors=int(k),
        std_ratio=float(std_ratio),
    )
    _, kept = pc.remove_statistical_outlier(int(k), float(std_ratio))
    return np.asarray(kept, dtype=np.int64)


def radius_outlier_indices(points: np.ndarray, radius: float, nb_points: int) -> np.ndarray:
    """Open3D ``remove_radius_outlier(nb_points, radius)``: the kept indices (int64, ascending)."""
    require("open3d")
    pc = to_o3d_cloud(PointCloud(points=points))
    record(
        "open3d.geometry.PointCloud.remove_radius_outlier",
        nb_points=int(nb_points),
        radius=float(radius),
    )
    _, kept = pc.remove_radius_outlier(int(nb_points), float(radius))
    return np.asarray(kept, dtype=np.int64)


def voxel_down_sample(cloud: PointCloud, voxel_size: float) -> dict:
    """Open3D ``voxel_down_sample``: its points, normals and colours as float64 arrays.

    Normals are averaged, not normalised; colours are floats in [0, 1], averaged; an absent
    attribute is None. The cells come in Open3D's order.
    """
    require("open3d")
    pc = to_o3d_cloud(cloud)
    record("open3d.geometry.PointCloud.voxel_down_sample", voxel_size=float(voxel_size))
    out = pc.voxel_down_sample(float(voxel_size))
    return {
        "points": np.asarray(out.points, dtype=np.float64),
        "normals": np.asarray(out.normals, dtype=np.float64) if out.has_normals() else None,
        "colors": np.asarray(out.colors, dtype=np.float64) if out.has_colors() else None,
    }


def crop_indices(points: np.ndarray, box) -> np.ndarray:
    """Indices of ``points`` inside the axis-aligned box ``x0,y0,z0,x1,y1,z1``, ascending.

    Open3D's ``AxisAlignedBoundingBox.get_point_indices_within_bounding_box``.
    """
    o3d = require("open3d")
    b = [float(x) for x in box]
    aabb = o3d.geometry.AxisAlignedBoundingBox(b[:3], b[3:])
    record("open3d.geometry.AxisAlignedBoundingBox.get_point_indices_within_bounding_box", box=b)
    kept = aabb.get_point_indices_within_bounding_box(
        o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    )
    return np.sort(np.asarray(kept, dtype=np.int64))


def _local(mesh: TriangleMesh):
    """``mesh`` about its bounding-box centre as an Open3D mesh, and that centre."""
    from recon_cli.geometry import local_origin

    v = np.asarray(mesh.vertices, dtype=np.float64)
    centre = local_origin(v)
    return to_o3d_mesh(TriangleMesh(v - centre, mesh.faces)), centre


def simplify_quadric(mesh: TriangleMesh, faces: int) -> TriangleMesh:
    """Open3D ``simplify_quadric_decimation`` to ``faces`` triangles (about a local origin)."""
    m, centre = _local(mesh)
    record("open3d.geometry.TriangleMesh.simplify_quadric_decimation", target=int(faces))
    out = from_o3d_mesh(m.simplify_quadric_decimation(int(faces)), mesh.history)
    out.vertices = out.vertices + centre
    return out


def smooth_taubin(mesh: TriangleMesh, iterations: int, lam: float, mu: float) -> TriangleMesh:
    """Open3D ``filter_smooth_taubin`` (about a local origin)."""
    m, centre = _local(mesh)
    record(
        "open3d.geometry.TriangleMesh.filter_smooth_taubin",
        number_of_iterations=int(iterations),
        lambda_filter=lam,
        mu=mu,
    )
    out = from_o3d_mesh(
        m.filter_smooth_taubin(number_of_iterations=int(iterations), lambda_filter=lam, mu=mu),
        mesh.history,
    )
    out.vertices = out.vertices + centre
    return out
