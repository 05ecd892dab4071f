"""``recon simplify``: quadric edge collapse, exact and as accurate as Open3D and PyMeshLab.

Keeps manifolds manifold, faces unflipped, boundaries in place and every attribute; exact on planar
and polyhedral shapes; as accurate as Open3D's and PyMeshLab's quadric decimation.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.backends import open3d_backend, pymeshlab_backend
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import PointCloud, TriangleMesh, bbox_diagonal
from recon_cli.io import read_ply, write_ply
from recon_cli.mesh.distance import closest_points
from recon_cli.mesh.sampling import face_normals, sample_surface
from recon_cli.mesh.topology import Connectivity, report
from recon_cli.stages import apply_stage
from recon_cli.stages.simplify import Decimator, simplify

import mesh_damage as D
import shapes as S
from shared_data import load_shared


# ---- generated families ------------------------------------------------------------------------
def terrain(n: int = 40, amplitude: float = 0.2):
    """An open height field over a square (one boundary loop), n x n vertices."""
    x = np.linspace(-1.0, 1.0, n)
    X, Y = np.meshgrid(x, x, indexing="ij")
    Z = amplitude * np.sin(3 * X) * np.cos(2 * Y)
    v = np.stack([X, Y, Z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
    f = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return v, f


def subdivided_cube(k: int = 8):
    """The unit cube, each side a k x k grid of split squares (closed, outward)."""
    v, f = S.box_mesh((0, 0, 0), (1, 1, 1))
    for _ in range(int(np.log2(k))):
        v, f = S._midpoint_split(v, f)
    return v, f


def compact(v, f):
    """The vertices ``f`` uses and ``f`` renumbered to them."""
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


KINDS = ("sphere", "torus", "dumbbell", "sheet", "cut", "terrain")


def family(seed: int) -> tuple[str, TriangleMesh]:
    """A closed or open mesh under a random rotation, scale 1e-3..1e3 and offset up to 1e6.

    Sphere, torus, thin rod, thin sheet, cut sphere or terrain.
    """
    rng = np.random.default_rng(seed)
    kind = KINDS[seed % len(KINDS)]
    if kind == "sphere":
        v, f = S.icosphere(4)
    elif kind == "torus":
        v, f = S.torus(nu=48, nv=24)
    elif kind == "dumbbell":
        v, f = S.implicit_mesh(S.dumbbell_fn, 48)
    elif kind == "sheet":
        v, f = S.implicit_mesh(S.bent_sheet_fn, 48)
    elif kind == "cut":
        _, cand, *_ = S.cut_sphere(rng, 4)
        v, f = compact(cand.vertices, cand.faces)
    else:
        v, f = terrain()
    scale = 10.0 ** rng.uniform(-3, 3)
    offset = rng.uniform(-1, 1, 3) * 10.0 ** rng.integers(0, 7)
    v = (v - v.mean(0)) @ S.random_rotation(rng).T * scale + offset
    return kind, TriangleMesh(vertices=v, faces=f)


def boundary_segments(m: TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """The end points of the boundary edges of ``m``: two (n, 3) arrays."""
    c = Connectivity(m.faces, len(m.vertices))
    e = c.edges[c.boundary_edges]
    return m.vertices[e[:, 0]], m.vertices[e[:, 1]]


def to_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of each point of ``p`` to the nearest segment ``a[i]-b[i]``."""
    d = b - a
    L = np.einsum("ij,ij->i", d, d)
    t = ((p[:, None, :] - a[None]) * d[None]).sum(-1) / np.where(L > 0, L, 1.0)[None]
    q = a[None] + np.clip(t, 0.0, 1.0)[..., None] * d[None]
    return np.linalg.norm(p[:, None] - q, axis=-1).min(axis=1)


def boundary_hausdorff(a: TriangleMesh, b: TriangleMesh) -> float:
    """Hausdorff distance between the boundary edges of ``a`` and ``b``, over ``a``'s diagonal.

    Measured from their end points to the other's segments.
    """
    a0, a1 = boundary_segments(a)
    b0, b1 = boundary_segments(b)
    d = max(to_segments(b0, a0, a1).max(), to_segments(a0, b0, b1).max())
    return float(d) / bbox_diagonal(a.vertices)


def chamfer(a: TriangleMesh, b: TriangleMesh, n: int = 20_000) -> tuple[float, float]:
    """Exact point-to-triangle Chamfer and Hausdorff of samples, over ``a``'s diagonal.

    Chamfer: the mean of both directions.
    """
    diag = bbox_diagonal(a.vertices)
    pa = sample_surface(a, n, seed=1).points
    pb = sample_surface(b, n, seed=2).points
    d1 = closest_points(b.vertices, b.faces, pa)[0]
    d2 = closest_points(a.vertices, a.faces, pb)[0]
    return 0.5 * float(d1.mean() + d2.mean()) / diag, float(max(d1.max(), d2.max())) / diag


def normal_agreement(inp: TriangleMesh, out: TriangleMesh) -> np.ndarray:
    """Cosine between each output face's normal and that of the input face nearest its centroid."""
    _, fi, _ = closest_points(inp.vertices, inp.faces, out.vertices[out.faces].mean(axis=1))
    n_in, _ = face_normals(inp.vertices, inp.faces)
    n_out, _ = face_normals(out.vertices, out.faces)
    return np.einsum("ij,ij->i", n_out, n_in[fi])


def assert_same_topology(inp: TriangleMesh, out: TriangleMesh) -> dict:
    """Assert ``out`` is manifold, oriented, clean and of ``inp``'s topology; its report."""
    r0, r = report(inp), report(out)
    for k in ("edge_manifold", "vertex_manifold", "consistently_oriented"):
        assert r[k] is True, k
    for k in ("watertight", "genus", "boundary_loops", "components", "euler"):
        if k in r0:
            assert r[k] == r0[k], (k, r0[k], r[k])
    assert r["degenerate_faces"] == r["duplicate_faces"] == 0
    return r


@pytest.mark.parametrize("seed", range(12))
def test_family_keeps_topology_orientation_boundary_and_reaches_the_target(seed):
    """Random family meshes reach the target with the same topology, no face turned over."""
    kind, m = family(seed)
    target = max(4, int(len(m.faces) * (0.1, 0.3, 0.05)[seed % 3]))
    out, rep = simplify(m, faces=target)
    closed = kind not in ("cut", "terrain")
    if closed and target % 2:
        assert rep["faces_out"] == target + 1 and "even number of faces" in rep["stopped"]
    else:
        assert rep["faces_out"] == target and rep["stopped"] is None
    assert len(out.faces) == rep["faces_out"] and len(out.vertices) == rep["vertices_out"]
    assert_same_topology(m, out)
    # no face turned over: each agrees with the input surface under it
    assert normal_agreement(m, out).min() > 0.3
    cd, hd = chamfer(m, out)
    assert cd < 3e-3 and hd < 2e-2, (cd, hd)
    if not closed:
        assert boundary_hausdorff(m, out) < 2e-3


@pytest.mark.parametrize("seed", [0, 1])
def test_cube_and_square_are_simplified_exactly(seed):
    """A split cube ends as its 8 corners and 12 faces; a flat square as 4 faces, in place.

    Randomly rotated, scaled and offset up to 1e6: the corners within a few ulps of the offset; the
    square keeps its plane, its straight sides and its 4 corners.
    """
    rng = np.random.default_rng(seed)
    R = S.random_rotation(rng)
    offset = rng.uniform(-1, 1, 3) * 1e6
    scale = 10.0 ** rng.uniform(-3, 3)
    # a finely split cube ends as its 8 corners and 12 faces, exactly
    v, f = subdivided_cube(8)
    corners, _ = S.box_mesh((0, 0, 0), (1, 1, 1))
    out, rep = simplify(TriangleMesh((v - 0.5) @ R.T * scale + offset, f), faces=12)
    assert rep["faces_out"] == 12 and len(out.vertices) == 8
    want = (corners - 0.5) @ R.T * scale + offset
    d = np.linalg.norm(out.vertices[:, None] - want[None], axis=-1).min(axis=1)
    ulp = np.spacing(np.abs(offset).max())  # what a coordinate near the offset can hold
    assert d.max() < 1e-9 * scale + 4 * ulp
    assert_same_topology(TriangleMesh(v, f), out)
    # a flat open square keeps its plane, its straight sides and its 4 corners
    v, f = terrain(20, amplitude=0.0)
    m = TriangleMesh(v @ R.T * scale + offset, f)
    out, rep = simplify(m, faces=4)
    assert rep["faces_out"] == 4
    local = (out.vertices - offset) @ R / scale
    eps = 1e-9 + 4 * ulp / scale
    assert np.abs(local[:, 2]).max() < eps
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    d = np.linalg.norm(local[:, None, :2] - square[None], axis=-1).min(axis=0)
    assert d.max() < eps
    assert boundary_hausdorff(m, out) < eps


def test_unmoved_vertices_keep_their_exact_coordinates():
    """Vertices no collapse moved keep their exact input coordinates."""
    _, m = family(5)  # terrain far from the origin
    d = Decimator(m.vertices, m.faces, 1000.0)
    d.run(len(m.faces) // 2, len(m.faces) // 2)
    from recon_cli.stages.simplify import _output

    out = _output(m, d)
    r = d.result()
    kept = np.flatnonzero(r["valive"])
    still = ~r["moved"][kept]
    assert still.sum() > 50 and r["moved"][kept].sum() > 50
    assert np.array_equal(out.vertices[still], m.vertices[kept[still]])


def test_ratio_one_returns_the_input():
    """Ratio 1 returns the input unchanged, no collapse made."""
    _, m = family(1)
    out, rep = simplify(m, ratio=1.0)
    assert rep["collapses"] == 0 and rep["stopped"] is None
    assert np.array_equal(out.vertices, m.vertices) and np.array_equal(out.faces, m.faces)


def test_minimum_and_parity():
    """A closed mesh goes down to a tetrahedron, stopping at even counts; an open one hits odd."""
    v, f = S.icosphere(2)
    m = TriangleMesh(v, f)
    out, rep = simplify(m, faces=4)  # the smallest closed surface: a tetrahedron
    assert rep["faces_out"] == 4 and len(out.vertices) == 4
    assert_same_topology(m, out)
    out, rep = simplify(m, faces=101)
    assert rep["faces_out"] == 102 and "even number of faces" in rep["stopped"]
    # an open mesh reaches odd counts (a boundary collapse removes one face)
    v, f = terrain(12)
    out, rep = simplify(TriangleMesh(v, f), faces=101)
    assert rep["faces_out"] == 101 and rep["stopped"] is None


def test_topology_stops_it_early_and_says_why():
    """A torus stops above 14 faces to keep its genus, and the report says why."""
    # a torus cannot go below 7 vertices (14 faces) without changing its genus
    v, f = S.torus(nu=12, nv=8)
    m = TriangleMesh(v, f)
    out, rep = simplify(m, faces=4)
    assert rep["faces_out"] > 4 and rep["stopped"].startswith(f"stopped at {rep['faces_out']}")
    assert "manifold" in rep["stopped"]
    r = assert_same_topology(m, out)
    assert r["genus"] == 1 and rep["faces_out"] >= 14


def test_non_manifold_parts_are_locked_and_the_rest_simplified():
    """Fins and a pinched vertex are locked; the rest is simplified, their topology kept."""
    rng = np.random.default_rng(3)
    v, f = S.icosphere(4)
    m = D.glue_fins(TriangleMesh(v, f), rng, 5)
    cones = D.two_cones(24)
    both = TriangleMesh(
        np.vstack([m.vertices, cones.vertices + 5.0]),
        np.vstack([m.faces, cones.faces + len(m.vertices)]),
    )
    r0 = report(both)
    assert r0["non_manifold_edges"] > 0 and r0["non_manifold_vertices"] > 0
    out, rep = simplify(both, ratio=0.2)
    # the fins are locked: no free boundary, so collapses keep the parity of the count
    target = round(0.2 * len(both.faces))
    odd = (len(both.faces) - target) % 2
    assert rep["faces_out"] == target + odd and rep["locked_vertices"] > 0
    assert (rep["stopped"] is None) == (odd == 0)
    assert rep["non_manifold_edges"] == r0["non_manifold_edges"]
    r = report(out)
    assert r["non_manifold_edges"] == r0["non_manifold_edges"]
    assert r["non_manifold_vertices"] == r0["non_manifold_vertices"]
    assert r["components"] == r0["components"]


def test_attributes_follow_the_collapses_with_their_types():
    """Colours, attributes and face attributes follow the collapses, in their types."""
    rng = np.random.default_rng(7)
    v, f = S.torus(nu=40, nv=20)
    v = v @ S.random_rotation(rng).T + 1e6
    x = v[:, 0] - v[:, 0].min()
    ramp = x / x.max()
    colors = np.stack(
        [np.rint(255 * ramp), np.full(len(v), 7), 255 - np.rint(255 * ramp), np.full(len(v), 200)],
        axis=1,
    ).astype(np.uint8)
    cls = np.where(ramp > 0.5, 6, 2).astype(np.uint8)
    m = TriangleMesh(
        vertices=v.astype(np.float32),
        faces=f,
        normals=(v - v.mean(0)).astype(np.float32),
        colors=colors,
        attributes={
            "x": x.astype(np.float32),
            "classification": cls,
            "intensity": np.rint(1000 * ramp).astype(np.uint16),
        },
        face_attributes={"face_id": np.arange(len(f), dtype=np.int32)},
        history=["made by the test"],
        point_dtype=np.float32,
    )
    out, rep = simplify(m, ratio=0.2)
    assert out.point_dtype == np.float32 and out.history == ["made by the test"]
    assert out.normals.dtype == np.float32 and out.colors.dtype == np.uint8
    assert out.colors.shape == (len(out.vertices), 4)
    assert {k: a.dtype for k, a in out.attributes.items()} == {
        "x": np.float32,
        "classification": np.uint8,
        "intensity": np.uint16,
    }
    assert out.face_attributes["face_id"].dtype == np.int32
    # interpolated at the new vertex: within an edge's reach of the value there
    xo = out.vertices[:, 0] - v[:, 0].min()
    edge = np.linalg.norm(np.diff(out.vertices[out.faces], axis=1), axis=-1).max()
    assert np.abs(out.attributes["x"] - xo).max() < edge
    assert np.abs(out.colors[:, 0] / 255.0 - xo / x.max()).max() < edge / x.max() + 1 / 255
    assert np.array_equal(out.colors[:, 1], np.full(len(out.vertices), 7))
    assert set(np.unique(out.attributes["classification"])) == {2, 6}
    assert np.allclose(np.linalg.norm(out.normals, axis=1), 1.0, atol=1e-6)
    ids = out.face_attributes["face_id"]
    assert len(np.unique(ids)) == len(ids)  # each face kept its own


@pytest.mark.parametrize("name", ["mug", "armadillo"])
def test_as_accurate_as_open3d_and_pymeshlab(name):
    """To 10 % of the faces: Chamfer at most Open3D's and within 2 % of PyMeshLab's."""
    m = load_shared(name)
    target = len(m.faces) // 10
    out, rep = simplify(m, faces=target)
    assert rep["faces_out"] in (target, target + 1)
    assert_same_topology(m, out)
    o3 = open3d_backend.simplify_quadric(m, target)
    ml = pymeshlab_backend.simplify_quadric(m, target)
    ours, theirs, meshlab = chamfer(m, out)[0], chamfer(m, o3)[0], chamfer(m, ml)[0]
    assert ours <= theirs, (ours, theirs)  # issue 45: Chamfer <= Open3D's (0.65x, 0.995x)
    assert ours <= 1.02 * meshlab, (ours, meshlab)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 10_000),
    frac=st.floats(0.0, 1.0),
    weight=st.sampled_from([0.0, 1.0, 1000.0]),
)
def test_invariants_on_random_meshes(seed, frac, weight):
    """Random meshes, targets and boundary weights: at least the target, manifold, oriented."""
    rng = np.random.default_rng(seed)
    v, f = (S.icosphere(2), terrain(9), S.torus(nu=10, nv=6))[seed % 3]
    v = v + rng.normal(scale=0.02, size=v.shape)
    m = TriangleMesh(v, f, face_attributes={"id": np.arange(len(f))})
    target = 4 + int(frac * (len(f) - 4))
    out, rep = simplify(m, faces=target, boundary_weight=weight)
    assert rep["faces_out"] >= target and len(out.faces) == rep["faces_out"]
    assert (rep["stopped"] is None) == (rep["faces_out"] == target)
    assert_same_topology(m, out)
    # every face still faces the way it did in the input (however far it was turned)
    n_in, _ = face_normals(m.vertices, m.faces)
    n_out, _ = face_normals(out.vertices, out.faces)
    assert np.einsum("ij,ij->i", n_out, n_in[out.face_attributes["id"]]).min() > 0


def test_a_stage_in_pipelines():
    """The simplify stage in pipelines; clouds, both targets, too many or too few faces refused."""
    v, f = S.icosphere(3)
    res = apply_stage("simplify", TriangleMesh(v, f, history=["x"]), {"faces": 100})
    assert len(res.output.faces) == 100 and res.report["faces_out"] == 100
    assert res.output.history[0] == "x" and "simplify" in res.output.history[-1]
    assert "faces=100" in res.output.history[-1]
    with pytest.raises(InputError, match="needs a triangle mesh"):
        apply_stage("simplify", PointCloud(v), {})
    with pytest.raises(ParameterError, match="not both"):
        simplify(TriangleMesh(v, f), faces=10, ratio=0.5)
    with pytest.raises(ParameterError, match="above the input's 1280 faces"):
        simplify(TriangleMesh(v, f), faces=2000)
    with pytest.raises(ParameterError, match="at least 4 faces"):
        simplify(TriangleMesh(v, f), ratio=0.001)


CASES = [
    (["--ratio", "0"], "--ratio must be a number with 0 < x <= 1"),
    (["--ratio", "1.5"], "--ratio must be a number with 0 < x <= 1"),
    (["--faces", "3"], "--faces must be an integer with 4 <= x"),
    (["--faces", "100000"], "--faces 100000 is above the input's 320 faces"),
    (["--faces", "10", "--ratio", "0.5"], "give --faces or --ratio, not both"),
    ("cloud", "simplify needs a triangle mesh, got a point cloud"),
]


@pytest.mark.parametrize("args, message", CASES)
def test_bad_input_one_line_exit_2_no_output(tmp_path, args, message):
    """Bad input on the command line: exit 2, one line with the message, nothing written."""
    v, f = S.icosphere(2)
    src = tmp_path / "in.ply"
    write_ply(PointCloud(v) if args == "cloud" else TriangleMesh(v, f), src)
    out = tmp_path / "out.ply"
    cmd = [sys.executable, "-m", "recon_cli.cli.main", "simplify", str(src), str(out)]
    r = subprocess.run(
        cmd + (["--faces", "10"] if args == "cloud" else args), capture_output=True, timeout=300
    )
    err = r.stderr.decode().strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1 and message in err, err
    assert "Traceback" not in err and not out.exists()
    assert sorted(os.listdir(tmp_path)) == ["in.ply"]


def test_command_writes_the_simplified_mesh(tmp_path):
    """``recon simplify --ratio 0.25`` writes a quarter of the icosphere's faces."""
    v, f = S.icosphere(3)
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    write_ply(TriangleMesh(v, f), src)
    r = subprocess.run(
        [sys.executable, "-m", "recon_cli.cli.main", "simplify", src, dst, "--ratio", "0.25"],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr.decode()
    out = read_ply(dst)
    assert len(out.faces) == 320 and "faces_out" in r.stderr.decode()


@pytest.mark.parametrize("room", [1.02, 4.0])
def test_compacting_the_adjacency_lists_changes_nothing(room):
    """Compacting the adjacency lists, tight or roomy, gives the same collapses in order."""
    # the vertex -> faces and vertex -> edges lists grow at their end with every collapse and
    # are compacted when full: tight (compacted every few collapses) or roomy (never), the
    # same collapses happen in the same order
    _, m = family(1)
    logs = []
    for factor in (None, room):
        d = Decimator(m.vertices, m.faces, 1000.0)
        if factor is not None:
            for name, slot in (("refs", d.K.M_REFS), ("erefs", d.K.M_EREFS)):
                used = int(d.meta[slot])
                grown = np.zeros(max(int(factor * used), used + 64), dtype=np.int64)
                grown[:used] = getattr(d, name)[:used]
                setattr(d, name, grown)
        d.run(len(m.faces) // 20, len(m.faces) // 20)
        r = d.result()
        logs.append((r["log_u"], r["log_v"], r["positions"][r["valive"]], r["faces"][r["falive"]]))
    assert len(logs[0][0]) == len(m.faces) * 19 // 40
    for a, b in zip(logs[0], logs[1], strict=True):
        assert np.array_equal(a, b)


def test_same_bytes_for_any_thread_count_and_run(tmp_path):
    """``recon simplify`` writes the same bytes on 1, 2 and 4 threads and when run again."""
    rng = np.random.default_rng(4)
    v, f = S.torus(nu=120, nv=60)
    v = v + rng.normal(scale=1e-3, size=v.shape)
    m = TriangleMesh(v, f, colors=rng.integers(0, 255, (len(v), 3)).astype(np.uint8))
    src = tmp_path / "in.ply"
    write_ply(m, src)
    outs = []
    for threads in ("1", "2", "4"):
        dst = tmp_path / f"out{threads}.ply"
        env = dict(os.environ, NUMBA_NUM_THREADS=threads)
        cmd = [sys.executable, "-m", "recon_cli.cli.main", "-q", "simplify", src, dst]
        r = subprocess.run([*cmd, "--ratio", "0.1"], capture_output=True, timeout=300, env=env)
        assert r.returncode == 0, r.stderr.decode()
        outs.append(dst.read_bytes())
    for _ in range(2):  # and in this process, twice
        again = tmp_path / "again.ply"
        write_ply(apply_stage("simplify", read_ply(src), {"ratio": 0.1}).output, again)
        outs.append(again.read_bytes())
    assert len(read_ply(tmp_path / "out1.ply").faces) == round(0.1 * len(f))
    assert all(o == outs[0] for o in outs[1:])


def depth_mesh(seed: int) -> TriangleMesh:
    """A single-view scan as a mesh: a simulated Kinect tabletop triangulated over its pixels.

    A simulated Kinect image (noise, flying pixels, NaN misses) triangulated over its pixel grid, no
    triangle across a depth jump. Open, with holes and pinched (non-manifold) vertices where two
    triangles touch.
    """
    import sensors

    rng = np.random.default_rng(seed)
    cam = sensors.DepthCamera(
        eye=np.array([0.0, -2.2, 1.3]), rotation=sensors.look_at((0.0, -2.2, 1.3), (0, 0.3, 0.2))
    )
    img = sensors.depth_image(cam, sensors.tabletop_scene(), rng)
    h, w, _ = img.shape
    idx = np.arange(h * w).reshape(h, w)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    tri = np.concatenate([np.stack([a, c, b], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    p = img.reshape(-1, 3)
    ok = np.isfinite(p[tri]).all(axis=(1, 2))
    tri = tri[ok]
    edge = np.linalg.norm(p[tri] - p[np.roll(tri, 1, axis=1)], axis=-1).max(axis=1)
    tri = tri[edge < 4 * np.median(edge)]
    v, f = compact(p, tri)
    return TriangleMesh(v, f, face_attributes={"id": np.arange(len(f))})


@pytest.mark.parametrize("seed", [0, 1])
def test_depth_camera_scans_keep_holes_pinches_and_orientation(seed):
    """Depth-camera meshes keep their holes, pinched vertices and orientation, simplified."""
    from recon_cli.stages.repair import repair

    raw = depth_mesh(seed)
    r0 = report(raw)
    assert r0["non_manifold_vertices"] > 0 and r0["boundary_loops"] > 3
    # pinched vertices are locked and stay pinched; nothing else changes its topology
    out, rep = simplify(raw, ratio=0.2)
    r = report(out)
    assert rep["faces_out"] == rep["faces_target"] and rep["stopped"] is None
    for k in ("components", "non_manifold_vertices", "non_manifold_edges", "euler_characteristic"):
        assert r[k] == r0[k], (k, r0[k], r[k])
    n_in, _ = face_normals(raw.vertices, raw.faces)
    n_out, _ = face_normals(out.vertices, out.faces)
    assert np.einsum("ij,ij->i", n_out, n_in[out.face_attributes["id"]]).min() > 0
    # made manifold (pinches split), every hole is kept; the jagged rim of the scan stays
    # within the surface's own error
    m, _ = repair(raw)
    out, rep = simplify(m, ratio=0.2)
    r0, r = report(m), report(out)
    for k in ("boundary_loops", "components", "euler_characteristic"):
        assert r[k] == r0[k], (k, r0[k], r[k])
    cd, hd = chamfer(m, out)
    assert cd < 1e-3 and boundary_hausdorff(m, out) < min(2 * hd, 2e-2)
