"""Build the ahead-of-time kernels (:mod:`recon_cli.aot`) with ``numba.pycc``.

Called by ``recon warmup`` after the warm-up has compiled (or loaded) every kernel for the
types recon uses: each public ``@njit`` kernel of :data:`~recon_cli.aot.MODULES`
is exported once per signature its dispatcher holds, from its own Python function (the
single source), into one extension module per kernel module, compiled for this CPU. Needs a
C compiler (pycc compiles numba's small C runtime into each module); without one, or when
pycc fails, the report says why and the kernels keep running JIT.
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
from recon_cli._kernels import numba_setup as _numba_setup  # noqa: F401  (cache directory, before numba)


def numba_type_key(t: Any) -> str | None:
    """The key :func:`recon_cli.aot.type_key` computes for a value of numba type ``t``.

    None for a type no ahead-of-time variant takes: records, lists, literals, omitted args...
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


def exports(
    module_name: str,
) -> tuple[list[tuple[str, Any, Any]], dict[str, dict[str, str]], list[str]]:
    """What to export from ``module_name``.

    (export name, signature, function) triples, the manifest's table ``{kernel: {signature key:
    export name}}``, and the kernels left to JIT (why).
    """
    from numba.core.registry import CPUDispatcher

    mod = importlib.import_module(module_name)
    entries: list[tuple[str, Any, Any]] = []
    table: dict[str, dict[str, str]] = {}
    skipped: list[str] = []
    for name, obj in sorted(vars(mod).items()):
        if (
            not isinstance(obj, CPUDispatcher)
            or obj.py_func.__module__ != module_name
            or name.startswith("_")
        ):
            continue
        if obj.targetoptions.get("parallel"):
            skipped.append(f"{name} (parallel)")
            continue
        for i, (args, cres) in enumerate(sorted(obj.overloads.items(), key=lambda kv: str(kv[0]))):
            key = "|".join(k or "?" for k in (numba_type_key(a) for a in args))
            if "?" in key.split("|") or "?" in key:
                skipped.append(f"{name}{tuple(str(a) for a in args)} (argument types)")
                continue
            export = f"{name}__{i}"
            # CompileResult's fields are set at run time (numba's own typing lacks them)
            entries.append((export, cres.signature, obj.py_func))  # type: ignore[attr-defined]
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


def build(
    modules: tuple[str, ...] = aot.MODULES,
    c_libraries: dict[str, str] | None = None,
    log: Callable[[str], None] | None = None,
    force: bool = False,
) -> dict:
    """Build the extensions of ``modules`` into :func:`~recon_cli.aot.build_dir`.

    The C ``c_libraries`` (name -> source) are built there too. Returns ``{"built": bool, "dir",
    "modules", "skipped", "seconds", "reason"}``: ``reason`` says why nothing was built (no
    compiler, pycc failed) or that the build was up to date.
    """
    t0 = time.perf_counter()
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
    with _quiet_pycc():
        from numba.pycc import CC
        from numba.pycc.platform import Toolchain

    parent = os.path.dirname(target)
    os.makedirs(parent, exist_ok=True)
    work = tempfile.mkdtemp(prefix=".build-", dir=parent)
    manifest: dict[str, Any] = {
        "fingerprint": os.path.basename(target),
        "modules": {},
        "libraries": {},
    }
    failures = []
    try:
        for name in modules:
            entries, table, skipped = exports(name)
            out["skipped"] += [f"{name}.{s}" for s in skipped]
            if not entries:
                continue
            ext = _extension_name(name)
            try:
                with _quiet_pycc():
                    cc = CC(ext, source_module=importlib.import_module(name))
                    cc.output_dir = work
                    cc.target_cpu = "host"
                    for export, sig, fn in entries:
                        cc.export(export, sig)(fn)
                    cc.compile()
            except Exception as exc:  # noqa: BLE001  (this module stays JIT; the report says why)
                failures.append(
                    f"{name}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                )
                continue
            manifest["modules"][name] = {
                "extension": ext,
                "file": cc.output_file,
                "functions": table,
            }
            out["modules"].append(name)
        for lib, source in (c_libraries or {}).items():
            try:
                tc = Toolchain()
                src = os.path.join(work, f"{lib}.c")
                with open(src, "w", encoding="utf-8") as fh:
                    fh.write(source)
                objs = tc.compile_objects([src], os.path.join(work, "obj"))
                file = f"lib{lib}.so"
                tc.link_shared(os.path.join(work, file), objs)
                manifest["libraries"][lib] = file
            except Exception as exc:  # noqa: BLE001
                failures.append(
                    f"{lib}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                )
        shutil.rmtree(os.path.join(work, "obj"), ignore_errors=True)
        for leaf in os.listdir(work):
            if leaf.endswith(".c"):
                os.remove(os.path.join(work, leaf))
        with open(os.path.join(work, aot.MANIFEST), "w", encoding="utf-8") as fh:
            json.dump(manifest, fh, indent=1, sort_keys=True)
        if os.path.exists(
            target
        ):  # a stale or partial build of this very state (or --force): ours replaces it
            shutil.rmtree(target, ignore_errors=True)
        os.replace(work, target)
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
