"""docs/rl-ecosystem.md: its Python examples run and print what the page says."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from server import domains
from server.rl.datasets import Dataset, DatasetEpisode, write_datasets
from tests.rl._support import REPOSITORY, run_python

PAGE = (REPOSITORY / "docs" / "rl-ecosystem.md").read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", PAGE, flags=re.S)


def run(code: str, cwd: Path) -> str:
    return run_python(code, cwd)


def test_the_page_has_its_three_examples() -> None:
    assert len(BLOCKS) == 3


def test_the_module_id_example_makes_the_environment(tmp_path: Path) -> None:
    run(BLOCKS[0] + "assert env.unwrapped.env.name == 'doorway'\n", tmp_path)


@pytest.mark.slow
def test_the_learning_loop_prints_what_the_page_says(tmp_path: Path) -> None:
    claimed = re.search(r"it prints `(.*?)`", PAGE)
    assert claimed is not None
    assert run(BLOCKS[1], tmp_path).strip() == claimed.group(1)


def test_the_minari_lines_load_a_dataset(tmp_path: Path) -> None:
    env = domains.make("doorway")
    start = int(np.flatnonzero(env.tasks[0].start)[0])
    episode = DatasetEpisode(0, [start, start], [0], {"kind": ["agent", "agent"]})
    write_datasets(
        [Dataset("doorway", "participants", [episode], "test", "none")],
        tmp_path / "study-minari",
    )
    out = run(BLOCKS[2] + "print(dataset.total_episodes, dataset.recover_environment().spec.id)\n",
              tmp_path)  # fmt: skip
    assert out.split() == ["1", "BAMStudy/Doorway-v0"]
