"""The pieces' boxes and reach (:mod:`recon_cli.stages.poisson.pieces`) against brute force."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from recon_cli.stages.poisson.pieces import piece_boxes, piece_reach, vertex_labels


@given(seed=st.integers(0, 2**31 - 1), nf=st.integers(1, 60), offset=st.sampled_from([0.0, 1e6]))
@settings(max_examples=40, deadline=None)
def test_boxes_labels_and_reach_as_a_brute_force(seed, nf, offset):
    """Piece boxes, vertex labels and reach agree with a brute force on random soups."""
    rng = np.random.default_rng(seed)
    nv, n = 50, 4
    verts = rng.normal(size=(nv, 3)) + offset
    faces = rng.integers(0, nv, (nf, 3))
    labels = rng.integers(0, n, nf)
    count, lo, hi = piece_boxes(verts, faces, labels, n)
    vlab = vertex_labels(faces, labels, nv)
    for p in range(n):
        mine = faces[labels == p].reshape(-1)
        assert count[p] == np.count_nonzero(labels == p)
        if len(mine):
            assert np.array_equal(lo[p], verts[mine].min(axis=0))
            assert np.array_equal(hi[p], verts[mine].max(axis=0))
        else:
            assert np.all(lo[p] == np.inf) and np.all(hi[p] == -np.inf)
    # a vertex takes the label of one of its faces
    for v in range(nv):
        on = labels[np.any(faces == v, axis=1)]
        assert (vlab[v] == -1) if not len(on) else (vlab[v] in on)
    targets = rng.normal(size=(rng.integers(0, 20), 3)) + offset
    ids = rng.integers(0, n, nv)
    far = piece_reach(verts, ids, n, targets)
    for p in range(n):
        pv = verts[ids == p]
        if not len(pv):
            assert far[p] == -np.inf
        elif not len(targets):
            assert far[p] == np.inf
        else:
            d = np.linalg.norm(pv[:, None] - targets[None], axis=2).min(axis=1).max()
            assert np.isclose(far[p], d, rtol=1e-12, atol=1e-9)
