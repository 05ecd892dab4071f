"""Marching cubes: ours (numba, asymptotic decider) vs ``skimage.measure.marching_cubes``."""

from __future__ import annotations

import numpy as np

from _util import measure, row


def metaballs(n: int, seed: int = 0) -> np.ndarray:
    """A smooth float32 field on n^3 with several blobs (a realistic surface, ~1% of cells cut)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(-1, 1, n, dtype=np.float32)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    f = np.full(X.shape, 1e9, np.float32)
    for _ in range(6):
        c = rng.uniform(-0.5, 0.5, 3).astype(np.float32)
        f = np.minimum(
            f,
            np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2)
            - np.float32(rng.uniform(0.2, 0.4)),
        )
    return f


def rows(quick: bool) -> list[dict]:
    """The section's rows: our marching cubes (and ``--method mt``) against skimage's, in-process.

    Metaballs at 128^3 and 256^3 (quick: 128^3), each in a forked child.
    """
    from skimage.measure import marching_cubes as sk_mc

    from recon_cli.stages.mcubes import marching_cubes

    marching_cubes(metaballs(16))  # compile (or load the numba cache) outside the timings
    out = []
    for n in [128] if quick else [128, 256]:
        f = metaballs(n)
        repeat = 3 if quick else 5
        ours = measure(lambda f=f: len(marching_cubes(f)[1]), repeat=repeat)
        ref = measure(lambda f=f: len(sk_mc(f, 0.0)[1]), repeat=repeat)
        ours_mt = measure(lambda f=f: len(marching_cubes(f, method="mt")[1]), repeat=repeat)
        out.append(
            row(
                "mcubes",
                f"metaballs {n}^3 (faces {ours['result']})",
                ours,
                "skimage",
                ref,
                note=f"skimage faces {ref['result']}; ours includes vertex normals",
            )
        )
        out.append(
            row("mcubes", f"--method mt {n}^3 (faces {ours_mt['result']})", ours_mt, "skimage", ref)
        )
    return out
