"""The house rules of imports, checked by walking every module's syntax tree.

1. The core never imports the app: no module of ``d2f_core`` imports ``app`` (the app
   depends on the core, never the other way round).
2. No module of ``d2f_core`` or ``app`` imports another module's private (underscore) names,
   neither ``from x import _name`` nor ``x._name`` on an imported module. A helper that two
   modules need gets a public name in one home. (Tests are white-box: they may reach the
   private helpers of the module they test, and are not walked.)
3. No import circle: the graph of which module imports which (function-level imports
   included) has no cycle in ``d2f_core`` or ``app``.
4. Inference apart from training and benchmarks: no inference module (the pipeline, the
   renderer, the networks, io, depth, the CLI and the app) imports ``d2f_core.train`` or
   ``d2f_core.bench``, directly or through another module.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: package name -> its folder (``assets/`` is installed as ``d2f_core.assets``)
PACKAGES = {"d2f_core": ROOT / "d2f_core", "app": ROOT / "app", "d2f_core.assets": ROOT / "assets"}

#: Private imports that remain, each with its reason (none now: every shared helper has a
#: public name in one home). ``test_known_exceptions_still_exist`` fails once one is gone,
#: so the list only shrinks.
KNOWN: set[tuple[str, str, str]] = set()


@dataclass(frozen=True)
class Problem:
    module: str
    line: int
    what: str
    target: str = ""
    name: str = ""

    def __str__(self) -> str:
        return f"{self.module}:{self.line}: {self.what}"


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def project_modules() -> dict[str, Path]:
    """Every module of the shipped packages (dotted name -> file); sub-folders count when
    they hold an ``__init__.py``."""
    out: dict[str, Path] = {}

    def walk(name: str, folder: Path) -> None:
        for path in sorted(folder.glob("*.py")):
            out[name if path.stem == "__init__" else f"{name}.{path.stem}"] = path
        for sub in sorted(folder.iterdir()):
            if sub.is_dir() and (sub / "__init__.py").is_file():
                walk(f"{name}.{sub.name}", sub)

    for name, folder in PACKAGES.items():
        walk(name, folder)
    return out


def _absolute(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    parts = module.split(".") if is_package else module.split(".")[:-1]
    parts = parts[: len(parts) - (node.level - 1)]
    return ".".join(parts + ([node.module] if node.module else []))


def import_problems(module: str, source: str, modules: set[str], is_package: bool = False):
    """The import-rule problems of one module's ``source`` (``modules``: the project's)."""
    tree = ast.parse(source)
    problems: list[Problem] = []
    aliases: dict[str, str] = {}  # local name -> project module it is bound to
    in_core = module == "d2f_core" or module.startswith("d2f_core.")

    def check_target(target: str, line: int, private: bool = True) -> None:
        if in_core and (target == "app" or target.startswith("app.")):
            problems.append(Problem(module, line, f"the core imports the app ({target})"))
        if private and any(_private(part) for part in target.split(".")) and target in modules:
            problems.append(
                Problem(module, line, f"imports a private module {target}", target, "(module)")
            )

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                check_target(a.name, node.lineno)
                if a.asname:
                    aliases[a.asname] = a.name
                else:
                    top = a.name.split(".")[0]
                    aliases[top] = top
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(module, is_package, node)
            check_target(base, node.lineno)
            base_private = any(_private(part) for part in base.split("."))
            for a in node.names:
                full = f"{base}.{a.name}"
                if full in modules:  # a module imported by name
                    check_target(full, node.lineno, private=not base_private)
                    aliases[a.asname or a.name] = full
                elif _private(a.name) and base in modules and base != module:
                    problems.append(
                        Problem(module, node.lineno, f"imports {a.name} from {base}", base, a.name)
                    )
        elif (
            isinstance(node, ast.Call)
            and in_core
            and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and str(node.args[0].value).split(".")[0] == "app"
        ):
            problems.append(Problem(module, node.lineno, "the core imports the app by name"))

    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            chain, value = [], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if not isinstance(value, ast.Name) or value.id not in aliases:
                continue
            target = ".".join([aliases[value.id], *reversed(chain)])
            if target in modules and target != module:
                problems.append(
                    Problem(module, node.lineno, f"uses {target}.{node.attr}", target, node.attr)
                )
    return problems


@pytest.fixture(scope="module")
def all_problems() -> list[Problem]:
    modules = project_modules()
    assert {"d2f_core.pipeline", "d2f_core.io", "d2f_core.train.synth.scene", "app.main"} <= set(
        modules
    )
    out: list[Problem] = []
    for name, path in modules.items():
        out += import_problems(name, path.read_text(), set(modules), path.stem == "__init__")
    return out


def test_core_never_imports_the_app(all_problems):
    bad = [str(p) for p in all_problems if "the app" in p.what]
    assert not bad, "\n".join(bad)


def test_no_module_imports_another_modules_private_names(all_problems):
    bad = [str(p) for p in all_problems if (p.module, p.target, p.name) not in KNOWN]
    assert not bad, "\n".join(bad)


def test_known_exceptions_still_exist(all_problems):
    seen = {(p.module, p.target, p.name) for p in all_problems}
    gone = sorted(KNOWN - seen)
    assert not gone, f"fixed; remove from KNOWN: {gone}"


# ------------------------------------------------------------------- the checker itself

MODULES = {"d2f_core", "d2f_core.rendering", "d2f_core.pipeline", "d2f_core.io", "app", "app.x"}
MODULES |= {"d2f_core._private", "d2f_core._private.rendering"}


def _whats(source: str, module: str = "d2f_core.pipeline") -> list[str]:
    return [p.what for p in import_problems(module, source, MODULES)]


@pytest.mark.parametrize(
    "source",
    [
        "from .rendering import _pool",
        "from d2f_core.rendering import render, _pool",
        "def f():\n    from .rendering import _pool",
        "from . import rendering\nrendering._LANES = 1",
        "import d2f_core.rendering as r\nx = r._pool",
        "import d2f_core.rendering\nx = d2f_core.rendering._pool",
        "from ._private import rendering",
        "from . import _private",
        "import d2f_core._private",
    ],
)
def test_checker_finds_private_imports(source):
    assert len(_whats(source)) == 1, _whats(source)


@pytest.mark.parametrize(
    "source",
    [
        "from app import x",
        "import app.x",
        "def f():\n    from app.x import y",
        "import importlib\nimportlib.import_module('app.x')",
    ],
)
def test_checker_finds_the_core_importing_the_app(source):
    assert [w for w in _whats(source) if "the app" in w], source
    assert not _whats(source, module="app.main")  # the app may import itself


@pytest.mark.parametrize(
    "source",
    [
        "from .rendering import render as _render",  # a private alias of a public name
        "from . import rendering\nrendering.render(x)",
        "import torch\ntorch._C",  # outside the project
        "x = self._cache",
        "from .rendering import __all__",
    ],
)
def test_checker_allows_public_names(source):
    assert not _whats(source), _whats(source)


def test_relative_imports_resolve_from_a_package_init():
    found = import_problems("d2f_core", "from .rendering import _pool", MODULES, True)
    assert [(p.target, p.name) for p in found] == [("d2f_core.rendering", "_pool")]


# ------------------------------------------------------------------- the import graph

#: the modules a render of a photo runs through, and the CLI and app that call them (and the
#: package's own ``__init__``)
INFERENCE = (
    "d2f_core.pipeline",
    "d2f_core.rendering",
    "d2f_core.networks",
    "d2f_core.io",
    "d2f_core.depth",
    "d2f_core.bundled",
    "d2f_core.sizing",
    "d2f_core.errors",
    "d2f_core.progress",
    "d2f_core.cli",
    "app",
)
#: app modules that time the app (they may use the benchmarks' scenes)
APP_BENCHMARKS = ("app.bench", "app.latency_bench")
TRAINING_AND_BENCHMARKS = ("d2f_core.train", "d2f_core.bench")


def _within(module: str, roots) -> bool:
    return any(module == r or module.startswith(r + ".") for r in roots)


def import_edges(module: str, source: str, modules: set[str], is_package: bool = False):
    """The project modules that ``module`` imports anywhere in ``source`` (function bodies
    included): ``from x import y`` counts as importing ``x.y`` where that is a module."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in modules:
                    out.add(a.name)
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(module, is_package, node)
            for a in node.names:
                full = f"{base}.{a.name}"
                if full in modules:
                    out.add(full)
                elif base in modules:
                    out.add(base)
    out.discard(module)
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = project_modules()
    names = set(modules)
    return {
        name: import_edges(name, path.read_text(), names, path.stem == "__init__")
        for name, path in modules.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                found.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circle(graph):
    found = cycles(graph)
    assert not found, "import circles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_inference_never_imports_training_or_benchmarks(graph):
    bad = []
    for start in graph:
        inference = start == "d2f_core" or _within(start, INFERENCE)
        if not inference or _within(start, APP_BENCHMARKS):
            continue
        seen, todo = {start}, [start]
        while todo:
            for nxt in graph[todo.pop()]:
                if nxt in seen:
                    continue
                if _within(nxt, TRAINING_AND_BENCHMARKS):
                    bad.append(f"{start} -> ... -> {nxt}")
                    continue
                seen.add(nxt)
                todo.append(nxt)
    assert not bad, "\n".join(sorted(bad))


def test_graph_sees_function_level_imports_and_circles():
    names = {"d2f_core.a", "d2f_core.b", "d2f_core.train", "d2f_core.pipeline"}
    assert import_edges("d2f_core.a", "def f():\n    from .b import x", names) == {"d2f_core.b"}
    assert import_edges("d2f_core.a", "from . import b, pipeline", names) == {
        "d2f_core.b",
        "d2f_core.pipeline",
    }
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
