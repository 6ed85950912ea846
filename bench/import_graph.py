"""The import graph of ``mission_runner`` and ``sitl``, read from the sources (stdlib ``ast`` only,
nothing is imported): its circles, the arrows that go up against the declared layer order, and the
function-level imports with and without a reason.

    python bench/import_graph.py            # the report of the tree this file is in
    python bench/import_graph.py --root DIR # the report of another checkout

Every import counts: module level, inside ``if TYPE_CHECKING:`` and inside a function. A circle
that only closes through a function-level or TYPE_CHECKING import is still a circle: the modules
in it cannot be understood, tested or moved one without the other.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("mission_runner", "sitl")

# mission_runner's layers, highest first: a module may import its own layer and the ones below it.
# A module is placed by the longest prefix listed. The same order as [tool.importlinter] in
# pyproject.toml (tests/test_layers.py holds the two together); docs/layers.md says what each holds.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("mission_runner.cli",),
    ("mission_runner.emulate", "mission_runner.px4sitl"),
    ("mission_runner.runner",),
    ("mission_runner.world",),
    ("mission_runner.sim",),
    ("mission_runner.live", "mission_runner.replay"),
    ("mission_runner.outputs",),
    ("mission_runner.figure_process",),
    ("mission_runner.layout",),
    ("mission_runner.figures", "mission_runner.recording"),
    ("mission_runner.checks",),
    ("mission_runner.wiring",),
    ("mission_runner.metrics",),
    ("mission_runner.sensors",),
    ("mission_runner.scenario",),
    ("mission_runner.config",),
    ("mission_runner.expressions",),
    ("mission_runner.bus",),
    ("mission_runner.records",),
    ("mission_runner.paths",),
    (
        "mission_runner.tasks",
        "mission_runner.clock",
        "mission_runner.argtypes",
        "mission_runner.errors",
        "mission_runner.limits",
        "mission_runner.environment",
    ),
    ("mission_runner.enclosing",),
)


@dataclass(frozen=True)
class Import:
    """One import statement's arrow from ``source`` to ``target`` (both modules of the tree)."""

    source: str
    target: str
    line: int
    kind: str  # "module", "type-checking" or "function"
    reason: str  # the text of the line's comment after `noqa: PLC0415`, or of the line above


def module_names(root: Path, packages: Iterable[str] = PACKAGES) -> dict[str, Path]:
    """Every module of ``packages`` under ``root``, by dotted name."""
    names: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            names[".".join(parts)] = path
    return names


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _walk(node: ast.AST, kind: str) -> Iterator[tuple[ast.Import | ast.ImportFrom, str]]:
    """Every import under ``node`` with where it sits: a function's body wins over TYPE_CHECKING."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child, kind
        elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            yield from _walk(child, "function")
        elif isinstance(child, ast.If) and _is_type_checking(child.test) and kind == "module":
            for statement in child.body:
                yield from _walk(ast.Module(body=[statement], type_ignores=[]), "type-checking")
            for statement in child.orelse:
                yield from _walk(ast.Module(body=[statement], type_ignores=[]), kind)
        else:
            yield from _walk(child, kind)


def _targets(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    """The dotted names ``node`` imports (submodules named in `from x import y` included)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = node.module or ""
    if node.level:
        anchor = module.split(".")
        if not is_package:
            anchor = anchor[:-1]
        anchor = anchor[: len(anchor) - (node.level - 1)]
        base = ".".join([*anchor, *([base] if base else [])])
    return [base] + [f"{base}.{alias.name}" for alias in node.names]


def _reason(lines: list[str], line: int) -> str:
    text = lines[line - 1]
    if "noqa: PLC0415" in text:
        return text.split("noqa: PLC0415", 1)[1].strip(" -:;,")
    above = lines[line - 2].strip() if line >= 2 else ""
    return above.lstrip("# ").strip() if above.startswith("#") else ""


def imports(root: Path = ROOT, packages: Iterable[str] = PACKAGES) -> list[Import]:
    """Every arrow between modules of ``packages``, one per import statement and target module."""
    names = module_names(root, packages)
    found: list[Import] = []
    for module, path in names.items():
        source = path.read_text(encoding="utf-8")
        lines = source.splitlines()
        is_package = path.name == "__init__.py"
        for node, kind in _walk(ast.parse(source, str(path)), "module"):
            # The deepest module each name reaches: `from .x import y` is an arrow to x.y if that is
            # a module, else to x (a name defined there).
            targets = {t for t in _targets(node, module, is_package) if t in names}
            deepest = {t for t in targets if not any(o.startswith(t + ".") for o in targets)}
            for target in sorted(deepest - {module}):
                found.append(Import(module, target, node.lineno, kind, _reason(lines, node.lineno)))
    return found


def circles(arrows: Iterable[Import]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), largest first."""
    graph: dict[str, set[str]] = {}
    for arrow in arrows:
        graph.setdefault(arrow.source, set()).add(arrow.target)
        graph.setdefault(arrow.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in sorted(graph[node]):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found, key=lambda c: (-len(c), c))


def layer_of(module: str) -> int | None:
    """The index of ``module``'s layer in :data:`LAYERS` (0 is the top), None if not placed."""
    best: tuple[int, int] | None = None
    for position, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and (
                best is None or len(prefix) > best[0]
            ):
                best = (len(prefix), position)
    return None if best is None else best[1]


def arrows_up(arrows: Iterable[Import]) -> list[Import]:
    """The arrows between ``mission_runner``'s modules from a lower layer to a higher one (or to a
    module no layer holds). ``sitl`` is a separate package the mission side may use."""
    up = []
    for arrow in arrows:
        # The package's own __init__ holds only the version: every layer may read it.
        if not (
            arrow.source.startswith("mission_runner.")
            and arrow.target.startswith("mission_runner.")
        ):
            continue
        source, target = layer_of(arrow.source), layer_of(arrow.target)
        if source is not None and (target is None or target < source):
            up.append(arrow)
    return up


def report(root: Path) -> str:
    arrows = imports(root)
    lines = [f"import graph of {', '.join(PACKAGES)} under {root}"]
    for package in PACKAGES:
        mine = [a for a in arrows if a.source.split(".")[0] == package]
        found = circles(mine)
        sizes = ", ".join(str(len(c)) for c in found) or "none"
        lines.append(f"{package}: {len(mine)} arrows, {len(found)} circles (sizes: {sizes})")
        lines.extend(f"  circle of {len(c)}: {' '.join(c)}" for c in found)
    up = arrows_up(arrows)
    lines.append(f"arrows up against the layer order: {len(up)}")
    lines.extend(f"  {a.source} -> {a.target} ({a.kind}, line {a.line})" for a in up)
    names = module_names(root, ("mission_runner",))
    unplaced = [m for m in names if m != "mission_runner" and layer_of(m) is None]
    lines.append(f"modules in no layer: {unplaced}")
    function_level = [a for a in arrows if a.kind == "function"]
    statements = function_level_statements(root)
    with_reason = sum(1 for _, _, reason in statements if reason)
    lines.append(
        f"function-level imports (statements, any target): {len(statements)}, "
        f"with a reason: {with_reason}, without: {len(statements) - with_reason}"
    )
    lines.append(f"function-level arrows inside the packages: {len(function_level)}")
    type_checking = [a for a in arrows if a.kind == "type-checking"]
    lines.append(f"TYPE_CHECKING arrows: {len(type_checking)}")
    return "\n".join(lines)


def function_level_statements(root: Path) -> list[tuple[str, int, str]]:
    """Every import statement inside a function, whatever it imports, with its reason."""
    found = []
    for module, path in module_names(root).items():
        source = path.read_text(encoding="utf-8")
        lines = source.splitlines()
        for node, kind in _walk(ast.parse(source, str(path)), "module"):
            if kind == "function":
                found.append((module, node.lineno, _reason(lines, node.lineno)))
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="checkout to read")
    parser.add_argument("--list-unreasoned", action="store_true", help="list imports without one")
    arguments = parser.parse_args(argv)
    print(report(arguments.root.resolve()))
    if arguments.list_unreasoned:
        for module, line, reason in function_level_statements(arguments.root.resolve()):
            if not reason:
                print(f"  no reason: {module}:{line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
