"""Running a simulation: the jobs of a run, where they run (in this process, a local process
pool, or a Dask distributed cluster) and how a run resumes.

The output folder holds ``run.json`` (the run's arguments, and the sessions that worked on
it) and ``jobs.jsonl``, the journal: one line per finished job with its rows, appended and
flushed as each job finishes. Started again with the same arguments, a run skips the jobs in
the journal; a folder that holds another run is refused before anything is written.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from server import domains
from server.cores import available_cores, share_threads
from server.domains.spec import EnvironmentSpec
from server.simulation.config import ConfigError, RunConfig
from server.simulation.progress import Progress
from server.simulation.protocols import Job, JobResult, run_agent

RUN_FILE = "run.json"
JOURNAL_FILE = "jobs.jsonl"
LOCK_FILE = ".lock"
FORMAT_VERSION = 1


class SimulationError(RuntimeError):
    """A run could not proceed (a job failed, the cluster is unreachable, ...)."""


def plan_jobs(config: RunConfig) -> list[Job]:
    """Every job of the run, agent-major so that any prefix mixes environments and learners
    (and the progress bar's time estimate is representative early on)."""
    return [
        Job(
            experiment=config.experiment,
            environment=environment,
            learner=learner,
            agent=agent,
            rounds=config.rounds,
            seed=config.seed,
            settings=tuple(sorted(config.settings_of(learner).items())),
        )
        for agent in range(config.agents)
        for environment in config.environments
        for learner in config.learners
    ]


def default_workers() -> int:
    return available_cores()


# -- files ---------------------------------------------------------------------------------


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _is_temporary(path: Path) -> bool:
    return path.name == LOCK_FILE or (path.name.startswith(".") and path.name.endswith(".tmp"))


@contextmanager
def locked(out: Path) -> Iterator[None]:
    """Hold ``out``'s lock: two runs working in one folder would do every job twice."""
    import fcntl

    with (out / LOCK_FILE).open("a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(
                f"another run is working in {out}; wait for it to finish or use another folder"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def atomic_write(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(temporary path)`` then rename it onto ``path``: readers never see a
    half-written file."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(handle)
    try:
        write(Path(temporary))
        os.chmod(temporary, 0o666 & ~_umask())  # mkstemp makes private files
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda temporary: temporary.write_text(text, encoding="utf-8"))


def read_run_file(out: Path) -> dict[str, Any] | None:
    path = out / RUN_FILE
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        RunConfig.from_json(data["arguments"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ConfigError(f"{path} is not a readable simulation run file: {error}") from None
    return dict(data)


def _differences(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    return [
        f"{key} is {old.get(key)!r} there, {new.get(key)!r} here"
        for key in sorted(set(old) | set(new))
        if old.get(key) != new.get(key)
    ]


def check_out_dir(out: Path, config: RunConfig) -> dict[str, Any] | None:
    """Refuse a folder that holds something else than this run (raises ``ConfigError``);
    return its run file if it holds this run."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} exists and is not a folder")
    if not out.exists():
        return None
    existing = read_run_file(out)
    if existing is None:
        # A run killed while writing its first file may leave one of our temporary files.
        if any(not _is_temporary(path) for path in out.iterdir()):
            raise ConfigError(
                f"--out {out} is not empty and holds no {RUN_FILE}: it is not a simulation "
                "output folder; choose a new or empty folder"
            )
        return None
    differences = _differences(existing["arguments"], config.to_json())
    if differences:
        raise ConfigError(
            f"--out {out} holds a different run ({'; '.join(differences)}); use another "
            "folder, or delete this one to start over"
        )
    effective = config.effective_settings()
    recorded = existing.get("effective_settings", effective)
    changed = [
        f"{learner} {name}: {recorded[learner].get(name)!r} there, {values.get(name)!r} here"
        for learner, values in effective.items()
        for name in sorted(set(values) | set(recorded.get(learner, {})))
        if recorded.get(learner, {}).get(name) != values.get(name)
    ]
    if changed:
        raise ConfigError(
            f"--out {out} was started with other learner settings ({'; '.join(changed)}): "
            "the learners' defaults changed since; use another folder, or delete this one to "
            "start over"
        )
    return existing


class Journal:
    """``jobs.jsonl``: one JSON line per finished job, flushed to disk as it finishes."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def read(self) -> dict[str, JobResult]:
        """Finished jobs by key. A line cut short (the run was killed while writing it) is
        dropped, and the file is rewritten without it so new lines append cleanly."""
        if not self.path.exists():
            return {}
        results: dict[str, JobResult] = {}
        text = self.path.read_text(encoding="utf-8")
        good: list[str] = []
        damaged = False
        for line in text.splitlines():
            try:
                entry = json.loads(line)
                result = JobResult(
                    str(entry["job"]),
                    list(entry["rows"]),
                    float(entry["seconds"]),
                    float(entry["update_seconds"]),
                )
            except (ValueError, KeyError, TypeError):
                damaged = True
                continue
            good.append(line)
            results.setdefault(result.key, result)
        if damaged or (text and not text.endswith("\n")):
            atomic_write_text(self.path, "".join(line + "\n" for line in good))
        return results

    def append(self, result: JobResult) -> None:
        line = json.dumps(
            {
                "job": result.key,
                "seconds": result.seconds,
                "update_seconds": result.update_seconds,
                "rows": result.rows,
            },
            allow_nan=True,
        )
        with self.path.open("a", encoding="utf-8") as handle:
            handle.write(line + "\n")
            handle.flush()
            os.fsync(handle.fileno())


# -- where jobs run ------------------------------------------------------------------------


def _start_worker(threads: int, environments: tuple[EnvironmentSpec, ...] = ()) -> None:
    # Ctrl-C reaches the whole process group; the parent stops the pool itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    domains.register_all(environments)  # the study's own, registered in the parent
    from server.learners.planning import set_planner_threads

    set_planner_threads(threads)


def spare_threads(processes: int) -> int:
    """Planner threads for each of ``processes`` busy processes: the cores they leave (the
    numbers do not depend on it, only the time)."""
    return share_threads(default_workers(), processes)


class LocalBackend:
    """Jobs in this process (one worker) or in a pool of ``workers`` processes."""

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ConfigError(f"--jobs must be at least 1, got {workers}")
        self.workers = workers

    def describe(self) -> str:
        if self.workers == 1:
            return "1 local process"
        return f"a pool of {self.workers} local processes"

    def results(self, jobs: Sequence[Job]) -> Iterator[JobResult]:
        if self.workers == 1 or len(jobs) <= 1:
            from server.learners.planning import using_planner_threads

            with using_planner_threads(spare_threads(1)):
                for job in jobs:
                    yield run_agent(job)
            return
        processes = min(self.workers, len(jobs))
        context = multiprocessing.get_context("spawn")
        pool = context.Pool(
            processes,
            initializer=_start_worker,
            initargs=(spare_threads(processes), domains.registered()),
        )
        try:
            yield from pool.imap_unordered(run_agent, jobs, chunksize=1)
            pool.close()
        finally:
            pool.terminate()
            pool.join()

    def close(self) -> None:
        pass


class DaskBackend:
    """Jobs on an existing Dask distributed cluster (the ``bam-study[dask]`` extra)."""

    def __init__(self, address: str, timeout: float = 30.0) -> None:
        from server.dask_client import SchedulerError, connect

        self.address = address
        try:
            self.client = connect(address, timeout)
        except SchedulerError as error:
            raise ConfigError(str(error)) from None

    def describe(self) -> str:
        return f"the Dask cluster at {self.address}"

    def results(self, jobs: Sequence[Job]) -> Iterator[JobResult]:
        from distributed import as_completed

        futures = self.client.map(run_agent, list(jobs), pure=False)
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            self.client.cancel(futures)

    def close(self) -> None:
        self.client.close()


Backend = LocalBackend | DaskBackend


# -- a run ---------------------------------------------------------------------------------


@dataclass
class RunOutcome:
    config: RunConfig
    results: list[JobResult]  # in plan order
    sessions: list[dict[str, Any]] = field(default_factory=list)
    complete: bool = True


def run_jobs(
    config: RunConfig,
    out: Path,
    backend: Backend,
    max_jobs: int | None = None,
    progress_stream: Any = None,
) -> RunOutcome:
    """Run the jobs of ``config`` not yet in ``out``'s journal (at most ``max_jobs`` of them
    when given: a partial run, for tests and benchmarks), journal each as it finishes, and
    return every finished job. ``check_out_dir`` must have accepted ``out``."""
    check_out_dir(out, config)
    out.mkdir(parents=True, exist_ok=True)
    with locked(out):
        return _run_jobs(config, out, backend, max_jobs, progress_stream)


def _run_jobs(
    config: RunConfig,
    out: Path,
    backend: Backend,
    max_jobs: int | None,
    progress_stream: Any,
) -> RunOutcome:
    existing = check_out_dir(out, config)  # again: another run may have started meanwhile
    run_file = existing or {
        "format": FORMAT_VERSION,
        "arguments": config.to_json(),
        "effective_settings": config.effective_settings(),
        "sessions": [],
    }
    if existing is None:
        atomic_write_text(out / RUN_FILE, json.dumps(run_file, indent=2) + "\n")
    journal = Journal(out / JOURNAL_FILE)
    plan = plan_jobs(config)
    planned = {job.key for job in plan}
    finished = {
        key: result
        for key, result in journal.read().items()
        if key in planned and len(result.rows) == config.rounds + 1
    }
    pending = [job for job in plan if job.key not in finished]
    if max_jobs is not None:
        pending = pending[:max_jobs]

    session: dict[str, Any] = {
        "started": datetime.now(UTC).isoformat(timespec="seconds"),
        "backend": backend.describe(),
        "jobs_resumed": len(finished),
        "jobs_run": 0,
        "seconds": 0.0,
    }
    started = time.monotonic()
    progress = Progress(len(plan), len(finished), stream=progress_stream)
    progress.start()
    try:
        for result in backend.results(pending):
            journal.append(result)
            finished[result.key] = result
            session["jobs_run"] += 1
            progress.advance()
    except (ConfigError, SimulationError):
        raise
    except Exception as error:
        # The finished jobs are in the journal: the run resumes from here once fixed.
        raise SimulationError(f"{error} (finished jobs are kept; run again to resume)") from error
    finally:
        progress.finish()
        session["seconds"] = time.monotonic() - started
        run_file["sessions"] = [*run_file.get("sessions", []), session]
        atomic_write_text(out / RUN_FILE, json.dumps(run_file, indent=2) + "\n")
    ordered = [finished[job.key] for job in plan if job.key in finished]
    return RunOutcome(config, ordered, run_file["sessions"], complete=len(ordered) == len(plan))
