"""``bam-study prolific`` and ``bam-study teach --platform prolific``: the study file's
``[prolific]`` table, the draft study it makes (Prolific's placeholders, the reward in cents, the
completion codes, the blocklist, the concurrency), the replica refusing what Prolific refuses,
and the whole run on a live server's replica: create, publish, simulated participants through
Prolific's link and completion redirect, status, places, pause."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from decimal import Decimal
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from server.app.export.columns import DICTIONARY
from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.platforms.prolific import (
    NO_CONSENT_REASON,
    ProlificClient,
    ProlificRefused,
    draft_study,
)
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Message, Participant, utcnow
from server.app.storage.replica_models import ProlificReplicaSubmission
from server.app.study_file import DEFAULT_STUDY_CONFIG, StudyConfigError, load_study_config
from server.commands import prolific as prolific_command
from server.commands.main import main
from tests.support.server import ADMIN_TOKEN, live, study_config

PILOT = "a1b2c3d4e5f60718293a4b5c"
PROLIFIC = {
    "name": "Teaching robots",
    "description": "Teach simulated robots in a grid world with the arrow keys.",
    "places": 3,
    "reward": 7.35,
    "estimated_minutes": 30,
    "maximum_minutes": 90,
    "previous_studies_blocklist": [PILOT],
    "public_url": "https://study.example.org/",
}
TEACH_PROLIFIC = ["--platform", "prolific", "--prolific-study"]
COMPLETION = {
    "mode": "prolific",
    "prolific_code": "C1A2B3C4",
    "prolific_no_consent_code": "NOCONSNT",
}


def toml_value(value: Any) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return str(value)


def study_file(folder: Path, completion: dict[str, str] | None = None, **prolific: Any) -> Path:
    """The paper's study file with a completion table and a [prolific] table (``None`` values
    left out; ``prolific`` empty of keys: no table)."""
    text = DEFAULT_STUDY_CONFIG.read_text()
    lines = [f"{key} = {toml_value(value)}" for key, value in (completion or COMPLETION).items()]
    text = text.replace('mode = "mturk"', "\n".join(lines))
    table = {**PROLIFIC, **prolific}
    if not prolific.get("omit"):
        text += "\n[prolific]\n" + "".join(
            f"{key} = {toml_value(value)}\n" for key, value in table.items() if value is not None
        )
    path = folder / "study.toml"
    path.write_text(text, encoding="utf-8")
    return path


# -- the [prolific] table and the draft it makes ------------------------------------------------
def test_the_draft_has_prolifics_placeholders_cents_codes_blocklist_and_concurrency(
    tmp_path: Path,
) -> None:
    study = load_study_config(study_file(tmp_path))
    fields = draft_study(study, max_concurrent=5)
    # The exact link the study page reads (PROLIFIC_PID, STUDY_ID, SESSION_ID at /study).
    assert fields["external_study_url"] == (
        "https://study.example.org/study?PROLIFIC_PID={{%PROLIFIC_PID%}}"
        "&STUDY_ID={{%STUDY_ID%}}&SESSION_ID={{%SESSION_ID%}}"
    )
    assert fields["reward"] == 735  # 7.35 as a float would give 734
    assert isinstance(fields["reward"], int)
    assert fields["prolific_id_option"] == "url_parameters"
    assert fields["completion_codes"] == [
        {
            "code": "C1A2B3C4",
            "code_type": "COMPLETED",
            "actor": "participant",
            "actions": [{"action": "MANUALLY_REVIEW"}],
        },
        {
            "code": "NOCONSNT",
            "code_type": "NO_CONSENT",
            "actor": "participant",
            "actions": [{"action": "REQUEST_RETURN", "return_reason": NO_CONSENT_REASON}],
        },
    ]
    assert NO_CONSENT_REASON.strip()
    assert fields["filters"] == [
        {"filter_id": "previous_studies_blocklist", "selected_values": [PILOT]}
    ]
    assert (fields["total_available_places"], fields["estimated_completion_time"]) == (3, 30)
    assert fields["maximum_allowed_time"] == 90
    assert fields["device_compatibility"] == ["desktop"]
    assert fields["submissions_config"] == {"max_concurrent_submissions": 5}
    assert fields["name"] == "Teaching robots" and fields["description"].startswith("Teach")

    # A rehearsal's link is the local server's; no blocklist, no filter; no NO_CONSENT code,
    # no second code.
    plain = load_study_config(
        study_file(
            tmp_path,
            completion={"mode": "prolific", "prolific_code": "DONE1"},
            previous_studies_blocklist=None,
        )
    )
    rehearsal = draft_study(plain, 2, "http://127.0.0.1:8000/")
    assert rehearsal["external_study_url"].startswith(
        "http://127.0.0.1:8000/study?PROLIFIC_PID={{%PROLIFIC_PID%}}&"
    )
    assert "filters" not in rehearsal
    assert [c["code"] for c in rehearsal["completion_codes"]] == ["DONE1"]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"reward": 6.555}, "prolific.reward: Decimal input should have no more than 2 decimal"),
        ({"reward": 0}, "prolific.reward: Input should be greater than 0"),
        ({"maximum_minutes": 20}, "maximum_minutes (20) is less than estimated_minutes (30)"),
        ({"maximum_minutes": 1440}, "maximum_minutes (1440) must be under 24 hours"),
        (
            {"maximum_minutes": 72},
            "maximum_minutes (72) is below Prolific's least maximum time for estimated_minutes "
            "30: 73",
        ),
        ({"places": 0}, "prolific.places: Input should be greater than or equal to 1"),
        ({"public_url": "http://study.example.org"}, "public address starts with https://"),
        ({"public_url": "https://study.example.org/study?x=1"}, "the server's address only"),
        ({"previous_studies_blocklist": ["pilot"]}, "'pilot': a Prolific study id is 24"),
        ({"rewrd": 6}, "prolific.rewrd: unknown key; did you mean reward?"),
        ({"name": None}, "prolific.name: Field required"),
    ],
)
def test_a_bad_prolific_table_is_refused_with_its_place_and_reason(
    tmp_path: Path, change: dict[str, Any], message: str
) -> None:
    with pytest.raises(StudyConfigError) as refused:
        load_study_config(study_file(tmp_path, **change))
    assert message in str(refused.value)


def test_the_concurrency_is_the_option_else_the_study_files_else_the_servers_capacity(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = Settings(admin_token=ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    asked: list[str] = []

    def limit(server: str, _: Settings) -> int | None:
        asked.append(server)
        return answer

    monkeypatch.setattr(prolific_command, "server_limit", limit)
    monkeypatch.setattr(prolific_command, "measured_capacity", lambda *_: 4)

    def args(**given: Any) -> argparse.Namespace:
        return argparse.Namespace(**{"max_concurrent": None, "replica": None, **given})

    answer: int | None = 7
    assert prolific_command.max_concurrent(args(max_concurrent=2), study, settings) == 2
    limited = study_config(completion=COMPLETION, prolific=PROLIFIC, max_active_participants=3)
    assert prolific_command.max_concurrent(args(), limited, settings) == 3
    assert asked == []
    # The server that will serve the study: the rehearsal's, else the public address.
    assert prolific_command.max_concurrent(args(replica="http://127.0.0.1:9"), study, settings) == 7
    assert prolific_command.max_concurrent(args(), study, settings) == 7
    assert asked == ["http://127.0.0.1:9", "https://study.example.org"]
    answer = None  # the server cannot tell: measured here
    assert prolific_command.max_concurrent(args(), study, settings) == 4


# -- the replica refuses what Prolific refuses -------------------------------------------------
def replica_client(db: Database) -> ProlificClient:
    return ProlificClient(
        "http://replica/prolific/api/v1",
        ADMIN_TOKEN,
        transport=ReplicaTransport(db, ADMIN_TOKEN),
        first_wait=0.0,
    )


def first_action(fields: dict[str, Any], code: int = 0) -> dict[str, Any]:
    action: dict[str, Any] = fields["completion_codes"][code]["actions"][0]
    return action


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        (lambda f: f.pop("description"), "description: This field is required"),
        (lambda f: first_action(f, 1).pop("return_reason"), "REQUEST_RETURN needs a return_reason"),
        (
            lambda f: f["completion_codes"][0]["actions"].append(
                {"action": "AUTOMATICALLY_APPROVE"}
            ),
            "MANUALLY_REVIEW cannot go with AUTOMATICALLY_APPROVE",
        ),
        (lambda f: first_action(f).update(action="AUTO_APPROVE"), "action is one of"),
        (lambda f: f["completion_codes"][0].update(actor="robot"), "actor is participant or"),
        (lambda f: f["completion_codes"][1].update(code="C1A2B3C4"), "is given twice"),
        (lambda f: f.update(device_compatibility=["watch"]), "device_compatibility"),
        (
            lambda f: f["filters"][0].update(selected_values=["pilot"]),
            "previous_studies_blocklist: selected_values are study ids",
        ),
        (
            lambda f: f.update(submissions_config={"max_concurrent_submissions": 0}),
            "max_concurrent_submissions is -1 (no limit) or at least 1",
        ),
        (lambda f: f.update(reward=7.35), "reward: a positive whole number"),
        (lambda f: f.update(maximum_allowed_time=24 * 60), "under 24 hours"),
        # 2 + 2 x 30 + 2 x sqrt(30) = 72.95: Prolific's floor for an estimate of 30 minutes.
        (lambda f: f.update(maximum_allowed_time=72), "at least 73 minutes"),
        (lambda f: f.update(maximum_allowed_time=31), "at least 73 minutes"),
    ],
)
def test_the_replica_refuses_a_draft_prolific_refuses_and_keeps_nothing(
    db: Database, spoil: Any, message: str
) -> None:
    fields = draft_study(study_config(completion=COMPLETION, prolific=PROLIFIC), 3)
    spoil(fields)
    client = replica_client(db)
    with pytest.raises(ProlificRefused, match=re.escape(message)):
        client.create_study(fields)
    made = client.create_study(
        draft_study(study_config(completion=COMPLETION, prolific=PROLIFIC), 3)
    )
    assert made["submissions_config"] == {"max_concurrent_submissions": 3}
    assert made["filters"][0]["selected_values"] == [PILOT]
    with db.read() as s:
        assert s.scalar(select(ProlificReplicaSubmission)) is None


# -- the command's refusals ---------------------------------------------------------------------
def run_command(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    try:
        status = main(argv)
    except SystemExit as exit_:  # argparse
        status = int(exit_.code or 0)
    out, err = capsys.readouterr()
    return status, out, err


def test_a_study_file_that_cannot_run_on_prolific_is_refused_before_anything_is_sent(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("BAM_PROLIFIC_TOKEN", "prolific-secret-token")
    monkeypatch.setenv("BAM_PROLIFIC_API_URL", "http://127.0.0.1:9/api/v1")  # nothing there
    sent: list[Any] = []
    monkeypatch.setattr(ProlificClient, "request", lambda *a, **k: sent.append(a))

    mturk = study_file(tmp_path, completion={"mode": "mturk"})
    status, _, err = run_command(
        ["prolific", "create", str(mturk), "--max-concurrent", "2"], capsys
    )
    assert status == 2 and 'the completion mode is "mturk"' in err

    bad = study_file(tmp_path, reward=6.555)
    status, _, err = run_command(["prolific", "create", str(bad), "--max-concurrent", "2"], capsys)
    assert status == 2 and "prolific.reward" in err and "2 decimal places" in err

    bare = study_file(tmp_path, omit=True)
    status, _, err = run_command(["prolific", "create", str(bare), "--max-concurrent", "2"], capsys)
    assert status == 2 and "has no [prolific] table" in err

    missing = tmp_path / "nowhere.toml"
    status, _, err = run_command(["prolific", "create", str(missing)], capsys)
    assert status == 2 and "cannot read the study configuration" in err

    status, _, err = run_command(["prolific", "publish", "not-an-id"], capsys)
    assert status == 2 and "is not a Prolific study id" in err
    status, _, err = run_command(["prolific", "add-places", "a" * 24, "0"], capsys)
    assert status == 2 and "at least 1" in err
    status, _, err = run_command(
        ["prolific", "create", str(study_file(tmp_path)), "--max-concurrent", "0"], capsys
    )
    assert status == 2 and "at least 1" in err

    monkeypatch.delenv("BAM_PROLIFIC_TOKEN")
    status, _, err = run_command(["prolific", "status", "a" * 24], capsys)
    assert status == 2 and "set BAM_PROLIFIC_TOKEN" in err
    assert sent == []

    # teach: Prolific participants need the study and the admin token; the study, Prolific.
    url = ["teach", "--url", "http://127.0.0.1:9"]
    monkeypatch.delenv("BAM_ADMIN_TOKEN", raising=False)
    status, _, err = run_command([*url, *TEACH_PROLIFIC, "a" * 24], capsys)
    assert status == 2 and "BAM_ADMIN_TOKEN" in err
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    status, _, err = run_command([*url, "--platform", "prolific"], capsys)
    assert status == 2 and "needs --prolific-study" in err
    status, _, err = run_command([*url, "--prolific-study", "a" * 24], capsys)
    assert status == 2 and "goes with --platform prolific" in err


# -- the whole run on a live server's replica ---------------------------------------------------
@pytest.fixture
def server(db: Database, settings: Settings, executor: ProcessPoolExecutor) -> Iterator[str]:
    """A study server running the Prolific study (the study file's learners made fast), whose
    dashboard says it serves 2 participants at once."""
    with server_with(db, settings, executor) as base:
        yield base


def test_a_study_runs_on_the_replica_from_the_command_line(
    server: str,
    db: Database,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    monkeypatch.delenv("BAM_PROLIFIC_TOKEN", raising=False)
    path = study_file(tmp_path)
    replica = ["--replica", server]

    status, out, err = run_command(["prolific", "create", str(path), *replica], capsys)
    assert status == 0, err
    study_id = out.strip()
    assert re.fullmatch(r"[0-9a-f]{24}", study_id)
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    made = client.get_study(study_id)
    assert made["status"] == "UNPUBLISHED"
    # The link is the rehearsal server's; the concurrency is what that server serves.
    assert made["external_study_url"].startswith(f"{server}/study?PROLIFIC_PID=")
    assert made["submissions_config"] == {"max_concurrent_submissions": 2}
    assert (made["reward"], made["total_available_places"]) == (735, 3)

    # Pausing a draft is refused by Prolific (the replica): one line, exit 1, no token.
    status, out, err = run_command(["prolific", "pause", study_id, *replica], capsys)
    assert status == 1 and "cannot PAUSE" in err and len(err.strip().splitlines()) == 1
    assert ADMIN_TOKEN not in err + out

    status, out, err = run_command(["prolific", "publish", study_id, *replica], capsys)
    assert (status, out.strip().splitlines()[-1]) == (0, f"study {study_id}: ACTIVE"), err

    status, out, err = run_command(
        [
            "teach",
            "--url",
            server,
            "--participants",
            "2",
            "--concurrency",
            "2",
            "--rounds",
            "1",
            *TEACH_PROLIFIC,
            study_id,
        ],
        capsys,
    )
    assert status == 0, out + err
    assert "participants completed  2 of 2" in out

    # The server's participants are the replica's, arrived through Prolific's link.
    submissions = {s["participant_id"]: s for s in client.submissions(study_id)}
    with db.read() as s:
        arrived = s.scalars(select(Participant)).all()
    assert len(arrived) == 2
    for participant in arrived:
        assert participant.platform == "prolific"
        assert participant.platform_study_id == study_id
        submission = submissions[participant.platform_participant_id]
        assert participant.platform_submission_id == submission["id"]
        assert (submission["status"], submission["study_code"]) == ("AWAITING REVIEW", "C1A2B3C4")

    status, out, err = run_command(["prolific", "status", study_id, *replica], capsys)
    assert status == 0, err
    assert re.search(r"^status\s+ACTIVE$", out, re.M), out
    assert re.search(r"^places\s+2 taken of 3$", out, re.M), out
    assert re.search(r"^  AWAITING REVIEW\s+2$", out, re.M), out

    status, out, err = run_command(["prolific", "add-places", study_id, "5", *replica], capsys)
    assert (status, out.strip()) == (0, f"study {study_id}: 5 places"), err
    status, out, err = run_command(["prolific", "add-places", study_id, "4", *replica], capsys)
    assert status == 1 and "places only go up" in err and "has 5 places" in err
    assert client.get_study(study_id)["total_available_places"] == 5

    status, out, err = run_command(["prolific", "pause", study_id, *replica], capsys)
    assert (status, out.strip()) == (0, f"study {study_id}: PAUSED"), err
    # Paused: the replica gives no one a place, and the simulated participant says so.
    status, out, err = run_command(
        ["teach", "--url", server, "--participants", "1", *TEACH_PROLIFIC, study_id], capsys
    )
    assert status == 1
    assert f"gave no place in study {study_id} (409)" in err and "is PAUSED" in err

    # Started again from our side; stopped for good; more places make it active again.
    status, out, err = run_command(["prolific", "start", study_id, *replica], capsys)
    assert (status, out.strip()) == (0, f"study {study_id}: ACTIVE"), err
    status, out, err = run_command(["prolific", "stop", study_id, *replica], capsys)
    assert (status, out.strip()) == (0, f"study {study_id}: COMPLETED"), err
    status, out, err = run_command(["prolific", "start", study_id, *replica], capsys)
    assert status == 1 and "cannot START" in err, err
    assert client.set_places(study_id, 6)["status"] == "ACTIVE"
    client.close()


@contextmanager
def server_with(
    db: Database,
    settings: Settings,
    executor: ProcessPoolExecutor,
    admits: int = 2,
    **changes: Any,
) -> Iterator[str]:
    """The study server of ``server`` with ``changes`` to its settings (its replica's
    currency, funds), admitting ``admits`` participants at once."""
    study = study_config(completion=COMPLETION, max_active_participants=admits)
    app = create_app(settings.model_copy(update=changes), study, db=db, executor=executor)
    with live(app) as base:
        yield base


def test_publish_checks_the_currency_the_hourly_pay_and_the_balance_before_it_publishes(
    db: Database,
    settings: Settings,
    executor: ProcessPoolExecutor,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    monkeypatch.setenv("BAM_PROLIFIC_CURRENCY", "GBP")
    fair = study_file(tmp_path)  # 3 places at 7.35 for 30 minutes: 14.70 an hour
    (tmp_path / "low").mkdir()
    low = study_file(tmp_path / "low", reward=2.5)  # 5.00 an hour

    def made(server: str, path: Path) -> str:
        status, out, err = run_command(
            ["prolific", "create", str(path), "--max-concurrent", "2", "--replica", server], capsys
        )
        assert status == 0, err
        return out.strip()

    # A workspace in another currency than BAM_PROLIFIC_CURRENCY: refused, naming both.
    with server_with(db, settings, executor, prolific_currency="USD") as server:
        study_id = made(server, fair)
        status, out, err = run_command(
            ["prolific", "publish", study_id, "--replica", server], capsys
        )
        assert status == 1
        assert "pays in USD, but BAM_PROLIFIC_CURRENCY is GBP" in err and "not published" in err
        client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
        assert client.get_study(study_id)["status"] == "UNPUBLISHED"
        client.close()

    # 25.00 GBP in the workspace: the study costs 3 x 7.35 with Prolific's fee, 29.39.
    with server_with(db, settings, executor, prolific_replica_funds=Decimal(25)) as server:
        client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
        study_id = made(server, fair)
        assert client.study_cost(735, 3) == 2939
        status, out, err = run_command(
            ["prolific", "publish", study_id, "--replica", server], capsys
        )
        assert status == 1, out
        assert "cost        29.39 GBP for 3 places at 7.35 GBP" in out
        assert "balance     25.00 GBP available" in out
        assert "hourly pay  14.70 GBP an hour" in out and "6.00 GBP" in out
        assert "has 25.00 GBP available, less than the study's cost of 29.39 GBP" in err
        assert "add at least 4.39 GBP" in err and len(err.strip().splitlines()) == 1
        assert client.get_study(study_id)["status"] == "UNPUBLISHED"
        client.close()

    with server_with(db, settings, executor) as server:  # 1,000.00 GBP
        client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
        workspace = client.workspace_of(client.get_study(made(server, fair)))
        before = client.balance(workspace)
        # Below Prolific's minimum hourly pay: refused unless forced.
        underpaid = made(server, low)
        status, out, err = run_command(
            ["prolific", "publish", underpaid, "--replica", server], capsys
        )
        assert status == 1
        assert "pays 5.00 GBP an hour" in err and "below Prolific's minimum of 6.00 GBP" in err
        assert "--force" in err and client.get_study(underpaid)["status"] == "UNPUBLISHED"
        assert client.balance(workspace) == before
        status, out, err = run_command(
            ["prolific", "publish", underpaid, "--force", "--replica", server], capsys
        )
        assert status == 0, err
        assert out.strip().splitlines()[-1] == f"study {underpaid}: ACTIVE"
        assert "publishing below Prolific's minimum" in err
        # Published, the study holds its cost: 3 x 2.50 with the fee, 10.00.
        after = client.balance(workspace)
        assert after["total_balance"] == before["total_balance"] == 100_000
        assert after["available_balance"] == before["available_balance"] - 1000
        # Published already: Prolific's refusal, not a second look at the money.
        status, out, err = run_command(
            ["prolific", "publish", underpaid, "--replica", server], capsys
        )
        assert status == 1 and "cannot PUBLISH" in err and out == ""
        client.close()


def test_a_refusal_of_prolifics_api_reaches_the_user_in_one_line_without_the_token(
    server: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("BAM_PROLIFIC_API_URL", f"{server}/prolific/api/v1")
    monkeypatch.setenv("BAM_PROLIFIC_TOKEN", "not-the-token-1234")
    status, out, err = run_command(["prolific", "status", "a" * 24], capsys)
    assert status == 1
    assert err.strip().splitlines() == [
        f"bam-study prolific status: Prolific refused GET /studies/{'a' * 24}/ (401): "
        "Invalid token."
    ]
    assert "not-the-token-1234" not in out + err
    monkeypatch.setenv("BAM_PROLIFIC_TOKEN", ADMIN_TOKEN)
    status, out, err = run_command(["prolific", "publish", "a" * 24], capsys)
    assert status == 1 and "(404)" in err and f"Study {'a' * 24} not found" in err


def test_the_replica_lets_in_no_more_than_max_concurrent_submissions_at_once(server: str) -> None:
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    made = client.create_study(draft_study(study, max_concurrent=1, base_url=server))
    client.transition_study(made["id"], "PUBLISH")
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    with (
        httpx.Client(base_url=server, headers=admin) as first,
        httpx.Client(base_url=server, headers=admin) as second,
    ):
        path = f"/prolific/studies/{made['id']}/take-part"
        assert first.post(path).status_code == 303
        busy = second.post(path)
        assert busy.status_code == 409 and "max_concurrent_submissions" in busy.text
        # The first finishes (the completion redirect): the second may take part.
        assert first.get("/prolific/submissions/complete?cc=C1A2B3C4").status_code == 200
        assert second.post(path).status_code == 303
    statuses = sorted(s["status"] for s in client.submissions(made["id"]))
    assert statuses == ["ACTIVE", "AWAITING REVIEW"]
    client.close()


@pytest.fixture
def one_at_once(db: Database, settings: Settings, executor: ProcessPoolExecutor) -> Iterator[str]:
    """A server that admits one participant at once (the server holds its Prolific study's
    concurrency to it)."""
    with server_with(db, settings, executor, admits=1) as base:
        yield base


def test_simulated_participants_beyond_the_studys_concurrency_wait_their_turn(
    one_at_once: str,
    db: Database,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = one_at_once
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    made = client.create_study(draft_study(study, max_concurrent=1, base_url=server))
    client.transition_study(made["id"], "PUBLISH")
    status, out, err = run_command(
        [
            "teach",
            "--url",
            server,
            "--participants",
            "2",
            "--concurrency",
            "2",
            "--rounds",
            "1",
            *TEACH_PROLIFIC,
            made["id"],
        ],
        capsys,
    )
    assert status == 0, out + err
    listed = list(client.submissions(made["id"]))
    assert [s["status"] for s in listed] == ["AWAITING REVIEW"] * 2
    # One at a time: the second began after the first had completed.
    first, second = sorted(listed, key=lambda s: s["started_at"])
    assert second["started_at"] >= first["completed_at"]
    client.close()


def test_a_simulated_participant_does_not_follow_a_link_to_another_server(
    server: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    made = client.create_study(draft_study(study, max_concurrent=1))  # the public address
    client.transition_study(made["id"], "PUBLISH")
    status, _, err = run_command(
        ["teach", "--url", server, "--participants", "1", *TEACH_PROLIFIC, made["id"]], capsys
    )
    assert status == 1
    assert "https://study.example.org/study?PROLIFIC_PID=" in err
    assert f"is not on {server}: make the rehearsal's study with" in err
    client.close()


def test_the_replica_gives_a_draft_without_a_maximum_time_the_largest(db: Database) -> None:
    """Prolific: "If it is not provided the default value is set to the max value"; the floor
    itself is accepted."""
    client = replica_client(db)
    fields = draft_study(study_config(completion=COMPLETION, prolific=PROLIFIC), 3)
    del fields["maximum_allowed_time"]
    assert client.create_study(fields)["maximum_allowed_time"] == 24 * 60 - 1
    fields["maximum_allowed_time"] = 73
    assert client.create_study(fields)["maximum_allowed_time"] == 73


def take_part(server: str, study_id: str, finish: bool, arrive: bool = False) -> tuple[str, str]:
    """A replica participant takes a place in the study (a new PROLIFIC_PID), arrives at the
    study server through the study's link when ``arrive``, and completes the submission with
    the study's code when ``finish``; their PROLIFIC_PID and submission id."""
    with httpx.Client(base_url=server, headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}) as who:
        taken = who.post(f"/prolific/studies/{study_id}/take-part")
        assert taken.status_code == 303, taken.text
        link = taken.headers["location"]
        pid = re.search(r"PROLIFIC_PID=([0-9a-f]{24})", link)
        submission = re.search(r"SESSION_ID=([0-9a-f]{24})", link)
        assert pid is not None and submission is not None
        if arrive:
            ids = {"PROLIFIC_PID": pid[1], "STUDY_ID": study_id, "SESSION_ID": submission[1]}
            arrived = httpx.post(f"{server}/api/arrivals", json=ids)
            assert arrived.status_code == 201, arrived.text
        if finish:
            assert who.get("/prolific/submissions/complete?cc=C1A2B3C4").status_code == 200
        return pid[1], submission[1]


def test_counts_prints_prolifics_count_of_the_studys_submissions_per_status(
    server: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    made = client.create_study(draft_study(study, max_concurrent=3, base_url=server))
    other = client.create_study(draft_study(study, max_concurrent=3, base_url=server))
    for study_id in (made["id"], other["id"]):
        client.transition_study(study_id, "PUBLISH")
    take_part(server, made["id"], finish=True)
    take_part(server, made["id"], finish=True)
    _, returned = take_part(server, made["id"], finish=False)
    take_part(server, other["id"], finish=False)  # another study's: not counted
    with httpx.Client(base_url=server, headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}) as who:
        assert who.post(f"/prolific/submissions/{returned}/return").status_code == 303

    counted = client.submission_counts(made["id"])
    assert counted == {
        "ACTIVE": 0,
        "APPROVED": 0,
        "AWAITING REVIEW": 2,
        "REJECTED": 0,
        "RESERVED": 0,
        "RETURNED": 1,
        "TIMED-OUT": 0,
        "PARTIALLY APPROVED": 0,
        "SCREENED OUT": 0,
        "TOTAL": 3,
    }
    # The same as counting the listed submissions one by one.
    listed = [s["status"] for s in client.submissions(made["id"])]
    assert {k: v for k, v in counted.items() if v and k != "TOTAL"} == {
        status: listed.count(status) for status in set(listed)
    }

    status, out, err = run_command(["prolific", "counts", made["id"], "--replica", server], capsys)
    assert status == 0, err
    lines = out.strip().splitlines()
    assert lines[0] == f"study {made['id']}"
    assert re.fullmatch(r"status\s+submissions", lines[1])
    rows = dict(line.rsplit(None, 1) for line in lines[2:])
    assert rows == {k: str(v) for k, v in counted.items()}
    assert lines[-1].split() == ["TOTAL", "3"]
    # In the order of Prolific's submission statuses.
    assert [line.rsplit(None, 1)[0] for line in lines[2:5]] == ["RESERVED", "ACTIVE", "TIMED-OUT"]

    status, out, err = run_command(["prolific", "counts", "a" * 24, "--replica", server], capsys)
    assert status == 1 and out == ""
    assert f"Study {'a' * 24} not found" in err and "(404)" in err
    status, _, err = run_command(["prolific", "counts", "not-a-study"], capsys)
    assert status == 2 and "is not a Prolific study id" in err
    client.close()


def test_message_sends_through_prolific_and_keeps_each_message_until_the_participant_is_erased(
    server: str,
    db: Database,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    monkeypatch.setenv("BAM_DATABASE_URL", db.engine.url.render_as_string(hide_password=False))
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    made = client.create_study(draft_study(study, max_concurrent=3, base_url=server))
    study_id = made["id"]
    client.transition_study(study_id, "PUBLISH")
    # Two finish (AWAITING REVIEW), one is still taking part; all three arrived at the server.
    first, _ = take_part(server, study_id, finish=True, arrive=True)
    second, _ = take_part(server, study_id, finish=True, arrive=True)
    working, _ = take_part(server, study_id, finish=False, arrive=True)
    replica = ["--replica", server]

    def stored() -> list[tuple[str, str, str, int, str]]:
        with db.read() as s:
            rows = s.scalars(select(Message).order_by(Message.id)).all()
            return [
                (m.platform_participant_id, m.body, m.sent_with, m.answer_status, m.backend)
                for m in rows
            ]

    # One participant: POST /messages/; Prolific keeps it, and so do we.
    thanks = "Thank you for teaching the robots! Your submission will be reviewed today."
    status, out, err = run_command(
        ["prolific", "message", "--study", study_id, "--to", first, "--body", thanks, *replica],
        capsys,
    )
    assert status == 0, err
    assert out.strip() == (
        f"sent to 1 participant(s) of study {study_id} (Prolific answered 204); stored in messages"
    )
    [kept] = client.messages_with(first)
    assert (kept["body"], kept["data"]["study_id"]) == (thanks, study_id)
    assert stored() == [(first, thanks, "messages", 204, "prolific-replica")]

    # Everyone awaiting review: one bulk call, to the two who finished and not the third.
    later = "A bonus follows within two days."
    everyone = ["--status", "AWAITING_REVIEW", "--body", later]
    status, out, err = run_command(
        ["prolific", "message", "--study", study_id, *everyone, *replica], capsys
    )
    assert status == 0, err
    assert out.startswith(f"sent to 2 participant(s) of study {study_id}"), out
    assert [m["body"] for m in client.messages_with(first)] == [thanks, later]
    assert [m["body"] for m in client.messages_with(second)] == [later]
    assert client.messages_with(working) == []
    assert stored()[1:] == [
        (first, later, "messages/bulk", 204, "prolific-replica"),
        (second, later, "messages/bulk", 204, "prolific-replica"),
    ]

    # Refused before anything is sent: an unknown participant (among known ones), an empty
    # message, a status Prolific does not have. Nothing is sent or stored.
    unknown = "f" * 24
    for argv, code, said in (
        (["--to", second, unknown, "--body", later], 1, f"{unknown}: no participant of study"),
        (["--to", second, "--body", "  "], 2, "the message is empty"),
        (["--status", "FINISHED", "--body", later], 2, "is not a Prolific submission status"),
    ):
        status, out, err = run_command(
            ["prolific", "message", "--study", study_id, *argv, *replica], capsys
        )
        assert (status, out) == (code, ""), err
        assert said in err.strip().splitlines()[-1], err
    assert len(stored()) == 3 and client.messages_with(unknown) == []
    assert [m["body"] for m in client.messages_with(second)] == [later]

    # One of ours whom Prolific refuses (no submission of the study on Prolific): its refusal
    # in one line, exit 1, nothing stored.
    stranger = {"PROLIFIC_PID": "e" * 24, "STUDY_ID": study_id, "SESSION_ID": "d" * 24}
    assert httpx.post(f"{server}/api/arrivals", json=stranger).status_code == 201
    status, out, err = run_command(
        ["prolific", "message", "--study", study_id, "--to", "e" * 24, "--body", later, *replica],
        capsys,
    )
    assert (status, out) == (1, "")
    assert "Prolific refused POST /messages/ (400)" in err and "has no submission in study" in err
    assert len(stored()) == 3

    # Exported, the ids pseudonymised as in participants.csv.
    tables = export_tables(db)
    messages = tables["messages"]
    assert list(messages.columns) == list(DICTIONARY["messages"])
    participants = tables["participants"].set_index("participant_id")
    assert list(messages["body"]) == [thanks, later, later]
    assert list(messages["prolific_answer"]) == [204, 204, 204]
    for _, row in messages.iterrows():
        assert row["platform_participant_id"].startswith("w_") and row["study_id"] == study_id
        assert (
            participants.loc[row["participant_id"], "platform_participant_id"]
            == row["platform_participant_id"]
        )
    first_pseudonym = messages["platform_participant_id"].iloc[0]

    # Erased with the participant: their two rows go, and the audit row counts them.
    status, out, err = run_command(["erase", first, "--yes"], capsys)
    assert status == 0, err
    assert "messages 2" in out
    assert [row[0] for row in stored()] == [second]
    erasures = export_tables(db)["erasures"]
    assert list(erasures["messages_rows"]) == [2]
    assert list(erasures["platform_participant_id"]) == [first_pseudonym]
    # Scrubbed like the other ids: the raw PROLIFIC_PID is replaced by its pseudonym.
    status, out, err = run_command(["db", "scrub"], capsys)
    assert status == 0, err
    with db.read() as s:
        assert s.scalars(select(Message.platform_participant_id)).all() == [
            messages["platform_participant_id"].iloc[2]
        ]
    assert list(export_tables(db)["messages"]["platform_participant_id"]) == list(
        messages["platform_participant_id"][2:]
    )
    client.close()


def test_the_replica_messages_every_recipient_or_none_and_lists_what_it_sent(db: Database) -> None:
    client = replica_client(db)
    made = client.create_study(
        draft_study(study_config(completion=COMPLETION, prolific=PROLIFIC), 3)
    )
    took_part, stranger = "a" * 24, "b" * 24
    with db.write() as s:
        s.add(
            ProlificReplicaSubmission(
                id="1" * 24,
                study_id=made["id"],
                participant_id=took_part,
                status="AWAITING REVIEW",
                started_at=utcnow(),
            )
        )
    # One recipient without a submission of the study: the bulk message goes to no one.
    with pytest.raises(ProlificRefused, match=f"Participant {stranger} has no submission"):
        client.send_message(made["id"], [took_part, stranger], "Hello")
    with pytest.raises(ProlificRefused, match="body: This field may not be blank"):
        client.send_message(made["id"], [took_part], "  ")
    with pytest.raises(ProlificRefused, match=f"Study {'c' * 24} not found"):
        client.send_message("c" * 24, [took_part], "Hello")
    assert client.messages_with(took_part) == []
    assert client.send_message(made["id"], [took_part, took_part], "Hello") == 204
    [sent] = client.messages_with(took_part)
    assert (sent["body"], sent["type"], sent["data"]) == (
        "Hello",
        "message",
        {"study_id": made["id"]},
    )
    with pytest.raises(ProlificRefused, match="user_id or created_after is required"):
        client.request("GET", "messages/")
    since = client.request("GET", "messages/", params={"created_after": "2026-01-01T00:00:00Z"})
    assert [m["id"] for m in since["results"]] == [sent["id"]]
    client.close()


# -- hooks, participant groups, scheduled publishing, the server's capacity ---------------------
def test_hooks_makes_the_secret_subscribes_confirms_and_the_webhook_checks_by_it(
    server: str,
    db: Database,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from server.app.platforms.prolific_replica import WORKSPACE_ID
    from server.app.platforms.prolific_sync import signature
    from server.app.storage.models import ProlificWebhookSecret

    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    monkeypatch.setenv("BAM_DATABASE_URL", db.engine.url.render_as_string(hide_password=False))
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    study = study_config(completion=COMPLETION, prolific=PROLIFIC)
    study_id = client.create_study(draft_study(study, max_concurrent=3, base_url=server))["id"]
    replica = ["--replica", server]

    status, out, err = run_command(["prolific", "hooks", study_id, *replica], capsys)
    assert status == 0, err
    assert f"workspace {WORKSPACE_ID}: a new signing secret, stored in the database" in out
    listed = client.subscriptions(WORKSPACE_ID)
    assert sorted(s["event_type"] for s in listed) == [
        "study.has_high_return_rate",
        "study.status.change",
        "submission.status.change",
    ]
    assert {s["target_url"] for s in listed} == {f"{server}/prolific/webhook"}
    assert all(s["is_enabled"] for s in listed)
    with db.read() as s:
        [stored] = s.scalars(select(ProlificWebhookSecret)).all()
    assert stored.workspace_id == WORKSPACE_ID
    secrets_now = client.request("GET", "hooks/secrets/", params={"workspace_id": WORKSPACE_ID})
    assert [x["value"] for x in secrets_now["results"]] == [stored.secret]
    assert stored.secret not in out + err

    # Publishing sends study.status.change to the subscription, which the server takes.
    client.transition_study(study_id, "PUBLISH")
    study_hook = next(s for s in listed if s["event_type"] == "study.status.change")

    def succeeded() -> bool:
        return [e["status"] for e in client.hook_events(study_hook["id"])] == ["SUCCEEDED"]

    from tests.support.server import wait_until

    wait_until(succeeded, "the study event's delivery")
    status, out, err = run_command(["prolific", "hooks", study_id, "--list", *replica], capsys)
    assert status == 0, err
    assert re.search(
        r"study\.status\.change\s+\S+/prolific/webhook  deliveries: 1 \(1 SUCCEEDED\)", out
    ), out
    assert "subscriptions of workspace" in out and "new signing secret" not in out

    # The webhook takes an event signed with the stored secret; run again, the secret is
    # replaced (the old one no longer signs) and no subscription is made twice.
    body = b'{"event_type": "study.status.change", "resource_id": "%s", "status": "PAUSED"}' % (
        study_id.encode()
    )
    import time

    def send(secret: str, event: str) -> httpx.Response:
        stamp = str(int(time.time()))
        return httpx.post(
            f"{server}/prolific/webhook",
            content=body,
            headers={
                "X-Prolific-Request-Signature": signature(secret, stamp, body),
                "X-Prolific-Request-Timestamp": stamp,
                "X-Event-ID": event,
            },
        )

    assert send(stored.secret, "e1").status_code == 200
    status, out, err = run_command(["prolific", "hooks", study_id, *replica], capsys)
    assert status == 0, err
    assert len(client.subscriptions(WORKSPACE_ID)) == 3
    with db.read() as s:
        [renewed] = s.scalars(select(ProlificWebhookSecret)).all()
    assert renewed.secret != stored.secret
    assert send(renewed.secret, "e2").status_code == 200
    assert send(stored.secret, "e3").status_code == 401

    # A database the secret cannot be stored in: refused before Prolific makes a new one.
    monkeypatch.setenv(
        "BAM_DATABASE_URL", f"sqlite:///{Path(db.engine.url.database or '.').parent}/none/x.db"
    )
    status, out, err = run_command(["prolific", "hooks", study_id, *replica], capsys)
    assert status != 0
    with db.read() as s:
        assert s.scalars(select(ProlificWebhookSecret.secret)).all() == [renewed.secret]
    client.close()


def test_create_waits_for_the_running_servers_capacity(monkeypatch: pytest.MonkeyPatch) -> None:
    """A server still measuring its capacity answers the queue with no limit: create asks
    again until it states one, and sends that, never a capacity measured on its own."""
    settings = Settings(admin_token=ADMIN_TOKEN)
    answers = iter([None, None, 79])
    waited: list[float] = []

    def get(url: str, **_: Any) -> httpx.Response:
        assert url == "http://127.0.0.1:9/api/admin/queue"
        return httpx.Response(200, json={"limit": next(answers)}, request=httpx.Request("GET", url))

    clock = iter(range(1000))
    limit = prolific_command.server_limit(
        "http://127.0.0.1:9", settings, get=get, sleep=waited.append, clock=lambda: next(clock)
    )
    assert limit == 79 and waited == [prolific_command.CAPACITY_ASK_SECONDS] * 2

    # One that never states it: refused, with what to give instead.
    def never(url: str, **_: Any) -> httpx.Response:
        return httpx.Response(200, json={"limit": None}, request=httpx.Request("GET", url))

    times = iter([0.0, 1.0, prolific_command.CAPACITY_WAIT_SECONDS + 1])
    with pytest.raises(prolific_command.Refused, match="give --max-concurrent N"):
        prolific_command.server_limit(
            "http://127.0.0.1:9",
            settings,
            get=never,
            sleep=waited.append,
            clock=lambda: next(times),
        )

    # No server there: None (create then measures the capacity itself).
    def down(url: str, **_: Any) -> httpx.Response:
        raise httpx.ConnectError("refused")

    assert prolific_command.server_limit("http://127.0.0.1:9", settings, get=down) is None


def test_create_makes_the_familys_group_blocks_it_and_adds_the_finishers(
    server: str,
    db: Database,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from server.app.platforms.prolific_replica import WORKSPACE_ID

    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    path = study_file(tmp_path, family_group="BAM teaching", follow_up_group="BAM follow-up")
    replica = ["--replica", server]
    status, out, err = run_command(["prolific", "create", str(path), *replica], capsys)
    assert status == 0, err
    first = out.strip()
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    groups = {
        g["name"]: g["id"]
        for g in client.request(
            "GET", "participant-groups/", params={"workspace_id": WORKSPACE_ID}
        )["results"]
    }
    assert set(groups) == {"BAM teaching", "BAM follow-up"}
    made = client.get_study(first)
    assert {
        "filter_id": "participant_group_blocklist",
        "selected_values": [groups["BAM teaching"]],
    } in made["filters"]
    assert made["completion_codes"][0]["actions"] == [
        {"action": "MANUALLY_REVIEW"},
        {"action": "ADD_TO_PARTICIPANT_GROUP", "participant_group": groups["BAM teaching"]},
        {"action": "ADD_TO_PARTICIPANT_GROUP", "participant_group": groups["BAM follow-up"]},
    ]
    client.transition_study(first, "PUBLISH")
    finisher, _ = take_part(server, first, finish=True)
    assert client.group_members(groups["BAM teaching"]) == [finisher]

    # The next study of the family finds the same group (none made twice) and keeps the
    # finisher out; a follow-up lets in only its group.
    status, out, err = run_command(["prolific", "create", str(path), *replica], capsys)
    second = out.strip()
    assert status == 0 and second != first
    listed = client.request("GET", "participant-groups/", params={"workspace_id": WORKSPACE_ID})
    assert len(listed["results"]) == 2
    client.transition_study(second, "PUBLISH")
    with httpx.Client(base_url=server, headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}) as who:
        barred = who.post(
            f"/prolific/studies/{second}/take-part", params={"participant_id": finisher}
        )
    assert barred.status_code == 403
    follow_up = study_file(tmp_path, only_group="BAM follow-up", previous_studies_blocklist=None)
    status, out, err = run_command(["prolific", "create", str(follow_up), *replica], capsys)
    assert status == 0, err
    assert client.get_study(out.strip())["filters"] == [
        {"filter_id": "participant_group_allowlist", "selected_values": [groups["BAM follow-up"]]}
    ]
    client.close()


def test_publish_at_schedules_the_study_after_the_money_checks(
    server: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from datetime import UTC, datetime, timedelta

    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    replica = ["--replica", server]
    status, out, err = run_command(
        ["prolific", "create", str(study_file(tmp_path)), *replica], capsys
    )
    study_id = out.strip()
    when = (datetime.now(UTC) + timedelta(days=1)).replace(microsecond=0)
    status, out, err = run_command(
        ["prolific", "publish", study_id, "--at", when.isoformat(), *replica], capsys
    )
    assert status == 0, err
    assert (
        "balance" in out
        and f"study {study_id}: SCHEDULED (to publish at {when.isoformat()})" in out
    )
    client = ProlificClient(f"{server}/prolific/api/v1", ADMIN_TOKEN)
    assert client.get_study(study_id)["status"] == "SCHEDULED"
    status, out, err = run_command(
        ["prolific", "publish", study_id, "--at", "2020-01-01T00:00+00:00", *replica], capsys
    )
    assert status == 2 and "is not in the future" in err
    status, out, err = run_command(
        ["prolific", "publish", study_id, "--at", "2030-01-01T09:00", *replica], capsys
    )
    assert status == 2 and "has no time zone" in err
    client.close()
