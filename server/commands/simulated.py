"""Simulated participants that take the study over HTTP, through the same API as the browser.

Each one arrives with MTurk-style parameters (or as a worker who accepted the HIT on the MTurk
replica: ``MTurkReplicaArrival``; or, on the Prolific replica, as a Prolific participant:
``ProlificArrival``), consents, goes through the tutorial and teaches
every agent: in rounds, each task gets a demonstration by the simulated teacher (with a chance
of suboptimal moves) from a random start, sometimes after moving the agent in idle mode, and
sometimes an agent try with A-SABL feedback; the number of rounds varies per agent. It then
finishes, checks its completion code and records the submission. Requests are retried with the
same sequence number through connection losses and server restarts, so every request is
acknowledged exactly once; ``ParticipantRun`` counts them and times them, each from its first
attempt (what a participant would wait), and counts the requests that needed a retry.

``SimulatedParticipant`` (about 360 lines) is a participant's whole way through the study,
step by step in the order of the pages, so it is one class in one module.
"""

from __future__ import annotations

import html
import http.client
import json
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import httpx
import numpy as np

from server.app.participants.tokens import TOKEN_HEADER
from server.app.storage.vocabulary import CheckStatus, Mode, ParticipantStatus, SessionKind
from server.domains import make as make_environment
from server.domains.base import ACTIONS
from server.teacher import Teacher


class StudyClientError(RuntimeError):
    """The server refused a request of a simulated participant (a bug, not a hiccup)."""


class Stopped(Exception):
    """The run was asked to stop; the participant sends nothing more."""


PARTICIPANT_KINDS = ("careful", "key-masher", "idle")
MTURK_PARAMETERS = ("assignmentId", "hitId", "workerId", "turkSubmitTo")
# The participant's token as the study page gives it to its script (templates/study.html).
PAGE_TOKEN = re.compile(
    r'<script type="application/json" id="participant-token">("[^"<]*")</script>'
)
# The study in the MTurk replica's HIT frame (templates/mturk_frame.html).
HIT_FRAME = re.compile(r'<iframe[^>]*id="hit-frame"[^>]*src="([^"]*)"')


@dataclass(frozen=True)
class MTurkReplicaArrival:
    """Arrive as a worker who accepted the HIT on the server's MTurk replica (``/mturk``,
    signed in with the admin token), with the parameters its HIT frame gives the study; at the
    end, post the completion form to ``turkSubmitTo``'s ``/mturk/externalSubmit``, as the page
    does, so that the replica has the assignment submitted (and a bonus can be paid for it)."""

    admin_token: str


@dataclass(frozen=True)
class ProlificArrival:
    """Arrive as a Prolific participant of ``study_id`` on the server's Prolific replica, as a
    browser does: take a place (``/prolific/studies/{id}/take-part``, the researcher's button,
    signed in with the admin token), open the study link it redirects to (PROLIFIC_PID,
    STUDY_ID and SESSION_ID filled in) and read the token the page gives its script; at the
    end, follow the completion redirect, which for a study of the replica is the replica's
    ``/prolific/submissions/complete?cc=CODE`` (standing in for Prolific's), so that the
    submission awaits review."""

    study_id: str
    admin_token: str


@dataclass(frozen=True)
class TeachingPlan:
    min_rounds: int = 1  # rounds of demonstrations per agent (one per task each)
    max_rounds: int = 3
    mistake_probability: float = 0.1  # the teacher's chance of a random move
    agent_try_probability: float = 0.5  # after each demonstration
    idle_move_probability: float = 0.3  # move the agent in idle mode before a demonstration
    refresh_probability: float = 0.05  # reload the state as a refreshed page would
    max_agent_steps: int | None = None  # per agent try (default: the environment's horizon)
    think_seconds: float = 0.0  # pause before each move (a person pressing keys)
    agent_step_seconds: float = 0.0  # pause before each agent step (the page's animation)
    episode_pause_seconds: float = 0.0  # pause before each episode (look, choose, reset)
    retry_seconds: float = 120.0  # keep retrying a request this long (server restarts)
    # How decisive the + and - are: A-SABL's alpha on the move's advantage (1.0: the paper's
    # simulated teacher, whose + and - agree with the move's worth only a little more often
    # than chance; 10: a person who judges each move and seldom errs)
    feedback_alpha: float = 1.0
    # careful: the teacher above; key-masher: random moves and random + or - on every agent
    # move; idle: careful, but away for idle_seconds before each agent
    kind: str = "careful"
    idle_seconds: float = 0.0
    # In an attention check (move the robot to the star): the chance of a random arrow instead
    # of one along the shortest way (a key-masher presses only random arrows).
    check_mistake_probability: float = 0.0

    def __post_init__(self) -> None:
        if not self.feedback_alpha > 0:
            raise ValueError(f"feedback_alpha must be above 0, got {self.feedback_alpha!r}")
        if not 0 <= self.check_mistake_probability <= 1:
            raise ValueError(
                "check_mistake_probability must be between 0 and 1, got "
                f"{self.check_mistake_probability!r}"
            )
        if self.kind not in PARTICIPANT_KINDS:
            raise ValueError(
                f"kind must be one of {', '.join(PARTICIPANT_KINDS)}, got {self.kind!r}"
            )


# The participants of the server benchmark (benchmarks/server.py, at its pace) and of the
# capacity's timing of the server's own work (server_share.py): two to four rounds an agent,
# at most 30 agent steps a try.
STUDY_PLAN = TeachingPlan(min_rounds=2, max_rounds=4, max_agent_steps=30)


@dataclass
class ParticipantRun:
    """What one simulated participant did, as the client saw it."""

    index: int
    worker_id: str
    assignment_id: str
    participant_id: int | None = None
    acknowledged: int = 0  # requests with a seq answered 2xx, each counted once
    retries: int = 0  # attempts sent again, over all requests
    # Latencies (from the first attempt) of the requests that needed at least one retry.
    retried_latencies: list[float] = field(default_factory=list)
    status: str | None = None  # the participant's status on arrival
    completed: bool = False
    stopped: bool = False
    completion_code: str | None = None
    sessions: int = 0
    episodes: int = 0
    attention_checks: int = 0  # checks taken
    failed_checks: int = 0  # of them failed (as the server decided)
    latencies: dict[str, list[float]] = field(default_factory=dict)
    # When each of ``latencies`` was first sent (time.perf_counter), in the same order.
    sent: dict[str, list[float]] = field(default_factory=dict)
    update_waits: list[float] = field(default_factory=list)
    error: str | None = None

    @property
    def retried_requests(self) -> int:
        return len(self.retried_latencies)


RETRY_STATUSES = {500, 502, 503, 504}
_dumps = json.dumps
# Failures of the connection, after which a request is sent again.
TRANSPORT_ERRORS = (httpx.TransportError, OSError, http.client.HTTPException)


class LightResponse:
    def __init__(self, status_code: int, headers: dict[str, str], content: bytes) -> None:
        self.status_code = status_code
        self.headers = headers
        self.content = content

    @property
    def text(self) -> str:
        return self.content.decode(errors="replace")

    def json(self) -> Any:
        return json.loads(self.content)


class LightClient:
    """A keep-alive HTTP/1.1 client on the standard library, with the part of httpx.Client's
    interface the simulated participants use: several times lighter than httpx, so that a
    benchmark's hundreds of simulated participants measure the server, not themselves."""

    def __init__(self, base_url: str, timeout: float = 60.0) -> None:
        parts = urlsplit(base_url)
        if parts.scheme != "http" or parts.hostname is None:
            raise ValueError(f"LightClient needs an http:// URL, got {base_url!r}")
        self.host, self.port, self.timeout = parts.hostname, parts.port or 80, timeout
        self.connection: http.client.HTTPConnection | None = None

    def request(
        self,
        method: str,
        path: str,
        json: Any = None,
        headers: dict[str, str] | None = None,
    ) -> LightResponse:
        body = None if json is None else _dumps(json).encode()
        sent = {"Content-Type": "application/json", **(headers or {})}
        if self.connection is None:
            self.connection = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout)
        try:
            self.connection.request(method, path, body=body, headers=sent)
            response = self.connection.getresponse()
            content = response.read()
        except Exception:
            self.close()
            raise
        return LightResponse(response.status, dict(response.getheaders()), content)

    def get(self, path: str, **kwargs: Any) -> LightResponse:
        return self.request("GET", path, **kwargs)

    def post(self, path: str, **kwargs: Any) -> LightResponse:
        return self.request("POST", path, **kwargs)

    def close(self) -> None:
        if self.connection is not None:
            self.connection.close()
            self.connection = None

    def __enter__(self) -> LightClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class SimulatedParticipant:
    def __init__(
        self,
        base_url: str,
        index: int,
        seed: int,
        plan: TeachingPlan,
        worker_id: str | None = None,
        assignment_id: str | None = None,
        client: httpx.Client | LightClient | None = None,
        stop: threading.Event | None = None,
        turn: tuple[threading.Event, threading.Event] | None = None,
        prolific: ProlificArrival | None = None,
        mturk_replica: MTurkReplicaArrival | None = None,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.prolific = prolific
        self.mturk_replica = mturk_replica
        # The browser's own requests (pages, redirects, cookies) on the Prolific replica.
        self.browser: httpx.Client | None = None
        # (the previous participant has consented, this one has): consents in order.
        self.turn = turn
        self.plan = plan
        self.rng = np.random.default_rng([seed, index])
        self.run = ParticipantRun(
            index,
            worker_id or f"SIMW{seed}X{index}",
            assignment_id or f"SIMA{seed}X{index}",
        )
        self.client = client or LightClient(self.base_url)
        self.token: str | None = None
        self.seq = 1
        self.stop = stop

    # -- HTTP ---------------------------------------------------------------------------------
    def request(self, method: str, path: str, kind: str, body: dict[str, Any] | None = None) -> Any:
        """Send until answered (same body, same seq); 4xx is an error of ours."""
        if self.stop is not None and self.stop.is_set():
            raise Stopped
        headers = {TOKEN_HEADER: self.token} if self.token else {}
        deadline = time.monotonic() + self.plan.retry_seconds
        delay = 0.05
        first_sent = time.perf_counter()  # latency counts every attempt, as a person waits
        retries = self.run.retries
        while True:
            try:
                response = self.client.request(method, path, json=body, headers=headers)
            except TRANSPORT_ERRORS as error:
                problem = f"{type(error).__name__}: {error}"
            else:
                if response.status_code not in RETRY_STATUSES:
                    break
                problem = f"{response.status_code}: {response.text[:200]}"
                if response.status_code == 503 and self.stop is not None and self.stop.is_set():
                    raise Stopped  # refused, so nothing was stored: safe to give up
                retry_after = response.headers.get("Retry-After")
                if retry_after and retry_after.isdigit():
                    delay = max(delay, float(retry_after) / 4)
            if time.monotonic() > deadline:
                raise StudyClientError(f"{method} {path} kept failing: {problem}")
            self.run.retries += 1
            time.sleep(delay)
            delay = min(delay * 2, 2.0)
        elapsed = time.perf_counter() - first_sent
        retried = self.run.retries > retries
        if retried:
            self.run.retried_latencies.append(elapsed)
        if response.status_code >= 400:
            raise StudyClientError(f"{method} {path} -> {response.status_code}: {response.text}")
        data = response.json()
        if kind == "agent_step" and (
            data["outcome"]["learning_wait_seconds"] is not None or retried
        ):
            # The agent waited for its learner's update: timed apart from plain steps.
            self.run.update_waits.append(elapsed)
            return data
        self.run.latencies.setdefault(kind, []).append(elapsed)
        self.run.sent.setdefault(kind, []).append(first_sent)
        return data

    def act(self, path: str, kind: str, **fields: Any) -> dict[str, Any]:
        """A request that changes something: it carries the next seq."""
        data = self.request("POST", path, kind, {"seq": self.seq, **fields})
        self.run.acknowledged += 1
        self.seq = data["participant"]["next_seq"]
        return data

    # -- the flow -----------------------------------------------------------------------------
    def take_part(self) -> ParticipantRun:
        try:
            self._take_part()
        except Stopped:
            self.run.stopped = True
        except Exception as error:
            self.run.error = f"{type(error).__name__}: {error}"
        finally:
            if self.browser is not None:
                self.browser.close()
        return self.run

    def _take_part(self) -> None:
        if self.turn is None:
            self._arrive_and_consent()
        else:
            previous, mine = self.turn
            previous.wait()
            try:
                self._arrive_and_consent()
            finally:
                mine.set()
        current = self.act("/api/participant/start", "start")["participant"]["current_session_id"]
        finish: dict[str, Any] = {}
        while current is not None:
            finish = self.teach(current)
            self.run.sessions += 1
            current = finish["participant"]["current_session_id"]
            if current is None and finish["participant"]["status"] == ParticipantStatus.TEACHING:
                finish = self.attention_check()  # between two agents
                current = finish["participant"]["current_session_id"]
        if finish["participant"]["status"] == ParticipantStatus.QUESTIONNAIRE:
            answers = self.questionnaire_answers()
            finish = self.act("/api/participant/questionnaire", "questionnaire", answers=answers)
        code = finish["participant"]["completion"]["code"]
        shown = self.request("GET", "/api/participant/completion", "completion")
        if shown["code"] != code:
            raise StudyClientError("the completion code changed on refresh")
        self.act("/api/participant/submission", "submission")
        if self.prolific is not None:
            self._back_to_prolific(shown)
        if self.mturk_replica is not None:
            self._submit_to_mturk_replica(shown, self.mturk_replica)
        self.run.completed = True
        self.run.completion_code = code

    def _arrive_and_consent(self) -> None:
        if self.prolific is not None:
            self._arrive_from_prolific(self.prolific)
        elif self.mturk_replica is not None:
            self._arrive_from_mturk(self._accept_on_mturk_replica(self.mturk_replica))
        else:
            self._arrive_from_mturk()
        if self.run.status == ParticipantStatus.WAITING:  # the study is full: as the page does
            while not (place := self.request("POST", "/api/participant/place", "place"))[
                "admitted"
            ]:
                if self.stop is not None and self.stop.is_set():
                    raise Stopped
                time.sleep(place["ask_seconds"])
        self.act("/api/participant/consent", "consent", agree=True)

    def _arrive_from_mturk(self, parameters: dict[str, str] | None = None) -> None:
        """Arrive with MTurk's parameters: the HIT frame's (``parameters``), or made up."""
        arrival = self.request(
            "POST",
            "/api/arrivals",
            "arrival",
            parameters
            or {
                "assignmentId": self.run.assignment_id,
                "hitId": "SIMHIT",
                "workerId": self.run.worker_id,
                "turkSubmitTo": f"{self.base_url}",
            },
        )
        self.token = arrival["token"]
        self.run.participant_id = arrival["participant"]["participant_id"]
        self.run.status = arrival["participant"]["status"]
        self.seq = arrival["participant"]["next_seq"]

    def _arrive_from_prolific(self, prolific: ProlificArrival) -> None:
        self.browser = httpx.Client(base_url=self.base_url, timeout=60.0)
        deadline = time.monotonic() + self.plan.retry_seconds
        while True:
            taken = self.browser.post(
                f"/prolific/studies/{prolific.study_id}/take-part",
                headers={"Authorization": f"Bearer {prolific.admin_token}"},
            )
            # The study has its max_concurrent_submissions under way: as a participant who
            # finds it again on Prolific's list a little later.
            busy = taken.status_code == 409 and "max_concurrent_submissions" in taken.text
            if not busy or time.monotonic() > deadline:
                break
            if self.stop is not None and self.stop.is_set():
                raise Stopped
            time.sleep(1.0)
        if taken.status_code != 303:
            raise StudyClientError(
                f"the Prolific replica gave no place in study {prolific.study_id} "
                f"({taken.status_code}): {_page_text(taken.text)}"
            )
        link = httpx.URL(taken.headers["location"])
        if not str(link).startswith(f"{self.base_url}/"):
            raise StudyClientError(
                f"study {prolific.study_id}'s link {link} is not on {self.base_url}: make the "
                f"rehearsal's study with bam-study prolific create --replica {self.base_url}"
            )
        self.run.worker_id = link.params.get("PROLIFIC_PID", "")
        self.run.assignment_id = link.params.get("SESSION_ID", "")
        page = self.browser.get(link)
        found = PAGE_TOKEN.search(page.text)
        if page.status_code != 200 or found is None:
            raise StudyClientError(f"GET {link} -> {page.status_code}: {_page_text(page.text)}")
        self.token = json.loads(found.group(1))
        me = self.request("GET", "/api/participant", "read_participant")
        self.run.participant_id = me["participant_id"]
        self.run.status = me["status"]
        self.seq = me["next_seq"]

    def _mturk_replica_browser(self, replica: MTurkReplicaArrival) -> httpx.Client:
        if self.browser is None:
            self.browser = httpx.Client(
                base_url=self.base_url,
                headers={"Authorization": f"Bearer {replica.admin_token}"},
                timeout=60.0,
            )
        return self.browser

    def _accept_on_mturk_replica(self, replica: MTurkReplicaArrival) -> dict[str, str]:
        """Accept the HIT on the replica as this participant's worker; the parameters the HIT
        frame gives the study (its assignment id is the replica's)."""
        browser = self._mturk_replica_browser(replica)
        accepted = self._browse(browser, "POST", "/mturk/accept", {"workerId": self.run.worker_id})
        if accepted.status_code != 303:
            raise StudyClientError(
                f"the MTurk replica did not give worker {self.run.worker_id} an assignment "
                f"({accepted.status_code}): {_page_text(accepted.text)}"
            )
        work = self._browse(browser, "GET", accepted.headers["location"])
        found = HIT_FRAME.search(work.text)
        if work.status_code != 200 or found is None:
            raise StudyClientError(f"the replica's HIT page -> {work.status_code}: no HIT frame")
        frame = httpx.URL(html.unescape(found.group(1)))
        parameters = {key: frame.params[key] for key in MTURK_PARAMETERS}
        self.run.assignment_id = parameters["assignmentId"]
        return parameters

    def _submit_to_mturk_replica(
        self, completion: dict[str, Any], replica: MTurkReplicaArrival
    ) -> None:
        """The completion form, posted to the replica's externalSubmit as the page does."""
        target, fields = completion.get("submit_url"), completion.get("submit_fields")
        if completion.get("mode") != "mturk" or not target or not fields:
            raise StudyClientError(f"the study sent no MTurk completion form: {completion}")
        if not str(target).startswith(f"{self.base_url}/"):
            raise StudyClientError(f"the completion form posts to {target}, not to this server")
        browser = self._mturk_replica_browser(replica)
        retries = self.run.retries
        posted = self._browse(browser, "POST", str(target)[len(self.base_url) :], fields)
        # Sent again after its answer was lost: the replica has it submitted already.
        landed_before = self.run.retries > retries and "was submitted" in posted.text
        if posted.status_code != 200 and not (posted.status_code == 409 and landed_before):
            raise StudyClientError(
                f"the replica's externalSubmit -> {posted.status_code}: {_page_text(posted.text)}"
            )

    def _browse(
        self, browser: httpx.Client, method: str, path: str, form: dict[str, str] | None = None
    ) -> httpx.Response:
        """A page request of the participant's browser, sent again through connection losses
        and 5xx answers (server restarts), as a person reloads."""
        deadline = time.monotonic() + self.plan.retry_seconds
        while True:
            try:
                answer = browser.request(method, path, data=form)
                if answer.status_code not in RETRY_STATUSES:
                    return answer
                problem = f"{answer.status_code}: {_page_text(answer.text)}"
            except TRANSPORT_ERRORS as error:
                problem = f"{type(error).__name__}: {error}"
            if time.monotonic() > deadline:
                raise StudyClientError(f"{method} {path} kept failing: {problem}")
            if self.stop is not None and self.stop.is_set():
                raise Stopped
            self.run.retries += 1
            time.sleep(0.5)

    def _back_to_prolific(self, completion: dict[str, Any]) -> None:
        """The completion redirect, to the replica's copy of Prolific's page."""
        assert self.browser is not None
        target = urlsplit(completion.get("redirect_url") or "")
        if completion.get("mode") != "prolific" or not target.path:
            raise StudyClientError(f"the study sent no Prolific completion redirect: {completion}")
        if target.scheme or target.netloc:
            raise StudyClientError(
                f"the study sent the participant to {completion['redirect_url']}, not to this "
                "server's Prolific replica"
            )
        landed = self.browser.get(urlunsplit(("", "", target.path, target.query, "")))
        if landed.status_code != 200:
            raise StudyClientError(
                f"Prolific's completion page (the replica's) -> {landed.status_code}: "
                f"{_page_text(landed.text)}"
            )

    def questionnaire_answers(self) -> dict[str, int | str]:
        """An answer to each question of the study's questionnaire, drawn at random (a text
        question gets a sentence saying who answered)."""
        questions = self.request("GET", "/api/study", "study")["questionnaire"]["questions"]
        answers: dict[str, int | str] = {}
        for question in questions:
            if question["kind"] == "likert":
                answers[question["id"]] = int(self.rng.integers(1, len(question["labels"]) + 1))
            elif question["kind"] == "choice":
                choices = question["choices"]
                answers[question["id"]] = choices[int(self.rng.integers(len(choices)))]
            else:
                text = f"Simulated participant {self.run.index}."
                answers[question["id"]] = text[: question["max_length"]]
        return answers

    def teach(self, session_id: int) -> dict[str, Any]:
        """Teach one agent to the end; returns the finish response."""
        view = self.request("GET", f"/api/sessions/{session_id}", "read_session")
        self.seq = view["participant"]["next_seq"]
        env = make_environment(view["summary"]["environment"])
        masher = self.plan.kind == "key-masher"
        teacher = Teacher(
            env,
            seed=int(self.rng.integers(2**31)),
            mistake_probability=1.0 if masher else self.plan.mistake_probability,
            alpha=self.plan.feedback_alpha,
        )
        if self.plan.kind == "idle":
            time.sleep(self.plan.idle_seconds)
        base = f"/api/sessions/{session_id}"
        tutorial = view["summary"]["kind"] == SessionKind.TUTORIAL
        rounds = (
            1
            if tutorial
            else int(self.rng.integers(self.plan.min_rounds, self.plan.max_rounds + 1))
        )
        state = view["teaching"]["agent"]["state"]
        task = view["teaching"]["task"]
        for _ in range(rounds):
            for k in range(len(env.tasks)):
                if k != task:
                    state = self.act(f"{base}/task", "task", task=k)["session"]["agent"]["state"]
                    task = k
                state = self.demonstrate(base, env, teacher, k)
                if self.rng.random() < self.plan.refresh_probability:
                    state = self.refresh(session_id, state)
                if tutorial or self.rng.random() < self.plan.agent_try_probability:
                    state = self.agent_try(base, env, teacher, k)
        return self.act(f"{base}/finish", "finish")

    def attention_check(self) -> dict[str, Any]:
        """Move the robot to the star as asked (careful and idle participants: the shortest
        way; key-mashers: random arrows) until the server ends the check; its last answer."""
        me = self.request("GET", "/api/participant", "read_participant")
        check = me["attention_check"]
        if check is None:
            raise StudyClientError("between two agents, but no attention check in progress")
        self.run.attention_checks += 1
        arrows = ("UP", "DOWN", "LEFT", "RIGHT")
        while True:
            (row, column), (star_row, column_star) = check["robot"], check["star"]
            if self.plan.kind == "key-masher" or self.rng.random() < (
                self.plan.check_mistake_probability
            ):
                action = arrows[int(self.rng.integers(len(arrows)))]
            elif row != star_row:
                action = "UP" if star_row < row else "DOWN"
            else:
                action = "LEFT" if column_star < column else "RIGHT"
            self._pause(self.plan.think_seconds)
            data = self.act(
                "/api/participant/attention-check/move", "attention_move", action=action
            )
            check = data["check"]
            if check["status"] != CheckStatus.ACTIVE:
                self.run.failed_checks += check["status"] == CheckStatus.FAILED
                return data

    def demonstrate(self, base: str, env: Any, teacher: Teacher, task: int) -> int:
        self._pause(self.plan.episode_pause_seconds)
        data = self.act(f"{base}/reset", "reset")
        state = data["session"]["agent"]["state"]
        if self.rng.random() < self.plan.idle_move_probability:
            self.act(f"{base}/mode", "mode", mode=Mode.IDLE)
            for _ in range(int(self.rng.integers(1, 4))):
                move = ACTIONS[int(self.rng.integers(1, len(ACTIONS)))]
                self._pause(self.plan.think_seconds)
                state = self.act(f"{base}/move", "move", action=move)["session"]["agent"]["state"]
        for _ in range(5):
            if not env.is_goal(task, state):
                break
            state = self.act(f"{base}/reset", "reset")["session"]["agent"]["state"]
        else:
            return state  # every start drawn was a goal: nothing to demonstrate
        # (On the goal, turning a mode on puts the agent at a random start first.)
        data = self.act(f"{base}/mode", "mode", mode=Mode.DEMONSTRATE)
        state = data["session"]["agent"]["state"]
        for _ in range(env.horizon):
            action = teacher.next_action(task, state)
            self._pause(self.plan.think_seconds)
            data = self.act(f"{base}/move", "move", action=ACTIONS[action])
            state = data["session"]["agent"]["state"]
            if data["outcome"]["episode_ended"]:
                self.run.episodes += 1
                return state
        data = self.act(f"{base}/end-episode", "end_episode")
        self.run.episodes += 1
        return int(data["session"]["agent"]["state"])

    def agent_try(self, base: str, env: Any, teacher: Teacher, task: int) -> int:
        self._pause(self.plan.episode_pause_seconds)
        state = self.act(f"{base}/reset", "reset")["session"]["agent"]["state"]
        self.act(f"{base}/mode", "mode", mode=Mode.AGENT)
        steps = self.plan.max_agent_steps or env.horizon
        for _ in range(steps):
            self._pause(self.plan.agent_step_seconds)
            data = self.act(f"{base}/agent-step", "agent_step")
            outcome = data["outcome"]
            if self.plan.kind == "key-masher":
                signal = int(self.rng.choice((-1, 1)))
            else:
                signal = teacher.feedback(task, outcome["state"], ACTIONS.index(outcome["action"]))
            if signal:
                self.act(f"{base}/feedback", "feedback", feedback=signal)
            state = data["session"]["agent"]["state"]
            if outcome["episode_ended"]:
                self.run.episodes += 1
                return state
        data = self.act(f"{base}/end-episode", "end_episode")
        self.run.episodes += 1
        return int(data["session"]["agent"]["state"])

    def refresh(self, session_id: int, state: int) -> int:
        """Read everything again as a reloaded page does; it must match what we know."""
        me = self.request("GET", "/api/participant", "read_participant")
        view = self.request("GET", f"/api/sessions/{session_id}", "read_session")
        if me["next_seq"] != self.seq or view["teaching"]["agent"]["state"] != state:
            raise StudyClientError("after a refresh the server's state differs from the page's")
        return state

    def _pause(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds * float(self.rng.uniform(0.5, 1.5)))


def _page_text(html: str) -> str:
    """A page's text, for a message."""
    return " ".join(re.sub(r"<[^>]+>", " ", html).split())[:300]


@dataclass
class StudyRun:
    participants: list[ParticipantRun]
    seconds: float

    @property
    def acknowledged(self) -> int:
        return sum(p.acknowledged for p in self.participants)

    @property
    def completed(self) -> int:
        return sum(p.completed for p in self.participants)

    @property
    def retried_latencies(self) -> list[float]:
        return [x for p in self.participants for x in p.retried_latencies]

    def latencies(self, kind: str) -> list[float]:
        return [x for p in self.participants for x in p.latencies.get(kind, [])]

    def timed(self, kind: str) -> list[tuple[float, float]]:
        """Each request of the kind as (when it was first sent, its latency)."""
        return [
            pair
            for p in self.participants
            for pair in zip(p.sent.get(kind, []), p.latencies.get(kind, []), strict=True)
        ]

    @property
    def update_waits(self) -> list[float]:
        return [x for p in self.participants for x in p.update_waits]


def run_participants(
    base_url: str,
    participants: int,
    concurrency: int,
    seed: int,
    plan: TeachingPlan,
    first_index: int = 0,
    progress: Callable[[ParticipantRun], None] | None = None,
    stop: threading.Event | None = None,
    ramp_seconds: float = 0.0,
    in_order: bool = False,
    prolific: ProlificArrival | None = None,
    mturk_replica: MTurkReplicaArrival | None = None,
) -> StudyRun:
    """Run simulated participants, ``concurrency`` at a time; each gets its own connection.
    The first ``concurrency`` arrive spread over ``ramp_seconds``; ``stop`` ends the run.
    ``in_order``: each arrives and consents once the one before has, so that the participants'
    numbers and domains do not depend on the threads' timing (a seeded server's study is then
    the same on every run). ``prolific``: each arrives as a Prolific participant on the
    server's Prolific replica; ``mturk_replica``: each accepts the HIT on the server's MTurk
    replica first and submits the assignment there at the end."""
    started = time.perf_counter()
    consented = [threading.Event() for _ in range(participants + 1)]
    consented[0].set()

    def one(index: int) -> ParticipantRun:
        slot = index - first_index
        if ramp_seconds > 0 and slot < concurrency:
            time.sleep(ramp_seconds * slot / concurrency)
        with LightClient(base_url) as client:
            turn = (consented[slot], consented[slot + 1]) if in_order else None
            run = SimulatedParticipant(
                base_url, index, seed, plan, client=client, stop=stop, turn=turn,
                prolific=prolific, mturk_replica=mturk_replica,
            ).take_part()  # fmt: skip
        if progress is not None:
            progress(run)
        return run

    indices = range(first_index, first_index + participants)
    with ThreadPoolExecutor(max_workers=max(1, concurrency)) as pool:
        runs = list(pool.map(one, indices))
    return StudyRun(runs, time.perf_counter() - started)


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def latency_row(label: str, values: list[float], width: int) -> str:
    """A table row: the label, the count, then p50, p95 and max in milliseconds (the count
    alone when there are no values)."""
    if not values:
        return f"{label:<{width}}{0:>8}"
    return (
        f"{label:<{width}}{len(values):>8}{percentile(values, 50) * 1000:>10.1f}"
        f"{percentile(values, 95) * 1000:>10.1f}{max(values) * 1000:>10.1f}"
    )


def summary_table(run: StudyRun, kinds: tuple[str, ...] | None = None) -> str:
    """Latency percentiles per request kind (milliseconds, from each request's first attempt),
    then the waits for learner updates and the requests that needed a retry."""
    if kinds is None:
        kinds = tuple(sorted({k for p in run.participants for k in p.latencies}))
    lines = [f"{'request':<18}{'count':>8}{'p50 ms':>10}{'p95 ms':>10}{'max ms':>10}"]
    rows = [(kind, run.latencies(kind)) for kind in kinds]
    rows += [("update wait", run.update_waits), ("retried", run.retried_latencies)]
    lines += [latency_row(label, values, 18) for label, values in rows if values]
    return "\n".join(lines)
