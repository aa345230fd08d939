"""A study server in its own process, for the benchmark, the end-to-end tests and demos:
``bam-study serve`` on a free local port, in its own process group so that stopping it also
stops its learner-update workers; and nginx in front of several of them (``Proxy``), as
docs/deployment.md configures it, on loopback ports."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

from server.learners.compile_notice import COMPILE_TIME

# uvicorn's access log line: ... "GET /api/health HTTP/1.1" 200
ACCESS_LINE = re.compile(r'"[A-Z]+ [^"]* HTTP/[\d.]+" (\d{3})')


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class ServerProcess:
    """``bam-study serve`` in a process of its own (tests of a real server thread use
    ``tests.browser.conftest.LiveServer``, the app served in a thread)."""

    def __init__(
        self,
        folder: Path,
        environment: dict[str, str],
        port: int | None = None,
        access_log: bool = False,
    ) -> None:
        """``environment``: the BAM_* settings (BAM_DATABASE_URL, ...); the server runs in
        ``folder`` and logs to ``folder/server-N.log`` (with ``access_log``, every request
        and its answer's status: ``answers``)."""
        self.folder = folder
        self.access_log = access_log
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.environment = {**os.environ, **environment}
        self.process: subprocess.Popen[bytes] | None = None
        self.starts = 0
        # Told how long the start has taken while the update processes warm up (``start``).
        self.waiting: Callable[[float, dict[str, Any]], None] | None = None

    @property
    def log_path(self) -> Path:
        return self.folder / f"server-{self.starts}.log"

    def start(
        self, timeout: float = 600.0, waiting: Callable[[float, dict[str, Any]], None] | None = None
    ) -> None:
        """Start the server and return once it is ready (``/api/health`` 200); ``waiting`` is
        told the seconds so far and the health answer while the update processes warm up."""
        self.starts += 1
        with open(self.log_path, "wb") as log:
            command = [sys.executable, "-m", "server.commands.main", "serve"]
            command += ["--port", str(self.port)] + (["--access-log"] if self.access_log else [])
            self.process = subprocess.Popen(
                command,
                env=self.environment,
                cwd=self.folder,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the server exited:\n{self.log()}")
            try:
                answer = httpx.get(f"{self.url}/api/health", timeout=1)
                if answer.status_code == 200:
                    return
                if waiting is not None and answer.status_code == 503:
                    waiting(time.monotonic() - (deadline - timeout), answer.json())
            except (httpx.HTTPError, ValueError):
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"the server did not start within {timeout} s:\n{self.log()}")

    def kill(self) -> None:
        """As a crash: SIGKILL to the server and its update workers."""
        if self.process is not None and self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=30)

    def stop(self) -> None:
        """SIGTERM (uvicorn shuts down gracefully), SIGKILL if that takes too long."""
        if self.process is None or self.process.poll() is not None:
            return
        os.killpg(self.process.pid, signal.SIGTERM)
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.kill()

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")[-4000:] if self.log_path.exists() else ""

    def logs(self) -> str:
        """Everything the server logged, over all its starts."""
        return "".join(
            path.read_text(errors="replace")
            for start in range(1, self.starts + 1)
            if (path := self.folder / f"server-{start}.log").exists()
        )

    def answers(self, status: int) -> list[str]:
        """The access log's lines of requests answered ``status`` (``access_log``); for 500,
        also uvicorn's report of each exception that escaped a request (answered 500)."""
        if not self.access_log:
            raise RuntimeError("the server was started without its access log")
        lines = self.logs().splitlines()
        answered = [
            line for line in lines if (m := ACCESS_LINE.search(line)) and m[1] == str(status)
        ]
        if status == 500:
            answered += [line for line in lines if "Exception in ASGI application" in line]
        return answered

    def __enter__(self) -> ServerProcess:
        self.start(waiting=self.waiting)
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()


class WarmUpNotice:
    """What a command says while its server's update processes load the learners' kernels:
    a first line saying why it waits (compiling them takes minutes on a machine whose cache
    lacks them), then the time so far and the processes ready, every ``every`` seconds."""

    def __init__(self, stream: Any, every: float = 15.0) -> None:
        self.stream = stream
        self.every = every
        self.said_at: float | None = None

    def __call__(self, seconds: float, health: dict[str, Any]) -> None:
        if self.said_at is None:
            print(
                "the server's update processes are loading the learners' compiled kernels "
                f"(the first time on a machine, they compile them, each kernel once, on every free "
                f"core: {COMPILE_TIME} in all; then a second or two)",
                file=self.stream,
                flush=True,
            )
            self.said_at = seconds
        elif seconds - self.said_at >= self.every:
            warm, of = health.get("update_processes_warm", 0), health.get("update_processes", "?")
            print(
                f"  ... {seconds:.0f} s, {warm} of {of} update processes ready",
                file=self.stream,
                flush=True,
            )
            self.said_at = seconds


NGINX_TEMP = ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")


def nginx_config(prefix: Path, port: int, upstreams: list[str]) -> str:
    """deploy/nginx.conf's proxy on 127.0.0.1:``port`` to ``upstreams`` (host:port), its files
    under ``prefix``."""
    servers = "\n".join(
        f"        server {address} max_fails=1 fail_timeout=5s;" for address in upstreams
    )
    temp = "\n".join(f"    {name}_temp_path {prefix / name};" for name in NGINX_TEMP)
    return f"""worker_processes 1;
pid {prefix / "nginx.pid"};
error_log {prefix / "error.log"} warn;
events {{ worker_connections 1024; }}
http {{
    access_log off;
{temp}
    upstream bam_study {{
{servers}
        keepalive 32;
    }}
    server {{
        listen 127.0.0.1:{port};
        client_max_body_size 1m;
        location / {{
            proxy_pass http://bam_study;
            proxy_http_version 1.1;
            proxy_set_header Connection "";
            proxy_set_header Host $http_host;
            proxy_set_header X-Forwarded-For $remote_addr;
            proxy_set_header X-Forwarded-Proto $scheme;
            proxy_next_upstream error timeout http_502;
            proxy_read_timeout 120s;
        }}
    }}
}}
"""


class Proxy:
    """Debian's nginx in a process of its own, in front of ``upstreams``, with its
    configuration and files in ``folder`` (``apt-get install nginx``; not its service)."""

    def __init__(self, folder: Path, upstreams: list[str], port: int | None = None) -> None:
        self.nginx = shutil.which("nginx") or "/usr/sbin/nginx"
        if not os.path.exists(self.nginx):
            raise RuntimeError("nginx is missing: apt-get install -y nginx")
        self.folder = folder
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.upstreams = upstreams
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout: float = 60.0) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        for name in NGINX_TEMP:
            (self.folder / name).mkdir(exist_ok=True)
            (self.folder / name).chmod(0o777)  # nginx's worker runs as another user under root
        config = self.folder / "nginx.conf"
        config.write_text(nginx_config(self.folder, self.port, self.upstreams))
        error_log = self.folder / "error.log"
        self.process = subprocess.Popen(
            [self.nginx, "-p", str(self.folder), "-c", str(config), "-e", str(error_log),
             "-g", "daemon off;"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.STDOUT,
        )  # fmt: skip
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"nginx exited: {error_log.read_text(errors='replace')}")
            try:
                if httpx.get(f"{self.url}/api/health", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"nginx did not answer within {timeout} s")

    def stop(self) -> None:
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGQUIT)  # nginx's graceful stop
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=30)

    def __enter__(self) -> Proxy:
        self.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.stop()
