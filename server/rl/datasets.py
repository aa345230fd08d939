"""Episodes of our environments written as Minari datasets, one per environment, into a new
folder that ``minari.load_dataset`` reads with ``MINARI_DATASETS_PATH`` set to it.

An episode of T actions has T + 1 observations (the state numbers of the Gymnasium
environment's default observation), T actions, T rewards (``step_reward``, as the Gymnasium
environment pays them), T terminations (always false: our environments have no terminal state)
and T truncations (true at the last step: the episode was cut there, by its teacher, its goal
or the horizon). ``infos`` holds T + 1 entries per key as Gymnasium's ``reset`` and ``step``
give them: entry 0 describes the start, entry t + 1 the t-th action.

The datasets are built in a hidden folder beside the output and moved into place at the end,
so a failure leaves no half-written dataset behind.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from server import domains
from server.rl.environments import environment_id, step_reward

NAMESPACE = "bam-study"


class DatasetError(ValueError):
    """The datasets cannot be written; the message says why (nothing was written)."""


def dataset_id(environment: str, name: str) -> str:
    """The Minari id of one environment's dataset: ``bam-study/doorway/participants-v0``."""
    domains.make(environment)  # an unknown name fails here, clearly
    return f"{NAMESPACE}/{environment}/{name}-v0"


@dataclass
class DatasetEpisode:
    """One episode of one task: the states it visited and the actions taken, with per-step
    information (``infos``: arrays of len(actions) + 1 entries, see the module docstring)."""

    task: int
    states: list[int]
    actions: list[int]
    infos: dict[str, list[Any]] = field(default_factory=dict)

    def buffer(self, environment: str) -> Any:
        from minari.data_collector import EpisodeBuffer

        env = domains.make(environment)
        steps = len(self.actions)
        if steps == 0 or len(self.states) != steps + 1:
            raise DatasetError(
                f"an episode needs at least one action and one more state than actions; got "
                f"{steps} actions and {len(self.states)} states"
            )
        for key, values in self.infos.items():
            if len(values) != steps + 1:
                raise DatasetError(f"info {key!r} has {len(values)} entries, not {steps + 1}")
        rewards = [
            step_reward(env, self.task, state, next_state)
            for state, next_state in zip(self.states[:-1], self.states[1:], strict=True)
        ]
        infos: dict[str, Any] = {"task": np.full(steps + 1, self.task, dtype=np.int64)}
        for key, values in self.infos.items():
            infos[key] = list(values) if isinstance(values[0], str) else np.asarray(values)
        return EpisodeBuffer(
            observations=np.asarray(self.states, dtype=np.int64),
            actions=np.asarray(self.actions, dtype=np.int64),
            rewards=rewards,
            terminations=[False] * steps,
            truncations=[False] * (steps - 1) + [True],
            infos=infos,
        )


@dataclass
class Dataset:
    """One environment's episodes, the dataset's name (``participants``, ...), a description
    and extra metadata (JSON values)."""

    environment: str
    name: str
    episodes: Sequence[DatasetEpisode]
    description: str
    algorithm: str
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return dataset_id(self.environment, self.name)


def existing_datasets(folder: Path) -> list[str]:
    """The ids of the Minari datasets in ``folder`` (a MINARI_DATASETS_PATH)."""
    return sorted(
        path.parent.relative_to(folder).as_posix()
        for path in folder.rglob("data")
        if (path / "metadata.json").is_file()
    )


def check_out_folder(out: Path) -> None:
    """``out`` must be a new or empty folder: never mix datasets of two exports."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()):
        held = existing_datasets(out)
        if held:
            raise DatasetError(
                f"{out} already holds Minari datasets ({', '.join(held[:3])}"
                f"{', ...' if len(held) > 3 else ''}): write into a new folder, or remove them"
            )
        raise DatasetError(f"{out} is not empty: write the datasets into a new folder")


@contextlib.contextmanager
def _datasets_path(folder: Path) -> Iterator[None]:
    """Minari finds its datasets through MINARI_DATASETS_PATH: point it at ``folder``."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(folder)
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def write_datasets(datasets: Sequence[Dataset], out: Path) -> list[str]:
    """Write every dataset into the new folder ``out``; returns their ids. All or nothing."""
    import minari

    check_out_folder(out)
    if not datasets or not any(dataset.episodes for dataset in datasets):
        raise DatasetError("there are no episodes to write")
    out = out.absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        with _datasets_path(staging), warnings.catch_warnings():
            # Minari warns of every optional field left out (author, code permalink, ...).
            warnings.simplefilter("ignore", UserWarning)
            for dataset in datasets:
                if not dataset.episodes:
                    continue
                written = minari.create_dataset_from_buffers(
                    dataset.id,
                    [episode.buffer(dataset.environment) for episode in dataset.episodes],
                    env=environment_id(dataset.environment),
                    algorithm_name=dataset.algorithm,
                    description=dataset.description,
                )
                written.storage.update_metadata(dataset.metadata)
        check_out_folder(out)  # nothing appeared meanwhile
        if out.is_dir():
            out.rmdir()
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [dataset.id for dataset in datasets if dataset.episodes]
