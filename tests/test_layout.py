"""The package's import rules (CONTRIBUTING.md, "Import rules"), checked on the source."""

from __future__ import annotations

import ast
from pathlib import Path

from shared_data import ROOT

PKG = ROOT / "recon_cli"


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        rel = p.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _imports(path: Path, top_level_only: bool):
    """(module, names, line) of every import of recon_cli in ``path``.

    (module imported, names imported, line) for every ``import``/``from`` of recon_cli in
    ``path``.
    """
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    for node in nodes:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module, [a.name for a in node.names], node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, [], node.lineno


def _package_of(module: str) -> str:
    return (
        module if MODULES.get(module, Path()).name == "__init__.py" else module.rpartition(".")[0]
    )


def test_no_module_imports_another_modules_private_name():
    """No module imports another module's private (underscore) name."""
    bad = []
    for mod, path in MODULES.items():
        own_pkg = _package_of(mod)
        for target, names, line in _imports(path, top_level_only=False):
            if not target.startswith("recon_cli"):
                continue
            for name in names:
                full = f"{target}.{name}"
                if full in MODULES:  # a module: private modules only from inside their own package
                    if (
                        name.startswith("_")
                        and _package_of(full) != own_pkg
                        and not own_pkg.startswith(_package_of(full))
                    ):
                        bad.append(
                            f"{path.relative_to(ROOT)}:{line}: imports private module {full}"
                        )
                elif name.startswith("_") and name != "__version__" and target != mod:
                    bad.append(f"{path.relative_to(ROOT)}:{line}: imports private name {full}")
    assert not bad, "\n".join(bad)


def test_no_import_cycle_at_module_level():
    """No import cycle among recon_cli's modules at module level."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for mod, path in MODULES.items():
        for target, names, _ in _imports(path, top_level_only=True):
            if not target.startswith("recon_cli"):
                continue
            deps = {target} | {f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES}
            graph[mod] |= {d for d in deps if d in MODULES and d != mod}
    # a package's __init__ importing its own submodules is how packages re-export: not a cycle
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if d.startswith(m + "."):
                continue
            if state.get(d) == 1:
                cycle = stack[stack.index(d) :] + [d]
                if not all(
                    b.startswith(a + ".") or a.startswith(b + ".")
                    for a, b in zip(cycle, cycle[1:], strict=False)
                ):
                    raise AssertionError("import cycle: " + " -> ".join(cycle))
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_no_import_cycle_through_function_level_imports():
    """No import cycle even counting the imports inside functions."""
    # imports inside functions too: a deferred import hides a cycle from Python, not from readers
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for mod, path in MODULES.items():
        for target, names, _ in _imports(path, top_level_only=False):
            deps = {target} | {f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES}
            graph[mod] |= {
                d
                for d in deps
                if d in MODULES
                and d != mod
                and not d.startswith(mod + ".")
                and not mod.startswith(d + ".")
            }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def strong(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for m in sorted(graph):
        if m not in index:
            strong(m)
    assert not cycles, f"modules importing each other: {cycles}"


def test_library_is_free_of_click_and_kernels_never_import_their_stage():
    """The library never imports click or the CLI, and kernels never import their stage."""
    for mod, path in MODULES.items():
        for target, _names, line in _imports(path, top_level_only=False):
            if not mod.startswith("recon_cli.cli"):
                assert target != "click" and not target.startswith("recon_cli.cli"), (
                    f"{path}:{line}"
                )
            if path.name.startswith("_") and path.name.endswith(("_kernel.py", "kernel.py")):
                stage = _package_of(mod)
                assert target != stage or stage == "recon_cli", (
                    f"{path}:{line}: a kernel imports its stage"
                )


def test_reference_libraries_only_in_backends():
    """Open3D and PyMeshLab are imported only in recon_cli.backends."""
    for mod, path in MODULES.items():
        if mod.startswith("recon_cli.backends"):
            continue
        for target, _, line in _imports(path, top_level_only=False):
            assert target.split(".")[0] not in ("open3d", "pymeshlab"), f"{path}:{line}"


# the size rules beside ruff's complexity limits (pyproject.toml): ruff counts branches and
# statements, not lines
MAX_FUNCTION_LINES = 120
MAX_MODULE_LINES = 1000
SIZE_RULES = {"C901", "PLR0912", "PLR0913", "PLR0915"}


def _ruff_lint() -> dict:
    """pyproject.toml's ``[tool.ruff.lint]`` table."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["ruff"]["lint"]


def _our_python_files() -> list[Path]:
    files = [
        p
        for top in ("recon_cli", "tests", "bench", "tools", "docs")
        for p in (ROOT / top).rglob("*.py")
    ]
    return [p for p in sorted(files) if "_build" not in p.parts]


def test_functions_and_modules_stay_short():
    """No function of our code is over MAX_FUNCTION_LINES lines, no module over MAX_MODULE_LINES."""
    long = []
    for path in _our_python_files():
        text = path.read_text(encoding="utf-8")
        rel = path.relative_to(ROOT)
        if len(text.splitlines()) > MAX_MODULE_LINES:
            long.append(f"{rel}: {len(text.splitlines())} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                size = node.end_lineno - first + 1
                if size > MAX_FUNCTION_LINES:
                    long.append(f"{rel}:{node.lineno}: {node.name} has {size} lines")
    assert not long, "split along the algorithm's steps:\n" + "\n".join(long)


def test_no_file_skips_a_lint_rule():
    """Lint selects the size rules, and no per-file ignore lets a file of ours skip a rule."""
    # the size and docstring rules hold for the library, the tests, the benchmarks, the
    # tools and the documentation's configuration alike
    lint = _ruff_lint()
    assert SIZE_RULES <= set(lint["select"]), lint["select"]
    assert lint.get("per-file-ignores", {}) == {}
