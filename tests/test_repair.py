"""``recon repair``: manifold, oriented, volume kept, holes filled.

Checked with Open3D, trimesh, PyMeshLab.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from recon_cli.backends import open3d_backend, pymeshlab_backend
from recon_cli.errors import InputError, ParameterError
from recon_cli.geometry import TriangleMesh, bbox_diagonal
from recon_cli.mesh.sampling import sample_surface
from recon_cli.mesh.topology import boundary_loops, report
from recon_cli.stages import apply_stage
from recon_cli.stages.repair import repair, run_stage

import mesh_damage as D
from shared_data import CLOSED_MESHES, load_shared, sampled_cloud, shared_path

DAMAGE = {
    "flips": lambda m, rng: D.flip_faces(m, rng, 0.1),
    "duplicates": lambda m, rng: D.duplicate_faces(m, rng, 80),
    "fins": lambda m, rng: D.glue_fins(m, rng, 30),
    "split_vertices": lambda m, rng: D.split_vertices(m, rng, 0.03),
    "all": lambda m, rng: D.glue_fins(
        D.duplicate_faces(D.flip_faces(D.split_vertices(m, rng), rng), rng), rng
    ),
}


def assert_clean(mesh: TriangleMesh, closed: bool | None = None) -> dict:
    """Manifold and oriented by our report, Open3D and trimesh; no duplicate/degenerate faces."""
    import trimesh

    rep = report(mesh)
    for k in ("edge_manifold", "vertex_manifold", "consistently_oriented", "orientable"):
        assert rep[k] is True, k
    assert rep["duplicate_faces"] == rep["degenerate_faces"] == rep["unreferenced_vertices"] == 0
    if len(mesh.faces):
        o3d = open3d_backend.manifold_checks(mesh, self_intersection=False)
        assert o3d["edge_manifold"] and o3d["vertex_manifold"] and o3d["orientable"]
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        assert tm.is_winding_consistent
        if closed is not None:
            assert tm.is_watertight == closed == o3d["watertight"] == rep["watertight"]
    return rep


def compacted(mesh: TriangleMesh) -> TriangleMesh:
    """``mesh`` without its unreferenced vertices (repair would drop them)."""
    used = np.unique(mesh.faces)
    remap = np.full(len(mesh.vertices), -1)
    remap[used] = np.arange(len(used))
    return TriangleMesh(vertices=mesh.vertices[used], faces=remap[mesh.faces])


def chamfer(a: TriangleMesh, b: TriangleMesh, n: int = 50_000) -> float:
    """Symmetric mean point-to-plane distance between dense surface samples (cKDTree).

    Point-to-plane (to the nearest sample's true tangent plane) removes the sampling bias of
    point-to-point distances (half the sample spacing, about 0.2 % of the kitten's diagonal).
    """
    sa = sample_surface(a, n, seed=1)
    sb = sample_surface(b, n, seed=2)
    out = []
    for p, q in ((sa, sb), (sb, sa)):
        _, j = cKDTree(q.points).query(p.points)
        out.append(np.abs(np.einsum("ij,ij->i", p.points - q.points[j], q.normals[j])).mean())
    return 0.5 * (out[0] + out[1])


@pytest.mark.parametrize("name", ["armadillo", "bunny_zipper", "kitten", "mug"])
def test_clean_meshes_pass_through_unchanged(name):
    """Clean shared meshes pass through repair unchanged, with no change counted."""
    mesh = load_shared(name)
    if name == "bunny_zipper":  # its 1113 unreferenced vertices would be removed: drop them first
        mesh = compacted(mesh)
    out, rep = repair(mesh)
    assert np.array_equal(out.faces, mesh.faces) and np.array_equal(out.vertices, mesh.vertices)
    changes = [
        k
        for k, v in rep.items()
        if k.endswith(
            (
                "_removed",
                "_merged",
                "_dropped",
                "_detached",
                "_split",
                "_added",
                "_flipped",
                "_reversed",
                "_cut",
            )
        )
        and v
    ]
    assert changes == []
    assert rep["watertight"] == (name in CLOSED_MESHES)


# every kind on kitten and mug; the armadillo (50k faces) with all defects at once
CASES = [(n, k) for n in ("kitten", "mug") for k in sorted(DAMAGE)] + [("armadillo", "all")]
assert {n for n, _ in CASES} == set(CLOSED_MESHES)


@pytest.mark.parametrize("name,kind", CASES)
def test_damaged_closed_meshes_come_back(name, kind):
    """Each kind of damage on a closed mesh is repaired: clean, the genus and volume back."""
    mesh = load_shared(name)
    ref = report(mesh)
    rng = np.random.default_rng(3)
    bad = DAMAGE[kind](mesh, rng)
    before = report(bad)
    assert not (
        before["edge_manifold"]
        and before["vertex_manifold"]
        and before["consistently_oriented"]
        and before["duplicate_faces"] == 0
    )
    out, rep = repair(bad)
    after = assert_clean(out, closed=True)
    assert after["genus"] == ref["genus"] and after["components"] == 1
    assert after["volume"] > 0
    assert after["volume"] == pytest.approx(ref["volume"], rel=1e-6)
    assert chamfer(out, mesh) < 1e-3 * bbox_diagonal(mesh.vertices)
    # nothing but the injected damage was touched
    assert len(out.faces) == len(mesh.faces) and len(out.vertices) == len(mesh.vertices)
    if kind == "flips":
        assert rep["faces_flipped"] == int(0.1 * len(mesh.faces))
    if kind == "duplicates":
        assert rep["duplicate_faces_removed"] == 80
    if kind == "fins":
        assert rep["non_manifold_edges"] == 30 and rep["non_manifold_faces_dropped"] == 30
    if kind == "split_vertices":
        assert rep["vertices_merged"] == len(bad.vertices) - len(mesh.vertices)


def test_inward_mesh_is_turned_outward():
    """A mesh wound inward is turned outward: its one component reversed, every face flipped."""
    mesh = load_shared("mug")
    inward = TriangleMesh(vertices=mesh.vertices, faces=mesh.faces[:, [0, 2, 1]])
    assert report(inward)["volume"] < 0
    out, rep = repair(inward)
    assert rep["components_reversed"] == 1 and rep["faces_flipped"] == len(mesh.faces)
    assert np.array_equal(out.faces, mesh.faces)


def test_open_mesh_follows_vertex_normals():
    """An open mesh's faces follow its vertex normals; without normals the larger area wins."""
    mesh = compacted(load_shared("bunny_zipper"))
    # the file is wound outward; true outward vertex normals from the faces
    fn = np.cross(
        *(mesh.vertices[mesh.faces[:, 1:]] - mesh.vertices[mesh.faces[:, :1]]).transpose(1, 0, 2)
    )
    vn = np.zeros_like(mesh.vertices)
    np.add.at(vn, mesh.faces.ravel(), np.repeat(fn, 3, axis=0))
    rng = np.random.default_rng(0)
    f = mesh.faces[:, [0, 2, 1]].copy()  # wound inward, except 10 % of faces
    i = rng.choice(len(f), len(f) // 10, replace=False)
    f[i] = mesh.faces[i]
    out, rep = repair(TriangleMesh(vertices=mesh.vertices, faces=f, normals=vn))
    assert_clean(out, closed=False)
    assert rep["faces_flipped"] == len(f) - len(i)
    assert np.array_equal(out.faces, mesh.faces)
    assert out.normals is not None and len(out.normals) == len(out.vertices)
    # without normals the larger area wins: inward here
    out2, _ = repair(TriangleMesh(vertices=mesh.vertices, faces=f))
    assert np.array_equal(out2.faces, mesh.faces[:, [0, 2, 1]])


def test_two_cones_are_split_at_the_tip():
    """Two cones touching at the tip are split there into two closed components."""
    cones = D.two_cones()
    out, rep = repair(cones)
    after = assert_clean(out, closed=None)
    assert rep["non_manifold_vertices_split"] == 1 and rep["vertices_added"] == 1
    assert after["components"] == 2 and after["watertight"] and after["component_genus"] == [0, 0]
    # each double cone: two cones of radius ~1 (16-gon) and heights 1 and 0.5
    ring_area = 0.5 * 16 * np.sin(2 * np.pi / 16)
    assert after["volume"] == pytest.approx(2 * ring_area * (1 + 0.5) / 3, rel=1e-12)
    assert np.array_equal(out.vertices[-1], out.vertices[0])  # the copy sits at the tip


def test_pinched_real_mesh_is_split():
    """The kitten and a copy pinched at a vertex: split into two pieces, twice the volume."""
    mesh = load_shared("kitten")
    v0, n = mesh.vertices, len(mesh.vertices)
    rm, lm = int(np.argmax(v0[:, 0])), int(np.argmin(v0[:, 0]))
    f1 = mesh.faces + n
    f1[f1 == lm + n] = rm
    pinched = TriangleMesh(
        vertices=np.concatenate([v0, v0 + (v0[rm] - v0[lm])]),
        faces=np.concatenate([mesh.faces, f1]),
    )
    out, rep = repair(pinched)
    after = assert_clean(out)
    assert (
        rep["non_manifold_vertices_split"] == 1 and after["components"] == 2 and after["genus"] == 2
    )
    assert after["volume"] == pytest.approx(2 * report(mesh)["volume"], rel=1e-6)


@pytest.mark.parametrize("name", ["kitten", "mug"])  # genus 0: the bunny test below
def test_hole_filling_restores_watertight_same_genus(name):
    """Holes cut in a closed mesh are filled: watertight, the same genus, near the original.

    A limit below the longest hole's length leaves that hole open.
    """
    mesh = load_shared(name)
    ref = report(mesh)
    k = 4
    holed = D.remove_patches(mesh, np.random.default_rng(11), k=k, rings=2)
    before = report(holed)
    assert before["boundary_loops"] == k and before["vertex_manifold"] and before["edge_manifold"]
    longest = max(len(x) for x in boundary_loops(holed.faces))
    out, rep = repair(holed, fill_holes=longest)
    after = assert_clean(out, closed=True)
    assert rep["holes"] == k and rep["holes_filled"] == k and rep["holes_skipped"] == 0
    assert after["genus"] == ref["genus"] and after["volume"] > 0
    assert chamfer(out, mesh) < 1e-3 * bbox_diagonal(mesh.vertices)
    # a limit below the longest loop leaves that one open
    out2, rep2 = repair(holed, fill_holes=longest - 1)
    assert rep2["holes_skipped"] >= 1 and not rep2["watertight"]
    assert_clean(out2, closed=False)


def test_hole_filling_on_bunny_base():
    """The bunny's 5 base holes are filled: watertight, genus 0, outward."""
    mesh = load_shared("bunny_zipper")
    out, rep = repair(mesh, fill_holes=400)
    after = assert_clean(out)
    assert (
        rep["holes"] == 5
        and rep["holes_filled"] == 5
        and after["watertight"]
        and after["genus"] == 0
    )
    assert after["volume"] > 0


def test_filled_planar_hole_is_flat_and_minimal():
    """A planar hole is filled flat with the fewest faces: the area exactly the square's."""
    # a unit square grid with the middle 2x2 cells removed: the fill must lie in the plane
    n = 6
    x, y = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1).astype(float)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            if 2 <= i <= 2 and 2 <= j <= 2:
                continue
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [[a, b, c], [a, c, d]]
    holed = TriangleMesh(vertices=v, faces=np.array(faces))
    out, rep = repair(holed, fill_holes=8)
    assert rep["holes_filled"] == 1 and rep["fill_faces_added"] == 2
    after = assert_clean(out, closed=False)
    assert after["area"] == pytest.approx((n - 1) ** 2, rel=1e-12)  # no overlap, no fold
    assert after["boundary_loops"] == 1


def test_merge_tolerance():
    """Split vertices jittered by 1e-9 stay apart exactly and merge with a tolerance.

    With ``merge_tolerance=1e-6`` every copy merges and the kitten is closed again.
    """
    mesh = load_shared("kitten")
    rng = np.random.default_rng(5)
    soup = D.split_vertices(mesh, rng, 0.05)
    jitter = soup.vertices.copy()
    jitter[len(mesh.vertices) :] += rng.normal(
        scale=1e-9 * bbox_diagonal(mesh.vertices), size=jitter[len(mesh.vertices) :].shape
    )
    soup = TriangleMesh(vertices=jitter, faces=soup.faces)
    exact, rep0 = repair(soup)
    assert rep0["vertices_merged"] == 0 and not rep0["watertight"]
    assert_clean(exact)
    out, rep = repair(soup, merge_tolerance=1e-6)
    assert rep["vertices_merged"] == len(soup.vertices) - len(mesh.vertices)
    assert rep["merge_distance"] == pytest.approx(1e-6 * bbox_diagonal(soup.vertices))
    after = assert_clean(out, closed=True)
    assert after["genus"] == 1


def test_small_components():
    """Components under ``min_component`` of the faces go; ``keep_largest`` keeps the largest."""
    kitten = load_shared("kitten")
    arm = load_shared("armadillo")
    small = TriangleMesh(
        vertices=kitten.vertices * 3 + 400, faces=kitten.faces
    )  # 12100 faces vs 50000
    both = TriangleMesh(
        vertices=np.concatenate([arm.vertices, small.vertices]),
        faces=np.concatenate([arm.faces, small.faces + len(arm.vertices)]),
    )
    out, rep = repair(both, min_component=0.2)
    assert rep["components_removed"] == 1 and rep["component_faces_removed"] == len(kitten.faces)
    assert np.array_equal(out.faces, arm.faces) and np.array_equal(out.vertices, arm.vertices)
    out, rep = repair(both, min_component=0.1)
    assert rep["components_removed"] == 0 and len(out.faces) == len(both.faces)
    out, rep = repair(both, keep_largest=True)
    assert len(out.faces) == len(arm.faces) and rep["components"] == 1


def test_pymeshlab_chain_agrees_on_counts():
    """Repairing a damaged mug agrees with PyMeshLab's chain on every count and the volume."""
    mesh = load_shared("mug")
    rng = np.random.default_rng(9)
    bad = D.flip_faces(D.duplicate_faces(D.split_vertices(mesh, rng), rng), rng)
    out, rep = repair(bad)
    ref = pymeshlab_backend.repair(bad)
    assert len(out.faces) == len(ref.faces) == len(mesh.faces)
    ours, theirs = report(out), report(ref)
    for k in (
        "edges",
        "components",
        "boundary_edges",
        "genus",
        "watertight",
        "consistently_oriented",
    ):
        assert ours[k] == theirs[k], k
    assert abs(ours["volume"]) == pytest.approx(abs(theirs["volume"]), rel=1e-9)


def test_repair_is_idempotent_on_open3d_ball_pivoting():
    """Repair of Open3D's ball pivoting is clean, and a second repair changes nothing."""
    cloud = sampled_cloud("kitten", 20_000)
    diag = bbox_diagonal(cloud.points)
    bpa = open3d_backend.ball_pivoting(cloud, [0.01 * diag, 0.02 * diag])
    once, _ = repair(bpa)
    assert_clean(once)
    twice, rep = repair(once)
    assert np.array_equal(twice.faces, once.faces) and np.array_equal(twice.vertices, once.vertices)
    assert rep["faces_flipped"] == 0


def test_marching_cubes_output_passes_unchanged():
    """A torus by skimage's marching cubes passes through repair unchanged."""
    from skimage.measure import marching_cubes

    g = np.linspace(-1.5, 1.5, 48)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    torus = (np.sqrt(x**2 + y**2) - 0.9) ** 2 + z**2 - 0.35**2
    verts, faces, _, _ = marching_cubes(torus, 0.0, spacing=(g[1] - g[0],) * 3)
    mesh = TriangleMesh(vertices=verts, faces=faces)
    rep0 = report(mesh)
    assert (
        rep0["watertight"]
        and rep0["genus"] == 1
        and rep0["volume"] > 0
        and rep0["degenerate_faces"] == 0
    )
    out, rep = repair(mesh)
    assert np.array_equal(out.faces, mesh.faces) and np.array_equal(out.vertices, mesh.vertices)


def test_attributes_follow_vertices():
    """Vertex and face attributes follow their vertices and faces, split copies included."""
    cones = D.two_cones()
    cones.normals = cones.vertices / np.maximum(
        np.linalg.norm(cones.vertices, axis=1, keepdims=True), 1e-9
    )
    cones.colors = np.arange(len(cones.vertices) * 3, dtype=np.uint8).reshape(-1, 3)
    cones.attributes = {"q": np.arange(len(cones.vertices), dtype=np.float32)}
    cones.face_attributes = {"label": np.arange(len(cones.faces), dtype=np.int32)}
    out, _ = repair(cones)
    assert out.attributes["q"][-1] == 0 and tuple(out.colors[-1]) == tuple(cones.colors[0])
    assert np.array_equal(out.face_attributes["label"], np.arange(len(cones.faces)))


REPAIR_KEYS = [
    "vertices_in", "faces_in", "vertices_merged", "merge_distance", "degenerate_faces_removed",
    "duplicate_faces_removed", "unreferenced_vertices_removed", "non_manifold_edges",
    "non_manifold_faces_dropped", "non_manifold_faces_detached", "non_manifold_vertices_split",
    "vertices_added", "non_orientable_edges_cut", "non_orientable_faces_dropped", "faces_flipped",
    "components_reversed", "holes", "holes_filled", "holes_skipped", "fill_faces_added",
    "components_removed", "component_faces_removed", "vertices_out", "faces_out", "components",
    "boundary_loops", "watertight", "genus", "volume",
]  # fmt: skip


def test_parameters_strings_and_errors():
    """Parameters given as text are accepted, bad ones refused; the report's keys are fixed."""
    mesh = load_shared("kitten")
    out, rep = repair(
        mesh, merge_tolerance="exact", fill_holes="5", min_component="0", keep_largest="false"
    )
    assert np.array_equal(out.faces, mesh.faces) and rep["merge_distance"] == 0
    assert list(rep) == REPAIR_KEYS and list(repair(mesh)[1]) == REPAIR_KEYS
    for kw in (
        {"merge_tolerance": "abc"},
        {"merge_tolerance": -1},
        {"fill_holes": -2},
        {"fill_holes": "x"},
        {"fill_holes": 2.5},
        {"min_component": 1.5},
        {"keep_largest": "maybe"},
    ):
        with pytest.raises(ParameterError):
            repair(mesh, **kw)
    with pytest.raises(InputError):
        repair(sampled_cloud("kitten", 100))
    bad = TriangleMesh(
        vertices=np.array([[0, 0, 0], [1, 0, 0], [np.nan, 0, 0]]), faces=np.array([[0, 1, 2]])
    )
    with pytest.raises(InputError):
        repair(bad)


def test_stage_and_cli(tmp_path):
    """The repair stage and command: history, report, file output and exit codes."""
    from click.testing import CliRunner

    from recon_cli.cli.main import cli, main
    from recon_cli.io import read_ply, write_ply

    mesh = load_shared("mug")
    bad = D.flip_faces(mesh, np.random.default_rng(1))
    bad.history = ["earlier line"]
    res = apply_stage("repair", bad, {"fill_holes": 10})
    assert (
        res.output.history[0] == "earlier line"
        and res.output.history[-1].startswith("recon ")
        and "repair" in res.output.history[-1]
    )
    assert res.report["stage"] == "repair" and res.report["watertight"] is True
    assert isinstance(run_stage(bad), type(res))
    src = tmp_path / "bad.ply"
    dst = tmp_path / "fixed.ply"
    write_ply(bad, src)
    r = CliRunner().invoke(cli, ["repair", str(src), str(dst), "--json", "--fill-holes", "20"])
    assert r.exit_code == 0, r.output
    fixed = read_ply(dst)
    assert np.array_equal(fixed.faces, mesh.faces)
    r = CliRunner().invoke(cli, ["repair", str(src), str(dst), "--backend", "pymeshlab"])
    assert r.exit_code == 0, r.output
    assert report(read_ply(dst))["consistently_oriented"] and len(read_ply(dst).faces) == len(
        mesh.faces
    )
    with pytest.raises(ParameterError):
        run_stage(bad, backend="pymeshlab", keep_largest=True)
    with pytest.raises(ParameterError):
        run_stage(bad, backend="open3d")
    with pytest.raises(SystemExit) as exc:
        main(["-q", "repair", str(shared_path("mug")), str(dst), "--merge-tolerance", "nope"])
    assert exc.value.code == 2


soups = st.integers(min_value=3, max_value=30).flatmap(
    lambda n: st.tuples(
        st.lists(st.tuples(*[st.integers(-2, 2)] * 3), min_size=n, max_size=n),
        st.lists(st.tuples(*[st.integers(0, n - 1)] * 3), min_size=0, max_size=80),
        st.integers(0, 8),
        st.sampled_from([None, 0.05]),
    )
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(soups)
def test_repair_of_any_soup_is_manifold_and_oriented(soup):
    """Repair of any face soup is manifold and oriented; a clean result is a fixed point."""
    v, f, fill, tolerance = soup
    mesh = TriangleMesh(
        vertices=np.array(v, dtype=float).reshape(-1, 3),
        faces=np.array(f, dtype=np.int64).reshape(-1, 3),
    )
    out, rep = repair(mesh, fill_holes=fill, merge_tolerance=tolerance)
    after = assert_clean(out)
    assert rep["faces_out"] == len(out.faces) and after["faces"] == len(out.faces)
    # a clean output passes unchanged (split vertices coincide with their twins: that is not clean)
    if len(np.unique(out.vertices, axis=0)) == len(out.vertices):
        twice, _ = repair(out)
        assert np.array_equal(twice.faces, out.faces) and np.array_equal(
            twice.vertices, out.vertices
        )


def test_our_marching_cubes_output_passes_unchanged():
    """Our marching cubes output of a torus passes through repair unchanged."""
    from recon_cli.stages.mcubes import marching_cubes

    g = np.linspace(-1.5, 1.5, 40)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    torus = np.sqrt((np.sqrt(x**2 + y**2) - 0.9) ** 2 + z**2) - 0.35
    v, f, *_ = marching_cubes(torus, 0.0, spacing=g[1] - g[0], origin=(g[0],) * 3)
    mesh = TriangleMesh(vertices=v, faces=f)
    rep0 = report(mesh)
    assert (
        rep0["watertight"]
        and rep0["genus"] == 1
        and rep0["consistently_oriented"]
        and rep0["volume"] > 0
    )
    out, rep = repair(mesh)
    assert np.array_equal(out.faces, mesh.faces) and np.array_equal(out.vertices, mesh.vertices)


@pytest.mark.slow  # over 10 s on a cold numba cache of the ball-pivoting kernels
def test_our_ball_pivoting_output_keeps_every_face():
    """Our ball pivoting output keeps every face, in order; only unused points go."""
    from recon_cli.stages.ballpivot import ball_pivoting

    cloud = sampled_cloud("kitten", 10_000)
    mesh = TriangleMesh(vertices=cloud.points, faces=ball_pivoting(cloud.points, cloud.normals))
    rep0 = report(mesh)
    assert rep0["edge_manifold"] and rep0["vertex_manifold"] and rep0["consistently_oriented"]
    out, rep = repair(mesh)
    # only the points no face uses go: every triangle is kept, in order, with its winding
    assert rep["unreferenced_vertices_removed"] == rep0["unreferenced_vertices"]
    assert np.array_equal(out.vertices[out.faces], mesh.vertices[mesh.faces])
    assert_clean(out)
