"""Whole participant runs in headless Chromium through the local Mechanical Turk replica: the HIT
page, preview, accept, consent, tutorial, every agent taught with real key presses, a reload
mid-episode, completion, the submission the replica records; a HIT returned halfway whose
assignment id goes to another worker; and the dashboard showing the runs and replaying them.

The tests of this module share one server and run in order (the dashboard test looks at the
runs the others made)."""

from __future__ import annotations

import json
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Locator, Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    admin_login,
    domain_toml,
    run_live_server,
    study_frame,
    study_toml,
)

# Whole HITs driven in Chromium through the replica, every agent taught (about 30 s a test):
# the slow tier, which CI runs.
pytestmark = [pytest.mark.browser, pytest.mark.slow]

DOMAINS = domain_toml("navigation", "two-rooms") + domain_toml("farming", "two-fields")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    yield from run_live_server(
        tmp_path_factory.mktemp("mturk-study"), study_toml(mode="mturk", domains_toml=DOMAINS)
    )


def accept_hit(page: Page, server: LiveServer, worker: str, preview: bool = False) -> Study:
    """On the replica's HIT page: (preview, then) accept as ``worker``; the study's iframe."""
    page.goto(f"{server.url}/mturk")
    page.fill("#workerId", worker)
    if preview:
        page.click('[data-action="preview"]')
        frame = study_frame(page)
        assert "assignmentId=ASSIGNMENT_ID_NOT_AVAILABLE" in frame.url
        expect(frame.locator(".preview-note")).to_be_visible()
        page.click('[data-action="accept"]')
    else:
        page.click('[data-action="accept"]')
    page.wait_for_url(re.compile(r"/mturk/work/\d+$"))
    frame = study_frame(page)
    # Exactly the parameters MTurk appends, turkSubmitTo pointing back at this server.
    query = dict(re.findall(r"[?&]([^=&]+)=([^&]*)", frame.url))
    assert sorted(query) == ["assignmentId", "hitId", "turkSubmitTo", "workerId"]
    assert query["workerId"] == worker
    assert query["turkSubmitTo"] == server.url.replace(":", "%3A").replace("/", "%2F")
    return Study(page, frame)


def consent_and_start(study: Study) -> None:
    frame = study.frame
    frame.locator('[data-action="agree"]').click()
    frame.locator('[data-action="start"]').click()
    expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)


def teach_agent(
    study: Study, server: LiveServer, first: bool, last: bool, screenshot: Path | None
) -> None:
    """One agent, as a participant would: the Next refusal (on the first agent), a demonstration
    of every task (one reloaded mid-episode), moves in idle mode, an agent try with both kinds of
    feedback, a task switch by mouse; then Next (after the last agent: the completion page)."""
    tasks = study.frame.locator(".task").count()

    def next_button() -> Locator:
        return study.frame.locator('[data-action="next"]')

    if first:
        # "Next agent" is refused before each task has a demonstration: by the page...
        expect(next_button()).to_be_disabled()
        expect(study.frame.locator(".next-reason")).to_contain_text(
            "Every task needs at least one demonstrated move first"
        )
        session = study.session
        study.press("n")
        expect(study.frame.locator(".status")).to_contain_text("Not yet")
        assert study.session == session
        # ... and by the server, asked directly with the participant's next sequence number.
        seq = study.page.request.get(f"{server.url}/api/participant").json()["next_seq"]
        refused = study.page.request.post(
            f"{server.url}/api/sessions/{session}/finish", data={"seq": seq}
        )
        assert refused.status == 409
        assert "demonstrat" in refused.json()["detail"]
    for task in range(tasks):
        study.demonstrate(task, reload_after=2 if task == 0 else None)
        if task == 0 and screenshot is not None:
            study.select_task(0)
            study.frame_screenshot(screenshot)
            # The same inside the replica's HIT page, as a worker sees it.
            study.page.screenshot(path=str(screenshot.with_name(f"mturk-{screenshot.name}")))
        if task < tasks - 1:
            expect(next_button()).to_be_disabled()
    study.idle_move()
    study.idle_move()
    study.let_agent_try_with_feedback()
    # Switching tasks with the mouse, and back with the keyboard.
    study.frame.locator('.task[data-task="1"]').click()
    study.wait_for("task", 1)
    study.focus()
    study.select_task(0)
    expect(next_button()).to_be_enabled()
    # No completion code exists before the last agent is finished.
    assert study.page.request.get(f"{server.url}/api/participant/completion").status == 409
    if not last:
        study.next_agent()
        return
    study.press("n")
    expect(study.frame.locator('[data-action="confirm-next"]')).to_be_visible()
    study.press("Enter")


def full_run(page: Page, server: LiveServer, worker: str, shots: Path, preview: bool) -> str:
    """A participant from the HIT page to the submission; returns the domain taught."""
    study = accept_hit(page, server, worker, preview=preview)
    consent_and_start(study)
    domain = study.teach.get_attribute("class")
    assert domain is not None
    name = re.search(r"domain-(\w+)", domain)
    assert name is not None
    domain_name = name.group(1)
    study.do_tutorial(screenshot=shots / f"tutorial-{domain_name}.png")
    agents = int(
        server.query(
            "SELECT count(*) FROM learning_sessions s JOIN participants p "
            "ON p.id = s.participant_id WHERE p.platform_participant_id = :w AND s.kind = 'study'",
            w=worker,
        )[0][0]
    )
    assert agents == 2
    for index in range(agents):
        expect(study.frame.locator(".progress-label")).to_have_text(
            f"Agent {index + 1} of {agents}"
        )
        shot = shots / f"teaching-{domain_name}.png" if index == 0 else None
        teach_agent(study, server, first=index == 0, last=index == agents - 1, screenshot=shot)
    # The completion code, shown only now, is the one the database committed.
    code = study.frame.locator('[data-testid="completion-code"]')
    expect(code).to_be_visible(timeout=WAIT_MS)
    (stored,) = server.query(
        "SELECT completion_code, status, platform_submission_id FROM participants "
        "WHERE platform_participant_id = :w",
        w=worker,
    )
    assert code.inner_text() == stored.completion_code
    assert stored.status == "completed"
    study.frame_screenshot(shots / "completion.png")
    study.frame.locator('[data-action="submit-hit"]').click()
    # The form posts from the top window to {turkSubmitTo}/mturk/externalSubmit.
    page.wait_for_url(f"{server.url}/mturk/externalSubmit")
    expect(page.locator('[data-testid="assignment"]')).to_have_text(stored.platform_submission_id)
    expect(page.locator('tr[data-field="completionCode"] td').nth(1)).to_have_text(
        stored.completion_code
    )
    (submission,) = server.query(
        "SELECT assignment_id, worker_id, fields FROM mturk_replica_submissions "
        "WHERE worker_id = :w",
        w=worker,
    )
    fields = json.loads(submission.fields)
    assert submission.assignment_id == stored.platform_submission_id == fields["assignmentId"]
    assert fields["completionCode"] == stored.completion_code
    (status,) = server.query(
        "SELECT status FROM participants WHERE platform_participant_id = :w", w=worker
    )
    assert status.status == "submitted"
    return domain_name


def test_a_participant_completes_the_hit_through_the_replica(
    page: Page, server: LiveServer, screenshot_dir: Path
) -> None:
    watch = Watch(server.url).attach(page)
    admin_login(page, server)
    page.screenshot(path=str(screenshot_dir / "mturk-replica.png"))
    full_run(page, server, "WORKERALPHA", screenshot_dir, preview=True)
    # Every event the page sent is stored once, with its feedback and idle moves.
    (participant,) = server.query("SELECT id, next_seq FROM participants")
    (events,) = server.query(
        "SELECT count(*) FROM events WHERE participant_id = :p", p=participant.id
    )
    assert events[0] == participant.next_seq - 1
    kinds = dict(
        server.query(
            "SELECT record, count(*) FROM events WHERE participant_id = :p GROUP BY record",
            p=participant.id,
        )
    )
    assert kinds["feedback"] >= 6 and kinds["transition"] >= 6 and kinds["demonstration"] > 0
    watch.check()


def test_a_returned_hit_goes_to_the_next_worker_without_mixing_data(
    page: Page, server: LiveServer, screenshot_dir: Path
) -> None:
    watch = Watch(server.url).attach(page)
    admin_login(page, server)
    # A worker accepts, does the tutorial, demonstrates to the first agent, returns the HIT.
    study = accept_hit(page, server, "WORKERBRAVO")
    assignment = page.locator('[data-testid="assignment"]').inner_text()
    consent_and_start(study)
    study.do_tutorial()
    study.demonstrate(0)
    page.click('[data-action="return-hit"]')
    page.wait_for_url(f"{server.url}/mturk")
    expect(page.locator('#assignments tr[data-worker="WORKERBRAVO"]')).to_have_attribute(
        "data-status", "returned"
    )
    # MTurk gives the same assignment id to the next worker who accepts.
    domain = full_run(page, server, "WORKERCHARLIE", screenshot_dir, preview=False)
    rows = server.query(
        "SELECT id, platform_participant_id, platform_submission_id, status, domain "
        "FROM participants ORDER BY id"
    )
    by_worker = {row.platform_participant_id: row for row in rows}
    bravo, charlie = by_worker["WORKERBRAVO"], by_worker["WORKERCHARLIE"]
    assert bravo.platform_submission_id == charlie.platform_submission_id == assignment
    assert bravo.status == "returned" and charlie.status == "submitted"
    # Balanced assignment: the first worker completed one domain, the next got the other.
    assert {by_worker["WORKERALPHA"].domain, domain} == {"navigation", "farming"}
    # Nothing of one is in the other's data.
    for row in (bravo, charlie):
        (foreign,) = server.query(
            "SELECT count(*) FROM events e JOIN learning_sessions s ON s.id = e.session_id "
            "WHERE e.participant_id = :p AND s.participant_id != :p",
            p=row.id,
        )
        assert foreign[0] == 0
    # The returned worker's data is all there, and stops where they returned the HIT.
    for row in (bravo, charlie):
        (stored,) = server.query(
            "SELECT count(*), max(seq) FROM events WHERE participant_id = :p", p=row.id
        )
        (next_seq,) = server.query("SELECT next_seq FROM participants WHERE id = :p", p=row.id)
        assert stored[0] == stored[1] == next_seq[0] - 1
    (bravo_agents,) = server.query(
        "SELECT count(*) FROM learning_sessions WHERE participant_id = :p AND status = 'active'"
        " AND kind = 'study' AND episodes = 1",
        p=bravo.id,
    )
    assert bravo_agents[0] == 1
    submissions = server.query("SELECT worker_id FROM mturk_replica_submissions ORDER BY id")
    assert [row.worker_id for row in submissions] == ["WORKERALPHA", "WORKERCHARLIE"]
    watch.check()


def test_the_dashboard_shows_the_runs_and_replays_a_session(
    page: Page, server: LiveServer, screenshot_dir: Path
) -> None:
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    rows = page.locator("#participants tbody tr[data-participant]")
    expect(rows).to_have_count(3)
    charlie = page.locator("#participants tr", has_text="WORKERCHARLIE")
    expect(charlie).to_have_attribute("data-status", "submitted")
    expect(charlie).to_contain_text("2 / 2")
    expect(page.locator("#mturk-submissions tbody tr")).to_have_count(2)
    # Each submitted field on its own line (assignmentId, completionCode).
    expect(page.locator("#mturk-submissions tbody tr").first.locator("li.field")).to_have_count(2)
    charlie.click()
    cards = page.locator("#detail .session-card")
    expect(cards).to_have_count(3)  # the tutorial and two agents
    expect(page.locator("#detail svg.curve").nth(2)).not_to_have_attribute(
        "data-points", "0", timeout=WAIT_MS
    )
    page.screenshot(path=str(screenshot_dir / "dashboard.png"), full_page=True)
    # The replay of the last agent reaches the state the session ended in.
    last = cards.nth(2)
    session = int(str(last.get_attribute("data-session")))
    last.locator('[data-action="replay"]').click()
    board = page.locator("#replay .grid-box")
    expect(board).to_have_attribute("data-frame", "0")
    page.click('#replay [data-action="last"]')
    (final,) = server.query("SELECT state FROM learning_sessions WHERE id = :s", s=session)
    expect(board).to_have_attribute("data-state", str(final.state))
    expect(page.locator("#replay g.agent")).to_have_attribute("data-state", str(final.state))
    page.locator("#replay").screenshot(path=str(screenshot_dir / "replay.png"))
    # The export downloads as a zip with the analysis' files.
    with page.expect_download() as download:
        page.click('[data-action="export"]')
    path = download.value.path()
    with zipfile.ZipFile(path) as archive:
        names = set(archive.namelist())
    assert any(name.endswith("evaluations.csv") for name in names), names
    watch.check()
