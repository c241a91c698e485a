"""The layers of docs/architecture.md ("Which way imports point"), checked on the source with
``ast`` (nothing is imported).

Every ``import`` counts, also those inside functions (a lazy import is still an arrow, and the one
most likely to go stale after a move), except those under ``if __name__ == "__main__":``, which
run only when a file is executed as a script, never on import.
"""

from __future__ import annotations

import ast
import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import capvector

PACKAGE = Path(capvector.__file__).parent

LAYERS = [
    ["cli"],
    ["workflows", "profiling", "serve"],
    ["module"],
    ["policy"],
    ["training", "callbacks"],
    ["objectives"],
    ["backbones"],
    ["data", "eval"],
    ["envs", "vectors"],
    ["io"],
    ["tool_cli"],
    ["errors", "registry"],
]
"""docs/architecture.md's picture: a module imports from its own layer or those below it."""
UPWARD: set[tuple[str, str]] = set()
"""Imports allowed to point up a layer: none."""

# None: `data.generate` records the missing demo files through the registry (Suite.record_demos),
# which imports a suite's simulator only when it records.
LAZY_SIM_IMPORTS: set[tuple[str, str]] = set()
# The evaluate, demo and expert tools run the suites themselves.
MAY_IMPORT_SIM = (
    "capvector.envs",
    "capvector.eval",
    "capvector.workflows.demos",
    "capvector.workflows.evaluate",
    "capvector.workflows.expert_success",
    "capvector.workflows.metaworld_experts",
)
SIMULATOR_FREE = ("capvector.envs", "capvector.envs.base", "capvector.envs.registry")
"""The suite contract and registry; with every suite's ``spec`` module, what training code may
import of ``envs/`` (tests/test_import_boundary.py imports them and checks)."""
LIGHTNING = ("lightning", "pytorch_lightning", "torchmetrics")


@dataclass(frozen=True)
class Import:
    source: str
    target: str
    """The capvector module that is imported (``from pkg import name`` names the package unless
    ``name`` is a module of it)."""
    names: tuple[str, ...]
    """What ``from target import ...`` binds; empty for ``import target``."""
    line: int
    lazy: bool
    """Inside a function."""

    def __str__(self) -> str:
        return f"{self.source}:{self.line} imports {self.target}"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


@cache
def tree(module: str) -> ast.Module:
    return ast.parse(modules()[module].read_text(), filename=str(modules()[module]))


def _is_main_guard(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (
        isinstance(test, ast.Compare)
        and isinstance(test.left, ast.Name)
        and test.left.id == "__name__"
        and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in test.comparators)
    )


def _walk(node: ast.AST, lazy: bool = False) -> Iterator[tuple[ast.AST, bool]]:
    for child in ast.iter_child_nodes(node):
        if _is_main_guard(child):
            continue
        inner = lazy or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
        yield child, inner
        yield from _walk(child, inner)


@cache
def imports_of(module: str) -> tuple[Import, ...]:
    package = module if modules()[module].name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node, lazy in _walk(tree(module)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.append(Import(module, alias.name, (), node.lineno, lazy))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            names = tuple(a.name for a in node.names)
            submodules = [n for n in names if f"{base}.{n}" in modules()]
            for name in submodules:
                found.append(Import(module, f"{base}.{name}", (), node.lineno, lazy))
            rest = tuple(n for n in names if n not in submodules)
            if rest or not submodules:
                found.append(Import(module, base, rest, node.lineno, lazy))
    return tuple(found)


def project_imports(module: str) -> list[Import]:
    return [i for i in imports_of(module) if i.target.split(".")[0] == "capvector"]


def _top_level(body: list[ast.stmt]) -> Iterator[ast.stmt]:
    """Statements that run on import: the body, and inside its ``if``, ``try`` and ``with``."""
    for node in body:
        yield node
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            continue
        for field in ("body", "orelse", "finalbody"):
            yield from _top_level(getattr(node, field, []))
        for handler in getattr(node, "handlers", []):
            yield from _top_level(handler.body)


@cache
def top_level_names(module: str) -> frozenset[str]:
    """Names a module binds outside its functions and classes (what ``from m import x`` finds)."""
    names: set[str] = set()
    for node in _top_level(tree(module).body):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.ImportFrom) and node.names[0].name == "*":
            names |= exported_names(node.module or "")
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.Assign | ast.AnnAssign | ast.AugAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
    return frozenset(names)


def exported_names(module: str) -> frozenset[str]:
    """What ``from module import *`` binds: its literal ``__all__``, else its public names."""
    if module not in modules():
        return frozenset()
    for node in tree(module).body:
        targets = node.targets if isinstance(node, ast.Assign) else []
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            with contextlib.suppress(ValueError):
                return frozenset(ast.literal_eval(node.value))
    return frozenset(n for n in top_level_names(module) if not n.startswith("_"))


def graph() -> dict[str, set[str]]:
    return {m: {i.target for i in project_imports(m)} for m in modules()}


def simulator_free(module: str) -> bool:
    return module in SIMULATOR_FREE or (
        inside(module, "capvector.envs") and module.endswith(".spec")
    )


def inside(module: str, *packages: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_every_project_import_names_a_module_and_what_it_defines() -> None:
    """A moved module leaves no import behind, also none inside a function that no test runs."""
    stale = []
    for module in modules():
        for imp in project_imports(module):
            if imp.target not in modules():
                stale.append(f"{imp}, which does not exist")
                continue
            missing = [n for n in imp.names if n != "*" and n not in top_level_names(imp.target)]
            if missing:
                stale.append(f"{imp}, which does not define {', '.join(missing)}")
    assert not stale, "\n".join(stale)


def test_no_import_cycles() -> None:
    found = cycles(graph())
    assert not found, "modules that import each other: " + "; ".join(" ⇄ ".join(c) for c in found)


def top(module: str) -> str:
    """``capvector.eval.rollout`` -> ``eval``; ``capvector.cli`` -> ``cli``."""
    return module.split(".")[1] if "." in module else module


LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}


def test_every_package_has_a_layer() -> None:
    unplaced = sorted({top(m) for m in modules() if m != "capvector"} - LAYER.keys())
    assert not unplaced, f"put {unplaced} into LAYERS and docs/architecture.md's picture"


def test_imports_point_down_the_layers() -> None:
    upward = [
        f"{imp}: {top(imp.target)} is a layer above {top(module)}"
        for module in modules()
        for imp in project_imports(module)
        # An unplaced module fails the test above, not this one.
        if LAYER.get(top(imp.target), len(LAYERS)) < LAYER.get(top(module), -1)
        and (module, imp.target) not in UPWARD
    ]
    assert not upward, "\n".join(upward)


def test_only_evaluation_and_demo_recording_import_the_simulator() -> None:
    """Training code (module, training, data, callbacks, objectives, backbones), vectors, io and
    the tools never import ``envs/`` beyond its specs and contract: ``eval/`` reaches it for
    rollouts, ``data.generate`` for demos."""
    wrong = []
    for module in modules():
        if inside(module, *MAY_IMPORT_SIM):
            continue
        for imp in project_imports(module):
            if not inside(imp.target, "capvector.envs") or simulator_free(imp.target):
                continue
            if (module, imp.target) in LAZY_SIM_IMPORTS and imp.lazy:
                continue
            wrong.append(str(imp))
    assert not wrong, "only eval/ and the demo tools may import envs/:\n" + "\n".join(wrong)


REGISTRY_ONLY = (
    "capvector.data",
    "capvector.workflows.evaluate",
    "capvector.workflows.demos",
    "capvector.workflows.sweep",
)
"""Reach suites only through ``envs.base`` and ``envs.registry`` (never a suite's package, not even
its spec module): a new suite is then found by its name, with no edit here."""


def test_data_and_the_suite_tools_dispatch_through_the_registry() -> None:
    wrong = [
        str(imp)
        for module in modules()
        if inside(module, *REGISTRY_ONLY)
        for imp in project_imports(module)
        if inside(imp.target, "capvector.envs") and imp.target not in SIMULATOR_FREE
    ]
    assert not wrong, "import envs.base / envs.registry instead:\n" + "\n".join(wrong)


def test_every_exception_is_still_needed() -> None:
    """An exception nobody needs any more is removed from ``LAZY_SIM_IMPORTS`` or ``UPWARD``
    (both are empty today; one test over them, not a parametrisation that pytest skips when
    empty)."""
    unused = [
        (source, target)
        for source, target in sorted(LAZY_SIM_IMPORTS | UPWARD)
        if not any(i.target == target for i in project_imports(source))
    ]
    assert not unused, unused


def test_module_uses_the_public_vector_api() -> None:
    internals = [
        str(i)
        for i in project_imports("capvector.module")
        if i.target.startswith("capvector.vectors.")
    ]
    assert not internals, "use `capvector.vectors` (its __init__):\n" + "\n".join(internals)


def test_vectors_reach_no_lightning() -> None:
    """Nothing ``vectors/`` imports, directly or through other capvector modules, imports
    Lightning: the vector tools run without it, and the math is shared, not wrapped."""
    edges = graph()
    wrong = []
    for start in (m for m in modules() if inside(m, "capvector.vectors")):
        seen, todo = {start}, [start]
        while todo:
            for target in sorted(edges[todo.pop()] - seen):
                seen.add(target)
                todo.append(target)
        for module in sorted(seen):
            for imp in imports_of(module):
                if imp.target.split(".")[0] in LIGHTNING:
                    wrong.append(f"{start} reaches {imp}")
    assert not wrong, "\n".join(sorted(set(wrong)))


def test_io_imports_only_io_and_errors() -> None:
    """``io/`` is the bottom layer: file names, atomic outputs, weight files, model cards."""
    wrong = [
        str(i)
        for m in modules()
        if inside(m, "capvector.io")
        for i in project_imports(m)
        if not inside(i.target, "capvector.io", "capvector.errors")
    ]
    assert "capvector.io" in modules(), "capvector/io/__init__.py is missing"
    assert not wrong, "\n".join(wrong)
