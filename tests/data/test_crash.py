"""kill -9 of a writer loses at most the episode in progress; resume completes the request; one writer at a time."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.data import DatasetWriter, open_dataset, verify_dataset
from coworld.data.lock import lock_path
from coworld.errors import DatasetError

HELPERS = str(Path(__file__).with_name("helpers.py"))
LENGTHS = [int(x) for x in np.random.default_rng(0).integers(30, 120, 40)]

# argv: helpers.py, dataset path, episodes wanted, seconds to sleep after each episode
WRITER_SCRIPT = """
import importlib.util, sys, time
spec = importlib.util.spec_from_file_location("helpers", sys.argv[1])
helpers = importlib.util.module_from_spec(spec)
spec.loader.exec_module(helpers)
from coworld.data import DatasetWriter
episodes = helpers.make_episodes(LENGTHS[: int(sys.argv[3])])
with DatasetWriter(sys.argv[2], quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
    for ep in episodes[writer.num_episodes :]:
        writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        print(writer.num_episodes, flush=True)
        time.sleep(float(sys.argv[4]))
    writer.close(complete=True)
""".replace("LENGTHS", repr(LENGTHS))

# argv: helpers.py, then the `coworld collect` arguments
COLLECT_SCRIPT = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("helpers", sys.argv[1])
helpers = importlib.util.module_from_spec(spec)
spec.loader.exec_module(helpers)
helpers.patch_envs(setattr, delay=0.01)
from coworld.data import DatasetWriter
add_episode = DatasetWriter.add_episode
def add_and_report(self, *args, **kwargs):
    add_episode(self, *args, **kwargs)
    print(self.num_episodes, flush=True)
DatasetWriter.add_episode = add_and_report
from coworld.cli import main
main(sys.argv[2:])
"""


def _start(script: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", script, HELPERS, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def _wait_for_episodes(proc: subprocess.Popen[str], count: int, timeout: float = 60.0) -> int:
    """Read the episode counts the child prints until it reports ``count``; return the last one."""
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"child exited early: {proc.stderr.read() if proc.stderr else ''}")
        if int(line) >= count:
            return int(line)
    raise AssertionError("child too slow")


def _kill(proc: subprocess.Popen[str]) -> None:
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def _assert_whole_prefix(path: Path, expected: list[dict[str, Any]]) -> int:
    """The dataset opens and holds exactly the first episodes of ``expected``, each whole; returns how many."""
    with open_dataset(path) as data:
        n = data.num_episodes
        assert n <= len(expected)
        for i in range(n):
            ep = data.episode(i)
            np.testing.assert_array_equal(ep["image"], expected[i]["observations"])
            np.testing.assert_array_equal(ep["reward"][1:], expected[i]["rewards"])
    return n


def test_kill_between_episodes_then_resume_completes_exactly(tmp_path: Path, helpers: ModuleType) -> None:
    path, wanted = tmp_path / "killed.h5", 10
    expected = helpers.make_episodes(LENGTHS[:wanted])
    proc = _start(WRITER_SCRIPT, str(path), "100", "0.2")
    reported = _wait_for_episodes(proc, 3)
    _kill(proc)
    assert reported <= _assert_whole_prefix(path, expected) <= reported + 1
    assert lock_path(path).exists()  # left behind by the killed writer: stale, taken over below
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        for ep in expected[writer.num_episodes :]:
            writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        writer.close(complete=True)
    assert _assert_whole_prefix(path, expected) == wanted
    assert verify_dataset(path) == []


def test_kills_in_the_middle_of_writes_leave_only_whole_episodes(tmp_path: Path, helpers: ModuleType) -> None:
    path, wanted = tmp_path / "hammered.h5", 40
    expected = helpers.make_episodes(LENGTHS[:wanted])
    rng = np.random.default_rng(1)
    for _ in range(4):  # writing back to back: a kill lands inside add_episode most of the time
        done = _assert_whole_prefix(path, expected) if path.exists() else 0  # before the writer starts
        proc = _start(WRITER_SCRIPT, str(path), str(wanted), "0")
        _wait_for_episodes(proc, done + int(rng.integers(1, 4)))
        time.sleep(float(rng.uniform(0.0, 0.01)))  # the child is writing its next episode
        _kill(proc)
        _assert_whole_prefix(path, expected)
    proc = _start(WRITER_SCRIPT, str(path), str(wanted), "0")
    assert proc.wait(timeout=120) == 0, proc.stderr.read() if proc.stderr else ""
    assert _assert_whole_prefix(path, expected) == wanted
    assert verify_dataset(path) == []


def test_a_second_concurrent_writer_fails_clearly(tmp_path: Path, helpers: ModuleType) -> None:
    path = tmp_path / "busy.h5"
    proc = _start(WRITER_SCRIPT, str(path), "5", "60")
    try:
        _wait_for_episodes(proc, 1)
        with pytest.raises(DatasetError, match=rf"locked by process {proc.pid} .*busy\.h5\.lock.*wait"):
            DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS)
        with pytest.raises(DatasetError, match=rf"being written by process {proc.pid}"):
            open_dataset(path)
    finally:
        _kill(proc)
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 1


def test_collect_resume_after_a_kill_collects_exactly_the_request(
    tmp_path: Path, helpers: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "collect.h5"
    args = [
        "collect",
        "--policy",
        "random",
        "--task",
        "fake_task",
        "--episodes",
        "15",
        "--out",
        str(path),
        "--workers",
        "2",
        "--quiet",
    ]
    proc = _start(COLLECT_SCRIPT, *args)
    _wait_for_episodes(proc, 4)
    _kill(proc)
    with open_dataset(path) as data:
        survived = [data.episode(i)["image"] for i in range(data.num_episodes)]
        assert not data.complete and 4 <= data.num_episodes < 15
    helpers.patch_envs(monkeypatch.setattr)
    result = CliRunner().invoke(main, [*args, "--resume"])
    assert result.exit_code == 0, result.output
    with open_dataset(path) as data:
        assert data.num_episodes == 15 and data.complete
        for i, image in enumerate(survived):
            np.testing.assert_array_equal(data.episode(i)["image"], image)
    assert verify_dataset(path) == []
