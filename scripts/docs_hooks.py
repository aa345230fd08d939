"""MkDocs hook: the reference tables that are generated from the code at build time.

A page asks for one with a line ``<!-- generated: NAME -->``; ``on_page_markdown`` puts the
table in its place. NAME is one of ``GENERATORS``:

- ``study-file``: every key of the study file, from the pydantic models in
  ``server/app/study_file/`` (their field types, defaults and descriptions);
- ``domains``: the domains, their environments and tutorials, from ``server.domains``;
- ``environment-legend``: each domain's map letters, from the domains in ``server.domains``;
- ``learner-settings``: every learner's settings, their types, defaults and descriptions, from
  the learners' ``settings_type`` dataclasses (``server/learners/settings.py`` and each
  learner's module);
- ``deployment-settings``: every ``BAM_*`` variable, from ``server/app/settings.py``;
- ``export-tables``: every exported file and column, from ``DICTIONARY`` and ``INTEGER_COLUMNS``
  in ``server/app/export/columns.py`` and ``DESCRIPTIONS`` in ``server/app/export/files.py`` (the
  definitions the export writes ``data_dictionary.csv`` from);
- ``minari-infos``: the per-step ``infos`` of the Minari export, from ``INFOS`` in
  ``server/app/export/minari.py``;
- ``analysis-outputs``: the files ``bam-study analyze`` writes, from the README it writes
  beside them (``analysis/report.py``).

A key without a description, or an unknown NAME, is logged as a warning, so that
``mkdocs build --strict`` fails until it is described.
"""

from __future__ import annotations

import inspect
import logging
import re
import types
import typing
from collections.abc import Callable
from typing import Any

from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

log = logging.getLogger("mkdocs.hooks.generated")
MARKER = re.compile(r"^<!-- generated: ([a-z-]+) -->$", re.MULTILINE)


def cell(text: object) -> str:
    """Text for a markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def code(value: object) -> str:
    return f"`{value}`" if value != "" else ""


TYPE_WORDS = {
    "str": "string",
    "SecretStr": "string (secret)",
    "Path": "file path",
    "bool": "boolean",
    "int": "integer",
    "float": "number",
    "Any": "any",
}


def unwrapped(annotation: Any) -> Any:
    """The type inside ``Annotated[...]`` (a field's constraints or a union's discriminator)."""
    while typing.get_origin(annotation) is typing.Annotated:
        annotation = typing.get_args(annotation)[0]
    return annotation


def table_models(annotation: Any) -> tuple[type[BaseModel], ...]:
    """The models a value of this type is a table of: one model, or each model of a union of
    models (tables told apart by a key, such as a question's ``kind``); empty for other types."""
    annotation = unwrapped(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return (annotation,)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        members = typing.get_args(annotation)
        if all(isinstance(m, type) and issubclass(m, BaseModel) for m in members):
            return tuple(members)
    return ()


def type_name(annotation: Any) -> str:
    """A field's type in the words of TOML and environment variables."""
    annotation = unwrapped(annotation)
    if annotation is type(None):
        return "unset"
    if table_models(annotation):
        return "table"
    origin = typing.get_origin(annotation)
    if origin is None:
        name = getattr(annotation, "__name__", str(annotation))
        return TYPE_WORDS.get(name, name)
    arguments = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(type_name(a) for a in arguments)
    if origin is typing.Literal:
        return "one of " + ", ".join(f'"{a}"' if isinstance(a, str) else str(a) for a in arguments)
    if origin in (tuple, list):
        item = arguments[0]
        if table_models(item):
            return "list of tables"
        return f"list of {type_name(item)}s"
    if origin is dict:
        inner = arguments[1]
        return "table of tables" if typing.get_origin(inner) is dict else "table"
    return str(annotation)


def toml_value(value: object) -> str:
    """A default as it is written in TOML (None: the setting is left unset)."""
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, tuple | list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return str(value)


def default_text(field: FieldInfo) -> str:
    if field.is_required():
        return "required"
    if field.default_factory is not None:
        made = field.default_factory()  # type: ignore[call-arg]
        if isinstance(made, int):
            return "the number of cores"
        return "empty" if not made else code(made)
    if field.default is PydanticUndefined or field.default is None:
        return "unset"
    if isinstance(field.default, BaseModel):
        return code(toml_value(field.default.model_dump()))
    if isinstance(field.default, tuple | list | dict) and not field.default:
        return "empty"
    return code(toml_value(field.default))


def constraints(field: FieldInfo) -> str:
    """The field's bounds and pattern, as the model checks them."""
    words = []
    unit = "items" if typing.get_origin(field.annotation) in (tuple, list) else "characters"
    for item in field.metadata:
        for name, sign in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
            if getattr(item, name, None) is not None:
                words.append(f"{sign} {getattr(item, name)}")
        for name, what in (("min_length", "at least"), ("max_length", "at most")):
            if getattr(item, name, None) is not None:
                count = getattr(item, name)
                words.append(
                    "not empty" if (name, count) == ("min_length", 1) else f"{what} {count} {unit}"
                )
        if getattr(item, "pattern", None) is not None:
            words.append(f"matches `{item.pattern}`")
    return "; ".join(words)


def described(where: str, field: FieldInfo) -> str:
    if not field.description:
        log.warning("%s has no description: give its Field a description", where)
        return ""
    return field.description


def model_table(
    model: type[BaseModel], prefix: str, name_of: Callable[[str], str] = lambda n: n
) -> list[str]:
    rows = ["| key | type | default | rules | meaning |", "| --- | --- | --- | --- | --- |"]
    for name, field in model.model_fields.items():
        key = name_of(name)
        rows.append(
            f"| `{key}` | {cell(type_name(field.annotation))} "
            f"| {cell(default_text(field))} | {cell(constraints(field))} "
            f"| {cell(described(f'{prefix}{key}', field))} |"
        )
    return rows


def nested_models(model: type[BaseModel]) -> list[tuple[str, tuple[type[BaseModel], ...], bool]]:
    """The (key, models, is_array) of the model's fields that are tables of their own: a table
    of one model, or of one of a union of models."""
    found = []
    for name, field in model.model_fields.items():
        annotation = unwrapped(field.annotation)
        arguments = typing.get_args(annotation)
        if table_models(annotation):
            found.append((name, table_models(annotation), False))
        elif typing.get_origin(annotation) in (tuple, list) and table_models(arguments[0]):
            found.append((name, table_models(arguments[0]), True))
        elif len(arguments) == 2 and arguments[0] is str and table_models(arguments[1]):
            # a table of tables by name: [environments.NAME]
            found.append((f"{name}.NAME", table_models(arguments[1]), False))
    return found


def discriminator(models: tuple[type[BaseModel], ...]) -> str:
    """The key whose value tells the models of a union apart: the one key that every model
    has as a different ``Literal``."""
    for name in models[0].model_fields:
        values = []
        for model in models:
            other = model.model_fields.get(name)
            if other is None or typing.get_origin(other.annotation) is not typing.Literal:
                break
            values.append(typing.get_args(other.annotation))
        else:
            if len(set(values)) == len(models):
                return name
    raise ValueError(f"no key tells {', '.join(m.__name__ for m in models)} apart")


def union_table(models: tuple[type[BaseModel], ...], prefix: str) -> list[str]:
    """One table for the tables of a union of models: each kind's description, then every key
    of any kind (the telling key first) with the kinds it belongs to."""
    key = discriminator(models)
    kinds = {model: str(typing.get_args(model.model_fields[key].annotation)[0]) for model in models}
    lines = [f"Each is one of {len(models)} kinds, chosen by its `{key}`:", ""]
    for model in models:
        doc = " ".join(inspect.cleandoc(model.__doc__ or "").split())
        if not doc:
            log.warning("%s has no docstring to describe its kind", model.__name__)
        lines.append(f'- `{key} = "{kinds[model]}"`: {doc}')
    lines += [
        "",
        "| key | kinds | type | default | rules | meaning |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    names = [key] + [name for model in models for name in model.model_fields if name != key]
    for name in dict.fromkeys(names):
        having = [model for model in models if name in model.model_fields]
        fields = [model.model_fields[name] for model in having]
        if name == key:
            type_text = "one of " + ", ".join(f'"{kinds[m]}"' for m in models)
        else:
            type_text = type_name(fields[0].annotation)
        which = "all" if len(having) == len(models) else ", ".join(kinds[m] for m in having)
        meanings = dict.fromkeys(described(f"{prefix}{name}", field) for field in fields)
        rows_of = dict.fromkeys((default_text(field), constraints(field)) for field in fields)
        if len(rows_of) > 1:
            raise ValueError(f"{prefix}{name} has different defaults or rules in its kinds")
        ((default, rules),) = rows_of
        lines.append(
            f"| `{name}` | {cell(which)} | {cell(type_text)} | {cell(default)} | {cell(rules)} "
            f"| {cell(' '.join(m for m in meanings if m))} |"
        )
    return lines


def table_header(path: str, is_array: bool) -> str:
    """A nested table's TOML header: ``[tutorial]``, ``[[domains]]``."""
    return f"[[{path}]]" if is_array else f"[{path}]"


def study_file(root: type[BaseModel] | None = None) -> str:
    """Every key of the study file (``root``: its model, by default ``StudyConfig``): the
    top-level keys, then each nested table (breadth first), each model's table once (a model
    met again points to where it is)."""
    if root is None:
        from server.app.study_file import StudyConfig

        root = StudyConfig
    lines = ["### Top-level keys", "", *model_table(root, "")]
    shown: dict[tuple[type[BaseModel], ...], str] = {}
    queue = [(key, models, is_array) for key, models, is_array in nested_models(root)]
    while queue:
        path, models, is_array = queue.pop(0)
        header = table_header(path, is_array)
        if models in shown:
            kind = "list of tables" if is_array else "table"
            lines += ["", f"`{path}` is a {kind} with the keys of `{shown[models]}`."]
            continue
        shown[models] = header
        lines += ["", f"### `{header}`", ""]
        if len(models) > 1:
            lines += union_table(models, f"{path}.")
        else:
            (model,) = models
            if model.__doc__ and model.__doc__ != BaseModel.__doc__:
                lines += [" ".join(inspect.cleandoc(model.__doc__).split()), ""]
            lines += model_table(model, f"{path}.")
        for model in models:
            queue += [
                (f"{path}.{key}", inner, array)
                for key, inner, array in nested_models(model)
                if (f"{path}.{key}", inner, array) not in queue
            ]
    return "\n".join(lines)


def domains_table() -> str:
    from server import domains

    lines = ["| domain | environments | tutorial environment |", "| --- | --- | --- |"]
    for name, environments in domains.DOMAINS.items():
        listed = ", ".join(f"`{e}`" for e in environments)
        lines.append(f"| `{name}` | {listed} | `{domains.TUTORIALS[name]}` |")
    return "\n".join(lines)


def environment_legend() -> str:
    """Each domain's map letters, from ``server.domains``."""
    from server.domains import farming, gravity, navigation

    rows = ["| domain | letter | meaning |", "| --- | --- | --- |"]
    rows.append(f"| navigation | `{navigation.WALL}` | wall |")
    rows.append(f"| navigation | `{navigation.FLOOR}` | floor |")
    rows.append("| navigation, gravity | a capital letter | the goal of the task it names |")
    rows.append(f"| gravity | `{gravity.PLAIN}` | plain cell |")
    for letter, colour in gravity.COLOURS.items():
        rows.append(f"| gravity | `{letter}` | {colour}: acting here sets its gravity |")
    for letter, terrain in farming.TERRAIN_OF_LETTER.items():
        machine = next((m for m, t in farming.TERRAIN_OF_MACHINE.items() if t == terrain), None)
        meaning = "free" if machine is None else f"entered with the {machine}"
        rows.append(f"| farming | `{letter}` | {terrain}: {meaning} |")
    for letter, machine in farming.MACHINE_OF_LETTER.items():
        rows.append(f"| farming | `{letter}` | the {machine}, on dirt: stepping here takes it |")
    return "\n".join(rows)


def learner_settings() -> str:
    from server.learners import DISPLAY_NAMES, LEARNERS

    described = {
        name: {i.name: i for i in cls.settings_type.described()} for name, cls in LEARNERS.items()
    }
    names = sorted({setting for infos in described.values() for setting in infos})
    lines = [
        "| setting | type | " + " | ".join(f"`{name}`" for name in LEARNERS) + " | description |",
        "| --- | --- |" + " --- |" * len(LEARNERS) + " --- |",
    ]
    for setting in names:
        infos = {name: own[setting] for name, own in described.items() if setting in own}
        values = [
            code(toml_value(infos[name].default)) if name in infos else "" for name in LEARNERS
        ]
        kind = next(iter(infos.values())).kind
        lines.append(
            f"| `{setting}` | {kind} | "
            + " | ".join(values)
            + f" | {_described(infos).replace('|', '&#124;')} |"
        )
    legend = ", ".join(f"`{name}`: {DISPLAY_NAMES[name]}" for name in LEARNERS)
    return "\n".join([*lines, "", f"Learners: {legend}. An empty cell: not a setting of it."])


def _described(infos: dict[str, Any]) -> str:
    """A setting's description, or each learner's where they differ (``cost_steps``)."""
    by_text: dict[str, list[str]] = {}
    for name, info in infos.items():
        by_text.setdefault(info.description, []).append(name)
    if len(by_text) == 1:
        return next(iter(by_text))
    return " ".join(
        f"{', '.join(f'`{n}`' for n in names)}: {text}" for text, names in by_text.items()
    )


def deployment_settings() -> str:
    from server.app.settings import Settings

    prefix = str(Settings.model_config.get("env_prefix", ""))
    return "\n".join(model_table(Settings, "", lambda name: f"{prefix}{name.upper()}"))


def export_tables() -> str:
    from server.app.export.columns import DICTIONARY, INTEGER_COLUMNS
    from server.app.export.files import DESCRIPTIONS

    lines: list[str] = []
    for name, columns in DICTIONARY.items():
        lines += [f"### `{name}.csv`", ""]
        if name not in DESCRIPTIONS:
            log.warning("export table %s has no entry in DESCRIPTIONS", name)
        else:
            lines += [DESCRIPTIONS[name], ""]
        lines += ["| column | kind | meaning |", "| --- | --- | --- |"]
        for column, meaning in columns.items():
            kind = "integer" if column in INTEGER_COLUMNS[name] else ""
            if not meaning:
                log.warning("export column %s.%s has no description", name, column)
            lines.append(f"| `{column}` | {kind} | {cell(meaning)} |")
        lines.append("")
    lines += ["### `data_dictionary.csv`", "", DESCRIPTIONS["data_dictionary"]]
    return "\n".join(lines)


def minari_infos() -> str:
    from server.app.export.minari import INFOS

    lines = ["| key of `infos` | meaning |", "| --- | --- |"]
    lines += [f"| `{key}` | {cell(meaning)} |" for key, meaning in INFOS.items()]
    return "\n".join(lines)


def analysis_outputs() -> str:
    """What ``bam-study analyze`` counts and writes, from the README it writes beside its
    outputs (with the default baseline, thresholds and false discovery rate; without the
    notes on a study's data, which the README adds)."""
    from analysis.options import DEFAULT_BASELINE, DEFAULT_FDR, DEFAULT_THRESHOLDS
    from analysis.report import describe_files

    return describe_files(DEFAULT_BASELINE, DEFAULT_THRESHOLDS, DEFAULT_FDR).strip()


GENERATORS: dict[str, Callable[[], str]] = {
    "analysis-outputs": analysis_outputs,
    "study-file": lambda: study_file(),
    "domains": domains_table,
    "environment-legend": environment_legend,
    "learner-settings": learner_settings,
    "deployment-settings": deployment_settings,
    "export-tables": export_tables,
    "minari-infos": minari_infos,
}


def render(markdown: str, where: str = "a page") -> str:
    """``markdown`` with every ``<!-- generated: NAME -->`` line replaced by its table."""

    def replace(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in GENERATORS:
            log.warning("%s asks for an unknown generated table %r", where, name)
            return match.group(0)
        return GENERATORS[name]()

    return MARKER.sub(replace, markdown)


def on_page_markdown(markdown: str, page: Any, **_: Any) -> str:
    return render(markdown, page.file.src_path)
