"""Environments defined in the study file: inline or in a file beside it, checked for every
problem with its line and column (a study with a bad map is refused), registered by name, and
the two example studies."""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import ValidationError

from server import domains
from server.app.study_file import (
    DEFAULT_STUDY_CONFIG,
    EnvironmentDefinition,
    StudyConfig,
    StudyConfigError,
    load_study_config,
    parse_study_config,
)
from server.commands.main import main
from server.domains.spec import EnvironmentSpec

EXAMPLES = Path(__file__).resolve().parents[3] / "server" / "examples"
CORRIDOR = """task: A
start: columns 3
    0123
  0 A...
  1 ....
"""


def study_data(**environments: dict[str, object]) -> dict[str, object]:
    data = tomllib.loads(DEFAULT_STUDY_CONFIG.read_text())
    data["environments"] = environments
    data["domains"] = [{"name": "navigation", "environments": list(environments)}]
    return data


@pytest.fixture
def forget() -> Iterator[None]:
    before = set(domains.names())
    yield
    for name in set(domains.names()) - before:
        domains.unregister(name)


def test_an_inline_map_is_an_environment_of_the_study(forget: None) -> None:
    study = parse_study_config(
        study_data(corridor={"domain": "navigation", "map": CORRIDOR, "horizon": 9})
    )
    (spec,) = study.environment_specs()
    assert (spec.name, spec.domain, spec.horizon) == ("corridor", "navigation", 9)
    study.register_environments()
    env = domains.make("corridor")
    assert (env.height, env.width, env.horizon, env.task_names) == (2, 4, 9, ("A",))
    assert domains.domain_of("corridor") == "navigation"


def test_family_the_former_name_of_domain_is_still_accepted_but_not_beside_it() -> None:
    study = parse_study_config(study_data(corridor={"family": "navigation", "map": CORRIDOR}))
    assert study.environments["corridor"].domain == "navigation"
    assert study.environment_specs()[0].domain == "navigation"
    both = {"family": "navigation", "domain": "navigation", "map": CORRIDOR}
    with pytest.raises(StudyConfigError, match="give domain or family \\(its former name\\)"):
        parse_study_config(study_data(corridor=both))


def test_an_environment_table_has_the_keys_of_an_environment_spec() -> None:
    """The table's keys are ``EnvironmentSpec``'s fields (but its name), in their order, with
    their defaults and the study file's descriptions and bounds, and ``map_file``; a definition
    gives back the spec."""
    keys = [f for f in dataclasses.fields(EnvironmentSpec) if f.name != "name"]
    table = EnvironmentDefinition.model_fields
    assert list(table) == ["domain", "map", "map_file", *(f.name for f in keys[2:])]
    plain = EnvironmentSpec("corridor", "navigation", CORRIDOR)
    for spec_field in keys[2:]:
        default = table[spec_field.name].get_default(call_default_factory=True)
        assert default == getattr(plain, spec_field.name)
    assert all(table[name].description for name in table)
    with pytest.raises(ValidationError, match="less than or equal to 1000"):
        EnvironmentDefinition(domain="navigation", map=CORRIDOR, horizon=1001)
    with pytest.raises(ValidationError, match="'navigation', 'gravity' or 'farming'"):
        EnvironmentDefinition(domain="cooking", map=CORRIDOR)
    every = {"horizon": 9, "colours": {"vines": "#6b8e23"}, "max_trapped_start_share": 0.5}
    definition = EnvironmentDefinition(domain="navigation", map=CORRIDOR, **every)
    assert definition.spec("corridor") == EnvironmentSpec(
        "corridor", "navigation", CORRIDOR, **every
    )


def test_a_map_file_is_read_relative_to_the_study_file(tmp_path: Path) -> None:
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "corridor.txt").write_text(CORRIDOR)
    data = study_data(corridor={"domain": "navigation", "map_file": "maps/corridor.txt"})
    study = parse_study_config(data, base=tmp_path)
    assert study.environments["corridor"].map == CORRIDOR
    with pytest.raises(StudyConfigError, match="cannot read map_file"):
        parse_study_config(data, base=tmp_path / "elsewhere")


def test_every_problem_of_every_map_is_listed_with_its_line_and_column() -> None:
    data = study_data(
        first={"domain": "navigation", "map": CORRIDOR.replace("  1 ....", "  1 ..x.")},
        second={"domain": "gravity", "map": "task: A\nstart: anywhere\n    01\n  0 Ao\n"},
        third={"domain": "navigation", "map": CORRIDOR, "terrains": {"v": "vines"}},
    )
    with pytest.raises(StudyConfigError) as raised:
        parse_study_config(data, "study.toml")
    message = str(raised.value)
    assert message.startswith("study.toml is not a valid study:")
    assert "environments.first: line 5, column 7: unknown character 'x'" in message
    assert "environments.second: line 4, column 6: no gravity for orange" in message
    assert "environments.third: terrains: a navigation environment has no terrains" in message


def test_a_map_larger_than_the_study_allows_is_refused() -> None:
    data = study_data(corridor={"domain": "navigation", "map": CORRIDOR})
    data["max_environment_states"] = 7
    with pytest.raises(StudyConfigError, match=r"8 states .* more than the 7 the study allows"):
        parse_study_config(data)


def test_a_domain_lists_only_its_family_s_environments_and_known_names() -> None:
    data = study_data(corridor={"domain": "navigation", "map": CORRIDOR})
    data["domains"] = [{"name": "farming", "environments": ["corridor", "two-fields"]}]
    with pytest.raises(StudyConfigError, match="'corridor' is a navigation environment"):
        parse_study_config(data)
    data["domains"] = [{"name": "navigation", "environments": ["corridor", "kitchen"]}]
    with pytest.raises(StudyConfigError, match="no environment 'kitchen'; valid: wall, "):
        parse_study_config(data)
    for name in ("doorway", "Bad_Name"):
        bad = study_data(**{name: {"domain": "navigation", "map": CORRIDOR}})
        with pytest.raises(StudyConfigError, match=f"'{name}'"):
            parse_study_config(bad)


def test_serve_refuses_a_study_with_a_bad_map(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "study.toml"
    text = (EXAMPLES / "office-study.toml").read_text()
    (tmp_path / "office-floor.txt").write_text(
        (EXAMPLES / "office-floor.txt").read_text().replace("  5 .......R", "  5 ...?...R")
    )
    path.write_text(text)
    monkeypatch.setenv("BAM_STUDY_CONFIG", str(path))
    assert main(["serve", "--database-url", f"sqlite:///{tmp_path / 'x.db'}"]) == 2
    error = capsys.readouterr().err
    assert "environments.office-floor: line 16, column 8: unknown character '?'" in error
    assert not (tmp_path / "x.db").exists()


@pytest.mark.parametrize("name", ["office-study", "vineyard-study"])
def test_the_example_studies_load(name: str) -> None:
    study: StudyConfig = load_study_config(EXAMPLES / f"{name}.toml")
    (spec,) = study.environment_specs()
    assert spec.problems() == []
    env = spec.build()
    if name == "office-study":
        assert env.domain == "navigation" and len(env.tasks) == 5
    else:
        assert env.domain == "farming" and env.feature_names[-1] == "trellis"
        assert "vines" in {terrain for row in env.layout["terrain"] for terrain in row}
