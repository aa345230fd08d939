"""The documentation site builds as CI builds it (`mkdocs build --strict`: any warning, a broken
link, a missing page or anchor, an undescribed key fails it), and its generated reference pages
list everything the code defines: every exported column, every study-file key, every setting."""

from __future__ import annotations

import html
import logging
import os
import re
import subprocess
import sys
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel, Field

from tests.script_support import ROOT, load_script

hooks = load_script(ROOT / "scripts" / "docs_hooks.py", "docs_hooks")


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("site")
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    log = built.stdout + built.stderr
    assert built.returncode == 0, log
    assert "WARNING" not in log, log
    return out


def page_text(site: Path, page: str) -> str:
    return html.unescape((site / page / "index.html").read_text(encoding="utf-8"))


def sections(text: str) -> dict[str, str]:
    """The page's h3 sections by their heading's text (tags removed)."""
    parts = re.split(r"<h3 id=\"[^\"]*\">(.*?)</h3>", text)
    return {
        re.sub(r"<[^>]+>", "", heading).replace("¶", "").strip(): body
        for heading, body in zip(parts[1::2], parts[2::2], strict=True)
    }


def test_every_exported_column_is_described_under_its_file(site: Path) -> None:
    from server.app.export.columns import DICTIONARY
    from server.app.export.files import DESCRIPTIONS

    found = sections(page_text(site, "data"))
    for name, columns in DICTIONARY.items():
        body = found[f"{name}.csv"]
        assert DESCRIPTIONS[name] in body
        for column, meaning in columns.items():
            assert f"<code>{column}</code>" in body, (name, column)
            # As the page renders it: `x` in a description is code.
            assert re.sub(r"`([^`]*)`", r"<code>\1</code>", meaning) in body, (name, column)


def study_keys(model: type[BaseModel]) -> list[tuple[str, str]]:
    """(section heading, key) of every field of the study file: the top-level keys, then each
    nested table under its TOML header, each model once."""
    keys = [("Top-level keys", name) for name in model.model_fields]
    seen: set[type[BaseModel]] = set()
    queue: list[tuple[str, type[BaseModel]]] = []

    def models(annotation: object) -> list[type[BaseModel]]:
        """The model, or each model of a union of them (inside ``Annotated``)."""
        while typing.get_origin(annotation) is typing.Annotated:
            annotation = typing.get_args(annotation)[0]
        members = typing.get_args(annotation) if typing.get_origin(annotation) else (annotation,)
        return [m for m in members if isinstance(m, type) and issubclass(m, BaseModel)]

    def nested(path: str, of: type[BaseModel]) -> None:
        for name, field in of.model_fields.items():
            inner = field.annotation
            items = typing.get_args(inner)
            where = f"{path}.{name}" if path else name
            if typing.get_origin(inner) is tuple and models(items[0]):
                queue.extend((f"[[{where}]]", m) for m in models(items[0]))
            elif isinstance(inner, type) and issubclass(inner, BaseModel):
                queue.append((f"[{where}]", inner))

    nested("", model)
    while queue:
        header, inner = queue.pop(0)
        if inner in seen:
            continue
        seen.add(inner)
        keys += [(header, name) for name in inner.model_fields if (header, name) not in keys]
        nested(header.strip("[]"), inner)
    return keys


def test_every_study_file_key_is_described_in_its_table(site: Path) -> None:
    from server.app.study_file import StudyConfig

    found = sections(page_text(site, "study-file"))
    keys = study_keys(StudyConfig)
    assert len(keys) > 20
    for section, key in keys:
        body = found[section]
        row = re.search(rf"<td><code>{re.escape(key)}</code></td>(.*?)</tr>", body, re.S)
        assert row is not None, (section, key)
        meaning = re.findall(r"<td>(.*?)</td>", row.group(1), re.S)[-1]
        assert meaning.strip(), f"{section} {key} has no meaning on the page"


def test_every_setting_and_learner_setting_is_listed(site: Path) -> None:
    from server.app.settings import Settings
    from server.learners import LEARNERS

    deployment = page_text(site, "deployment")
    for name, field in Settings.model_fields.items():
        assert f"<code>BAM_{name.upper()}</code>" in deployment
        assert field.description and field.description in deployment, name
    study_file = page_text(site, "study-file")
    for cls in LEARNERS.values():
        for setting in cls.default_settings:
            assert f"<code>{setting}</code>" in study_file, setting


def test_the_api_reference_renders_the_learners_docstrings(site: Path) -> None:
    from server.learners.base import Learner

    api = page_text(site, "api")
    assert Learner.__doc__ is not None
    first_line = Learner.__doc__.strip().splitlines()[0]
    assert first_line in api
    assert 'id="server.learners.bam.BAM"' in api


class Leaf(BaseModel):
    depth: int = Field(3, description="The third level.")


class Branch(BaseModel):
    leaves: tuple[Leaf, ...] = Field(description="Tables two levels down.")
    again: Leaf = Field(Leaf(), description="A model already shown.")


class Root(BaseModel):
    branch: Branch = Field(description="A table.")


def test_tables_nested_deeper_get_their_own_section_once() -> None:
    text = hooks.study_file(Root)
    headers = re.findall(r"^### `(.*)`$", text, re.MULTILINE)
    assert headers == ["[branch]", "[[branch.leaves]]"]
    assert "`branch.again` is a table with the keys of `[[branch.leaves]]`." in text
    assert "| `depth` | integer | `3` |  | The third level. |" in text


class Said(BaseModel):
    """Words."""

    kind: typing.Literal["said"] = Field(description="said: words.")
    words: str = Field(description="What was said.")
    loud: bool = Field(False, description="Shouted.")


class Shown(BaseModel):
    """A picture."""

    kind: typing.Literal["shown"] = Field(description="shown: a picture.")
    picture: str = Field(description="The picture's file.")
    loud: bool = Field(False, description="Shouted.")


class Talk(BaseModel):
    parts: tuple[typing.Annotated[Said | Shown, Field(discriminator="kind")], ...] = Field(
        (), description="The talk's parts."
    )


def test_a_list_of_tables_of_several_kinds_gets_one_table_of_their_keys() -> None:
    """A list of tables told apart by a key (the questionnaire's questions) reads as a list of
    tables, with every kind's keys in one table, not as a Python type."""
    text = hooks.study_file(Talk)
    assert "| `parts` | list of tables | empty |  | The talk's parts. |" in text
    assert "typing" not in text and "Annotated" not in text and "FieldInfo" not in text
    assert re.findall(r"^### `(.*)`$", text, re.MULTILINE) == ["[[parts]]"]
    assert '- `kind = "said"`: Words.' in text
    assert '- `kind = "shown"`: A picture.' in text
    assert (
        '| `kind` | all | one of "said", "shown" | required |  | said: words. shown: a picture. |'
    ) in text
    assert "| `words` | said | string | required |  | What was said. |" in text
    assert "| `picture` | shown | string | required |  | The picture's file. |" in text
    assert "| `loud` | all | boolean | `false` |  | Shouted. |" in text


def test_the_questionnaire_questions_keys_are_in_a_table() -> None:
    text = hooks.study_file()
    assert "typing." not in text and "Annotated" not in text
    section = text.split("### `[[questionnaire.questions]]`", 1)[1].split("###", 1)[0]
    for key in ("id", "kind", "text", "labels", "choices", "required"):
        assert re.search(rf"^\| `{key}` \| ", section, re.MULTILINE), key


class Undescribed(BaseModel):
    described: int = Field(1, description="Has one.")
    bare: int = 2


def test_an_undescribed_key_or_unknown_table_is_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A warning is what fails `mkdocs build --strict`: a key added without a description
    cannot reach the site silently."""
    with caplog.at_level(logging.WARNING, logger="mkdocs.hooks.generated"):
        rows = hooks.model_table(Undescribed, "x.")
        assert len(rows) == 4
        assert [r.message for r in caplog.records] == [
            "x.bare has no description: give its Field a description"
        ]
        caplog.clear()
        assert hooks.render("<!-- generated: nothing-such -->", "page.md")
        assert "unknown generated table 'nothing-such'" in caplog.records[0].message


TEAM_WORDS = re.compile(
    r"\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|this|that|"
    r"previous|last|next|work) session\b|\brounds? of work\b|\bthe lead\b",
    re.IGNORECASE,
)


def test_the_documents_speak_of_the_project_only() -> None:
    """Figures are labelled by machine and command, never by when in the work they were
    taken ("learning session" and "session cookie" are the product's words)."""
    documents = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    found = [
        f"{path.name}: {match.group(0)}"
        for path in documents
        for match in TEAM_WORDS.finditer(path.read_text(encoding="utf-8"))
    ]
    assert found == []


def test_the_code_names_no_issue_of_the_tracker() -> None:
    """Docstrings and --help texts say what a thing does, not which piece of work made it."""
    sources = [
        path
        for folder in ("server", "analysis", "benchmarks", "scripts", "migrations")
        for path in sorted((ROOT / folder).rglob("*.py"))
    ]
    assert len(sources) > 50
    found = [
        f"{path.relative_to(ROOT)}: {match.group(0)}"
        for path in sources
        for match in re.finditer(r"\bissues? #?\d+", path.read_text(encoding="utf-8"), re.I)
    ]
    assert found == []


def test_the_readme_links_to_pages_and_pictures_that_exist() -> None:
    """The README is read on its own (not built by MkDocs): its relative links must resolve."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme)
    local = [t for t in targets if "://" not in t]
    assert any(t.startswith("docs/screenshots/") for t in local)
    assert any(t.endswith(".md") for t in local)
    assert [t for t in local if not (ROOT / t).is_file()] == []
