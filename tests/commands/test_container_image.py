"""The container image and the compose file, built and run by a Docker engine where one answers
(CI's machines have none: these tests are skipped there, and `test_container.py` checks the
containers' commands without an engine).

- The image built from the Dockerfile migrates a fresh PostgreSQL database and serves the
  study; simulated participants teach through it over HTTP, the container is restarted in the
  middle, and the export taken inside the container holds every event the participants had
  acknowledged.
- `compose.yaml` brings up PostgreSQL, the migration and the server in that order; a
  participant teaches through the published port, and after `down` and `up` the participant is
  still there (the data live in the volume).

The images come from `BAM_CHECK_PYTHON_IMAGE` (default python:3.11-slim) and
`BAM_CHECK_POSTGRES_IMAGE` (default postgres:16); `scripts/container-check/build-standins.sh`
builds stand-ins from Debian's packages for an engine that cannot pull from Docker Hub."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from server.commands.live import free_port
from tests.support.server import POSTGRES_URL

ROOT = Path(__file__).resolve().parents[2]
PYTHON_IMAGE = os.environ.get("BAM_CHECK_PYTHON_IMAGE", "python:3.11-slim")
POSTGRES_IMAGE = os.environ.get("BAM_CHECK_POSTGRES_IMAGE", "postgres:16")
ADMIN_TOKEN = "container-check-token"

pytestmark = pytest.mark.slow


def run(argv: list[str], timeout: float = 900, **kwargs: object) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kwargs)  # type: ignore[call-overload,no-any-return]


def engine_answers() -> bool:
    if shutil.which("docker") is None:
        return False
    return run(["docker", "info"], timeout=30).returncode == 0


def image_available(image: str) -> bool:
    if run(["docker", "image", "inspect", image], timeout=30).returncode == 0:
        return True
    return run(["docker", "pull", image], timeout=300).returncode == 0


@pytest.fixture(scope="module")
def engine() -> None:
    if not engine_answers():
        pytest.skip("no Docker engine answers here (docker info)")


def needs(image: str) -> None:
    if not image_available(image):
        pytest.skip(
            f"the image {image} is neither here nor pullable; "
            "scripts/container-check/build-standins.sh builds stand-ins"
        )


def wait_healthy(url: str, seconds: float = 120) -> None:
    deadline = time.monotonic() + seconds
    while True:
        try:
            if httpx.get(f"{url}/api/health", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline:
            raise AssertionError(f"{url} did not answer /api/health in {seconds} s")
        time.sleep(0.5)


def teach(url: str, participants: int, first_index: int, seed: int) -> int:
    """Simulated participants through the whole flow; the events they had acknowledged."""
    options = {"--participants": participants, "--concurrency": 2, "--rounds": 1}
    options |= {"--seed": seed, "--first-index": first_index}
    arguments = [str(part) for option in options.items() for part in option]
    completed = run(
        [sys.executable, "-m", "server.commands.main", "teach", "--url", url, *arguments]
    )
    assert completed.returncode == 0, completed.stderr
    assert f"participants completed  {participants} of {participants}" in completed.stdout
    return int(completed.stdout.split("events acknowledged")[1].split()[0])


def statuses(url: str, token: str) -> list[str]:
    response = httpx.get(
        f"{url}/api/admin/participants", headers={"Authorization": f"Bearer {token}"}, timeout=10
    )
    assert response.status_code == 200, response.text
    return [participant["status"] for participant in response.json()]


@pytest.fixture
def database() -> Iterator[str]:
    """A new PostgreSQL database on this machine's server, dropped afterwards."""
    name = f"container_{uuid.uuid4().hex[:10]}"
    admin = create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield make_url(POSTGRES_URL).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def test_the_image_serves_a_study_on_postgresql_across_a_restart(
    engine: None, database: str
) -> None:
    needs(PYTHON_IMAGE)
    tag = f"bam-study-check:{uuid.uuid4().hex[:8]}"
    name = f"bam-study-check-{uuid.uuid4().hex[:8]}"
    build = ["docker", "build", "--network", "host", "--build-arg", f"PYTHON_IMAGE={PYTHON_IMAGE}"]
    built = run([*build, "-t", tag, str(ROOT)])
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    environment = ["-e", f"BAM_DATABASE_URL={database}", "-e", f"BAM_ADMIN_TOKEN={ADMIN_TOKEN}"]
    try:
        # The server refuses an out-of-date PostgreSQL schema; the image's migration fixes it.
        port = free_port()
        serve = ["bam-study", "serve", "--host", "127.0.0.1", "--port", str(port)]
        refused = run(["docker", "run", "--rm", "--network", "host", *environment, tag, *serve])
        assert refused.returncode != 0 and "db upgrade" in refused.stdout + refused.stderr
        container = ["docker", "run", "--rm", "--network", "host", *environment, tag]
        upgraded = run([*container, "bam-study", "db", "upgrade"])
        assert upgraded.returncode == 0, upgraded.stderr
        # The planner's passes split over OpenMP threads in the image (GNU OpenMP installed).
        probe = "from server.learners.planning import compiled_threads; print(compiled_threads())"
        threads = run([*container, "python", "-c", probe])
        assert threads.stdout.strip() == "True", threads.stdout + threads.stderr
        detached = ["docker", "run", "-d", "--name", name, "--network", "host", *environment]
        started = run([*detached, tag, *serve])
        assert started.returncode == 0, started.stderr
        url = f"http://127.0.0.1:{port}"
        wait_healthy(url)
        # The update processes start with the server and load the kernels compiled into the
        # image's numba cache at build time (server.app.updates.warmup).
        cached = run([*container, "sh", "-c", "find ~/.cache/numba -name '*.nbc' | wc -l"])
        assert int(cached.stdout.strip() or 0) > 0, cached.stdout + cached.stderr
        deadline = time.monotonic() + 120
        while (logs := run(["docker", "logs", name])).stderr.count("update process") < 2:
            assert time.monotonic() < deadline, logs.stdout[-2000:] + logs.stderr[-2000:]
            time.sleep(0.5)
        acknowledged = teach(url, participants=2, first_index=0, seed=11)
        assert run(["docker", "restart", name]).returncode == 0
        wait_healthy(url)
        acknowledged += teach(url, participants=1, first_index=2, seed=12)
        assert statuses(url, ADMIN_TOKEN) == ["submitted"] * 3
        exported = run(["docker", "exec", name, "bam-study", "export", "--out", "/tmp/export"])
        assert exported.returncode == 0, exported.stderr
        events = run(["docker", "exec", name, "sh", "-c", "tail -n +2 /tmp/export/events.csv"])
        assert len(events.stdout.splitlines()) == acknowledged
    finally:
        run(["docker", "rm", "-f", name], timeout=60)
        run(["docker", "rmi", "-f", tag], timeout=120)


def compose_command(folder: Path) -> list[str]:
    """``docker compose`` (v2), else ``docker-compose`` (v1) on a copy of the file without
    the top-level ``name`` (v1 predates it; the project name comes from -p instead)."""
    if run(["docker", "compose", "version"], timeout=30).returncode == 0:
        return ["docker", "compose", "-f", str(ROOT / "compose.yaml")]
    if shutil.which("docker-compose") is None:
        pytest.skip("neither docker compose nor docker-compose is installed")
    lines = (ROOT / "compose.yaml").read_text().splitlines(keepends=True)
    copy = folder / "compose.yaml"
    copy.write_text("".join(line for line in lines if not line.startswith("name:")))
    return ["docker-compose", "-f", str(copy), "--project-directory", str(ROOT)]


def test_compose_brings_up_postgresql_the_migration_and_the_server(
    engine: None, tmp_path: Path
) -> None:
    needs(PYTHON_IMAGE)
    needs(POSTGRES_IMAGE)
    compose = [*compose_command(tmp_path), "-p", f"bamcheck{uuid.uuid4().hex[:8]}"]
    port = free_port()
    environment = {
        **os.environ,
        "POSTGRES_PASSWORD": uuid.uuid4().hex,
        "BAM_ADMIN_TOKEN": ADMIN_TOKEN,
        "BAM_PORT": str(port),
        "PYTHON_IMAGE": PYTHON_IMAGE,
        "POSTGRES_IMAGE": POSTGRES_IMAGE,
    }
    url = f"http://127.0.0.1:{port}"
    try:
        up = run([*compose, "up", "--build", "-d"], env=environment)
        assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
        wait_healthy(url)
        migrate = run([*compose, "ps", "-a", "migrate"], env=environment)
        assert "Exit 0" in migrate.stdout or "Exited (0)" in migrate.stdout, migrate.stdout
        teach(url, participants=1, first_index=0, seed=13)
        assert statuses(url, ADMIN_TOKEN) == ["submitted"]
        assert run([*compose, "down"], env=environment).returncode == 0
        assert run([*compose, "up", "-d"], env=environment).returncode == 0
        wait_healthy(url)
        assert statuses(url, ADMIN_TOKEN) == ["submitted"]  # kept in the volume
        server = run([*compose, "ps", "-q", "server"], env=environment).stdout.strip()
        health = run(["docker", "inspect", "--format", "{{json .State.Health}}", server])
        deadline = time.monotonic() + 60
        while json.loads(health.stdout or "{}").get("Status") != "healthy":
            assert time.monotonic() < deadline, health.stdout
            time.sleep(2)
            health = run(health.args)
    finally:
        run([*compose, "down", "-v", "--rmi", "local"], env=environment, timeout=300)
