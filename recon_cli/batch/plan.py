"""Which inputs a batch runs.

Expanding files, folders and globs, output names, what is up to date.
"""

from __future__ import annotations

import glob
import json
import os
from collections.abc import Iterable
from pathlib import Path

from recon_cli.errors import InputError, ParameterError

# file suffixes taken from a folder given as an input
INPUT_SUFFIXES = (".ply", ".npz")
# suffixes an output can have (a grid is written as .npz, a 3D Tiles tileset as a .tiles
# folder, anything else as PLY)
OUTPUT_SUFFIXES = (".ply", ".npz", ".tiles")
SUMMARY_NAME = "batch.json"

STATUS_OK = "ok"
STATUS_FAILED = "failed"
STATUS_SKIPPED = "skipped"
STATUS_INTERRUPTED = "interrupted"

_GLOB_CHARS = set("*?[")


# ----------------------------------------------------------------------------- inputs and plan


def expand_inputs(inputs: Iterable[str | os.PathLike]) -> list[tuple[str, str | None]]:
    """Expand files, folders and glob patterns into a list of ``(path, problem)``.

    A folder gives its files ending in ``.ply`` or ``.npz`` (not recursive, sorted); a
    pattern (``*``, ``?``, ``[``; ``**`` recurses) gives its matching files, sorted; any
    other argument is taken as a file. ``problem`` is None for a usable path, or a
    one-line reason (no such file, a folder or pattern with nothing in it) so that the
    argument is reported as failed instead of silently dropped. The same file named twice
    is kept once.
    """
    out: list[tuple[str, str | None]] = []
    seen: set[str] = set()

    def add(path: str, problem: str | None = None) -> None:
        key = os.path.realpath(path) if problem is None else "\0" + path
        if key in seen:
            return
        seen.add(key)
        out.append((path, problem))

    for arg in inputs:
        arg = os.fspath(arg)
        if os.path.isdir(arg):
            found = sorted(
                str(p)
                for p in Path(arg).iterdir()
                if p.is_file() and p.suffix.lower() in INPUT_SUFFIXES
            )
            if not found:
                add(arg, "folder holds no .ply or .npz file")
            for p in found:
                add(p)
        elif os.path.exists(arg):
            add(arg)
        elif _GLOB_CHARS & set(arg):
            found = sorted(p for p in glob.glob(arg, recursive=True) if os.path.isfile(p))
            if not found:
                add(arg, "no file matches this pattern")
            for p in found:
                add(p)
        else:
            add(arg, "no such file")
    return out


def output_base(out_dir: str | os.PathLike, input_path: str) -> str:
    """``DIR/<stem>`` for ``input_path`` (the suffix is chosen when the output is known)."""
    return os.path.join(os.fspath(out_dir), Path(input_path).stem)


def existing_output(base: str) -> str | None:
    """The newest of ``base.ply`` / ``base.npz`` that exists, or None."""
    best, best_t = None, None
    for suffix in OUTPUT_SUFFIXES:
        p = base + suffix
        try:
            t = os.stat(p).st_mtime_ns
        except OSError:
            continue
        if best_t is None or t > best_t:
            best, best_t = p, t
    return best


def is_up_to_date(output: str | None, input_path: str, pipeline_path: str) -> bool:
    """True when ``output`` exists and is strictly newer than the input and the pipeline file."""
    if output is None:
        return False
    try:
        t_out = os.stat(output).st_mtime_ns
        t_in = os.stat(input_path).st_mtime_ns
        t_pipe = os.stat(pipeline_path).st_mtime_ns
    except OSError:
        return False
    return t_out > t_in and t_out > t_pipe


def plan_batch(
    pipeline_path: str | os.PathLike,
    inputs: Iterable[str | os.PathLike],
    out_dir: str | os.PathLike,
    force: bool = False,
) -> list[dict]:
    """One entry per input: ``{"input", "base", "action", ...}``.

    ``action`` is one of ``"run"``, ``"skip"`` (up to date, see :func:`is_up_to_date`) or
    ``"fail"`` (``error`` says why: a missing file, an empty folder or pattern).

    Raises
    ------
    InputError
        No inputs at all, or none usable (missing, an empty folder, a pattern matching nothing).
    ParameterError
        Two inputs that would write the same output name, or an output that would
        overwrite its input.
    """
    pipeline_path = os.fspath(pipeline_path)
    expanded = expand_inputs(inputs)
    if not expanded:
        raise InputError("no inputs given")
    if all(problem is not None for _, problem in expanded):
        # nothing to run at all (a missing or empty folder, a pattern matching nothing): bad input,
        # not a batch
        path, problem = expanded[0]
        assert problem is not None  # every input has one
        more = f" (and {len(expanded) - 1} more inputs, none usable)" if len(expanded) > 1 else ""
        raise InputError(problem + more, path)
    entries = []
    by_base: dict[str, str] = {}
    for path, problem in expanded:
        if problem is not None:
            entries.append(
                {
                    "input": path,
                    "base": None,
                    "action": "fail",
                    "error": f"{path}: {problem}",
                    "error_type": "InputError",
                }
            )
            continue
        base = os.path.abspath(output_base(out_dir, path))
        key = base
        if key in by_base:
            raise ParameterError(
                f"inputs {by_base[key]!r} and {path!r} would both write {base}.ply/.npz/.tiles "
                "(rename one or run them apart)"
            )
        by_base[key] = path
        for suffix in OUTPUT_SUFFIXES:
            if os.path.exists(base + suffix) and os.path.samefile(base + suffix, path):
                raise ParameterError(
                    f"output {base + suffix} would overwrite its input; choose another --out folder"
                )
        out = existing_output(base)
        if not force and is_up_to_date(out, path, pipeline_path):
            entries.append({"input": path, "base": base, "action": "skip", "output": out})
        else:
            entries.append({"input": path, "base": base, "action": "run"})
    return entries


def read_previous(summary_path: str) -> dict[str, dict]:
    """The records of an earlier run's summary file by input (empty when there is none)."""
    try:
        with open(summary_path, encoding="utf-8") as f:
            doc = json.load(f)
        return {
            r["input"]: r for r in doc.get("inputs", []) if isinstance(r, dict) and "input" in r
        }
    except (OSError, ValueError, TypeError, KeyError):
        return {}
