"""Build the ahead-of-time kernels (:mod:`recon_cli.aot`) with ``numba.pycc``.

Called by ``recon warmup`` after the warm-up has compiled (or loaded) every kernel for the
types recon uses: each public ``@njit`` kernel of :func:`modules_to_build`
is exported once per signature the warm-up gave it (:func:`signatures`, gathered from its
worker processes), from its own Python function (the single source), into one extension
module per kernel module, compiled for this CPU; the extensions are built in parallel
(:func:`compile_extension`, one job each). Needs a C compiler (pycc compiles numba's small
C runtime into each module); without one, or when pycc fails, the report says why and the
kernels keep running JIT.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

from recon_cli import aot
from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache dir, before numba)


def numba_type_key(t: Any) -> str | None:
    """The :func:`recon_cli.aot.type_key` of a value of numba type ``t``.

    None for a type no ahead-of-time variant takes: records, lists, literals, omitted arguments.
    """
    from numba.core import types
    from numba.np.numpy_support import as_dtype

    if isinstance(t, types.Literal):
        return None
    if isinstance(t, types.Array):
        if not isinstance(t.dtype, (types.Boolean, types.Integer, types.Float, types.Complex)):
            return None
        flags = ("" if t.mutable else "r") + ("" if t.aligned else "u")
        return f"{as_dtype(t.dtype).str}:{t.ndim}{t.layout}{flags}"
    if isinstance(t, types.Boolean):
        return "bool"
    if isinstance(t, (types.Integer, types.Float, types.Complex)):
        return str(t)
    if isinstance(t, (types.UniTuple, types.Tuple)):
        parts = [numba_type_key(s) for s in t.types]
        return None if None in parts else "(" + ",".join(parts) + ")"  # type: ignore[arg-type]
    if isinstance(t, types.NoneType):
        return "none"
    return None


def signatures(module_name: str) -> dict[str, list[tuple[Any, Any]]]:
    """The ``(argument types, return type)`` of every variant of ``module_name``'s kernels.

    Those its public kernels hold in this process (compiled or loaded from the cache): what a
    warm-up worker hands back so that another process can build them (numba types pickle).
    """
    from numba.core.registry import CPUDispatcher

    mod = importlib.import_module(module_name)
    out: dict[str, list[tuple[Any, Any]]] = {}
    for name, obj in sorted(vars(mod).items()):
        if (
            isinstance(obj, CPUDispatcher)
            and obj.py_func.__module__ == module_name
            and not name.startswith("_")
            and obj.overloads
        ):
            out[name] = [
                # CompileResult's fields are set at run time (numba's own typing lacks them)
                (tuple(args), cres.signature.return_type)  # type: ignore[attr-defined]
                for args, cres in obj.overloads.items()
            ]
    return out


def exports(
    module_name: str, sigs: dict[str, list[tuple[Any, Any]]] | None = None
) -> tuple[list[tuple[str, Any, Any]], dict[str, dict[str, str]], list[str]]:
    """What to export from ``module_name``.

    (export name, signature, function) triples, the manifest's table ``{kernel: {signature key:
    export name}}``, and the kernels left to JIT (why).

    ``sigs`` (as :func:`signatures` gives them, from any process) names the variants; by
    default those the kernels hold in this process.

    """
    from numba.core.registry import CPUDispatcher

    mod = importlib.import_module(module_name)
    if sigs is None:
        sigs = signatures(module_name)
    entries: list[tuple[str, Any, Any]] = []
    table: dict[str, dict[str, str]] = {}
    skipped: list[str] = []
    for name, variants in sorted(sigs.items()):
        obj = getattr(mod, name, None)
        if not isinstance(obj, CPUDispatcher):
            skipped.append(f"{name} (not a kernel of the module)")
            continue
        if obj.targetoptions.get("parallel"):
            skipped.append(f"{name} (parallel)")
            continue
        unique = {tuple(args): ret for args, ret in variants}
        for i, (args, ret) in enumerate(sorted(unique.items(), key=lambda kv: str(kv[0]))):
            key = "|".join(k or "?" for k in (numba_type_key(a) for a in args))
            if "?" in key.split("|") or "?" in key:
                skipped.append(f"{name}{tuple(str(a) for a in args)} (argument types)")
                continue
            export = f"{name}__{i}"
            entries.append((export, ret(*args), obj.py_func))
            table.setdefault(name, {})[key] = export
    return entries, table, skipped


@contextlib.contextmanager
def _quiet_pycc() -> Iterator[None]:
    """Pycc's pending-deprecation warning, for the length of the build only."""
    from numba.core.errors import NumbaPendingDeprecationWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NumbaPendingDeprecationWarning)
        yield


def compiler_problem() -> str | None:
    """Why no C compiler can build the extensions (None when one works)."""
    try:
        with _quiet_pycc():
            from numba.pycc.platform import external_compiler_works
    except ImportError as exc:  # setuptools missing
        return f"numba.pycc unavailable: {exc}"
    try:
        works = external_compiler_works()
    except Exception as exc:  # noqa: BLE001  (any failure of the probe means: no compiler)
        return f"no working C compiler: {exc}"
    return None if works else "no working C compiler (install gcc or clang)"


def _extension_name(module_name: str) -> str:
    return "recon_aot_" + module_name.replace(".", "_")


def compile_extension(
    name: str, work: str, sigs: dict[str, list[tuple[Any, Any]]] | None = None
) -> dict:
    """Build the extension of kernel module ``name`` into the folder ``work``.

    One job of :func:`build`, possibly in another process. Returns ``{"module", "entry"}`` (its
    manifest entry, None when nothing was exported), ``"skipped"`` and ``"failure"`` (None, or
    why pycc failed).
    """
    out: dict[str, Any] = {"module": name, "entry": None, "skipped": [], "failure": None}
    entries, table, skipped = exports(name, sigs)
    out["skipped"] = [f"{name}.{s}" for s in skipped]
    if not entries:
        return out
    ext = _extension_name(name)
    try:
        with _quiet_pycc():
            from numba.pycc import CC

            cc = CC(ext, source_module=importlib.import_module(name))
            cc.output_dir = work
            cc.target_cpu = "host"
            for export, sig, fn in entries:
                cc.export(export, sig)(fn)
            cc.compile()
    except Exception as exc:  # noqa: BLE001  (this module stays JIT; the report says why)
        out["failure"] = f"{name}: {_first_line(exc)}"
        return out
    out["entry"] = {"extension": ext, "file": cc.output_file, "functions": table}
    return out


def compile_library(lib: str, source: str, work: str) -> dict:
    """Compile the C ``source`` into ``work``/lib<lib>.so: ``{"library", "file", "failure"}``."""
    out: dict[str, Any] = {"library": lib, "file": None, "failure": None}
    try:
        with _quiet_pycc():
            from numba.pycc.platform import Toolchain

        tc = Toolchain()
        src = os.path.join(work, f"{lib}.c")
        with open(src, "w", encoding="utf-8") as fh:
            fh.write(source)
        objs = tc.compile_objects([src], os.path.join(work, f"obj-{lib}"))
        tc.link_shared(os.path.join(work, f"lib{lib}.so"), objs)
        out["file"] = f"lib{lib}.so"
    except Exception as exc:  # noqa: BLE001
        out["failure"] = f"{lib}: {_first_line(exc)}"
    return out


def _first_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"


def modules_to_build() -> tuple[str, ...]:
    """The kernel modules to build: :data:`~recon_cli.aot.MODULES`, then the stages' ones.

    The ``_kernel`` of each stage whose package sets ``AOT = True`` (its command's work is
    smaller than numba's start-up), in registry order.
    """
    import importlib

    from recon_cli.stages import STAGES

    out = list(aot.MODULES)
    for where in list(STAGES.values()):
        module = where.partition(":")[0] if isinstance(where, str) else ""
        if module and not module.startswith("<"):
            if getattr(importlib.import_module(module), "AOT", False):
                out.append(f"{module}._kernel")
    return tuple(out)


def build(
    modules: tuple[str, ...] | None = None,
    c_libraries: dict[str, str] | None = None,
    log: Callable[[str], None] | None = None,
    force: bool = False,
    sigs: dict[str, dict[str, list[tuple[Any, Any]]]] | None = None,
    submit: Callable[..., Any] | None = None,
    done: Callable[[], None] | None = None,
) -> dict:
    """Build the extensions of ``modules`` into :func:`~recon_cli.aot.build_dir`.

    ``modules`` defaults to :func:`modules_to_build`. The C ``c_libraries`` (name -> source)
    are built there too.

    ``sigs`` gives each module's variants (``{module: signatures(module)}``, gathered from the
    warm-up's workers); by default those its kernels hold in this process. With ``submit``
    (an executor's ``submit``) each extension and library is a job of its own, run there (in
    parallel); ``done`` is called as each job ends.

    Returns ``{"built": bool, "dir", "modules", "skipped", "seconds", "reason"}``: ``reason``
    says why nothing was built (no compiler, pycc failed) or that the build was up to date.

    """
    t0 = time.perf_counter()
    if modules is None:
        modules = modules_to_build()
    target = aot.build_dir()
    out: dict[str, Any] = {
        "built": False,
        "dir": target,
        "modules": [],
        "skipped": [],
        "reason": None,
    }
    if not aot.enabled():
        out["reason"] = "RECON_AOT=0"
        return out
    have = aot.manifest()
    wanted = set(modules) <= set(have.get("modules", {})) and set(c_libraries or {}) <= set(
        have.get("libraries", {})
    )
    if not force and wanted:
        out.update(
            built=True,
            reason="up to date",
            modules=list(have["modules"]),
            libraries=sorted(have["libraries"]),
        )
        return out
    problem = compiler_problem()
    if problem:
        out["reason"] = problem
        return out
    parent = os.path.dirname(target)
    os.makedirs(parent, exist_ok=True)
    work = tempfile.mkdtemp(prefix=".build-", dir=parent)
    manifest: dict[str, Any] = {
        "fingerprint": os.path.basename(target),
        "modules": {},
        "libraries": {},
    }
    try:
        failures = _compile_all(modules, c_libraries, sigs, work, submit, done, manifest, out)
        _install(work, manifest, target)
    finally:
        if os.path.exists(work):
            shutil.rmtree(work, ignore_errors=True)
    aot.reset()
    out["built"] = bool(manifest["modules"])
    out["libraries"] = sorted(manifest["libraries"])
    if failures:
        out["reason"] = "; ".join(failures)
        if log is not None:
            for f in failures:
                log(f"ahead-of-time build: {f}")
    out["seconds"] = time.perf_counter() - t0
    return out


def _compile_all(
    modules: tuple[str, ...],
    c_libraries: dict[str, str] | None,
    sigs: dict[str, dict[str, list[tuple[Any, Any]]]] | None,
    work: str,
    submit: Callable[..., Any] | None,
    done: Callable[[], None] | None,
    manifest: dict,
    out: dict,
) -> list[str]:
    """Compile every extension and C library into ``work``; the failures.

    The built ones are entered in ``manifest``; ``out``'s ``modules`` and ``skipped`` are filled in.
    """
    # the slowest first: a module's pycc build is seconds, the C library a fraction of one
    jobs: list[tuple[Callable[..., dict], tuple]] = [
        (compile_extension, (name, work, None if sigs is None else sigs.get(name, {})))
        for name in modules
    ]
    jobs += [(compile_library, (lib, source, work)) for lib, source in (c_libraries or {}).items()]
    failures = []
    for result in _run_jobs(jobs, submit, done):
        if result.get("failure"):
            failures.append(result["failure"])
        if "module" in result:
            out["skipped"] += result["skipped"]
            if result["entry"] is not None:
                manifest["modules"][result["module"]] = result["entry"]
        elif result.get("file"):
            manifest["libraries"][result["library"]] = result["file"]
    out["modules"] = [name for name in modules if name in manifest["modules"]]
    return failures


def _install(work: str, manifest: dict, target: str) -> None:
    """Clear ``work`` of the compilers' leftovers, write its manifest, rename it ``target``."""
    for leaf in os.listdir(work):
        path = os.path.join(work, leaf)
        if leaf.startswith("obj-"):
            shutil.rmtree(path, ignore_errors=True)
        elif leaf.endswith(".c"):
            os.remove(path)
    with open(os.path.join(work, aot.MANIFEST), "w", encoding="utf-8") as fh:
        json.dump(manifest, fh, indent=1, sort_keys=True)
    if os.path.exists(target):  # a stale or partial build of this very state (or --force)
        shutil.rmtree(target, ignore_errors=True)
    os.replace(work, target)


def _run_jobs(
    jobs: list[tuple[Callable[..., dict], tuple]],
    submit: Callable[..., Any] | None,
    done: Callable[[], None] | None,
) -> Iterator[dict]:
    """Each job's result, in turn here or through ``submit`` as they end.

    A job that died (e.g. with its worker process) gives a failure.
    """
    if submit is None:
        for fn, args in jobs:
            result = fn(*args)
            if done is not None:
                done()
            yield result
        return
    from concurrent.futures import as_completed

    futures = {}
    for fn, args in jobs:
        try:
            futures[submit(fn, *args)] = args[0]
        except Exception as exc:  # noqa: BLE001  (the executor is gone, e.g. a worker died)
            if done is not None:
                done()
            yield {"failure": f"{args[0]}: {_first_line(exc)}"}
    for future in as_completed(futures):
        try:
            result = future.result()
        except Exception as exc:  # noqa: BLE001  (a worker that died: this job stays undone)
            result = {"failure": f"{futures[future]}: {_first_line(exc)}"}
        if done is not None:
            done()
        yield result
