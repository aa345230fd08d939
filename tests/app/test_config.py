"""The study configuration: the shipped paper's study, and clear errors for bad files."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.app.settings import Settings
from server.app.study_file import (
    DEFAULT_STUDY_CONFIG,
    StudyConfigError,
    load_study_config,
    parse_study_config,
)
from server.commands.main import main

PAPER = DEFAULT_STUDY_CONFIG.read_text()


def test_the_default_is_the_papers_study() -> None:
    study = load_study_config()
    assert [(d.name, d.environments) for d in study.domains] == [
        ("navigation", ("two-rooms", "doorway")),
        ("farming", ("two-fields", "three-fields")),
    ]
    assert study.learners == ("bam", "model-based", "cloning") and study.agents == 3
    assert study.completion.mode == "mturk" and "3.00 USD" in study.payment
    assert study.tutorial.enabled and study.domains[0].tutorial_environment == "navigation-tutorial"
    assert not study.allow_repeat_workers


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            ('environments = ["two-rooms", "doorway"]', 'environments = ["two-rooms", "flip"]'),
            "'flip' is not in domain 'navigation'",
        ),
        (('name = "farming"', 'name = "cooking"'), "unknown domain 'cooking'"),
        (
            ('learners = ["bam", "model-based", "cloning"]', 'learners = ["bam", "magic"]'),
            "unknown learner 'magic'",
        ),
        (('mode = "mturk"', 'mode = "prolific"'), "needs prolific_code"),
        (('mode = "mturk"', 'mode = "email"'), "completion.mode"),
        (('title = "Teach a robot"', 'title = ""'), "title"),
        (
            ('title = "Teach a robot"', 'title = "x"\nsurprise = 1'),
            "surprise: unknown key; valid keys: ",
        ),
        (
            ("# [learner_settings.bam]", "learner_settings = { bam = { speed = 2 } }"),
            "learner_settings.bam: unknown setting(s) speed; valid: alpha, alternations, beta",
        ),
        (
            ("# [learner_settings.bam]", "learner_settings = { bam = { alternations = 2.5 } }"),
            "learner_settings.bam: alternations must be an integer, got 2.5",
        ),
        (
            ("# [learner_settings.bam]", 'learner_settings = { cloning = { optimizers = "x" } }'),
            "learner_settings.cloning: optimizers must be one of 'per-task', 'joint', got 'x'",
        ),
        (('hex = "#CC79A7"', 'hex = "purple"'), "colours.5.hex"),
        (
            ("allow_anonymous = false", "allow_anonymous = false\nagents_per_environment = 4"),
            "6 colours for up to 8 agents",
        ),
    ],
)
def test_bad_studies_are_refused_with_the_place_of_the_problem(
    tmp_path: Path, change: tuple[str, str], message: str
) -> None:
    old, new = change
    assert old in PAPER
    path = tmp_path / "study.toml"
    path.write_text(PAPER.replace(old, new, 1))
    with pytest.raises(StudyConfigError) as error:
        load_study_config(path)
    assert str(path) in str(error.value)
    assert message in str(error.value)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(StudyConfigError, match="cannot read"):
        load_study_config(tmp_path / "missing.toml")
    path = tmp_path / "broken.toml"
    path.write_text("title = ")
    with pytest.raises(StudyConfigError, match="not valid TOML"):
        load_study_config(path)


def test_settings_come_from_the_environment(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("BAM_DATABASE_URL", f"sqlite:///{tmp_path / 'x.db'}")
    monkeypatch.setenv("BAM_ADMIN_TOKEN", "hunter2")
    monkeypatch.setenv("BAM_UPDATE_WORKERS", "3")
    settings = Settings()
    assert settings.is_sqlite and settings.update_workers == 3
    assert settings.admin_token is not None and settings.admin_token.get_secret_value() == "hunter2"
    assert "hunter2" not in repr(settings)
    monkeypatch.setenv("BAM_COOKIE_SAMESITE", "none")
    with pytest.raises(ValidationError, match="BAM_COOKIE_SECURE"):
        Settings()
    monkeypatch.delenv("BAM_COOKIE_SAMESITE")
    monkeypatch.setenv("BAM_UPDATE_WORKERS", "0")
    with pytest.raises(ValidationError):
        Settings()
    monkeypatch.delenv("BAM_UPDATE_WORKERS")
    assert Settings().update_threads == len(os.sched_getaffinity(0))
    monkeypatch.setenv("BAM_UPDATE_THREADS", "3")
    assert Settings().update_threads == 3
    for bad in ("0", "two"):
        monkeypatch.setenv("BAM_UPDATE_THREADS", bad)
        with pytest.raises(ValidationError, match="update_threads"):
            Settings()


def test_serve_refuses_a_bad_study(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "study.toml"
    path.write_text(
        PAPER.replace('learners = ["bam", "model-based", "cloning"]', 'learners = ["nobody"]')
    )
    monkeypatch.setenv("BAM_STUDY_CONFIG", str(path))
    assert main(["serve", "--database-url", f"sqlite:///{tmp_path / 'x.db'}"]) == 2
    assert "unknown learner 'nobody'" in capsys.readouterr().err
    assert not (tmp_path / "x.db").exists()


def test_the_cores_counted_are_the_process_s_not_the_host_s(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A container's cpuset narrows the CPU affinity but not os.cpu_count(): the update
    threads' default follows the affinity, and the count where there is none."""
    from server import cores

    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0, 3, 5}, raising=False)
    monkeypatch.setattr(cores.os, "cpu_count", lambda: 64)
    assert cores.available_cores() == 3
    assert Settings().update_threads == 3
    monkeypatch.delattr(cores.os, "sched_getaffinity")
    assert cores.available_cores() == 64


@pytest.mark.parametrize(
    ("change", "where", "suggestion"),
    [
        ({"agents_per_enviroment": 2}, "agents_per_enviroment", "agents_per_environment"),
        ({"tutorial": {"enabeld": False}}, "tutorial.enabeld", "enabled"),
        (
            {"domains": [{"name": "navigation", "environmnets": ["two-rooms"]}]},
            "domains.0.environmnets",
            "environments",
        ),
        (
            {
                "questionnaire": {
                    "questions": [{"id": "q", "kind": "text", "text": "Q?", "max_lenght": 5}]
                }
            },
            "questionnaire.questions.0.text.max_lenght",
            "max_length",
        ),
    ],
)
def test_a_misspelt_key_is_unknown_and_the_nearest_is_suggested(
    change: dict[str, object], where: str, suggestion: str
) -> None:
    data = tomllib.loads(PAPER)
    data.update(change)
    with pytest.raises(StudyConfigError) as raised:
        parse_study_config(data, "study.toml")
    lines = str(raised.value).splitlines()
    assert f"  {where}: unknown key; did you mean {suggestion}?" in lines, lines
    assert "Extra inputs are not permitted" not in str(raised.value)


def test_an_unknown_key_with_no_near_one_lists_the_valid_keys() -> None:
    data = tomllib.loads(PAPER)
    data["completion"] = {**data["completion"], "zzzz": 1}
    with pytest.raises(StudyConfigError) as raised:
        parse_study_config(data, "study.toml")
    [line] = [line for line in str(raised.value).splitlines() if "zzzz" in line]
    assert line.startswith("  completion.zzzz: unknown key; valid keys: ")
    assert "mode" in line


EXAMPLES = Path(__file__).resolve().parents[2] / "server" / "examples"


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("horizn", "unknown key; did you mean horizon?"),
        ("zzzz", "unknown key; valid keys: colours, domain, gravity, gravity_colours, horizon"),
    ],
)
def test_an_unknown_key_inside_an_environment_is_named_with_the_environments_keys(
    tmp_path: Path, key: str, expected: str
) -> None:
    """Inside ``[environments.NAME]`` (a table under a name of the study's choosing) the keys
    are an environment's, not none (the list was empty)."""
    text = (EXAMPLES / "office-study.toml").read_text()
    table = 'map_file = "office-floor.txt"'
    (tmp_path / "office-floor.txt").write_text((EXAMPLES / "office-floor.txt").read_text())
    study = tmp_path / "study.toml"
    study.write_text(text.replace(table, f"{table}\n{key} = 40", 1))
    with pytest.raises(StudyConfigError) as raised:
        load_study_config(study)
    [line] = [line for line in str(raised.value).splitlines() if key in line]
    assert line.startswith(f"  environments.office-floor.{key}: {expected}"), line


def test_a_studys_environments_register_from_a_path_given_as_text() -> None:
    from server import domains
    from server.commands.studies import register_study

    known = set(domains.names())
    try:
        assert register_study(str(EXAMPLES / "office-study.toml")) == ("office-floor",)
    finally:
        for name in set(domains.names()) - known:
            domains.unregister(name)


def test_an_unknown_environment_of_a_domain_is_located_in_the_domain() -> None:
    data = tomllib.loads(PAPER)
    data["domains"][0]["environments"] = [*data["domains"][0]["environments"], "kitchen"]
    with pytest.raises(StudyConfigError) as raised:
        parse_study_config(data, "study.toml")
    lines = str(raised.value).splitlines()
    name = data["domains"][0]["name"]
    assert f"  domains.0.environments: domain {name!r}: no environment 'kitchen'" in "\n".join(
        lines
    ), lines
    assert "(top level)" not in str(raised.value)
