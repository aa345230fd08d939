"""The container's commands, run without a container engine (CI's machines have none;
`test_container_image.py` builds and runs the image and the compose file where one answers):
the build context that `.dockerignore` leaves, the compose file's migration command, and the
Dockerfile's CMD and HEALTHCHECK, all read from the files themselves and run against a fresh
PostgreSQL schema with the environment compose gives. A change to any of those files that
breaks the deployment fails here."""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

from server.commands.live import free_port
from tests.support.server import ADMIN_TOKEN

ROOT = Path(__file__).resolve().parents[2]


def dockerfile() -> dict[str, str]:
    """The Dockerfile's instructions (continuation lines joined), the last of each kind."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    instructions: dict[str, str] = {}
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            keyword, _, rest = line.partition(" ")
            instructions[keyword.upper()] = rest.strip()
    return instructions


def dockerfile_env() -> dict[str, str]:
    """ENV KEY=VALUE pairs of the Dockerfile."""
    pairs = re.findall(r"(\w+)=(\S+)", dockerfile()["ENV"])
    return dict(pairs)


def ignored(path: str, patterns: list[str]) -> bool:
    """Whether ``.dockerignore`` keeps ``path`` (relative, with /) out of the build context: a
    pattern excludes a path it matches and everything under it; ``**/`` matches any depth."""
    parts = path.split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    for pattern in patterns:
        if pattern.startswith("**/"):
            tail = pattern[3:]
            if any(fnmatch.fnmatchcase(part, tail) for part in parts):
                return True
        elif any(fnmatch.fnmatchcase(prefix, pattern) for prefix in prefixes):
            return True
    return False


def dockerignore() -> list[str]:
    lines = (ROOT / ".dockerignore").read_text().splitlines()
    return [line.strip().rstrip("/") for line in lines if line.strip() and not line.startswith("#")]


def build_context(destination: Path) -> list[str]:
    """Copy the committed files that `.dockerignore` lets into the image (COPY . .)."""
    files = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    patterns = dockerignore()
    kept = [f for f in files if not ignored(f, patterns) and (ROOT / f).is_file()]
    for name in kept:
        target = destination / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, target)
    return kept


def compiled_kernels(destination: Path) -> int:
    """The image's last RUN, which compiles the learners' kernels into numba's cache in the
    image: here the kernels this checkout compiled before the tests (tests/conftest.py) copied
    beside the build context's sources, so that the server's update processes load them as in
    the image instead of compiling them for minutes (numba keys each cached kernel by its
    source's hash, not its path). Returns the files copied (none where numba's cache is kept
    elsewhere, under NUMBA_CACHE_DIR: then the update processes compile them)."""
    copied = 0
    for cached in sorted((ROOT / "server").glob("**/__pycache__/*.nb[ic]")):
        target = destination / cached.relative_to(ROOT)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(cached, target)
        copied += 1
    return copied


def test_the_build_context_keeps_data_out_and_the_server_in() -> None:
    patterns = dockerignore()
    # Study data and local environments never go into the image.
    for path in (
        "bam-study.db",
        "bam-study.db-wal",
        "bam-demo/study.sqlite",
        "bam-demo/export/events.csv",
        ".venv/bin/python",
        ".git/config",
        "server/__pycache__/cli.cpython-311.pyc",
    ):
        assert ignored(path, patterns), path
    # What `bam-study serve` needs at run time does.
    for path in (
        "pyproject.toml",
        "alembic.ini",
        "migrations/env.py",
        "server/commands/main.py",
        "server/config/study.toml",
        "server/domains/maps/doorway.txt",
        "server/templates/dashboard.html",
        "server/static",
    ):
        assert (ROOT / path).exists(), path
        assert not ignored(path, patterns), path


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["postgresql"], indirect=True)
def test_the_containers_commands_run_a_server_on_postgresql(
    database_url: str, tmp_path: Path
) -> None:
    app = tmp_path / "app"  # WORKDIR /app
    assert dockerfile()["WORKDIR"] == "/app"
    kept = build_context(app)
    assert "server/config/study.toml" in kept
    # The image compiles the kernels as it is built (in two processes side by side).
    assert "warm_up_in_processes(" in dockerfile()["RUN"]
    compiled_kernels(app)
    compose = yaml.safe_load((ROOT / "compose.yaml").read_text())
    services = compose["services"]
    port = free_port()
    environment = {
        **{k: v for k, v in os.environ.items() if not k.startswith("BAM_")},
        **dockerfile_env(),
        # compose's settings for the server, its database URL pointing at the test schema.
        "BAM_DATABASE_URL": database_url,
        "BAM_ADMIN_TOKEN": ADMIN_TOKEN,
        "PYTHONPATH": str(app),  # `pip install -e .` in /app
    }
    assert "BAM_DATABASE_URL" in services["server"]["environment"]
    assert "BAM_DATABASE_URL" in services["migrate"]["environment"]
    bin_dir = Path(sys.executable).parent

    def command(argv: list[str]) -> list[str]:
        """The image's console script and python are this environment's."""
        assert argv[0] in ("bam-study", "python"), argv
        return [str(bin_dir / argv[0]), *argv[1:]]

    # Without the migration, the server refuses the empty PostgreSQL schema.
    cmd = json.loads(dockerfile()["CMD"])
    assert cmd[:2] == ["bam-study", "serve"] and "--host" in cmd and "--port" in cmd
    served = [*cmd]
    served[served.index("--port") + 1] = str(port)
    refused = subprocess.run(
        command(served), cwd=app, env=environment, capture_output=True, text=True, timeout=120
    )
    assert refused.returncode != 0
    assert "bam-study db upgrade" in refused.stdout + refused.stderr

    # compose's one-shot migration service.
    migrate = subprocess.run(
        command(services["migrate"]["command"]),
        cwd=app,
        env=environment,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert migrate.returncode == 0, migrate.stderr

    # The image's CMD, listening on all interfaces as in the container.
    log = (tmp_path / "server.log").open("wb")
    server = subprocess.Popen(
        command(served), cwd=app, env=environment, stdout=log, stderr=subprocess.STDOUT
    )
    try:
        # /api/health answers 503 until the update processes have loaded the kernels.
        deadline = time.monotonic() + 600
        health = None
        while time.monotonic() < deadline and server.poll() is None:
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=1)
                if health.status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        assert health is not None and health.status_code == 200, (
            tmp_path / "server.log"
        ).read_text()
        # The HEALTHCHECK, as the engine would run it inside the container.
        check = dockerfile()["HEALTHCHECK"]
        probe = check[check.index("CMD ") + 4 :].replace(":8000/", f":{port}/")
        argv = [str(bin_dir / "python"), "-c", re.search(r'-c "(.*)"$', probe).group(1)]
        assert subprocess.run(argv, cwd=app, timeout=30).returncode == 0
        # A participant can start the study through it.
        study = httpx.get(
            f"http://127.0.0.1:{port}/study",
            params={
                "assignmentId": "A1",
                "hitId": "H1",
                "workerId": "W1",
                "turkSubmitTo": "https://workersandbox.mturk.com",
            },
            timeout=10,
        )
        assert study.status_code == 200, study.text
        assert "consent" in study.text.lower()
    finally:
        server.terminate()
        server.wait(timeout=30)
        log.close()
