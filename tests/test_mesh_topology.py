"""Connectivity and topology report: counts against PyMeshLab, Open3D and trimesh."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recon_cli.backends import open3d_backend, pymeshlab_backend
from recon_cli.errors import InputError
from recon_cli.geometry import TriangleMesh
from recon_cli.mesh.topology import (
    Connectivity,
    boundary_loops,
    faces_to_edges,
    is_consistently_oriented,
    is_edge_manifold,
    is_vertex_manifold,
    is_watertight,
    report,
)

import mesh_damage as D
from shared_data import ALL_MESHES, CLOSED_MESHES, load_shared, shared_path

REPORT_KEYS = [
    "vertices", "edges", "faces", "components", "boundary_edges", "boundary_loops",
    "non_manifold_edges", "non_manifold_vertices", "duplicate_faces", "degenerate_faces",
    "unreferenced_vertices", "consistently_oriented", "orientable", "edge_manifold",
    "vertex_manifold", "watertight", "euler_characteristic", "genus", "component_genus", "area",
    "volume",
]  # fmt: skip

TETRA = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
TETRA_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def damaged(kind: str, name: str = "kitten") -> TriangleMesh:
    """A damaged copy of a shared mesh (or two cones), by the kind of damage."""
    rng = np.random.default_rng(7)
    if kind == "cones":
        return D.two_cones()
    m = load_shared(name)
    return {
        "flips": lambda: D.flip_faces(m, rng),
        "duplicates": lambda: D.duplicate_faces(m, rng),
        "fins": lambda: D.glue_fins(m, rng),
        "patches": lambda: D.remove_patches(m, rng),
        "split_vertices": lambda: D.split_vertices(m, rng),
        "pinched": lambda: _pinched(m),
    }[kind]()


def _pinched(m: TriangleMesh) -> TriangleMesh:
    """``m`` and a translated copy touching it at one shared vertex (a mesh pinched at a point)."""
    v0, n = m.vertices, len(m.vertices)
    rm, lm = int(np.argmax(v0[:, 0])), int(np.argmin(v0[:, 0]))
    f1 = m.faces + n
    f1[f1 == lm + n] = rm  # the copy's leftmost vertex is the original's rightmost one
    return TriangleMesh(
        vertices=np.concatenate([v0, v0 + (v0[rm] - v0[lm])]), faces=np.concatenate([m.faces, f1])
    )


def _compare_references(mesh: TriangleMesh, rep: dict) -> None:
    pml = pymeshlab_backend.topological_measures(mesh)
    o3d = open3d_backend.manifold_checks(mesh, self_intersection=False)
    c = Connectivity(mesh.faces, len(mesh.vertices))
    assert rep["faces"] == pml["faces_number"]
    assert rep["edges"] == pml["edges_number"]
    assert rep["components"] == pml["connected_components_number"]
    assert rep["boundary_edges"] == pml["boundary_edges"]
    # PyMeshLab's non_two_manifold_edges is unreliable (after the first call in a process it
    # returns the incident-face count), so edges are checked against Open3D and the incident
    # faces against PyMeshLab
    assert rep["non_manifold_edges"] == o3d["non_manifold_edges"]
    nm_faces = np.unique(
        c.edge_half_edges[np.isin(c.half_edge_edge[c.edge_half_edges], c.non_manifold_edges)] // 3
    )
    assert len(nm_faces) == pml["incident_faces_on_non_two_manifold_edges"]
    assert (
        rep["non_manifold_vertices"]
        == pml["non_two_manifold_vertices"]
        == o3d["non_manifold_vertices"]
    )
    nm_vfaces = np.flatnonzero(np.isin(mesh.faces, c.non_manifold_vertices).any(axis=1))
    assert len(nm_vfaces) == pml["incident_faces_on_non_two_manifold_vertices"]
    assert rep["unreferenced_vertices"] == pml["unreferenced_vertices"]
    assert rep["edge_manifold"] == o3d["edge_manifold"]
    assert rep["vertex_manifold"] == o3d["vertex_manifold"]
    if pml["is_mesh_two_manifold"]:
        assert rep["boundary_loops"] == pml["number_holes"]
        # Open3D's orientability is defined on edge-manifold meshes only
        assert rep["orientable"] == o3d["orientable"]
    if rep["watertight"] and rep["vertex_manifold"]:
        assert rep["genus"] == pml["genus"]
        assert o3d["watertight"]


def test_faces_to_edges_matches_trimesh():
    """faces_to_edges gives trimesh's edges, each face's three in order."""
    import trimesh

    f = load_shared("kitten").faces[:100]
    e, idx = faces_to_edges(f, return_index=True)
    assert np.array_equal(e, trimesh.geometry.faces_to_edges(f))
    assert np.array_equal(idx, np.repeat(np.arange(100), 3))
    assert e.shape == (300, 2)


@pytest.mark.parametrize("name", ALL_MESHES)
def test_report_shared_meshes_agree_with_references(name):
    """The report of each shared mesh agrees with Open3D, PyMeshLab and trimesh.

    Closed meshes: watertight, their volume and genus; the bunny: open with 5 boundary loops.
    """
    import trimesh

    mesh = load_shared(name)
    rep = report(mesh)
    assert list(rep) == REPORT_KEYS
    _compare_references(mesh, rep)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert rep["area"] == pytest.approx(tm.area, rel=1e-12)
    assert rep["consistently_oriented"] == tm.is_winding_consistent
    assert rep["duplicate_faces"] == 0 and rep["degenerate_faces"] == 0
    if name in CLOSED_MESHES:
        assert rep["watertight"] and rep["volume"] > 0
        assert rep["volume"] == pytest.approx(tm.volume, rel=1e-9)
        assert rep["genus"] == {"armadillo": 0, "kitten": 1, "mug": 1}[name]
        assert rep["component_genus"] == [rep["genus"]]
    else:
        # SOURCES.md: the bunny is open at the base with 5 boundary loops
        assert rep["boundary_loops"] == 5 and rep["volume"] is None and rep["genus"] is None


@pytest.mark.parametrize(
    "kind", ["flips", "duplicates", "fins", "patches", "split_vertices", "cones", "pinched"]
)
def test_report_damaged_meshes_agree_with_references(kind):
    """The report of each kind of damage agrees with the references and counts the damage."""
    mesh = damaged(kind)
    rep = report(mesh)
    _compare_references(mesh, rep)
    expected = {
        "flips": dict(
            consistently_oriented=False, orientable=True, watertight=True, non_manifold_edges=0
        ),
        "duplicates": dict(duplicate_faces=50, non_manifold_edges=150, edge_manifold=False),
        "fins": dict(
            non_manifold_edges=20, boundary_edges=40, boundary_loops=20, edge_manifold=False
        ),
        "patches": dict(
            boundary_loops=3, watertight=False, edge_manifold=True, vertex_manifold=True
        ),
        "split_vertices": dict(non_manifold_edges=0, vertex_manifold=False),
        "cones": dict(components=2, non_manifold_vertices=1, watertight=True, genus=None),
        "pinched": dict(components=2, non_manifold_vertices=1, watertight=True, genus=None),
    }[kind]
    for k, v in expected.items():
        assert rep[k] == v, k


def test_flips_orientation_agrees_with_trimesh():
    """Flipped faces: not consistently oriented, as trimesh says; the intact kitten is."""
    import trimesh

    mesh = damaged("flips")
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert is_consistently_oriented(mesh.faces) == tm.is_winding_consistent is False
    assert is_consistently_oriented(load_shared("kitten").faces)


def test_boundary_loops_follow_half_edges():
    """The bunny's 5 boundary loops follow its boundary half-edges, each vertex once."""
    mesh = load_shared("bunny_zipper")
    c = Connectivity(mesh.faces, len(mesh.vertices))
    loops = c.boundary_loops
    assert len(loops) == 5
    assert sum(len(lp) for lp in loops) == len(c.boundary_edges)
    directed = {tuple(e) for e in c.half_edges[c.edge_half_edges[c.edge_ptr[c.boundary_edges]]]}
    for lp in loops:
        assert len(set(lp.tolist())) == len(lp)  # a manifold boundary visits each vertex once
        for a, b in zip(lp, np.roll(lp, -1), strict=True):
            assert (a, b) in directed
    assert [len(x) for x in boundary_loops(mesh.faces)] == [len(x) for x in loops]


def test_predicates_on_small_meshes():
    """The predicates on a tetrahedron, flipped, opened, with a fin, and on two cones."""
    assert is_watertight(TETRA) and is_edge_manifold(TETRA) and is_vertex_manifold(TETRA)
    assert is_consistently_oriented(TETRA)
    flipped = TETRA.copy()
    flipped[0] = flipped[0, [0, 2, 1]]
    assert not is_consistently_oriented(flipped) and Connectivity(flipped).is_orientable
    open_ = TETRA[:3]
    assert not is_watertight(open_) and [len(x) for x in boundary_loops(open_)] == [3]
    fin = np.concatenate([TETRA, [[0, 1, 4]]])
    assert not is_edge_manifold(fin) and is_vertex_manifold(fin)
    cones = D.two_cones()
    assert not is_vertex_manifold(cones.faces) and is_watertight(cones.faces)
    rep = report(TriangleMesh(vertices=TETRA_V, faces=TETRA))
    assert rep["volume"] == pytest.approx(1 / 6, rel=1e-12)
    assert rep["euler_characteristic"] == 2 and rep["genus"] == 0
    assert rep["edges"] == 6 and rep["components"] == 1


def test_mobius_strip_is_not_orientable():
    """A Möbius strip is manifold and not orientable, for us and for Open3D."""
    n = 12
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    # a strip whose ends are glued with a half twist: vertex i on one side meets i + n on the other
    faces = []
    for i in range(n):
        a, b = i, (i + 1) % n
        ta, tb = a + n, b + n
        if i == n - 1:
            tb, b = b, b + n  # the twist
        faces += [[a, b, ta], [b, tb, ta]]
    v = np.concatenate(
        [
            np.stack([np.cos(t), np.sin(t), np.full(n, -0.2)], 1),
            np.stack([np.cos(t), np.sin(t), np.full(n, 0.2)], 1),
        ]
    )
    mesh = TriangleMesh(vertices=v, faces=np.array(faces))
    rep = report(mesh)
    o3d = open3d_backend.manifold_checks(mesh, self_intersection=False)
    assert rep["edge_manifold"] and rep["vertex_manifold"]
    assert rep["orientable"] is False and o3d["orientable"] is False
    assert rep["consistently_oriented"] is False
    assert rep["boundary_loops"] == 1  # a Moebius strip has a single boundary curve


def test_duplicate_and_degenerate_counts():
    """Duplicate faces (either winding), degenerate faces and unreferenced vertices are counted."""
    f = np.concatenate(
        [TETRA, TETRA[:1, [0, 2, 1]], np.roll(TETRA[1:2], 1, axis=1), [[0, 0, 1]], [[0, 1, 1]]]
    )
    v = np.concatenate([TETRA_V, [[0.5, 0, 0]]])
    f = np.concatenate([f, [[0, 1, 4]]])  # collinear: zero area
    c = Connectivity(f, len(v), v)
    assert c.duplicate_faces.tolist() == [4, 5]
    assert c.degenerate_faces.tolist() == [6, 7, 8]
    rep = report(TriangleMesh(vertices=np.concatenate([v, [[9.0, 9, 9]]]), faces=f))
    assert (
        rep["duplicate_faces"] == 2
        and rep["degenerate_faces"] == 3
        and rep["unreferenced_vertices"] == 1
    )


def test_per_component_genus_and_volume():
    """Two shells: their own genus (largest first), the summed volume and Euler characteristics."""
    kitten = load_shared("kitten")
    arm = load_shared("armadillo")
    both = TriangleMesh(
        vertices=np.concatenate([arm.vertices, kitten.vertices + 500]),
        faces=np.concatenate([arm.faces, kitten.faces + len(arm.vertices)]),
    )
    rep = report(both)
    assert rep["components"] == 2
    assert rep["component_genus"] == [0, 1]  # largest (armadillo) first
    assert rep["genus"] == 1
    assert rep["volume"] == pytest.approx(
        report(arm)["volume"] + report(kitten)["volume"], rel=1e-9
    )
    c = Connectivity(both.faces, len(both.vertices), both.vertices)
    assert c.component_euler.tolist() == [2, 0]


def test_invalid_faces_raise():
    """Faces that are not triangles of valid integer indices are refused."""
    with pytest.raises(InputError):
        Connectivity(np.array([[0, 1]]))
    with pytest.raises(InputError):
        Connectivity(np.array([[0, 1, -1]]))
    with pytest.raises(InputError):
        Connectivity(np.array([[0, 1, 5]]), n_vertices=3)
    with pytest.raises(InputError):
        Connectivity(np.array([[0.5, 1, 2]]))


def test_empty_mesh_report():
    """A mesh without faces reports zero faces, edges and components, not watertight, no genus."""
    rep = report(TriangleMesh(vertices=np.zeros((3, 3)), faces=np.zeros((0, 3), dtype=np.int64)))
    assert rep["faces"] == 0 and rep["edges"] == 0 and rep["components"] == 0
    assert rep["unreferenced_vertices"] == 3 and rep["watertight"] is False and rep["genus"] is None


def test_info_cli_prints_topology():
    """``recon info`` prints the mug's topology (genus 1, watertight), the bunny's boundary."""
    from click.testing import CliRunner

    from recon_cli.cli.main import cli

    res = CliRunner().invoke(cli, ["info", "--json", str(shared_path("mug"))])
    assert res.exit_code == 0, res.output
    topo = json.loads(res.output)[0]["topology"]
    assert topo["genus"] == 1 and topo["watertight"] is True and topo["faces"] == 10168
    res = CliRunner().invoke(cli, ["info", str(shared_path("bunny_zipper"))])
    assert res.exit_code == 0 and "boundary_loops" in res.output


soups = st.integers(min_value=3, max_value=25).flatmap(
    lambda n: st.tuples(
        st.lists(st.tuples(*[st.integers(-2, 2)] * 3), min_size=n, max_size=n),
        st.lists(st.tuples(*[st.integers(0, n - 1)] * 3), min_size=0, max_size=60),
    )
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(soups)
def test_report_never_crashes_and_is_consistent(soup):
    """Random face soups: the report never fails and its counts agree with one another."""
    v, f = soup
    mesh = TriangleMesh(
        vertices=np.array(v, dtype=float).reshape(-1, 3),
        faces=np.array(f, dtype=np.int64).reshape(-1, 3),
    )
    rep = report(mesh)
    c = Connectivity(mesh.faces, len(mesh.vertices), mesh.vertices)
    # every half-edge that is not a self-loop lies on exactly one edge
    assert int(c.edge_face_count.sum()) == int((c.half_edges[:, 0] != c.half_edges[:, 1]).sum())
    # components only share vertices, each shared one counted once per extra component
    pairs = {
        (int(comp), int(vv))
        for comp, row in zip(c.face_components, mesh.faces, strict=True)
        for vv in row
    }
    shared = len(pairs) - len({vv for _, vv in pairs})
    assert rep["euler_characteristic"] == int(c.component_euler.sum()) - shared
    assert rep["edge_manifold"] == (rep["non_manifold_edges"] == 0)
    assert rep["watertight"] == (
        rep["faces"] > 0 and rep["boundary_edges"] == 0 and rep["non_manifold_edges"] == 0
    )
    if rep["genus"] is not None:
        assert rep["watertight"] and rep["vertex_manifold"] and rep["orientable"]
    if len(mesh.faces) and rep["degenerate_faces"] == 0:
        o3d = open3d_backend.manifold_checks(mesh, self_intersection=False)
        assert rep["non_manifold_edges"] == o3d["non_manifold_edges"]
        assert rep["non_manifold_vertices"] == o3d["non_manifold_vertices"]


def _scipy_labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Reference connected components (scipy numbers them by smallest member, like ours)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    g = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(n, n))
    return connected_components(g, directed=False)[1]


@pytest.mark.parametrize("kind", ["fins", "cones", "split_vertices", "duplicates"])
def test_union_find_labels_match_scipy(kind):
    """Fans and components (numba union-find) equal scipy's graph components, label for label."""
    mesh = damaged(kind)
    c = Connectivity(mesh.faces, len(mesh.vertices))
    hs, ptr = c.edge_half_edges.astype(np.int64), c.edge_ptr.astype(np.int64)
    same = np.ones(len(hs) - 1, dtype=bool)
    same[ptr[1:-1] - 1] = False  # consecutive half-edges of one edge
    a, b = hs[:-1][same], hs[1:][same]
    flat = mesh.faces.ravel()
    nxt_a, nxt_b = a - a % 3 + (a % 3 + 1) % 3, b - b % 3 + (b % 3 + 1) % 3
    s = flat[a] == flat[b]
    ref = _scipy_labels(
        3 * len(mesh.faces), np.r_[a, nxt_a], np.r_[np.where(s, b, nxt_b), np.where(s, nxt_b, b)]
    )
    assert np.array_equal(c.corner_fans(), ref)
    assert np.array_equal(c.corner_fans(a, b), ref)
    n_fans = len(np.unique(ref))
    assert int(c.vertex_fan_count.sum()) == n_fans
    assert (n_fans > int(c.referenced.sum())) == (kind in ("cones", "split_vertices"))
    comp = _scipy_labels(len(mesh.faces), a // 3, b // 3)
    sizes = np.bincount(comp)
    # ours: largest first, ties by first face
    expected = np.argsort(np.argsort(-sizes, kind="stable"), kind="stable")[comp]
    assert np.array_equal(c.face_components, expected)


def test_int32_faces_and_unpacked_keys_give_the_same_connectivity():
    """int32 faces and the argsort fallback give the packed sort's connectivity.

    int32 faces are used without a copy, and the argsort fallback (keys too large to pack an index
    into) groups edges exactly as the packed sort does.
    """
    mesh = damaged("fins")
    c64 = Connectivity(mesh.faces, len(mesh.vertices))
    f32 = mesh.faces.astype(np.int32)
    c32 = Connectivity(f32, len(mesh.vertices))
    assert c32.faces is f32 and c64.faces is mesh.faces
    assert c32.half_edge_edge.dtype == np.int32 and c32.edge_half_edges.dtype == np.int32
    big = Connectivity(mesh.faces, 2**31)  # n * n * 3m >= 2^62: unpacked keys, int64 indices
    assert big.half_edge_edge.dtype == np.int64
    for c in (c32, big):
        assert np.array_equal(c.half_edge_edge, c64.half_edge_edge)
        assert np.array_equal(c.edge_ptr, c64.edge_ptr)
        assert np.array_equal(c.edge_half_edges, c64.edge_half_edges)
        assert np.array_equal(c.edges, c64.edges)
        assert np.array_equal(c.face_components, c64.face_components)
        assert c.is_consistently_oriented == c64.is_consistently_oriented
    # (not on ``big``: per-vertex arrays of 2^31 entries)
    assert np.array_equal(c32.non_manifold_vertices, c64.non_manifold_vertices)
    assert np.array_equal(c32.corner_fans(), c64.corner_fans())
    # half-edges of an edge are listed in increasing order, edges by (lo, hi)
    h = c64.edge_half_edges
    first = np.zeros(len(h), dtype=bool)
    first[c64.edge_ptr[:-1]] = True
    assert np.all(np.diff(h)[~first[1:]] > 0)
    keys = c64.edges[:, 0] * len(mesh.vertices) + c64.edges[:, 1]
    assert np.all(np.diff(keys) > 0) and np.all(c64.edges[:, 0] < c64.edges[:, 1])
    assert np.array_equal(c64.half_edges, faces_to_edges(mesh.faces))


def test_vertex_faces_csr():
    """The vertex-to-face lists are exactly the faces using each vertex."""
    mesh = damaged("cones")
    c = Connectivity(mesh.faces, len(mesh.vertices))
    for v in range(len(mesh.vertices)):
        got = c.vertex_faces[c.vertex_ptr[v] : c.vertex_ptr[v + 1]]
        assert got.tolist() == np.flatnonzero((mesh.faces == v).any(axis=1)).tolist()


def _reference_groups(faces: np.ndarray, n: int):
    """Edge groups and duplicate faces by one stable sort of int64 keys (the old way)."""
    flat = faces.reshape(-1)
    a, b = flat, faces[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keep = np.flatnonzero(a != b)
    key = lo[keep] * n + hi[keep]
    order = np.argsort(key, kind="stable")
    he = keep[order]
    starts = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]]) if len(he) else []
    ptr = np.r_[starts, len(he)]
    s = np.sort(faces, axis=1)
    first = np.unique(s, axis=0, return_index=True)[1]
    dup = np.setdiff1d(np.arange(len(faces)), first)
    return ptr, he, dup


@pytest.mark.parametrize("spread", [1, 1000])
def test_bucketed_edges_and_duplicates_match_one_sort(spread):
    """Bucketing by the smaller vertex gives the groups of a stable sort of ``lo * n + hi``.

    A 3000-face fan (a bucket beyond the insertion sort), repeated-index faces, duplicates
    in both windings, a 30-face non-manifold edge; ``spread`` 1000 declares far more vertices
    than corners (buckets of several vertices).
    """
    rng = np.random.default_rng(3)
    k = 3000
    ff = [[0, 1 + i, 1 + (i + 1) % k] for i in range(k)]
    ff += [[k + 1, 1 + i, 1 + (i + 1) % k] for i in range(0, k, 2)]
    ff += [[0, 1, 1], [1, 1, 0], [5, 5, 5], [5, 5, 5], [0, 2, 1], [2, 1, 0], [0, 1, 2]]
    ff += [[1, 2, k + 3 + j] for j in range(30)]
    ff += rng.integers(0, 60, size=(400, 3)).tolist()
    faces = np.array(ff)[rng.permutation(len(ff))] * spread
    n = int(faces.max()) + 1
    c = Connectivity(faces, n)
    ptr, he, dup = _reference_groups(faces, n)
    assert np.array_equal(c.edge_ptr, ptr) and np.array_equal(c.edge_half_edges, he)
    assert np.array_equal(c.duplicate_faces, dup)
    assert len(dup) >= 4 and len(c.non_manifold_edges) >= 1


def test_report_memory_per_face_is_bounded():
    """report() allocates about 35 bytes a face at its peak (numba's arrays are traced too).

    With a sort of int64 half-edge keys and sorted copies of the faces it took 83 bytes a face
    on this mesh, and 145M faces did not fit in 24 GiB.
    """
    import tracemalloc

    from shapes import torus

    v, f = torus(nu=400, nv=300)
    report(TriangleMesh(vertices=TETRA_V, faces=TETRA))  # compiled before measuring
    tracemalloc.start()
    try:
        rep = report(TriangleMesh(vertices=v, faces=f))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert rep["genus"] == 1 and rep["faces"] == len(f) == 240_000
    assert peak < 48 * len(f), peak / len(f)


def test_forget_drops_the_arrays_and_the_answers_stay():
    """forget() drops every array but the mesh's, and the answers stay the same."""
    # report() frees the adjacency this way before the areas: the same object answers again
    from shapes import torus

    v, f = torus(nu=20, nv=12)
    c = Connectivity(f, len(v), v)
    before = (c.n_edges, c.n_components, c.component_genus, float(c.face_areas.sum()))
    assert "_edge_groups" in c.__dict__
    c.forget()
    assert not any(
        isinstance(x, np.ndarray)
        for x in c.__dict__.values()
        if x is not c.faces and x is not c.vertices
    )
    assert (c.n_edges, c.n_components, c.component_genus, float(c.face_areas.sum())) == before
