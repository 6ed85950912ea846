"""The layers of docs/layers.md hold: neither package has an import circle and no arrow of
``mission_runner`` goes up the layer order, counting every import (module level, inside a
function, under ``if TYPE_CHECKING:``). ``lint-imports`` checks the same order from pyproject.toml;
this reads the sources itself, so a function-level or type-only import cannot hide a circle."""

import importlib.util
import sys
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _import_graph() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "import_graph", ROOT / "bench" / "import_graph.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while being built
    spec.loader.exec_module(module)
    return module


graph = _import_graph()


@pytest.fixture(scope="module")
def arrows() -> list[Any]:
    """Every import of both packages (their every source parsed: read once, only read)."""
    return list(graph.imports(ROOT))


def test_the_graph_sees_every_kind_of_import(arrows: list[Any]) -> None:
    kinds = {arrow.kind for arrow in arrows}
    assert kinds == {"module", "function", "type-checking"}
    assert {arrow.source.split(".")[0] for arrow in arrows} == {"mission_runner", "sitl"}


def test_a_circle_through_a_function_and_type_checking_import_is_found(tmp_path: Path) -> None:
    package = tmp_path / "mission_runner"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "low.py").write_text("def f():\n    from .high import g\n")
    (package / "high.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .low import f\n"
    )
    arrows = graph.imports(tmp_path, ("mission_runner",))
    assert graph.circles(arrows) == [["mission_runner.high", "mission_runner.low"]]


def test_no_import_circle_in_either_package(arrows: list[Any]) -> None:
    for package in ("mission_runner", "sitl"):
        mine = [arrow for arrow in arrows if arrow.source.split(".")[0] == package]
        assert graph.circles(mine) == [], package


def test_no_arrow_goes_up_and_every_module_has_a_layer(arrows: list[Any]) -> None:
    up = [f"{a.source} -> {a.target} ({a.kind}, line {a.line})" for a in graph.arrows_up(arrows)]
    assert up == []
    names = graph.module_names(ROOT, ("mission_runner",))
    assert [
        name for name in names if name != "mission_runner" and graph.layer_of(name) is None
    ] == []


def test_the_layer_order_is_the_one_lint_imports_checks() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    (contract,) = [c for c in config["tool"]["importlinter"]["contracts"] if c["type"] == "layers"]
    declared = [
        sorted(f"mission_runner.{name.strip()}" for name in layer.split("|"))
        for layer in contract["layers"]
    ]
    assert declared == [sorted(layer) for layer in graph.LAYERS]


def test_every_function_level_import_says_why() -> None:
    """A function-level import is kept only for a heavy or optional library, or for a command
    line whose ``--help`` must not load what the command runs, with its reason after
    ``# noqa: PLC0415 -``."""
    unexplained = [
        f"{module}:{line}"
        for module, line, reason in graph.function_level_statements(ROOT)
        if not reason
    ]
    assert unexplained == []
