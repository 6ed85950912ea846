"""The documentation names only what exists: links, paths, functions, commands and make targets.

Docs are read by newcomers and their commands are run as written; a name that moved or a link to a
file nobody has costs them more than a failing test costs us. Fast and unmarked, so `make check`
runs it.
"""

from __future__ import annotations

import contextlib
import io
import re
import unicodedata
from collections.abc import Iterator
from functools import cache
from pathlib import Path

import pytest

from mission_runner import cli

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250

#: Targets of PX4-Autopilot's own Makefile that the docs tell people to build there, not here.
FOREIGN_MAKE_TARGETS = frozenset({"px4_sitl_default"})

#: Top-level folders whose backticked paths must exist in the repository.
TREE_PREFIXES = ("mission_runner/", "configs/", "bench/", "tests/", "sitl/", "docs/")

#: Where a backticked module path without its package (`world/world.py`, `step.py`) may live.
MODULE_ROOTS = ("", "mission_runner/", "mission_runner/enclosing/", "sitl/", "bench/")

FENCE = re.compile(r"^(```|~~~).*?^\1[ \t]*$", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`([^`\n]+)`")
LINK = re.compile(r"\[[^\]\n]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#{1,6}[ \t]+(.+?)[ \t]*#*[ \t]*$", re.MULTILINE)
PATH_TOKEN = re.compile(r"(?<![\w./-])((?:" + "|".join(TREE_PREFIXES) + r")[\w./-]*)")
MODULE_TOKEN = re.compile(r"^(?:[a-z_]+/)*[a-z_][a-z0-9_]*\.py$")
#: "`world/world.py` `_schedule_events`" and "`step.py: enclosing_step`".
MODULE_AND_NAME = re.compile(
    r"`((?:[a-z_]+/)*[a-z_][a-z0-9_]*\.py)(?:`[ \t]+`|:[ \t]*)([A-Za-z_]\w*)`"
)
CLI_COMMAND = re.compile(r"(?<![\w-])mission-runner[ \t]+([a-z][a-z0-9-]*)")
MAKE_TARGET = re.compile(r"(?<![\w-])make[ \t]+([a-z][\w-]*)")


def documents() -> list[Path]:
    return [ROOT / "README.md", ROOT / "sitl" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


def without_fences(text: str) -> str:
    """The prose: fenced blocks blanked (their line count kept for messages)."""
    return FENCE.sub(lambda block: "\n" * block.group(0).count("\n"), text)


def code_texts(text: str) -> Iterator[str]:
    """Everything set as code: fenced blocks and inline spans."""
    yield from (block.group(0) for block in FENCE.finditer(text))
    yield from (span.group(1) for span in INLINE_CODE.finditer(without_fences(text)))


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to '-'."""
    text = re.sub(r"[`*]|\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


@cache
def anchors(path: Path) -> frozenset[str]:
    return frozenset(slug(h) for h in HEADING.findall(without_fences(path.read_text())))


@cache
def cli_commands() -> frozenset[str]:
    """The subcommands `mission-runner --help` lists: the entry point, whichever module builds
    the parser."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        cli.main(["--help"])
    return frozenset(re.findall(r"^ {4}([a-z][a-z0-9-]*)(?:\s|$)", out.getvalue(), re.MULTILINE))


@cache
def make_targets() -> frozenset[str]:
    text = (ROOT / "Makefile").read_text()
    return frozenset(re.findall(r"^([A-Za-z][\w-]*)[ \t]*:(?!=)", text, re.MULTILINE))


def module_file(name: str) -> Path | None:
    """The repository file a backticked module path names, trying the packages it may be in."""
    for base in MODULE_ROOTS:
        if (ROOT / base / name).is_file():
            return ROOT / base / name
    if "/" not in name:
        found = [
            *sorted(ROOT.glob(f"mission_runner/**/{name}")),
            *sorted(ROOT.glob(f"sitl/{name}")),
            *sorted(ROOT.glob(f"tests/**/{name}")),
        ]
        return found[0] if found else None
    return None


def broken_links(path: Path) -> Iterator[str]:
    for target in LINK.findall(without_fences(path.read_text())):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            yield f"link to a missing file: {target}"
        elif anchor and (linked.suffix != ".md" or anchor not in anchors(linked)):
            yield f"link to a missing heading: {target}"


def missing_paths(path: Path) -> Iterator[str]:
    for code in code_texts(path.read_text()):
        if code.startswith("```"):
            continue  # commands in blocks name output folders and PX4's files too
        for found in PATH_TOKEN.findall(code):
            token = found.rstrip(".")  # a path ending a sentence inside the span
            if "<" not in token and "*" not in token and not (ROOT / token).exists():
                yield f"no such path: {token}"
        if MODULE_TOKEN.match(code) and module_file(code) is None:
            yield f"no such module: {code}"


#: A function, class or module-level name (a constant or table) defined in a module.
DEFINITION = r"^(?:\s*(?:async\s+)?(?:def|class)\s+{name}\b|{name}\s*(?::[^=\n]+)?=)"


def missing_definitions(path: Path) -> Iterator[str]:
    for module, name in MODULE_AND_NAME.findall(without_fences(path.read_text())):
        found = module_file(module)
        if found is None:
            yield f"no such module: {module} (for {name})"
        elif not re.search(DEFINITION.format(name=re.escape(name)), found.read_text(), re.M):
            yield f"{module} defines no {name}"


def unknown_commands(path: Path) -> Iterator[str]:
    for code in code_texts(path.read_text()):
        for command in CLI_COMMAND.findall(code):
            if command not in cli_commands():
                yield f"mission-runner has no command {command!r}"
        for target in MAKE_TARGET.findall(code):
            if target not in make_targets() and target not in FOREIGN_MAKE_TARGETS:
                yield f"the Makefile has no target {target!r}"


@pytest.mark.parametrize("path", documents(), ids=_name)
def test_every_link_path_definition_and_command_a_document_names_exists(path: Path) -> None:
    problems = [
        *broken_links(path),
        *missing_paths(path),
        *missing_definitions(path),
        *unknown_commands(path),
    ]
    assert not problems, f"{_name(path)}:\n  " + "\n  ".join(problems)


def test_the_readme_fits_in_its_budget() -> None:
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= README_MAX_LINES, (
        f"README.md has {lines} lines (at most {README_MAX_LINES}): move detail into docs/"
    )


def test_no_document_points_at_files_outside_the_repository() -> None:
    """ALGORITHM.md lived with the team's shared documents; readers of the repository have only
    docs/algorithm.md."""
    naming = [_name(p) for p in documents() if "ALGORITHM.md" in p.read_text()]
    assert not naming, f"ALGORITHM.md is not in the repository, yet named by {naming}"


def test_the_checker_catches_what_it_is_for(tmp_path: Path) -> None:
    """Each rule, on a small document that breaks it."""
    bad = tmp_path / "bad.md"
    bad.write_text(
        "# Title\n[gone](nowhere.md) [anchor](#no-such-heading) [ok](#title)\n"
        "`configs/nope.yaml` `world/world.py` `no_such_function`\n"
        "`mission-runner fly` `make deploy`\n"
    )
    assert list(broken_links(bad)) == [
        "link to a missing file: nowhere.md",
        "link to a missing heading: #no-such-heading",
    ]
    assert list(missing_paths(bad)) == ["no such path: configs/nope.yaml"]
    assert list(missing_definitions(bad)) == ["world/world.py defines no no_such_function"]
    assert list(unknown_commands(bad)) == [
        "mission-runner has no command 'fly'",
        "the Makefile has no target 'deploy'",
    ]
