"""The study server's deployment settings, read from the environment (prefix ``BAM_``).

The study itself (domains, environments, learners, texts) is in the study file (its schema and
loader: ``server.app.study_file``); these settings say where and how the server runs.
"""

from __future__ import annotations

import ipaddress
import re
from decimal import Decimal
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError

from server.app.platform_registry import platforms
from server.cores import available_cores

DEFAULT_DATABASE_URL = "sqlite:///bam-study.db"
# A Dask scheduler's address: protocol, host (a name, IPv4, or [IPv6]) and port.
SCHEDULER_ADDRESS = re.compile(r"(tcp|tls|ws|wss)://(\[[0-9A-Fa-f:.]+\]|[^\s/:\[\]]+):\d{1,5}")


class Settings(BaseSettings):
    """Every deployment setting, one environment variable each (``BAM_DATABASE_URL``, ...)."""

    model_config = SettingsConfigDict(env_prefix="BAM_", extra="ignore")

    database_url: str = Field(
        DEFAULT_DATABASE_URL,
        description="SQLAlchemy URL; the default is a SQLite file in the working folder.",
    )
    admin_token: SecretStr | None = Field(
        None,
        description="The experimenter's token (16 characters or more): signs in to /dashboard "
        "and /mturk, and is the bearer token of /api/admin; unset locks them all.",
    )
    study_config: Path | None = Field(
        None, description="The study configuration (TOML); unset uses the paper's study."
    )
    secret: SecretStr | None = Field(
        None,
        description="Salt for pseudonymised worker ids in exports; unset uses the random salt "
        "created with the database.",
    )
    seed: int | None = Field(
        None,
        ge=0,
        description="Draw the server's random choices (a tie in the domain assignment, the "
        "learners' order, the agents' seeds) from this seed and the participant's number, so "
        "that the same arrivals give the same study (the demo); unset: the system's randomness.",
    )
    update_workers: int = Field(2, ge=1, le=64, description="Processes for learner updates.")
    update_threads: int = Field(
        default_factory=available_cores,
        ge=1,
        le=64,
        description="Planner threads for learner updates (one per task at most): an update "
        "running alone, with none waiting for a process, uses them all; updates running together, "
        "or one with others waiting, share them. Default: the number of cores.",
    )
    update_scheduler: str = Field(
        "",
        description="Address of a Dask distributed scheduler (tcp://host:8786) whose workers "
        "run the learner updates; empty: local update processes (BAM_UPDATE_WORKERS).",
    )
    update_worker_niceness: int = Field(
        10, ge=0, le=19, description="Nice increment of update processes, so requests come first."
    )
    update_lease_seconds: float = Field(
        30.0,
        ge=1,
        le=3600,
        description="How long a server's claim on a learner update holds without its renewal "
        "(every third of it): when a server of several on one PostgreSQL dies, the others take "
        "its updates over after this long.",
    )
    agent_wait_seconds: float = Field(
        30.0, gt=0, le=600, description="How long an agent step waits for its learner's update."
    )
    update_interval_seconds: float = Field(
        10.0,
        gt=0,
        le=3600,
        description="How often a participant teaching queues a learner update on average (an "
        "episode end, a new agent), for the capacity that serve prints and the dashboard "
        "shows (the simulated participants of benchmarks/server.py queue one about every 10 s).",
    )
    active_minutes: float = Field(
        30.0, gt=0, description="A participant idle for longer no longer counts for balancing."
    )
    abandon_minutes: float = Field(
        120.0, gt=0, description="A participant idle for longer is marked abandoned."
    )
    max_body_bytes: int = Field(
        4096, ge=256, le=1_048_576, description="Largest request body accepted."
    )
    cookie_name: str = Field(
        "bam_participant",
        pattern=r"^[A-Za-z0-9_\-]+$",
        description="Name of the participant's cookie (it holds the participant's token).",
    )
    cookie_samesite: Literal["lax", "strict", "none"] = Field(
        "lax",
        description="'none' (with BAM_COOKIE_SECURE) lets the cookie work inside the MTurk iframe.",
    )
    cookie_secure: bool = Field(False, description="Send the cookie over HTTPS only.")
    mturk_submit_hosts: str = Field(
        "www.mturk.com,workersandbox.mturk.com",
        description="Hosts accepted in turkSubmitTo (comma-separated; the server's own host is "
        "always accepted, for a local replica).",
    )
    review_backend: str = Field(
        "replica",
        json_schema_extra=lambda schema: _listed(schema, review_backends()),
        description="Where the dashboard's approvals, rejections and bonuses go: 'replica' (the "
        "local replica of each participant's platform: the MTurk replica at /mturk, the Prolific "
        "replica at /prolific), 'mturk' (Mechanical Turk through boto3's client, which must be "
        "installed; credentials as boto3 finds them) or 'prolific' (Prolific's API, with "
        "BAM_PROLIFIC_TOKEN).",
    )
    prolific_api_url: str = Field(
        "https://api.prolific.com/api/v1",
        pattern=r"^https?://[A-Za-z0-9.-]+(:[0-9]+)?(/[A-Za-z0-9._~/-]*)?$",
        description="Prolific's API, for BAM_REVIEW_BACKEND=prolific.",
    )
    prolific_token: SecretStr | None = Field(
        None,
        description="Prolific's API token (Settings > API tokens in Prolific's app); never "
        "logged or exported.",
    )
    prolific_currency: Literal["GBP", "USD"] = Field(
        "GBP",
        description="The currency of the Prolific workspace's studies: rewards and bonuses are "
        "paid in it.",
    )
    prolific_replica_funds: Decimal = Field(
        Decimal(1000),
        ge=0,
        max_digits=10,
        decimal_places=2,
        description="The funds in the local Prolific replica's workspace, in "
        "BAM_PROLIFIC_CURRENCY: its balance is these less the rewards and bonuses paid there.",
    )
    prolific_webhook_secret: SecretStr | None = Field(
        None,
        description="The Prolific workspace's webhook signing secret, as POST /hooks/secrets/ "
        "gives it (one per workspace; a new one replaces the old), not the X-Hook-Secret that "
        "confirms a subscription. Not needed with bam-study prolific hooks, which makes the "
        "secret and stores it in the database: /prolific/webhook accepts events signed with "
        "this, with a stored one, or with the server's Prolific replica's own.",
    )
    mturk_endpoint_url: str = Field(
        "https://mturk-requester-sandbox.us-east-1.amazonaws.com",
        pattern=r"^https://[A-Za-z0-9.-]+(:[0-9]+)?/?$",
        description="MTurk's requester API for BAM_REVIEW_BACKEND=mturk: the sandbox by "
        "default; https://mturk-requester.us-east-1.amazonaws.com pays real money.",
    )
    mturk_region: str = Field(
        "us-east-1",
        pattern=r"^[a-z0-9-]+$",
        description="AWS region of MTurk's requester API (MTurk runs in us-east-1).",
    )
    forwarded_allow_ips: str = Field(
        "",
        description="The addresses of the proxies in front of the server (comma-separated IPs "
        "or networks, or '*' for any), whose X-Forwarded-For and X-Forwarded-Proto headers are "
        "believed: the client's address (its sign-in limit) and scheme are then theirs. Empty: "
        "no proxy is trusted and the headers are ignored.",
    )
    opentelemetry: bool = Field(
        False,
        description="Trace requests and record their metrics with OpenTelemetry (FastAPI's own "
        "instrumentation, to the providers configured in the environment). Off, FastAPI looks "
        "for the providers on no request: a tenth of a move's CPU time on the server.",
    )
    live_funnel_seconds: float = Field(
        1.0,
        ge=0.1,
        le=60,
        description="How often the live dashboard's funnel is computed while someone watches it "
        "(once for every watcher).",
    )
    live_curves_seconds: float = Field(
        2.0,
        ge=0.1,
        le=600,
        description="How often the live dashboard's learning curves are computed while someone "
        "watches them.",
    )
    live_mirror_seconds: float = Field(
        0.25,
        ge=0.05,
        le=10,
        description="How often a watched participant's view is asked whether it changed: a move "
        "reaches the one-way mirror within this and the time to read it.",
    )
    live_reader: Literal["process", "server"] = Field(
        "process",
        description="Where the live views read the database while dashboards are open: in a "
        "process of their own at the update processes' priority (process), beside the server on "
        "another core, or in the server's process (server: a one-core machine).",
    )
    sqlite_busy_timeout_ms: int = Field(
        10_000, ge=0, description="How long a SQLite connection waits for a lock held elsewhere."
    )
    sqlite_synchronous: Literal["full", "normal"] = Field(
        "full",
        description="SQLite's synchronous mode (WAL): 'full' keeps every acknowledged request "
        "through an OS crash or power loss; 'normal' only through a crash of the server.",
    )

    @field_validator("database_url")
    @classmethod
    def _known_backend(cls, value: str) -> str:
        if not value.startswith(("sqlite", "postgresql")):
            raise ValueError("must be a sqlite:// or postgresql:// URL")
        folder = sqlite_folder(value)
        if folder is not None and not folder.is_dir():
            raise ValueError(
                f"the folder {folder} does not exist"
                if not folder.exists()
                else f"{folder} is not a folder"
            )
        return value

    @field_validator("forwarded_allow_ips")
    @classmethod
    def _proxy_addresses(cls, value: str) -> str:
        for address in value.split(","):
            address = address.strip()
            if not address or address == "*":
                continue
            try:
                ipaddress.ip_network(address)
            except ValueError:
                raise ValueError(
                    f"lists IP addresses or networks (or '*'), got {address!r}"
                ) from None
        return value.strip()

    @field_validator("review_backend")
    @classmethod
    def _review_backend(cls, value: str) -> str:
        if value not in review_backends():
            raise ValueError(f"must be one of {', '.join(map(repr, review_backends()))}")
        return value

    @field_validator("update_scheduler")
    @classmethod
    def _scheduler_address(cls, value: str) -> str:
        value = value.strip()
        if value and not SCHEDULER_ADDRESS.fullmatch(value):
            raise ValueError(
                "must be a Dask scheduler address such as tcp://host:8786 (or empty for local "
                "update processes)"
            )
        return value

    @model_validator(mode="after")
    def _secure_cross_site_cookie(self) -> Settings:
        if self.cookie_samesite == "none" and not self.cookie_secure:
            raise ValueError(
                "BAM_COOKIE_SAMESITE=none needs BAM_COOKIE_SECURE=true (browsers drop it otherwise)"
            )
        return self

    @property
    def is_sqlite(self) -> bool:
        return self.database_url.startswith("sqlite")

    @field_validator("mturk_submit_hosts")
    @classmethod
    def _plain_hosts(cls, value: str) -> str:
        for host in value.split(","):
            if host.strip() and not re.fullmatch(r"[A-Za-z0-9.-]+", host.strip()):
                raise ValueError(
                    f"BAM_MTURK_SUBMIT_HOSTS lists host names only (no scheme, port or path), "
                    f"got {host.strip()!r}"
                )
        return value

    @property
    def submit_origins(self) -> frozenset[str]:
        """The origins accepted in turkSubmitTo (HTTPS on the default port)."""
        hosts = (h.strip().lower() for h in self.mturk_submit_hosts.split(","))
        return frozenset(f"https://{host}" for host in hosts if host)


def _listed(schema: dict[str, Any], values: list[str]) -> None:
    schema["enum"] = values


def review_backends() -> list[str]:
    """BAM_REVIEW_BACKEND's choices: the replicas, or a platform that reviews."""
    return ["replica", *(platform.name for platform in platforms() if platform.reviews)]


def sqlite_folder(url: str) -> Path | None:
    """The folder of a SQLite database file (None for another database, or one in memory)."""
    try:
        parsed = make_url(url)
    except ArgumentError:
        return None
    database = parsed.database
    if parsed.get_backend_name() != "sqlite" or not database or database == ":memory:":
        return None
    if database.startswith("file:") or parsed.query.get("mode") == "memory":
        return None
    return Path(database).parent


class SettingsError(ValueError):
    """Bad settings, in one line that names the flags or variables that were set."""


def load_settings(flags: dict[str, tuple[str, object | None]] | None = None) -> Settings:
    """The settings from the environment, with the command-line flags that were given on top
    (``flags``: setting name -> (flag, value); a value of None is a flag not given). Raises
    ``SettingsError`` naming each bad value by the flag or the ``BAM_*`` variable it came from."""
    given = {name: value for name, (_, value) in (flags or {}).items() if value is not None}
    try:
        return Settings(**given)  # type: ignore[arg-type]
    except ValidationError as error:
        problems = []
        for item in error.errors():
            message = item["msg"].removeprefix("Value error, ")
            if not item["loc"]:
                problems.append(message)
                continue
            name = str(item["loc"][0])
            source = (flags or {})[name][0] if name in given else f"BAM_{name.upper()}"
            problems.append(f"{source}={item['input']!r}: {message}")
        raise SettingsError("; ".join(problems)) from None


@lru_cache
def get_settings() -> Settings:
    return Settings()
