"""The documentation's markdown as a reader of the repository sees it: the getting-started page's
command table lists every subcommand, and every table generated at build time says so where it
stands empty."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from server.commands.main import build_parser
from tests.script_support import ROOT, load_script

hooks = load_script(ROOT / "scripts" / "docs_hooks.py", "docs_hooks")
DOCS = ROOT / "docs"


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser's subcommands by name."""
    found: dict[str, argparse.ArgumentParser] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found.update(action.choices)
    return found


def actions(parser: argparse.ArgumentParser) -> list[str]:
    """A subcommand's own sub-subcommands: its subparsers (``prolific create``) or the choices
    of its positional argument (``db upgrade``)."""
    named = list(subcommands(parser))
    for action in parser._actions:
        if not action.option_strings and action.choices and not named:
            named += [str(choice) for choice in action.choices]
    return named


def command_rows() -> list[str]:
    """The rows of the table under getting-started.md's "## Commands", by their first cell."""
    page = (DOCS / "getting-started.md").read_text(encoding="utf-8")
    section = page.split("\n## Commands\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `bam-study")]
    assert rows, "no command table under ## Commands"
    return [re.split(r"(?<!\\)\|", row)[1].strip() for row in rows]


def test_the_parser_has_the_subcommands_the_test_knows_of() -> None:
    """The enumeration below finds the subcommands and their actions (not an empty list)."""
    found = subcommands(build_parser())
    assert {"demo", "serve", "db", "check", "erase", "fidelity", "prolific"} <= set(found)
    assert {"upgrade", "scrub"} <= set(actions(found["db"]))
    assert {"create", "publish"} <= set(actions(found["prolific"]))


def test_the_command_table_lists_every_subcommand_and_its_actions() -> None:
    cells = command_rows()
    missing = []
    for name, sub in subcommands(build_parser()).items():
        own = [cell for cell in cells if re.match(rf"`bam-study {re.escape(name)}\b", cell)]
        if not own:
            missing.append(name)
            continue
        for action in actions(sub):
            # `bam-study db scrub ...`, or `current` after `bam-study db upgrade` in one cell
            spelled = re.compile(
                rf"`bam-study {re.escape(name)} {re.escape(action)}\b|`{re.escape(action)}`"
            )
            if not any(spelled.search(cell) for cell in own):
                missing.append(f"{name} {action}")
    assert missing == [], f"getting-started.md's command table lacks: {missing}"


NOTE = re.compile(
    r"^\*The (?:table|tables|list) below (?:is|are) generated from (?P<source>.+) when the site "
    r"is built: see (?:it|them) with `mkdocs serve`, or read (?:that file|those files)\.\*$"
)


def placeholders() -> list[tuple[Path, str, int]]:
    """Every generated-table placeholder in docs/*.md (page, table, offset), as the build hook
    finds them."""
    found = []
    for path in sorted(DOCS.glob("*.md")):
        text = path.read_text(encoding="utf-8")
        found += [(path, match.group(1), match.start()) for match in hooks.MARKER.finditer(text)]
    return found


def test_the_build_hook_has_placeholders_to_fill() -> None:
    assert {name for _, name, _ in placeholders()} == set(hooks.GENERATORS)


@pytest.mark.parametrize(
    ("path", "name", "start"),
    placeholders(),
    ids=[f"{path.name}:{name}" for path, name, _ in placeholders()],
)
def test_a_generated_table_says_where_to_read_it(path: Path, name: str, start: int) -> None:
    """In the raw markdown the table is a comment: the line before it says that it is made when
    the site is built, and names the code it is made from, which exists."""
    before = [line for line in path.read_text(encoding="utf-8")[:start].splitlines() if line]
    note = NOTE.match(before[-1])
    assert note, f"{path.name}: no note before the {name} table: {before[-1]!r}"
    sources = re.findall(r"`([^`]+)`", note.group("source"))
    files = [source for source in sources if "/" in source]
    assert files, f"{path.name}: the note names no file or folder of the code"
    assert [source for source in files if not (ROOT / source).exists()] == []


def test_the_learner_settings_table_gives_each_settings_type_and_description() -> None:
    from server.learners import LEARNERS

    table = hooks.learner_settings()
    rows = {line.split(" | ")[0].strip("| `"): line for line in table.splitlines()}
    for cls in LEARNERS.values():
        for info in cls.settings_type.described():
            row = rows[info.name]
            assert f"| `{info.name}` | {info.kind} |" in row, info.name
            assert info.description.replace("|", "&#124;") in row, info.name
    assert '| `optimizer` | "momentum" or "lbfgs" or "warm-lbfgs" |' in table
    assert "| `cost_steps` | integer |" in rows["cost_steps"]
    assert "`bam`: Momentum steps on the costs in each alternation." in rows["cost_steps"]
