"""``bam-study check`` and ``bam-study simulate --study`` on the two example studies, and a
study's own environments as Gymnasium ids."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import gymnasium as gym
import matplotlib.image
import numpy as np
import pytest

from server import domains
from server.commands import check
from server.commands.main import main
from server.domains.figure import environment_figure
from server.learners.evaluation import optimal_returns
from tests.domains.test_reachability import NEWCOMER

EXAMPLES = Path(__file__).resolve().parents[2] / "server" / "examples"
STUDIES = {"office-study": "office-floor", "vineyard-study": "vineyard"}


@pytest.mark.parametrize("study", sorted(STUDIES))
def test_check_draws_each_environment_with_its_optimal_returns(
    study: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check", str(EXAMPLES / f"{study}.toml"), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    name = STUDIES[study]
    env = domains.make(name)
    assert f"no problems; 1 environment(s): {name}" in printed
    # The text drawing: the column header, then each row; goal cells as task numbers.
    assert "    " + "".join(str(c % 10) for c in range(env.width)) in printed.splitlines()
    row, column = env.tasks[0].goal_cells[0]
    drawn = next(line for line in printed.splitlines() if line.startswith(f"{row:>3} "))
    assert drawn[4 + column] == "1"
    for number, (task, best) in enumerate(zip(env.tasks, optimal_returns(env), strict=True)):
        assert f"  {number + 1}: {task.name}, {best:.1f}" in printed
    for learner in ("bam", "cloning"):
        assert re.search(rf"^  {learner}: \d+\.\d\d s", printed, re.MULTILINE)
    assert f"{env.width} x {env.height} cells (width x height)" in printed
    for number, task in enumerate(env.tasks, start=1):
        assert re.search(rf"^  {number}: {task.name}: 0 of \d+ starts;", printed, re.MULTILINE)
    # The picture: 32 px a cell at least, with its title and legend below.
    image = matplotlib.image.imread(tmp_path / f"{name}.png")
    assert image.shape[0] > env.height * 32 and image.shape[1] >= env.width * 32


def test_check_warns_above_the_capacity(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With a learner timed at 1e-5 s per unit of size, the vineyard (869,400 units) takes
    8.7 s, above the capacity; 1e-9 s is far below it."""
    rates = {"bam": 1e-5, "cloning": 1e-9}
    monkeypatch.setattr(check, "calibrate", lambda names: {n: rates[n] for n in names})
    main(["check", str(EXAMPLES / "vineyard-study.toml"), "--out", str(tmp_path)])
    printed = capsys.readouterr().out
    assert "  bam: 8.69 s  WARNING: above the 2.0 s the server can serve" in printed
    assert "  cloning: 0.00 s\n" in printed and "1 warning(s)" in printed


def test_check_lists_every_problem_and_fails(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    study = tmp_path / "vineyard-study.toml"
    text = (EXAMPLES / "vineyard-study.toml").read_text()
    study.write_text(text.replace("  8 ..P..W..H..T..", "  8 ..P..W..H..X..").replace(
        'works_on = { trellis = "vines" }', ""))  # fmt: skip
    assert main(["check", str(study), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert "environments.vineyard: works_on: say which terrain the trellis works on" in error
    assert "line 16, column 16: unknown character 'X'" in error
    assert not (tmp_path / "out").exists()


def test_check_refuses_a_gravity_map_with_trapped_starts_and_names_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The map of the issue: every start on the bottom row, no colour on it."""
    study = tmp_path / "newcomer-study.toml"
    text = (EXAMPLES / "office-study.toml").read_text()
    text = text.replace('domain = "navigation"\nmap_file = "office-floor.txt"', f"""domain = "gravity"
map = '''
{NEWCOMER}'''""").replace('name = "navigation"\nenvironments = ["office-floor"]',
        'name = "gravity"\nenvironments = ["office-floor"]')  # fmt: skip
    study.write_text(text)
    assert main(["check", str(study), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert (
        "line 13, column 5: task 'Well': 11 of its 36 start states (30.6% of the simulations' "
        "start probability) can never reach its goal, whatever the agent does (gravity south at "
        "row 6, columns 0-8; gravity east at row 6, column 8; gravity west at row 6, column 0)"
    ) in error
    assert "task 'Tower': 13 of its 36 start states" in error
    assert not (tmp_path / "out").exists()


def test_a_study_file_may_accept_trapped_starts_up_to_its_share(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``max_trapped_start_share`` in the environment's table: the share the message offers
    (0.37 covers both tasks) is accepted; one below the larger share still refuses."""
    text = (EXAMPLES / "office-study.toml").read_text()
    navigation = 'domain = "navigation"\nmap_file = "office-floor.txt"'
    domain = 'name = "navigation"\nenvironments = ["office-floor"]'
    study = tmp_path / "newcomer-study.toml"
    for share, code in ((0.36, 2), (0.37, 0)):
        gravity = f'domain = "gravity"\nmax_trapped_start_share = {share}\nmap = """\n{NEWCOMER}"""'
        gravity_domain = domain.replace("navigation", "gravity")
        study.write_text(text.replace(navigation, gravity).replace(domain, gravity_domain))
        assert main(["check", str(study), "--out", str(tmp_path / f"out-{share}")]) == code
        error = capsys.readouterr().err
        assert ("task 'Tower': 13 of its 36 start states" in error) == (code == 2), error


def test_the_picture_has_every_goal_with_its_task_number_and_a_legend() -> None:
    env = domains.make("doorway")
    figure = environment_figure(env)
    (axes,) = figure.axes
    texts = [text.get_text() for text in axes.texts]
    for number, task in enumerate(env.tasks, start=1):
        assert texts.count(str(number)) == len(task.goal_cells)
    legend = [text.get_text() for text in axes.get_legend().get_texts()]
    assert legend[:4] == ["1: goal of A", "2: goal of B", "3: goal of C", "4: goal of D"]
    assert "wall" in legend and "a start cell" in legend
    assert axes.get_title() == "doorway (navigation): 11 x 11 cells (width x height)"
    assert figure.dpi * figure.get_figwidth() / env.width >= 32


def test_check_prints_the_traps_of_the_papers_gravity_maps(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert check.print_traps(domains.make("choices")) == 0
    printed = capsys.readouterr().out
    assert (
        "  1: A: 4 of 240 starts (1.7% of the simulations' start probability, 0.0% of the user "
        "study's: gravity east at column 14, rows 0-3); 0 of the 240 reachable states"
    ) in printed


@pytest.mark.parametrize("study", sorted(STUDIES))
def test_a_short_simulation_of_each_example(study: str, tmp_path: Path) -> None:
    out = tmp_path / "run"
    argv = ["simulate", "--study", str(EXAMPLES / f"{study}.toml"), "--experiment",
            "demonstrations", "--learners", "bam", "--agents", "1", "--rounds", "1", "--jobs",
            "1", "--learner-setting", "alternations=1", "--learner-setting", "cost_steps=5",
            "--learner-setting", "dynamics_steps=5", "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    with (out / "summary.csv").open() as file:
        rows = list(csv.DictReader(file))
    name = STUDIES[study]
    assert [(row["environment"], row["round"]) for row in rows] == [(name, "0"), (name, "1")]
    optimum = float(optimal_returns(domains.make(name)).sum())
    assert float(rows[0]["optimal_return"]) == pytest.approx(optimum)
    returns = [float(row["mean_normalized_return"]) for row in rows]
    assert all(0.0 <= value <= 1.0 for value in returns)
    assert float(rows[1]["mean_update_seconds"]) > 0.0  # the round's update ran
    if study == "office-study":
        # One round of demonstrations teaches BAM the way around the office, in part (in the
        # vineyard, five steps of each kind do not yet learn which machine enters the vines).
        assert returns[1] > returns[0]


def test_a_study_s_environment_is_a_gymnasium_id() -> None:
    from server.commands.studies import register_study

    (name,) = register_study(EXAMPLES / "office-study.toml")
    env = gym.make("BAMStudy-office-study/OfficeFloor-v0")
    observation, _ = env.reset(seed=0, options={"task": 4})
    own = domains.make(name)
    assert env.spec is not None and env.spec.max_episode_steps == own.horizon
    assert own.tasks[4].start[int(observation)] > 0
    total = 0.0
    for _ in range(own.horizon):
        _, reward, _, truncated, _ = env.step(0)
        total += float(reward)
    assert truncated and np.isfinite(total)


@pytest.mark.slow
@pytest.mark.parametrize("study", sorted(STUDIES))
def test_demo_runs_the_example_study_end_to_end(
    study: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``bam-study demo --study``: a server on SQLite, a simulated participant teaching the
    study's own environment (the office floor; the vineyard, with its vines and trellis), the
    export and the analysis, with small learner settings; then ``bam-study export`` of its
    database."""
    from server.commands.demo import DemoOptions, check, run_demo

    name = STUDIES[study]
    options = DemoOptions(
        out=tmp_path / "demo",
        participants=1,
        concurrency=1,
        rounds=(1, 1),
        workers=1,
        study=EXAMPLES / f"{study}.toml",
        learner_settings="\n[learner_settings.bam]\nalternations = 1\ncost_steps = 5\n"
        "dynamics_steps = 5\n",
    )
    check(options)
    table = run_demo(options)
    assert "| BAM " in table and "| Behavioral Cloning " in table
    env = domains.make(name)
    export = options.out / "export"
    with (export / "sessions.csv").open() as file:
        sessions = [row for row in csv.DictReader(file) if row["environment"] == name]
    assert sorted(row["learner"] for row in sessions) == ["bam", "cloning"]
    assert {row["domain"] for row in sessions} == {env.domain}
    assert all(int(row["demonstrated_actions"]) > 0 for row in sessions)
    with (export / "evaluations.csv").open() as file:
        evaluations = [row for row in csv.DictReader(file) if row["environment"] == name]
    # Each agent's policy evaluated on the study's environment: before teaching, then after.
    by_session = {row["session_id"] for row in sessions}
    assert {row["session_id"] for row in evaluations} == by_session
    for session in by_session:
        indices = sorted(int(r["update_index"]) for r in evaluations if r["session_id"] == session)
        assert indices[0] == 0 and len(indices) >= 2
    done = [row for row in evaluations if row["status"] == "done"]
    assert done and all(0.0 <= float(row["normalized_return"]) <= 1.0 for row in done)
    # The episodes name the study's tasks, and their states are states of its environment.
    with (export / "episodes.csv").open() as file:
        episodes = [row for row in csv.DictReader(file) if row["session_id"] in by_session]
    assert episodes
    assert {row["task_name"] for row in episodes} <= set(env.task_names)
    assert all(0 <= int(row["end_state"]) < env.num_states for row in episodes)
    if name == "vineyard":
        # The teacher drove the trellis into the vines: the events' states say so.
        with (export / "events.csv").open() as file:
            states = [
                int(row["next_state"])
                for row in csv.DictReader(file)
                if row["session_id"] in by_session and row["next_state"]
            ]
        on_vines = [
            env.feature_names[env.feature_of(s)]
            for s in states
            if env.layout["terrain"][env.cell_of(s)[0]][env.cell_of(s)[1]] == "vines"
        ]
        assert on_vines and set(on_vines) == {"trellis"}

    # ``bam-study export`` in a process that has not registered the study's environment (as a
    # fresh one): refused with a hint without the study file; with it (--study or
    # BAM_STUDY_CONFIG), the same tables as the demo's own export.
    url = f"sqlite:///{options.out / 'study.sqlite'}"
    monkeypatch.delenv("BAM_STUDY_CONFIG", raising=False)
    domains.unregister(name)
    assert main(["export", "--database-url", url, "--out", str(tmp_path / "without")]) == 1
    error = capsys.readouterr().err
    assert f"unknown environment {name!r}" in error and "--study or BAM_STUDY_CONFIG" in error
    for how in ("option", "setting"):
        argv = ["--study", str(options.study)] if how == "option" else []
        if how == "setting":
            domains.unregister(name)
            monkeypatch.setenv("BAM_STUDY_CONFIG", str(options.study))
        out = tmp_path / how
        assert main(["export", "--database-url", url, "--out", str(out), *argv]) == 0
        for table in ("sessions", "episodes", "events", "evaluations", "quality"):
            assert (out / f"{table}.csv").read_text() == (export / f"{table}.csv").read_text()


def test_a_study_s_teacher_datasets_are_minari_datasets(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import minari

    from server.commands.studies import register_study
    from server.rl.teacher_datasets import write_teacher_datasets

    (name,) = register_study(EXAMPLES / "office-study.toml")
    ids = write_teacher_datasets([name], 1, 1, 0, tmp_path / "minari")
    assert ids == ["bam-study/office-floor/simulated-teacher-v0"]
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    dataset = minari.load_dataset(ids[0])
    assert dataset.spec.env_spec is not None
    assert dataset.spec.env_spec.id == "BAMStudy-office-study/OfficeFloor-v0"
    env = domains.make(name)
    # One demonstration per task, each from a start of its task to its goal.
    episodes = list(dataset.iterate_episodes())
    assert len(episodes) == len(env.tasks)
    for episode in episodes:
        task = int(episode.infos["task"][0])
        assert env.tasks[task].start[int(episode.observations[0])] > 0
        assert env.is_goal(task, int(episode.observations[-1]))


@pytest.mark.slow
def test_demo_runs_on_the_prolific_replica(tmp_path: Path) -> None:
    """``bam-study demo --platform prolific``: the study made and published on the server's
    Prolific replica, the simulated participants arriving there as Prolific participants and
    sent back to it at the end: every submission awaits review, and the export and the
    analysis are made as for MTurk arrivals."""
    from sqlalchemy import select

    from server.app.storage.db import Database
    from server.app.storage.models import Participant
    from server.app.storage.replica_models import ProlificReplicaSubmission
    from server.commands.demo import DemoOptions, check, run_demo

    options = DemoOptions(
        out=tmp_path / "demo",
        participants=2,
        concurrency=2,
        rounds=(1, 1),
        workers=1,
        study=EXAMPLES / "office-study.toml",
        platform="prolific",
        learner_settings="\n[learner_settings.bam]\nalternations = 1\ncost_steps = 5\n"
        "dynamics_steps = 5\n",
    )
    check(options)
    table = run_demo(options)
    assert "| BAM " in table
    db = Database.from_url(f"sqlite:///{options.out / 'study.sqlite'}")
    try:
        with db.read() as s:
            submissions = list(s.scalars(select(ProlificReplicaSubmission)))
            participants = list(s.scalars(select(Participant)))
    finally:
        db.dispose()
    assert [row.status for row in submissions] == ["AWAITING REVIEW"] * 2
    assert {row.study_code for row in submissions} == {"C1DEMO01"}
    assert sorted(
        (p.platform, p.status, p.platform_participant_id) for p in participants
    ) == sorted(("prolific", "submitted", row.participant_id) for row in submissions)
    with (options.out / "export" / "participants.csv").open() as file:
        assert [row["platform"] for row in csv.DictReader(file)] == ["prolific"] * 2


def test_a_study_file_goes_on_prolific_for_the_demo() -> None:
    """The study's [completion] table in Prolific's mode and a [prolific] table, whatever the
    file said; the file still reads as a study."""
    import tomllib

    from server.app.study_file import DEFAULT_STUDY_CONFIG, parse_study_config
    from server.commands.demo import on_prolific

    for path in (DEFAULT_STUDY_CONFIG, EXAMPLES / "office-study.toml"):
        text = on_prolific(path.read_text())
        study = parse_study_config(tomllib.loads(text), str(path), path.parent)
        assert study.completion.mode == "prolific" and study.prolific is not None
    assert "[prolific]" in on_prolific('title = "x"\n')
    assert on_prolific('title = "x"\n').count("[completion]") == 1


def test_teach_at_an_address_where_no_server_listens_says_so_at_once(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Asked once before any participant starts (each retried for two minutes in silence)."""
    import socket

    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]  # bound, never listening: connections are refused
        assert main(["teach", "--url", f"http://127.0.0.1:{port}", "--participants", "1"]) == 1
    error = capsys.readouterr().err
    assert f"no study server answers at http://127.0.0.1:{port}" in error
    assert "bam-study serve" in error


def test_teach_takes_the_study_file_whose_environments_its_teachers_need(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("title = 1\n")
    url = ["teach", "--url", "http://127.0.0.1:9", "--participants", "1"]
    assert main([*url, "--study", str(bad)]) == 2
    assert "is not a valid study" in capsys.readouterr().err
    known = set(domains.names())
    try:
        assert main([*url, "--study", str(EXAMPLES / "office-study.toml")]) == 1  # no server
        assert set(domains.names()) - known == {"office-floor"}
    finally:
        for name in set(domains.names()) - known:
            domains.unregister(name)


def test_teach_refuses_a_study_whose_environments_it_was_not_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused before any simulated participant arrives (on Prolific each took a place and
    then failed with 'unknown environment'); with the study file, the same server is taught."""
    import tomllib

    from server.app.main import create_app
    from server.app.storage.db import Database
    from server.app.study_file import parse_study_config
    from tests.support.databases import migrated_sqlite
    from tests.support.server import FAST_LEARNERS, live, make_settings

    path = EXAMPLES / "office-study.toml"
    data = tomllib.loads(path.read_text())
    data["learner_settings"] = FAST_LEARNERS
    study = parse_study_config(data, str(path), path.parent)
    db = Database.from_url(migrated_sqlite(tmp_path / "study.db"))
    app = create_app(make_settings(str(db.engine.url)), study, db=db)
    try:
        with live(app) as url:
            assert client_study(url)["environments"] == ["navigation-tutorial", "office-floor"]
            # The server's process knows its study's environments; a teacher started apart
            # from it knows only the built-in ones.
            domains.unregister("office-floor")
            teach = ["teach", "--url", url, "--participants", "1", "--rounds", "1-1"]
            assert main(teach) == 1
            error = capsys.readouterr().err
            assert f"the study at {url} teaches environments of its own (office-floor)" in error
            assert "--study FILE" in error
            assert main([*teach, "--study", str(path)]) == 0
            assert "participants completed  1 of 1" in capsys.readouterr().out
    finally:
        db.dispose()


def client_study(url: str) -> dict[str, object]:
    import httpx

    response = httpx.get(f"{url}/api/study")
    assert response.status_code == 200
    return dict(response.json())


@pytest.mark.parametrize(
    ("argv", "usage"),
    [
        (["check", "x.toml", "--bogus"], "usage: bam-study check "),
        (["db", "scrub", "--bogus"], "usage: bam-study db "),
        (["prolific", "status", "a" * 24, "--bogus"], "usage: bam-study prolific status "),
    ],
)
def test_a_wrong_flag_is_answered_with_its_subcommands_usage(
    argv: list[str], usage: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exited:
        main(argv)
    assert exited.value.code == 2
    error = capsys.readouterr().err
    assert error.startswith(usage) and "unrecognized arguments: --bogus" in error


def test_a_command_waiting_for_its_servers_warm_up_says_why_and_how_long() -> None:
    import io

    from server.commands.live import WarmUpNotice

    stream = io.StringIO()
    notice = WarmUpNotice(stream, every=15.0)
    for seconds, warm in ((0.5, 0), (5.0, 0), (16.0, 1), (20.0, 1), (31.5, 1)):
        notice(seconds, {"update_processes_warm": warm, "update_processes": 2})
    lines = stream.getvalue().splitlines()
    assert "compiled kernels" in lines[0] and "about a minute" in lines[0]
    assert lines[1:] == [
        "  ... 16 s, 1 of 2 update processes ready",
        "  ... 32 s, 1 of 2 update processes ready",
    ]


def test_the_example_prolific_study_passes_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("BAM_PROLIFIC_CURRENCY", raising=False)  # GBP, the example's
    monkeypatch.setattr(check, "calibrate", lambda names: dict.fromkeys(names, 1e-9))
    study = EXAMPLES / "prolific-study.toml"
    assert main(["check", str(study), "--out", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert "no problems; 2 environment(s): two-rooms, doorway" in captured.out
    assert captured.err == ""
    # No [dataset] table: every question of the release is open.
    assert (
        "release: not answered in [dataset], and listed as such: rai:annotatorDemographics, "
        "rai:dataBiases, rai:dataUseCases, rai:dataSocialImpact, [dataset] license, [dataset] "
        "url, [dataset] citation, [dataset] authors\n"
    ) in captured.out
    answered = tmp_path / "answered.toml"
    answered.write_text(study.read_text() + ANSWERED_DATASET)
    assert main(["check", str(answered), "--out", str(tmp_path)]) == 0
    assert (
        "release: [dataset] answers every question the export cannot\n" in capsys.readouterr().out
    )


ANSWERED_DATASET = """
[dataset]
license = "CC0-1.0"
url = "https://example.org/data"
authors = ["A. Author"]
citation = "Author, A. (2026). Data."
annotator_demographics = "Adults on Prolific in the United Kingdom."
biases = "People who chose a game-like study."
use_cases = "Research on learning from people; not for judging individuals."
social_impact = "None known."
"""


def prolific_copy(folder: Path, *replacements: tuple[str, str]) -> Path:
    """The example Prolific study with each (old, new) replaced (each old must be there)."""
    text = (EXAMPLES / "prolific-study.toml").read_text()
    for old, new in replacements:
        assert old in text, old
        text = text.replace(old, new)
    path = folder / "broken-prolific-study.toml"
    path.write_text(text)
    return path


def test_check_refuses_a_prolific_study_prolific_would_refuse_or_that_speaks_of_mturk(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("BAM_PROLIFIC_CURRENCY", raising=False)
    monkeypatch.setattr(check, "calibrate", lambda names: dict.fromkeys(names, 1e-9))
    out = tmp_path / "out"
    study = prolific_copy(
        tmp_path,
        ("reward = 4.50", "reward = 2.50"),
        ("return your submission on Prolific", "return the HIT on Mechanical Turk"),
        ("Your Prolific ID is used", "Your worker ID is used"),
    )
    assert main(["check", str(study), "--out", str(out)]) == 1
    error = capsys.readouterr().err
    assert (
        "prolific.reward: 2.50 GBP for an estimated 30 minutes is 5.00 GBP an hour, below "
        "Prolific's minimum of 6.00 GBP an hour (at least 3.00 GBP)"
    ) in error
    assert "consent: speaks of MTurk ('HIT', 'Mechanical Turk', 'worker ID')" in error
    assert "2 problem(s) for Prolific" in error
    assert not out.exists()

    # The minimum is the workspace currency's: 3.50 for 30 minutes is enough in GBP, not USD.
    cheaper = prolific_copy(tmp_path, ("reward = 4.50", "reward = 3.50"))
    assert main(["check", str(cheaper), "--out", str(out)]) == 0
    capsys.readouterr()
    monkeypatch.setenv("BAM_PROLIFIC_CURRENCY", "USD")
    assert main(["check", str(cheaper), "--out", str(tmp_path / "out-usd")]) == 1
    assert "7.00 USD an hour, below Prolific's minimum of 8.00 USD an hour" in (
        capsys.readouterr().err
    )
    monkeypatch.delenv("BAM_PROLIFIC_CURRENCY")

    # A maximum time below Prolific's floor: the file itself is refused, as `serve` refuses it.
    hurried = prolific_copy(tmp_path, ("maximum_minutes = 90", "maximum_minutes = 31"))
    assert main(["check", str(hurried), "--out", str(tmp_path / "out-hurried")]) == 2
    assert "below Prolific's least maximum time for estimated_minutes 30: 73" in (
        capsys.readouterr().err
    )

    # No [prolific] table: nothing for `prolific create` to make.
    text = (EXAMPLES / "prolific-study.toml").read_text()
    bare = tmp_path / "bare-prolific-study.toml"
    bare.write_text(text[: text.index("\n[prolific]\n")] + text[text.index("\n[[domains]]") :])
    assert main(["check", str(bare), "--out", str(tmp_path / "out-bare")]) == 1
    assert "no [prolific] table" in capsys.readouterr().err


def test_check_finds_the_default_study_s_mturk_wording_when_it_runs_on_prolific(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The paper's study file switched to Prolific as it stands: its consent speaks of MTurk."""
    monkeypatch.delenv("BAM_PROLIFIC_CURRENCY", raising=False)
    default = Path(__file__).resolve().parents[2] / "server" / "config" / "study.toml"
    prolific = (EXAMPLES / "prolific-study.toml").read_text()
    table = prolific[prolific.index("\n[prolific]\n") : prolific.index("\n[[domains]]")]
    study = tmp_path / "study.toml"
    study.write_text(
        default.read_text().replace(
            'mode = "mturk"', 'mode = "prolific"\nprolific_code = "C7K2M9QX"'
        )
        + "\n"
        + table
    )
    assert main(["check", str(study), "--out", str(tmp_path / "out")]) == 1
    error = capsys.readouterr().err
    assert "consent: speaks of MTurk (" in error and "'Mechanical Turk'" in error
    assert "'HIT'" in error and "'requester'" in error
