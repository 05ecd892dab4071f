"""A stage's peak memory, predicted before it runs; the run refused up front when it cannot fit.

Each heavy stage has a model: the process's peak resident bytes from its input's size (points,
faces, grid cells, read from the file's header where the format tells them) and the stage's
parameters, with figures calibrated on generated clouds (``bench/memory_model.py``,
``bench/calibration.md``: "Memory model"). Poisson's lives in its package
(``recon_cli.stages.poisson.memory``). A run whose prediction exceeds the execution's budget
(:meth:`recon_cli.execution.Execution.budget`) and that cannot go in slabs is refused with the
figure and the smallest ``--memory`` that would do; every stage's report says
``"memory": {"predicted_bytes": ..., "peak_bytes": ...}``.

This module imports nothing heavy.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from recon_cli.errors import ParameterError
from recon_cli.memory import AOT_BASE, JIT_BASE, TORCH_BASE

MIB = 1 << 20


def aot_base(module: str) -> int:
    """The base of a stage whose kernels are ``module``.

    ``AOT_BASE`` when they are built ahead of time (no numba loaded), else ``JIT_BASE``
    (:mod:`recon_cli.memory`).
    """
    from recon_cli import aot

    return AOT_BASE if module in aot.manifest().get("modules", {}) else JIT_BASE


@dataclass(frozen=True)
class Size:
    """What a stage's memory follows in its input.

    ``points``: a cloud's points or a mesh's vertices; ``faces``: a mesh's triangles; ``cells``: a
    grid's samples; ``lo``/``hi``: the bounding box when known (a LAS header's), else None.
    """

    points: int = 0
    faces: int = 0
    cells: int = 0
    lo: tuple[float, ...] | None = None
    hi: tuple[float, ...] | None = None


def _points_of(data: Any) -> Any:
    """A cloud's points or a mesh's vertices (None for anything else)."""
    pts = getattr(data, "points", None)
    return getattr(data, "vertices", None) if pts is None else pts


def size_of(data: Any) -> Size:
    """The size of a loaded cloud, mesh or grid."""
    from recon_cli.grid import Grid

    if isinstance(data, Grid):
        return Size(cells=int(data.sdf.size))
    pts = _points_of(data)
    faces = getattr(data, "faces", None)
    n = 0 if pts is None else len(pts)
    box = (tuple(map(float, pts.min(axis=0))), tuple(map(float, pts.max(axis=0)))) if n else None
    return Size(
        points=n,
        faces=0 if faces is None else len(faces),
        lo=box[0] if box else None,
        hi=box[1] if box else None,
    )


def size_from_header(path: str, format: str | None = None) -> Size | None:
    """The size of file ``path`` from its header alone: binary and ASCII PLY, LAS/LAZ, grid npz.

    None where the header does not say (other formats, ``-``, a file that is not readable:
    the reader then says why).
    """
    if path == "-" or format or not os.path.isfile(path):
        return None
    low = path.lower()
    try:
        if low.endswith(".ply"):
            from recon_cli.io.ply import parse_header

            with open(path, "rb") as f:
                head = f.read(1 << 16)
            ply, _ = parse_header(head, path)
            els = {e.name: e.count for e in ply.elements}
            return Size(points=int(els.get("vertex", 0)), faces=int(els.get("face", 0)))
        if low.endswith((".las", ".laz")):
            return _las_size(path)
        if low.endswith(".npz"):
            from recon_cli.io.npz import grid_shape

            return Size(cells=math.prod(grid_shape(path)))
    except Exception:  # noqa: BLE001 - the reader refuses the file in one line later
        return None
    return None


def _las_size(path: str) -> Size:
    with open(path, "rb") as f:
        head = f.read(375)
    if head[:4] != b"LASF" or len(head) < 227:
        raise ValueError("not LAS")
    import struct

    count = int.from_bytes(head[107:111], "little")
    if head[25] >= 4 and len(head) >= 255:
        count = int.from_bytes(head[247:255], "little") or count
    mx, nx, my, ny, mz, nz = struct.unpack_from("<6d", head, 179)
    return Size(points=count, lo=(nx, ny, nz), hi=(mx, my, mz))


# ---- the stages' models -------------------------------------------------------------------------
# bytes per unit of input (bench/calibration.md, Memory model: the stage's row; re-measured by
# bench/memory_model.py STAGE)
NORMALS_POINT_BYTES = 440
NORMALS_NEIGHBOUR_BYTES = 5
BALLPIVOT_POINT_BYTES = 790
SDF_BASE = 140 * MIB
SDF_POINT_BYTES = 250
SDF_FACE_BYTES = 340
SDF_CELL_BYTES = 105
SDF_MESH_CELL_BYTES = 12
MCUBES_CELL_BYTES = 7
SIMPLIFY_FACE_BYTES = 400
REPAIR_FACE_BYTES = 130
SMOOTH_FACE_BYTES = 200
FILTER_POINT_BYTES = 145
FILTER_OUTLIERS_BASE = 100 * MIB
FILTER_OUTLIERS_POINT_BYTES = 190
FIT_POINT_BYTES = 890
FIT_CELL_BYTES = 78


def _slabs(points: int, ex: Any, per_point: float, cap: int, local: Any) -> int | None:
    """The slabs a run takes.

    ``--partitions``; on local workers, the fewest their memory holds
    (:func:`recon_cli.slabs.plan.default_partitions`); in this process ``local()``. None: the
    slabs depend on a cluster not started yet (``--scheduler``).
    """
    if ex is None:
        return 1
    if ex.partitions is not None:
        return int(ex.partitions)
    if ex.workers is not None:
        from recon_cli.slabs.plan import default_partitions

        return default_partitions(points, ex.workers, ex.worker_memory(), per_point, cap)
    if ex.scheduler is not None:
        return None
    return int(local())


def _normals(size: Size, p: dict, ex: Any, data: Any) -> int | None:
    knn = p.get("knn") or 30
    one = int(JIT_BASE + (NORMALS_POINT_BYTES + NORMALS_NEIGHBOUR_BYTES * knn) * size.points)
    if p.get("backend", "native") != "native":
        return one
    from recon_cli.stages.normals.distributed import MAX_SLABS, slab_bytes_per_point, slab_count

    per = slab_bytes_per_point(knn)
    budget = ex.budget() if ex is not None else None
    slabs = _slabs(
        size.points, ex, per, MAX_SLABS, lambda: slab_count(None, size.points, None, knn, budget)[0]
    )
    if slabs is None:
        return None
    if slabs == 1 and not (ex is not None and ex.distributed):
        return one
    held = NORMALS_POINT_BYTES * size.points if data is not None else 0
    return int(JIT_BASE + held + per * size.points / slabs)


def _poisson(size: Size, p: dict, ex: Any, data: Any) -> int | None:
    from recon_cli.stages.poisson import memory as M

    depth, spn = int(p.get("depth", 8)), float(p.get("samples_per_node", 1.5))
    pts = _points_of(data)
    if pts is not None:
        tree = M.tree_of(pts, depth, float(p.get("scale", 1.1)), spn)
    else:
        tree = M.tree_estimate(size.points, depth, spn)
    if p.get("backend", "native") != "native":
        return M.one_piece_bytes(size.points, tree)
    from recon_cli.stages.poisson.slab import MAX_PARTITIONS
    from recon_cli.stages.poisson.stage import local_slabs

    per = M.slab_bytes(size.points, tree, 1) / max(size.points, 1)
    slabs = _slabs(
        size.points, ex, per, MAX_PARTITIONS, lambda: local_slabs(size.points, ex, depth)
    )
    if slabs is None:
        return None
    if slabs == 1 and not (ex is not None and ex.distributed):
        one = M.one_piece_bytes(size.points, tree)
        kept = M.heap_room(size.points, depth, None if ex is None else ex.budget())
        return M.kept_heap_bytes(one) if kept else one
    return M.slab_run_bytes(size.points, tree, slabs, in_memory=data is not None)


def _ballpivot(size: Size, p: dict, ex: Any, data: Any) -> int:
    base = aot_base("recon_cli.stages.ballpivot._kernel")
    return int(base + BALLPIVOT_POINT_BYTES * size.points)


def grid_cells(size: Size, p: dict) -> int | None:
    """The cells of the grid a stage samples (``resolution``/``voxel_size``, ``padding``)."""
    res = int(p.get("resolution") or 128)
    vs = p.get("voxel_size")
    if size.lo is None or size.hi is None:
        return None if vs else res**3
    ext = [h - lo for lo, h in zip(size.lo, size.hi, strict=True)]
    side = max(ext) * (1 + 2 * float(p.get("padding", 0.05)))
    h = float(vs) if vs else (side / res if side > 0 else 1.0)
    if not h > 0:
        return None
    pad = side - max(ext)
    return math.prod(max(1, math.ceil((e + pad) / h) + 1) for e in ext)


def _sdf(size: Size, p: dict, ex: Any, data: Any) -> int | None:
    cells = grid_cells(size, p)
    if cells is None:
        return None
    if size.faces:
        return int(SDF_BASE + SDF_FACE_BYTES * size.faces + SDF_MESH_CELL_BYTES * cells)
    return int(SDF_BASE + SDF_POINT_BYTES * size.points + SDF_CELL_BYTES * cells)


def _mcubes(size: Size, p: dict, ex: Any, data: Any) -> int:
    return int(aot_base("recon_cli.stages.mcubes._kernel") + MCUBES_CELL_BYTES * size.cells)


def _mesh(face_bytes: int, module: str | None) -> Callable[[Size, dict, Any, Any], int]:
    def model(size: Size, p: dict, ex: Any, data: Any) -> int:
        base = JIT_BASE if module is None else aot_base(module)
        return int(base + face_bytes * size.faces)

    return model


def _filter(size: Size, p: dict, ex: Any, data: Any) -> int:
    if p.get("outliers") is not None or p.get("radius_outliers") is not None:  # a k-d tree
        return int(FILTER_OUTLIERS_BASE + FILTER_OUTLIERS_POINT_BYTES * size.points)
    base = aot_base("recon_cli.stages.filter._kernel")
    return int(base + FILTER_POINT_BYTES * size.points)


def _fit_sdf(size: Size, p: dict, ex: Any, data: Any) -> int | None:
    cells = grid_cells(size, {"resolution": p.get("resolution") or 128, **p})
    if cells is None:
        return None
    return int(TORCH_BASE + FIT_POINT_BYTES * size.points + FIT_CELL_BYTES * cells)


#: stage -> ``f(size, params, execution, data) -> bytes`` (None: the input's size does not say)
MODELS: dict[str, Callable[[Size, dict, Any, Any], int | None]] = {
    "normals": _normals,
    "poisson": _poisson,
    "ballpivot": _ballpivot,
    "sdf": _sdf,
    "mcubes": _mcubes,
    "simplify": _mesh(SIMPLIFY_FACE_BYTES, None),
    "repair": _mesh(REPAIR_FACE_BYTES, "recon_cli.mesh._topology_kernel"),
    "smooth": _mesh(SMOOTH_FACE_BYTES, None),
    "filter": _filter,
    "fit-sdf": _fit_sdf,
}
# the stages that cut their work into slabs when the memory needs it (their model says how many)
SLABBED = ("normals", "poisson")


def predict(
    stage: str, size: Size, params: dict, execution: Any = None, data: Any = None
) -> int | None:
    """The peak resident bytes of the process running ``stage`` (None: no model, or unknown).

    ``params``: the stage's checked parameters (defaults filled in); ``execution``: the
    :class:`recon_cli.execution.Execution` (its slabs); ``data``: the loaded input when it is,
    for the figures a header does not give (Poisson's finest cells).
    """
    model = MODELS.get(stage)
    if model is None or (size.points == 0 and size.cells == 0):
        return None
    return model(size, params, execution, data)


def predict_in_force(stage: str, data: Any, params: dict) -> int | None:
    """:func:`predict` on loaded ``data`` under the execution in force, refused over its budget.

    The execution: :func:`recon_cli.execution.current`; ``params``: the stage's checked
    parameters, defaults filled in.

    Raises
    ------
    ParameterError
        The prediction exceeds the budget (:func:`check_fits`).
    """
    from recon_cli.execution import current

    ex = current()
    predicted = predict(stage, size_of(data), params, ex, data)
    check_fits(stage, predicted, ex.budget())
    return predicted


# past this the figure is no use (a voxel of 1e-300 asks for 1e900 bytes): no machine has it
HUGE_BYTES = 1 << 80


def check_fits(stage: str, predicted: int | None, budget: int | None, where: str = "") -> None:
    """Refuse a run whose ``predicted`` peak exceeds ``budget`` bytes, with the least that does.

    Raises
    ------
    ParameterError
        One line: the prediction and the smallest ``--memory`` that would do.
    """
    if predicted is None or budget is None or predicted <= budget:
        return
    # a grid of absurd size (a voxel of 1e-300) is past what a float prints: no machine has it
    head = f"{where}: " if where else ""
    if predicted > HUGE_BYTES:
        raise ParameterError(
            f"{head}{stage} needs more than {_size(HUGE_BYTES)} of memory: no machine has it"
        )
    need = -(-predicted // MIB)
    raise ParameterError(
        f"{head}{stage} needs about {_size(predicted)} of memory, more than the "
        f"{_size(budget)} it may use; give --memory {need}MiB or more (or a machine with it)"
    )


def _size(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB" if nbytes >= 2**30 else f"{nbytes / 2**20:.3g} MiB"


def peak_bytes() -> int | None:
    """The largest peak resident memory of this process and of its ended children (bytes)."""
    from recon_cli.memory import peak_mb

    own = peak_mb()
    kids = 0
    try:
        import resource
        import sys

        kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        kids = kids if sys.platform == "darwin" else kids * 1024
    except (ImportError, OSError):  # pragma: no cover - non-POSIX
        pass
    if own is None:
        return kids or None
    return max(int(own * MIB), int(kids))


def entry(predicted: int | None, peak: int | None = None) -> dict:
    """A report's ``memory`` entry (``peak``: now's, by default)."""
    return {"predicted_bytes": predicted, "peak_bytes": peak_bytes() if peak is None else peak}
