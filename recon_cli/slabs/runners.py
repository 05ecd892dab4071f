"""Jobs split into parts that keep a state between steps: where the parts' steps run.

A job (a distributed Poisson reconstruction, distributed normals) cuts its data into parts
(slabs), each with a state that lives where the part runs, and moves step by step: every
step applies one function to every part's state, mutating it, and returns a small message
per part to the coordinator, which combines them into the global values of the next step.

Two runners with one interface (``run(name, fn, args) -> messages``):

- :class:`LocalRunner`: every part in this process, one after another (tests, the library
  without a cluster);
- :class:`DaskRunner`: each part's state a Dask future on a worker, each step a task on it
  (Dask runs a part's steps where its state is: the states never move). With a spill folder
  (more parts than workers), a large state is written to a file after each step and read
  back by the next, so a worker holds only the part it runs; the file a step read goes as
  soon as the step has written its own, so the folder holds at most one file per part (a step
  that only reads its state, :func:`reads_only`, keeps the file it read). Each worker keeps
  the last part it ran in memory and runs it first at the next step (a snake order): with two
  parts a worker, half the writes and reads. Given each part's load, the parts are spread
  heaviest first, each to the least loaded worker. An argument that every
  part's task of a step shares (the coarse levels, their coefficients) then goes to a file
  once, the tasks carrying its path (:class:`Shared`). A step's task
  returns ``(state, message)``; the coordinator gathers the messages only. A worker that dies
  loses the states it held: Dask recomputes them from their lineage (every step again, from
  the part's first one, the coordinator's values being part of the tasks), on another
  worker; a step whose worker dies again (``allowed-failures``) fails the job.

Both advance an optional :class:`Overall` bar over the whole job (each phase its share,
a part's share as each part finishes: partitions done, and an estimate of the time left
over every phase) and note per step (phase): the wall time, the slowest part's time and the
largest part's peak memory (from the messages' ``seconds`` and ``peak_mb``), and the bytes the
messages and arguments carried (Dask's ``sizeof``).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable
from typing import Any


def note_phase(phases: dict, name: str, msgs: list[dict], wall: float, moved: int = 0) -> None:
    """Add a step's figures to ``phases[name]`` (steps of one name add up)."""
    p = phases.setdefault(
        name,
        {
            "seconds": 0.0,
            "part_seconds_max": 0.0,
            "cpu_seconds": 0.0,
            "peak_mb_max": 0.0,
            "bytes_moved": 0,
        },
    )
    p["seconds"] += wall
    p["part_seconds_max"] = max(
        p["part_seconds_max"], max((m.get("seconds", 0.0) for m in msgs), default=0.0)
    )
    p["cpu_seconds"] += sum(m.get("cpu_seconds", 0.0) for m in msgs)
    p["peak_mb_max"] = max(
        p["peak_mb_max"], max((m.get("peak_mb") or 0.0 for m in msgs), default=0.0)
    )
    p["bytes_moved"] += int(moved)


class Overall:
    """One progress bar over a whole job.

    Phase ``name`` is ``weights[name]`` of it (its first run only: a phase run again, such as a
    median's second round, adds nothing), a part's share added as each part finishes; the
    coordinator's own steps through :meth:`step`. ``bar`` is a :func:`recon_cli.progress.task` (its
    total the weights' sum over the phases that will run).
    """

    def __init__(self, bar: Any, weights: dict[str, float]):
        self.bar = bar
        self.weights = dict(weights)
        self.seen: set[str] = set()

    def claim(self, name: str) -> float:
        """The weight a phase's run adds (0 after its first run)."""
        if name in self.seen:
            return 0.0
        self.seen.add(name)
        return float(self.weights.get(name, 0.0))

    def advance(self, amount: float) -> None:
        """Move the bar by ``amount`` of the coordinator's own steps."""
        if amount > 0:
            self.bar.advance(amount)

    @contextlib.contextmanager
    def step(self, name: str):
        """A coordinator's step (one long call): the bar moves on an estimate meanwhile."""
        w = self.claim(name)
        if w > 0:
            self.bar.expect(w)
        yield
        self.advance(w)


def _sizeof(obj: Any) -> int:
    if "dask" not in sys.modules:  # a run in one process does not import Dask for this
        return state_bytes(obj)
    from dask.sizeof import sizeof

    return int(sizeof(obj))


def state_bytes(obj: Any, depth: int = 0, seen: set | None = None) -> int:
    """Bytes of the numpy arrays a part's state holds, each buffer once.

    What Dask's memory accounting sees of it: its own estimate of an object is a few hundred
    bytes. A view counts its base array, once however many views of it the state holds.
    """
    import numpy as np

    if seen is None:
        seen = set()
    if isinstance(obj, np.ndarray):
        base = obj
        while isinstance(base.base, np.ndarray):
            base = base.base
        if id(base) in seen:
            return 0
        seen.add(id(base))
        return int(base.nbytes)
    if depth > 4 or obj is None or isinstance(obj, (int, float, str, bool)):
        return 0
    if isinstance(obj, dict):
        return sum(state_bytes(v, depth + 1, seen) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(state_bytes(v, depth + 1, seen) for v in obj)
    if hasattr(obj, "__dict__"):
        return sum(state_bytes(v, depth + 1, seen) for v in vars(obj).values())
    return 0


# a step's own peak memory is measured from its start (the high-water mark reset) in a worker
# process; in the coordinating process the mark stays the whole run's (what the user sees)
_OWN_PEAK = {"reset": True}


def timed(fn: Callable) -> Callable:
    """A step that also reports its wall and CPU seconds and the process's peak memory."""
    from recon_cli.memory import peak_mb, reset_peak

    def step(state: Any, *args: Any) -> dict:
        if _OWN_PEAK["reset"]:
            reset_peak()
        t0, c0 = time.perf_counter(), time.process_time()
        msg = fn(state, *args) or {}
        msg["seconds"] = time.perf_counter() - t0
        msg["cpu_seconds"] = time.process_time() - c0
        msg["peak_mb"] = peak_mb()
        msg["pid"] = os.getpid()
        return msg

    step.__name__ = fn.__name__
    step.__qualname__ = fn.__qualname__
    step.__doc__ = fn.__doc__
    step.__module__ = fn.__module__
    return step


class LocalRunner:
    """Every part in this process, one after another.

    With ``spill_dir``, a part's state goes to a file there after each step and is read back by
    its next step, so the process holds one part's state at a time (out of core); the parts run
    in a snake order (the last part of a step first at the next one), so the state in memory is
    the one that runs next. Small states stay in memory as long as those held together come to
    less than ``spill_bytes``: with many parts, small ones each, they added up past the slab's
    own state the memory plan counts.
    """

    def __init__(
        self,
        states: list,
        progress: Any = None,
        label: str = "parts",
        overall: Overall | None = None,
        spill_dir: str | None = None,
        spill_bytes: int | None = None,
    ):
        self.states: list[Any] = list(states)
        self.phases: dict[str, dict] = {}
        self.progress = progress
        self.label = label
        self.overall = overall
        self.spill_dir = spill_dir
        self.spill_bytes = SPILL_BYTES if spill_bytes is None else int(spill_bytes)
        self.round = 0
        self.spilled_bytes = 0
        self.held: dict[int, int] = {}  # the bytes of each part's state in memory, but the next

    def run(self, name: str, fn: Callable, args: Callable[[int], tuple]) -> list[dict]:
        """Step ``name``: ``fn(state, *args(k))`` on every part ``k``; returns their messages."""
        from recon_cli.progress import task

        t0 = time.perf_counter()
        self.round += 1
        n = len(self.states)
        out: list[Any] = [None] * n
        spilled = self.spilled_bytes
        order = list(range(n)) if self.round % 2 else list(range(n - 1, -1, -1))
        share = self.overall.claim(name) / max(n, 1) if self.overall else 0.0
        writes = not getattr(fn, "reads_only", False)
        old = _OWN_PEAK["reset"]
        _OWN_PEAK["reset"] = False
        try:
            with task(self.progress, f"{self.label}: {name}", total=n) as bar:
                for pos, k in enumerate(order):
                    spill = None
                    self.held.pop(k, None)
                    if self.spill_dir is not None and writes and pos < n - 1:
                        room = self.spill_bytes - sum(self.held.values())
                        spill = (self._path(k), max(room, 0))
                    before = self.states[k]
                    self.states[k], out[k] = _step(before, fn, args(k), spill)
                    now = self.states[k]
                    if self.spill_dir is not None and pos < n - 1 and not isinstance(now, Spilled):
                        self.held[k] = _sizeof(now)
                    if isinstance(now, Spilled) and spill is not None:
                        self.spilled_bytes += os.path.getsize(now.path)
                    elif isinstance(before, Spilled) and not isinstance(now, Spilled):
                        os.unlink(before.path)  # the state is in memory again
                    bar.advance(1)
                    if share and self.overall is not None:
                        self.overall.advance(share)
        finally:
            _OWN_PEAK["reset"] = old
        # the bytes a step moves here are those its states wrote to their files
        note_phase(self.phases, name, out, time.perf_counter() - t0, self.spilled_bytes - spilled)
        return out

    def _path(self, k: int) -> str:
        assert self.spill_dir is not None
        return os.path.join(self.spill_dir, f"{self.label}-{k}.state")

    def close(self) -> None:
        """Let go of the parts' states (and their files)."""
        for s in self.states:
            if isinstance(s, Spilled):
                with contextlib.suppress(OSError):
                    os.unlink(s.path)
        self.states = []


def map_tasks(
    client: Any,
    fn: Callable,
    items: list[tuple],
    progress: Any = None,
    label: str = "tasks",
    done: Callable[[], None] | None = None,
) -> list[Any]:
    """``fn(*item)`` for each item, on the ``client``'s cluster or in this process, in order.

    Tasks that keep no state (a chunk's scan or sort). ``done()`` is called as each one ends.
    """
    from recon_cli.progress import task

    out: list[Any] = [None] * len(items)
    with task(progress, label, total=len(items)) as bar:
        if client is None:
            old, _OWN_PEAK["reset"] = _OWN_PEAK["reset"], False  # the process's mark is the run's
            try:
                for i, item in enumerate(items):
                    out[i] = fn(*item)
                    bar.advance(1)
                    if done is not None:
                        done()
            finally:
                _OWN_PEAK["reset"] = old
            return out
        from distributed import as_completed

        futs = [client.submit(fn, *item, pure=False) for item in items]
        index = {f.key: i for i, f in enumerate(futs)}
        for f in as_completed(futs):
            out[index[f.key]] = f.result()
            bar.advance(1)
            if done is not None:
                done()
    return out


# a state at least this large is written to its file between steps when the runner spills
SPILL_BYTES = 64 << 20


def reads_only(fn: Callable) -> Callable:
    """Mark a step that does not change its state: a spilled state is not written again."""
    fn.reads_only = True  # type: ignore[attr-defined]
    return fn


# with a spill folder, an argument all parts of a step share, this large or more, is written
# there once and each task reads it when it runs: Dask pickles a task's arguments into the
# task, so the coordinator held 48 copies of the coarse levels (8.5 GiB at 20M points, depth
# 12) and each worker those of the tasks queued on it (past its 4 GiB limit)
SHARED_BYTES = 16 << 20


class Spilled:
    """A part's state written to ``path`` (pickled) between two steps."""

    def __init__(self, path: str):
        self.path = path


class Shared:
    """An argument every part's task of a step shares, written to ``path`` (pickled) once."""

    def __init__(self, path: str):
        self.path = path


def _resolve(arg: Any) -> Any:
    import pickle

    if isinstance(arg, Shared):
        with open(arg.path, "rb") as f:
            return pickle.load(f)
    return arg


def _step(state: Any, fn: Callable, args: tuple, spill: tuple | None = None) -> tuple[Any, dict]:
    import pickle

    from recon_cli.memory import release_free_heap

    args = tuple(_resolve(a) for a in args)
    live = not isinstance(state, Spilled)
    spilled = state
    if not live:
        with open(state.path, "rb") as f:
            state = pickle.load(f)
    msg = fn(state, *args)
    if getattr(fn, "reads_only", False):
        # the state is as it was: its file (or the live object) stays the state
        if not live:
            del state
            release_free_heap()  # the copy read for this step goes (as below)
        return spilled, msg
    if spill is not None and _sizeof(state) >= spill[1]:
        path = spill[0]
        with open(path + ".tmp", "wb") as f:
            pickle.dump(state, f, protocol=5)
        os.replace(path + ".tmp", path)
        if live and hasattr(state, "__dict__"):
            # the previous round's key holds this object (mutated by the step) until the round
            # ends: its contents go now (a lost state is recomputed from the first step)
            vars(state).clear()
        state = Spilled(path)
        # its arrays are freed: their heap goes back to the system, else the holes the states
        # read back leave (glibc) kept 4M points in 32 slabs at 1.8-2.1 GB against 1.03 now
        release_free_heap()
    return state, msg


def _spread(n: int, workers: list, loads: list[float] | None) -> list:
    """The worker of each of ``n`` parts.

    In turn; with ``loads``, the heaviest first, each to the least loaded worker (the
    longest-processing-time rule: a step's wall is its busiest worker's).
    """
    if not workers:
        return [None] * n
    if loads is None:
        return [workers[k % len(workers)] for k in range(n)]
    total = dict.fromkeys(workers, 0.0)
    out: list = [None] * n
    for k in sorted(range(n), key=lambda k: (-loads[k], k)):
        w = min(workers, key=lambda w: (total[w], w))
        out[k] = w
        total[w] += loads[k]
    return out


def _first(pair: tuple) -> Any:
    return pair[0]


def _second(pair: tuple) -> Any:
    return pair[1]


def _start(x: Any) -> Any:
    # a copy: the task's argument is not the state a recomputation would start from
    import copy

    return copy.deepcopy(x)


def register_dask_sizes(*kinds: type) -> None:
    """Tell Dask the sizes of states of these types: their arrays' bytes (:func:`state_bytes`).

    Dask's own estimate of an object is a few hundred bytes; its spill and memory limits need the
    arrays'. Does nothing unless Dask is already imported, so a run in one process never imports
    it: a worker process has imported Dask before it unpickles a step (which imports the state's
    module, whose import calls this), and :class:`DaskRunner` registers its states in the client.
    """
    if "dask" not in sys.modules:
        return
    from dask.sizeof import sizeof

    for kind in kinds:
        sizeof.register(kind)(state_bytes)


class DaskRunner:
    """Each part's state on a Dask worker (module docstring)."""

    def __init__(
        self,
        client: Any,
        states: list,
        progress: Any = None,
        label: str = "parts",
        overall: Overall | None = None,
        spill_dir: str | None = None,
        spill_bytes: int = SPILL_BYTES,
        shared_bytes: int = SHARED_BYTES,
        loads: list[float] | None = None,
    ):
        self.client = client
        register_dask_sizes(*{type(s) for s in states if type(s).__module__ != "builtins"})
        # with more parts than workers, a worker would hold all its parts' states: each large
        # state goes to a file in spill_dir (shared by the workers) between its steps instead
        self.spill_dir = spill_dir
        self.spill_bytes = spill_bytes
        self.shared_bytes = shared_bytes
        self.phases: dict[str, dict] = {}
        self.progress = progress
        self.label = label
        self.overall = overall
        self.token = os.urandom(4).hex()
        self.round = 0
        # per part, the round whose file holds its state (None: the state is not in a file)
        self.files: list[int | None] = [None] * len(states)
        # the parts whose state a worker kept in memory after the last step that wrote them
        self.live = set(range(len(states)))
        workers = sorted(client.scheduler_info().get("workers", {}))
        placed = _spread(len(states), workers, loads)
        self.states = []
        for k, s in enumerate(states):
            # spread the parts over the workers; a part's later steps follow its state
            where = [placed[k]] if workers else None
            self.states.append(
                client.submit(
                    _start,
                    s,
                    key=f"{label}-{self.token}-{k}-start",
                    workers=where,
                    allow_other_workers=True,
                    pure=False,
                )
            )

    def _result(self, future: Any, k: int, name: str) -> Any:
        """A step's result; its own error as it is, a worker that died as one line.

        Raises :class:`~recon_cli.errors.StageFailed` when every worker that ran part ``k``'s
        step died (killed, or over its memory limit): the scheduler gave up on it.
        """
        from distributed import KilledWorker

        from recon_cli.errors import StageFailed

        try:
            return future.result()
        except KilledWorker as exc:
            raise StageFailed(
                f"{self.label}: the worker processes running part {k + 1}'s {name} step died "
                f"{exc.allowed_failures + 1} times (killed or out of memory): give the workers "
                "more memory (--memory) or cut the cloud into more slabs (--partitions)"
            ) from None

    def run(self, name: str, fn: Callable, args: Callable[[int], tuple]) -> list[dict]:
        """Step ``name``: ``fn(state, *args(k))`` on every part ``k``; returns their messages."""
        import dask
        from distributed import as_completed

        from recon_cli.progress import task

        t0 = time.perf_counter()
        self.round += 1
        c = self.client
        pairs, states, msgs_f = [], [], []
        moved = 0
        given = [args(k) for k in range(len(self.states))]
        moved += sum(_sizeof(a) for a in given)
        given = self._share(given)
        writes = not getattr(fn, "reads_only", False)
        order, keep = self._plan(writes)
        submitted: dict[int, tuple] = {}
        for pos, k in enumerate(order):
            a = given[k]
            tag = f"{self.label}-{self.token}-{k}-{self.round}-{name}"
            # the arguments go in the task (a recomputed part reads them again from its
            # lineage), however large: Dask's warning of large graphs is not for this
            path = self._spill_path(k, self.round)
            spill = None if path is None or k in keep else (path, self.spill_bytes)
            with dask.config.set({"distributed.admin.large-graph-warning-threshold": "1TiB"}):
                p = c.submit(
                    _step,
                    self.states[k],
                    fn,
                    a,
                    spill,
                    key=f"{tag}-step",
                    pure=False,
                    priority=len(order) - pos,
                )
            # the message goes as soon as its step is done, before the worker's next step
            top = len(order) + 1
            submitted[k] = (
                p,
                c.submit(_first, p, key=f"{tag}-state", pure=False, priority=top),
                c.submit(_second, p, key=f"{tag}-msg", pure=False, priority=top),
            )
        for k in range(len(self.states)):
            pairs.append(submitted[k][0])
            states.append(submitted[k][1])
            msgs_f.append(submitted[k][2])
        submitted = {}
        if writes:
            self.live = keep
        index = {f.key: k for k, f in enumerate(msgs_f)}
        out: list[Any] = [None] * len(msgs_f)
        share = self.overall.claim(name) / max(len(msgs_f), 1) if self.overall else 0.0
        with task(self.progress, f"{self.label}: {name}", total=len(msgs_f)) as bar:
            for f in as_completed(msgs_f):
                k = index[f.key]
                out[k] = self._result(f, k, name)
                # the part's previous state is released now, not when the round ends, and
                # its file goes: with every part spilled, the folder holds one round, not three
                # (a state lost later is recomputed from the part's first step, which writes
                # its files again)
                self.states[k] = states[k]
                if writes:
                    self._replaced(k)
                bar.advance(1)
                if share and self.overall is not None:
                    self.overall.advance(share)
        moved += sum(_sizeof(m) for m in out)
        self.states = states
        for f in pairs + msgs_f:
            f.release()
        # the files a recomputed part's earlier steps wrote again stay until close(): a part
        # lost to a dead worker is recomputed at once, in the background, reading each file its
        # previous step wrote (removing them here raced with it: FileNotFoundError in a test)
        note_phase(self.phases, name, out, time.perf_counter() - t0, moved)
        return out

    def _plan(self, writes: bool) -> tuple[list[int], set[int]]:
        """The step's order of the parts and those whose new state stays in memory.

        Each worker runs first the part whose state it kept in memory and keeps the last one it
        runs (a step that only reads keeps the same ones): half the states' writes and reads of
        a folder with two parts a worker, while a worker still holds one state at a time.
        """
        n = len(self.states)
        order = sorted(range(n), key=lambda k: (k not in self.live, k))
        if self.spill_dir is None:
            return order, set(range(n))
        if not writes:
            return order, self.live
        from distributed import wait

        wait(self.states)  # the first steps' states may still be on their way to their workers
        holders = self.client.who_has(self.states)
        last: dict[Any, int] = {}
        for k in order:
            # where the part's state is now (Dask may have recomputed it elsewhere)
            where = holders.get(self.states[k].key) or ()
            last[tuple(sorted(where))[:1]] = k
        return order, set(last.values())

    def _share(self, given: list[tuple]) -> list[tuple]:
        """The parts' arguments, each large one they all share replaced by its :class:`Shared`.

        Only with a spill folder (the files are removed by :meth:`close`: a part recomputed from
        its lineage reads them again).
        """
        import pickle

        if self.spill_dir is None or len(given) < 2:
            return given
        out = [list(a) for a in given]
        for i, x in enumerate(given[0]):
            if not all(len(a) > i and a[i] is x for a in given):
                continue
            if _sizeof(x) < self.shared_bytes:
                continue
            path = os.path.join(self.spill_dir, f"{self.label}-{self.token}-{self.round}-{i}.arg")
            with open(path + ".tmp", "wb") as f:
                pickle.dump(x, f, protocol=5)
            os.replace(path + ".tmp", path)
            ref = Shared(path)
            for a in out:
                a[i] = ref
        return [tuple(a) for a in out]

    def _replaced(self, k: int) -> None:
        """Part ``k``'s step of this round is done: the file it read is no longer its state."""
        if self.spill_dir is None:
            return
        old = self.files[k]
        path = self._spill_path(k, self.round)
        self.files[k] = self.round if path is not None and os.path.exists(path) else None
        if old is not None and old != self.files[k]:
            old_path = self._spill_path(k, old)
            if old_path is not None:
                with contextlib.suppress(OSError):
                    os.unlink(old_path)

    def _spill_path(self, k: int, rnd: int) -> str | None:
        if self.spill_dir is None:
            return None
        return os.path.join(self.spill_dir, f"{self.label}-{self.token}-{k}-{rnd}.state")

    def _unspill(self, last: int) -> None:
        """Remove the states' files of rounds up to ``last``."""
        if self.spill_dir is None:
            return
        head = f"{self.label}-{self.token}-"
        for name in os.listdir(self.spill_dir):
            if name.startswith(head) and name.endswith(".state"):
                k, rnd = (int(x) for x in name[len(head) : -len(".state")].rsplit("-", 1))
                if rnd <= last and not (k < len(self.files) and self.files[k] == rnd):
                    with contextlib.suppress(OSError):
                        os.unlink(os.path.join(self.spill_dir, name))

    def close(self) -> None:
        """Let go of the parts' states (and their files)."""
        self.files = []
        self._unspill(self.round)
        if self.spill_dir is not None:
            head = f"{self.label}-{self.token}-"
            for name in os.listdir(self.spill_dir):
                if name.startswith(head) and name.endswith(".arg"):
                    with contextlib.suppress(OSError):
                        os.unlink(os.path.join(self.spill_dir, name))
        for f in self.states:
            f.release()
        self.states = []
