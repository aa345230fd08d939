"""`bam-study serve` and the other commands as a user meets them: a port in use fails at once
with one line, bad settings are one line naming the flag or variable set, the console says when
the dashboard is locked, and `serve --lab` lets a lab participant in at /study."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from server.app.study_file import load_study_config
from server.commands.main import main
from server.commands.serve import listening_address, startup_notes
from tests.support.server import free_port


def test_serve_on_a_port_in_use_fails_at_once_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    database = tmp_path / "study.db"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(["serve", "--port", str(port), "--database-url", f"sqlite:///{database}"])
    captured = capsys.readouterr()
    assert code == 1
    assert captured.err.strip().splitlines() == [
        f"bam-study serve: cannot listen on 127.0.0.1:{port}: the address is already in use "
        "(another server?); choose another --port"
    ]
    assert not database.exists()  # nothing started: no database, no update processes


@pytest.mark.parametrize(
    ("argv", "environment", "line"),
    [
        (
            ["export", "--database-url", "mysql://x/y", "--out", "out"],
            {},
            "bam-study export: --database-url='mysql://x/y': must be a sqlite:// or "
            "postgresql:// URL",
        ),
        (
            ["db", "check"],
            {"BAM_DATABASE_URL": "mysql://x/y"},
            "bam-study db: BAM_DATABASE_URL='mysql://x/y': must be a sqlite:// or "
            "postgresql:// URL",
        ),
        (
            ["serve", "--port", "1"],
            {"BAM_UPDATE_WORKERS": "many"},
            "bam-study serve: BAM_UPDATE_WORKERS='many': Input should be a valid integer, "
            "unable to parse string as an integer",
        ),
        (
            ["db", "check"],
            {"BAM_COOKIE_SAMESITE": "none"},
            "bam-study db: BAM_COOKIE_SAMESITE=none needs BAM_COOKIE_SECURE=true (browsers "
            "drop it otherwise)",
        ),
    ],
)
def test_bad_settings_are_one_line_naming_what_the_user_set(
    argv: list[str],
    environment: dict[str, str],
    line: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    monkeypatch.chdir(tmp_path)
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    assert main(argv) == 2
    assert capsys.readouterr().err.splitlines() == [line]


def test_a_bad_study_file_is_one_line_naming_the_variable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    study = tmp_path / "study.toml"
    study.write_text('title = "x"\nagents_per_environment = 0\n')
    monkeypatch.setenv("BAM_STUDY_CONFIG", str(study))
    assert main(["serve", "--port", "1"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"bam-study serve: BAM_STUDY_CONFIG: {study} is not a valid study:")
    assert "agents_per_environment" in lines[0]


def test_the_console_says_where_it_listens_who_may_enter_and_what_is_locked() -> None:
    paper = load_study_config()
    assert startup_notes("http://127.0.0.1:8000", True, paper) == [
        "Serving at http://127.0.0.1:8000 (the study at /study).",
        "This study runs on Mechanical Turk: /study turns away visitors without its parameters "
        "(serve --lab lets them in).",
        "The dashboard is open at http://127.0.0.1:8000/dashboard: sign in with BAM_ADMIN_TOKEN.",
    ]
    lab = paper.model_copy(update={"allow_anonymous": True})
    assert startup_notes("http://[::1]:8080", False, lab) == [
        "Serving at http://[::1]:8080 (the study at /study).",
        "Lab participants enter at /study with no parameters.",
        "BAM_ADMIN_TOKEN is not set: the dashboard (/dashboard), the MTurk replica (/mturk) "
        "and the admin API are locked. Set it and restart to use them.",
    ]
    assert listening_address("0.0.0.0", 8000) == "http://0.0.0.0:8000"
    assert listening_address("::1", 8080) == "http://[::1]:8080"


def test_serve_lab_lets_a_participant_in_without_parameters(tmp_path: Path) -> None:
    """The README's first `serve`, as written: the default study, `--lab`, no admin token."""
    port = free_port()
    environment = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("BAM_") or k == "BAM_TEST_POSTGRES_URL"
    }
    environment["BAM_UPDATE_WORKERS"] = "1"
    server, log = start_serve(tmp_path, environment, "--lab", "--access-log", "--port", str(port))
    pid = "5f4e3d2c1b0a99887766aabb"
    try:
        wait_until_answering(server, log, f"http://127.0.0.1:{port}", ready=False)
        httpx.get(f"http://127.0.0.1:{port}/study?PROLIFIC_PID={pid}", timeout=10)
        arrived = httpx.post(f"http://127.0.0.1:{port}/api/arrivals", json={}, timeout=10)
        assert arrived.status_code == 201, arrived.text
        assert arrived.json()["participant"]["platform"] == "lab"
        page = httpx.get(f"http://127.0.0.1:{port}/study", timeout=10)
        assert page.status_code == 200 and "participant-token" in page.text
        dashboard = httpx.get(f"http://127.0.0.1:{port}/api/admin/participants", timeout=10)
        assert dashboard.status_code == 503 and "BAM_ADMIN_TOKEN" in dashboard.text
    finally:
        server.terminate()
        server.wait(timeout=30)
    text = log.read_text()
    assert "Lab participants enter at /study with no parameters." in text
    assert "BAM_ADMIN_TOKEN is not set: the dashboard (/dashboard)" in text
    assert f"Serving at http://127.0.0.1:{port} (the study at /study)." in text
    # The access log writes the participant's id as its pseudonym.
    assert "GET /study?PROLIFIC_PID=w_" in text and pid not in text


def test_a_server_stopped_after_serving_participants_leaves_nothing_behind(
    tmp_path: Path,
) -> None:
    """SIGTERM to a server whose update processes have run learner updates: it stops, and
    its update processes leave no semaphore for the resource tracker to clean up."""
    from sqlalchemy import create_engine, text

    from tests.browser.conftest import domain_toml, study_toml

    port = free_port()
    url = f"http://127.0.0.1:{port}"
    study = tmp_path / "study.toml"
    study.write_text(
        study_toml(
            mode="lab",
            domains_toml=domain_toml("navigation", "wall"),
            learners='["cloning"]',
            agents=1,
            tutorial=False,
        )
    )
    database = f"sqlite:///{tmp_path / 'study.db'}"
    environment = {k: v for k, v in os.environ.items() if not k.startswith("BAM_")}
    environment.update(
        BAM_DATABASE_URL=database, BAM_STUDY_CONFIG=str(study), BAM_UPDATE_WORKERS="2"
    )
    server, log = start_serve(tmp_path, environment, "--port", str(port))
    try:
        wait_until_answering(server, log, url, ready=True)
        deadline = time.monotonic() + 180
        with httpx.Client(base_url=url, timeout=30) as client:
            arrived = client.post("/api/arrivals", json={})
            assert arrived.status_code == 201, arrived.text
            seq = arrived.json()["participant"]["next_seq"]
            session = None
            for path, body in (
                ("/api/participant/consent", {"agree": True}),
                ("/api/participant/start", {}),
                ("mode", {"mode": "demonstrate"}),
                ("move", {"action": "UP"}),
                ("mode", {"mode": "idle"}),  # the episode ends: a learner update
            ):
                where = path if path.startswith("/") else f"/api/sessions/{session}/{path}"
                answer = client.post(where, json={"seq": seq, **body})
                assert answer.status_code == 200, answer.text
                seq = answer.json()["participant"]["next_seq"]
                session = answer.json()["participant"]["current_session_id"]
        engine = create_engine(database)
        try:
            while True:
                with engine.connect() as connection:
                    statuses = (
                        connection.execute(text("SELECT status FROM learner_updates"))
                        .scalars()
                        .all()
                    )
                if len(statuses) == 2 and set(statuses) == {"done"}:
                    break
                assert time.monotonic() < deadline, statuses
                time.sleep(0.2)
        finally:
            engine.dispose()
        spawned = children(server.pid)  # the update processes, the resource tracker
        assert len(spawned) >= 3, spawned
        server.send_signal(signal.SIGTERM)
        # Stopped by the signal, after a graceful shutdown (uvicorn raises it again).
        assert server.wait(timeout=60) in (0, -signal.SIGTERM), log.read_text()
        deadline = time.monotonic() + 30
        while alive := [pid for pid in spawned if running(pid)]:
            assert time.monotonic() < deadline, f"still running: {alive}"
            time.sleep(0.1)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
    output = log.read_text()
    assert "Application shutdown complete." in output
    assert "leaked semaphore" not in output and "resource_tracker" not in output, output


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    try:
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"  # not a zombie
    except OSError:
        return False


def test_ctrl_c_during_the_first_start_s_compile_stops_at_once_and_quietly(
    tmp_path: Path,
) -> None:
    """Ctrl-C (SIGINT to the process group) while the update processes compile the kernels
    into an empty cache: the server and its processes end without waiting for the compile,
    and the console shows no traceback (a worker's 'Exception in initializer', asyncio's
    'Future exception was never retrieved')."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    environment = {k: v for k, v in os.environ.items() if not k.startswith("BAM_")}
    environment.update(
        BAM_DATABASE_URL=f"sqlite:///{tmp_path / 'study.db'}",
        BAM_UPDATE_WORKERS="2",
        NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"),  # empty: a first start
    )
    log = tmp_path / "serve.log"
    with log.open("wb") as out:
        server = subprocess.Popen(
            [sys.executable, "-m", "server.commands.main", "serve", "--port", str(port)],
            cwd=tmp_path,
            env=environment,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group, as a terminal's foreground job
        )
    try:
        wait_until_answering(server, log, url, ready=False)
        while "waiting for 2 update process(es)" not in log.read_text():
            assert server.poll() is None, log.read_text()
            time.sleep(0.1)
        # Still compiling: a cache that empty takes most of a minute to fill, at the least.
        assert httpx.get(f"{url}/api/health", timeout=10).status_code == 503
        os.killpg(server.pid, signal.SIGINT)
        server.wait(timeout=60)
        deadline = time.monotonic() + 60
        while True:  # the update processes, in the same group, are gone too
            try:
                os.killpg(server.pid, 0)
            except ProcessLookupError:
                break
            assert time.monotonic() < deadline, "an update process outlived the server"
            time.sleep(0.2)
    finally:
        if server.poll() is None:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
    text = log.read_text()
    assert "Application shutdown complete." in text
    for noise in ("Traceback", "Exception in initializer", "never retrieved"):
        assert noise not in text, text


def start_serve(
    folder: Path, environment: dict[str, str], *args: str
) -> tuple[subprocess.Popen[bytes], Path]:
    """`bam-study serve` with ``args`` in ``folder``; its console goes to the returned log."""
    log = folder / "serve.log"
    with log.open("wb") as out:
        server = subprocess.Popen(
            [sys.executable, "-m", "server.commands.main", "serve", *args],
            cwd=folder,
            env=environment,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    return server, log


def wait_until_answering(
    server: subprocess.Popen[bytes], log: Path, url: str, ready: bool, seconds: float = 180
) -> None:
    """Until /api/health answers (with ``ready``: 200, once the update processes are warm)."""
    deadline = time.monotonic() + seconds
    while True:
        assert server.poll() is None, log.read_text()
        try:
            answer = httpx.get(f"{url}/api/health", timeout=1)
            if not ready or answer.status_code == 200:
                return
        except httpx.HTTPError:
            pass
        assert time.monotonic() < deadline, log.read_text()
        time.sleep(0.2)


@pytest.mark.parametrize("port", ["99999", "65536", "-5", "0"])
def test_a_port_out_of_range_is_one_line(
    port: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    database = tmp_path / "study.db"
    assert main(["serve", "--port", port, "--database-url", f"sqlite:///{database}"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"bam-study serve: --port must be a number from 1 to 65535, got {port}"
    ]
    assert not database.exists()


def test_an_empty_admin_token_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("BAM_ADMIN_TOKEN", "")
    database = tmp_path / "study.db"
    code = main(["serve", "--port", str(free_port()), "--database-url", f"sqlite:///{database}"])
    assert code == 2
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith("bam-study serve: BAM_ADMIN_TOKEN is set but empty")
    assert "unset it" in line and "16 characters" in line
    assert not database.exists()


@pytest.mark.parametrize("command", [["serve", "--port", "8000"], ["db", "upgrade"]])
def test_a_sqlite_file_in_a_missing_folder_is_named(
    command: list[str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(tmp_path)
    url = "sqlite:////no/such/dir/x.db"
    assert main([*command, "--database-url", url]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"bam-study {command[0]}: --database-url={url!r}: the folder /no/such/dir does not exist"
    ]
    monkeypatch.setenv("BAM_DATABASE_URL", f"sqlite:///{tmp_path / 'missing' / 'x.db'}")
    assert main(["db", "check"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"bam-study db: BAM_DATABASE_URL='sqlite:///{tmp_path / 'missing' / 'x.db'}': the folder "
        f"{tmp_path / 'missing'} does not exist"
    ]
