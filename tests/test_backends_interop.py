"""Conversions to and from Open3D and trimesh: ``to_open3d()``, ``to_trimesh()``, ``geometry_from``.

Round trips keep double precision, colours, normals and attributes.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.backends.interop import library_of
from recon_cli.errors import InputError
from recon_cli.geometry import PointCloud, TriangleMesh, geometry_from

from shapes import cloud_family, mesh_family

SEEDS = st.integers(min_value=0, max_value=2**31 - 1)


def _same_cloud(a: PointCloud, b: PointCloud, attributes: bool = True) -> None:
    assert b.points.dtype == np.float64 and np.array_equal(a.points, b.points)
    assert np.array_equal(a.normals, b.normals) and np.array_equal(a.colors, b.colors)
    assert b.colors.dtype == np.uint8 and b.colors.shape == a.colors.shape
    if attributes:
        assert set(b.attributes) == set(a.attributes)
        for k, v in a.attributes.items():
            assert b.attributes[k].dtype == v.dtype and np.array_equal(b.attributes[k], v), k


@settings(max_examples=15, deadline=None)
@given(SEEDS)
def test_cloud_round_trips(seed):
    """Clouds through trimesh and Open3D come back exactly; legacy Open3D drops the attributes."""
    # clouds at offsets up to 1e6 and scales 1e-2 .. 1e3: every digit of the coordinates back
    c = cloud_family(seed)
    _same_cloud(c, geometry_from(c.to_trimesh()))
    _same_cloud(c, geometry_from(c.to_open3d(tensor=True)))
    # legacy Open3D holds points, normals and RGB (as floats in [0, 1]): those come back exactly
    legacy = c.to_open3d()
    assert isinstance(legacy, o3d.geometry.PointCloud) and not hasattr(legacy, "point")
    back = geometry_from(legacy)
    _same_cloud(c, back, attributes=False)
    assert back.attributes == {}


@settings(max_examples=15, deadline=None)
@given(SEEDS)
def test_mesh_round_trips(seed):
    """Meshes through trimesh and both Open3Ds keep vertices, faces, normals, colours and data."""
    m = mesh_family(seed)
    m.attributes["quality"] = np.arange(len(m.vertices), dtype=np.float32)
    m.face_attributes["label"] = np.arange(len(m.faces), dtype=np.int32) % 7
    for obj in (m.to_trimesh(), m.to_open3d(tensor=True), m.to_open3d()):
        back = geometry_from(obj)
        assert isinstance(back, TriangleMesh)
        assert back.vertices.dtype == np.float64 and np.array_equal(back.vertices, m.vertices)
        assert np.array_equal(back.faces, m.faces)
        if m.normals is None:
            assert back.normals is None and back.colors is None
        else:
            assert np.array_equal(back.normals, m.normals)
            assert np.array_equal(back.colors, m.colors) and back.colors.dtype == np.uint8
        if not isinstance(obj, o3d.geometry.TriangleMesh):  # legacy Open3D has no attributes
            assert np.array_equal(back.attributes["quality"], m.attributes["quality"])
            assert np.array_equal(back.face_attributes["label"], m.face_attributes["label"])


def test_trimesh_mesh_keeps_its_vertex_order_and_given_normals_only():
    """A trimesh copy keeps duplicate vertices in order; only normals that were given come back."""
    rng = np.random.default_rng(3)
    v = rng.normal(size=(6, 3)) + 1e6
    v[5] = v[0]  # a duplicate vertex: trimesh's processing would merge it
    f = np.array([[0, 1, 2], [2, 3, 4], [5, 1, 3]])
    tm = TriangleMesh(vertices=v, faces=f).to_trimesh()
    assert np.array_equal(tm.vertices, v) and np.array_equal(tm.faces, f)
    back = geometry_from(tm)
    assert back.normals is None  # trimesh computes normals on request; none were given
    given_normals = trimesh.Trimesh(v, f, vertex_normals=np.tile([0.0, 0.0, 1.0], (6, 1)))
    assert np.array_equal(
        geometry_from(given_normals).normals[:, 2], np.ones(len(given_normals.vertices))
    )


def test_rgba_keeps_alpha_and_opaque_alpha_reads_as_rgb():
    """RGBA colours keep their alpha through trimesh and Open3D; RGB colours stay three channels."""
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(20, 3))
    rgba = rng.integers(0, 256, (20, 4)).astype(np.uint8)
    rgba[0, 3] = 7
    c = PointCloud(points=pts, colors=rgba)
    assert np.array_equal(geometry_from(c.to_trimesh()).colors, rgba)
    assert np.array_equal(geometry_from(c.to_open3d(tensor=True)).colors, rgba)
    rgb = PointCloud(points=pts, colors=rgba[:, :3])
    assert geometry_from(rgb.to_trimesh()).colors.shape == (20, 3)


def test_other_library_objects_are_refused_in_one_line():
    """A LineSet, a trimesh Scene or a dict is refused with one line naming what it is."""
    assert library_of(np.zeros(3)) is None and library_of(trimesh.Trimesh()) == "trimesh"
    with pytest.raises(InputError, match="Open3D LineSet is not a point cloud or a triangle mesh"):
        geometry_from(o3d.geometry.LineSet())
    with pytest.raises(InputError, match="trimesh Scene is not"):
        geometry_from(trimesh.Scene())
    with pytest.raises(InputError, match="got dict"):
        geometry_from({})
