"""``coworld tasks`` and ``coworld render``, through click and as a real process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from click.testing import CliRunner

from coworld.cli import main
from coworld.envs import PAIRS, TASKS


def test_tasks_lists_every_task_and_pair() -> None:
    result = CliRunner().invoke(main, ["tasks"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    for name, task in TASKS.items():
        row = next(line for line in lines if line.split()[:1] == [name])
        assert row.split()[1:5] == [
            task.family,
            str(task.action_size),
            str(task.episode_length),
            str(task.action_repeat),
        ]
    for source, target in PAIRS:
        assert any(line.split() == [source, "->", target] for line in lines)
    need = next(line for line in lines if "need --source" in line)
    alone = next(line for line in lines if "target dataset alone" in line)
    assert need.split(": ")[1].split(", ") == ["coworld", "dreamerv2-finetune", "dreamerv2-finetune-ewc"]
    alone_algos = {"dreamerv2", "curl", "curl-cql", "drq-bc", "dreamerv2-penalty", "lompo"}
    assert set(alone.split(": ")[1].split(", ")) == alone_algos


def test_render_writes_the_frames_of_an_episode(tmp_path: Path) -> None:
    result = CliRunner().invoke(main, ["render", "--task", "toy_reach", "--out", str(tmp_path), "--frames", "4"])
    assert result.exit_code == 0, result.output
    files = sorted(tmp_path.glob("toy_reach_*.png"))
    assert [f.name for f in files] == [f"toy_reach_{i:04d}.png" for i in range(4)]
    frames = [iio.imread(f) for f in files]
    assert all(frame.shape == (64, 64, 3) for frame in frames)
    assert not np.array_equal(frames[0], frames[3])  # the dot moved


def test_unknown_task_exits_2_with_one_line(tmp_path: Path) -> None:
    code = "import sys; sys.argv = ['coworld'] + sys.argv[1:]; from coworld.cli import run; run()"
    result = subprocess.run(
        [sys.executable, "-c", code, "render", "--task", "walker_jog", "--out", str(tmp_path / "x")],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONWARNINGS": "ignore"},
    )
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert result.stderr.startswith("error: unknown task 'walker_jog'; valid tasks: walker_walk")
    assert not (tmp_path / "x").exists()
