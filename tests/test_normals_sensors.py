"""Normals of real sensor files: camera orientation, organized clouds, raw PCD pipelines.

--orient camera towards the scanner position(s) the file gives (PCD VIEWPOINT, E57 poses with each
point towards its own scan, LAS up), neighbourhoods from an organized cloud's pixels, and a raw
organized PCD through `recon run` normals -> poisson.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from recon_cli.errors import InputError
from recon_cli.geometry import PixelGrid, PointCloud, Sensor
from recon_cli.io.load import load, save
from recon_cli.stages.normals import estimate_normals, orient_normals, run_stage

from sensors import (
    DepthCamera,
    depth_image,
    exact_image,
    look_at,
    tabletop_scene,
    true_normals,
    write_organized_pcd,
)
from shapes import random_rotation

RECON = [sys.executable, "-m", "recon_cli.cli.main"]


def recon(*args):
    """``recon ARGS`` as a process: its completed process (output captured)."""
    return subprocess.run([*RECON, *map(str, args)], capture_output=True, timeout=600)


def _view(rng, offset, w=96, h=72):
    """A camera at a random place around the tabletop (shifted by ``offset``), looking at it."""
    az = rng.uniform(-2.6, -0.5)
    eye = np.array([2.4 * np.cos(az), 2.4 * np.sin(az), rng.uniform(0.7, 1.9)])
    up = random_rotation(rng)[:, 0] * 0.3 + [0, 0, 1]
    rot = look_at(eye, [0, 0.3, 0.2], up)
    return DepthCamera(eye=eye + offset, rotation=rot, width=w, height=h)


def _organized_case(seed, offset=0.0, w=96, h=72):
    """A noisy depth image of the tabletop, its camera and the true normals at its valid pixels."""
    rng = np.random.default_rng(seed)
    off = np.array([offset, 0.5 * offset, -0.25 * offset])
    scene = tabletop_scene()

    def shifted(p):
        return scene(p - off)

    cam = _view(rng, off, w, h)
    org = depth_image(cam, shifted, rng)
    exact = exact_image(cam, shifted).reshape(-1, 3)
    valid = np.isfinite(org.reshape(-1, 3)).all(axis=1)
    truth = true_normals(shifted, exact[valid])
    return org, cam, truth


def _angles(n, truth):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, truth), -1, 1)))


@pytest.mark.parametrize("seed, offset", [(0, 0.0), (1, 1e6), (2, 0.0)])
def test_orient_camera_uses_the_viewpoint_of_an_organized_pcd(seed, offset, tmp_path):
    """An organized PCD's VIEWPOINT orients every normal towards the scanner, near the true normals.

    Neighbourhoods from the pixels (15x15 window), the pixels and sensors carried to the output.
    """
    org, cam, truth = _organized_case(seed, offset)
    path = tmp_path / "raw.pcd"
    write_organized_pcd(path, org, cam, dtype="f8")
    cloud = load(path)
    res = run_stage(cloud, orient="camera")
    nrm = res.output.normals
    facing = np.einsum("ij,ij->i", nrm, cam.eye - cloud.points)
    assert (facing >= 0).all()  # every normal faces the scanner
    ang = _angles(nrm, truth)  # the visible side of the scene faces the camera: same signs
    assert np.median(ang) < 12 and (ang < 90).mean() > 0.97
    assert res.report["viewpoints"] == [cloud.sensors[0].describe()]
    assert res.report["neighbours"].startswith("pixels (15x15 window in 96x72)")
    assert res.output.pixels is not None and res.output.sensors == cloud.sensors


def test_pixel_neighbourhoods_as_accurate_as_the_kdtree():
    """Pixel-window neighbourhoods are as accurate as the kd-tree's, within 2 %.

    A radius or ``neighbours="kdtree"`` uses the kd-tree; pixels asked of an unorganized cloud are
    refused.
    """
    org, _, truth = _organized_case(4, w=160, h=120)
    flat = org.reshape(-1, 3)
    valid = np.isfinite(flat).all(axis=1)
    pts = flat[valid]
    grid = PixelGrid(((120, 160),), np.flatnonzero(valid))
    tree, _, _ = estimate_normals(pts, knn=30)
    pix, _, _ = estimate_normals(pts, knn=30, pixels=grid)
    a_tree = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", tree, truth)), 0, 1)))
    a_pix = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", pix, truth)), 0, 1)))
    # the same k nearest for nearly every point: the same errors to the true normals
    assert abs(a_pix.mean() - a_tree.mean()) < 0.02 * a_tree.mean()
    assert abs(np.median(a_pix) - np.median(a_tree)) < 0.02 * np.median(a_tree)
    assert (np.abs(np.einsum("ij,ij->i", pix, tree)) > 1 - 1e-9).mean() > 0.98
    # a radius, or a cloud without pixels: the kd-tree; pixels asked of an unorganized cloud:
    # refused
    cloud = PointCloud(pts, pixels=grid)
    assert run_stage(cloud, radius=0.05, orient="none").report["neighbours"] == "kdtree"
    assert run_stage(cloud, orient="none", neighbours="kdtree").report["neighbours"] == "kdtree"
    with pytest.raises(InputError, match="needs an organized cloud"):
        run_stage(PointCloud(pts), neighbours="pixels")


def _sphere_scan(eye, n, rng):
    """Points of the unit sphere visible from ``eye``, and their outward normals."""
    d = rng.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    seen = np.einsum("ij,ij->i", d, eye - d) > 0.05
    return d[seen][:n]


@pytest.mark.parametrize("backend", ["native", "open3d"])
def test_e57_scans_each_oriented_towards_their_own_scanner(tmp_path, backend):
    """E57 scans with their poses: each scan's points oriented towards their own scanner."""
    pye57 = pytest.importorskip("pye57")
    if backend == "open3d":
        pytest.importorskip("open3d")
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    eyes = [np.array([0.0, -3.0, 0.5]), np.array([0.2, 3.0, -0.4]), np.array([3.0, 0.1, 0.0])]
    e = pye57.E57(str(tmp_path / "s.e57"), mode="w")
    world = []
    for k, eye in enumerate(eyes):
        p = _sphere_scan(eye, 1500, rng) * 2.0 + [1e5, 2e5, 0]
        rot = Rotation.random(random_state=k)
        trans = eye * 2.0 + [1e5, 2e5, 0]
        local = rot.inv().apply(p - trans).astype(np.float32).astype(np.float64)
        world.append(rot.apply(local) + trans)
        q = rot.as_quat()
        e.write_scan_raw(
            {"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]},
            rotation=np.array([q[3], q[0], q[1], q[2]]),
            translation=trans,
        )
    e.close()
    cloud = load(tmp_path / "s.e57")
    res = run_stage(cloud, knn=15, orient="camera", backend=backend)
    nrm, scan = res.output.normals, cloud.attributes["scan"]
    centre = np.array([1e5, 2e5, 0])
    outward = (cloud.points - centre) / np.linalg.norm(cloud.points - centre, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", nrm, outward) > 0.9).all()  # each visible side faces out
    for k, eye in enumerate(eyes):
        mine = scan == k
        towards = eye * 2.0 + centre - cloud.points[mine]
        assert (np.einsum("ij,ij->i", nrm[mine], towards) > 0).all()
    assert len(res.report["viewpoints"]) == 3 and res.report["viewpoints"][1].endswith(
        f": {int((scan == 1).sum())} points"
    )
    # one sensor for the whole cloud would turn the far scans' normals inward
    wrong, _ = orient_normals(cloud.points, nrm, "camera", sensors=cloud.sensors[:1], scan=None)
    assert (np.einsum("ij,ij->i", wrong, outward) < 0).mean() > 0.3
    with pytest.raises(InputError, match="no per-point attribute 'scan'"):
        orient_normals(cloud.points, nrm, "camera", sensors=cloud.sensors)
    with pytest.raises(InputError, match=r"integer 0\.\.2"):
        orient_normals(cloud.points, nrm, "camera", sensors=cloud.sensors, scan=scan + 1)


def test_las_up_orients_terrain_upwards(tmp_path):
    """A LAS terrain tile with ``--orient camera``: normals oriented up (airborne)."""
    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 300, (4000, 2))
    z = 20 * np.sin(xy[:, 0] / 40) + 10 * np.cos(xy[:, 1] / 25)
    pts = np.column_stack([xy + [6e5, 4.9e6], z]).round(2)
    save(PointCloud(pts, point_dtype=np.float64), tmp_path / "tile.laz")
    r = recon("normals", tmp_path / "tile.laz", tmp_path / "n.ply", "--orient", "camera", "--json")
    rep = json.loads(r.stdout)
    assert r.returncode == 0 and rep["viewpoints"] == ["LAS up (airborne) towards (0, 0, 1)"]
    assert (load(tmp_path / "n.ply").normals[:, 2] > 0.5).all()


def test_no_scanner_position_is_a_one_line_error_naming_the_file(tmp_path):
    """No scanner position: a one-line error naming the file, exit 2, no output.

    Two scanner positions without a per-point scan index are refused too.
    """
    save(PointCloud(np.random.default_rng(0).random((200, 3))), tmp_path / "plain.ply")
    r = recon("normals", tmp_path / "plain.ply", tmp_path / "o.ply", "--orient", "camera")
    err = r.stderr.decode().strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1
    assert err.startswith(f"recon: error: {tmp_path / 'plain.ply'}: --orient camera needs --camera")
    assert not (tmp_path / "o.ply").exists()
    two = PointCloud(
        np.random.default_rng(1).random((20, 3)),
        sensors=[Sensor(position=(0, 0, 5)), Sensor(position=(0, 0, -5))],
    )
    with pytest.raises(InputError, match="gives 2 scanner positions but no per-point"):
        run_stage(two, orient="camera")


def test_raw_organized_pcd_through_recon_run_normals_camera_poisson(tmp_path):
    """A raw organized PCD through ``recon run`` normals then poisson: a surface on the points.

    The NaN pixels dropped and counted; the mesh within 5 mm (median) of the points, facing the
    camera.
    """
    from recon_cli.mesh.distance import closest_points

    org, cam, _ = _organized_case(5, offset=0.0, w=160, h=120)
    write_organized_pcd(tmp_path / "raw.pcd", org, cam)
    pipe = tmp_path / "p.toml"
    pipe.write_text(
        '[[stage]]\nname = "normals"\norient = "camera"\n\n[[stage]]\nname = "poisson"\ndepth = 8\n'
    )
    r = recon("run", pipe, tmp_path / "raw.pcd", tmp_path / "mesh.ply", "--json")
    assert r.returncode == 0, r.stderr.decode()
    rep = json.loads(r.stdout)
    nan = int((~np.isfinite(org).all(axis=2)).sum())
    assert rep["read"]["invalid_dropped"] == nan and rep["read"]["organized"] == "160x120"
    assert rep["stages"][0]["viewpoints"][0].startswith("PCD VIEWPOINT at (")
    mesh = load(tmp_path / "mesh.ply")
    pts = load(tmp_path / "raw.pcd").points.astype(np.float64)
    dist, face, _ = closest_points(mesh.vertices, mesh.faces, pts)
    assert np.median(dist) < 0.005 and np.percentile(dist, 90) < 0.02  # metres
    # the surface faces the camera where the points are: the camera's side is outside
    v = mesh.vertices[mesh.faces[face]]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    assert (np.einsum("ij,ij->i", fn, cam.eye - pts) > 0).mean() > 0.95
