"""kill -9 of a writer loses at most the episode in progress; resume completes the request; one writer at a time."""

from __future__ import annotations

import time
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.data import DatasetWriter, open_dataset, verify_dataset
from coworld.data.lock import lock_path
from coworld.errors import DatasetError

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


def test_kill_between_episodes_then_resume_completes_exactly(
    tmp_path: Path, helpers: ModuleType, processes: ModuleType
) -> None:
    path, wanted = tmp_path / "killed.h5", 10
    expected = helpers.make_episodes(LENGTHS[:wanted])
    proc = processes.start_script(WRITER_SCRIPT, str(path), "100", "0.2")
    reported = processes.wait_for_episodes(proc, 3)
    processes.kill(proc)
    assert reported <= helpers.assert_whole_prefix(path, expected) <= reported + 1
    assert lock_path(path).exists()  # left behind by the killed writer: stale, taken over below
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        for ep in expected[writer.num_episodes :]:
            writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        writer.close(complete=True)
    assert helpers.assert_whole_prefix(path, expected) == wanted
    assert verify_dataset(path) == []


def test_kills_in_the_middle_of_writes_leave_only_whole_episodes(
    tmp_path: Path, helpers: ModuleType, processes: ModuleType
) -> None:
    path, wanted = tmp_path / "hammered.h5", 40
    expected = helpers.make_episodes(LENGTHS[:wanted])
    rng = np.random.default_rng(1)
    for _ in range(4):  # writing back to back: a kill lands inside add_episode most of the time
        done = helpers.assert_whole_prefix(path, expected) if path.exists() else 0  # before the writer starts
        proc = processes.start_script(WRITER_SCRIPT, str(path), str(wanted), "0")
        processes.wait_for_episodes(proc, done + int(rng.integers(1, 4)))
        time.sleep(float(rng.uniform(0.0, 0.01)))  # the child is writing its next episode
        processes.kill(proc)
        helpers.assert_whole_prefix(path, expected)
    proc = processes.start_script(WRITER_SCRIPT, str(path), str(wanted), "0")
    assert proc.wait(timeout=120) == 0, proc.stderr.read() if proc.stderr else ""
    assert helpers.assert_whole_prefix(path, expected) == wanted
    assert verify_dataset(path) == []


def test_a_second_concurrent_writer_fails_clearly(tmp_path: Path, helpers: ModuleType, processes: ModuleType) -> None:
    path = tmp_path / "busy.h5"
    proc = processes.start_script(WRITER_SCRIPT, str(path), "5", "60")
    try:
        processes.wait_for_episodes(proc, 1)
        with pytest.raises(DatasetError, match=rf"locked by process {proc.pid} .*busy\.h5\.lock.*wait"):
            DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS)
        with pytest.raises(DatasetError, match=rf"being written by process {proc.pid}"):
            open_dataset(path)
    finally:
        processes.kill(proc)
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 1


def test_collect_resume_after_a_kill_collects_exactly_the_request(
    tmp_path: Path, helpers: ModuleType, processes: ModuleType, monkeypatch: pytest.MonkeyPatch
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
    proc = processes.start_script(processes.COLLECT_SCRIPT, *args)
    processes.wait_for_episodes(proc, 4)
    processes.kill(proc)
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


def test_a_collection_killed_and_resumed_is_the_uninterrupted_one(
    tmp_path: Path, helpers: ModuleType, processes: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    args = ["collect", "--policy", "random", "--task", "fake_task", "--episodes", "15", "--workers", "2", "--quiet"]
    path = tmp_path / "killed.h5"
    proc = processes.start_script(processes.COLLECT_SCRIPT, *args, "--out", str(path))
    processes.wait_for_episodes(proc, 4)
    processes.kill(proc)
    with open_dataset(path) as data:  # the record of what was killed counts the rows it holds
        assert not data.complete and data.metadata["collector"]["steps"] == data.num_steps
    helpers.patch_envs(monkeypatch.setattr)
    for out, resume in ((path, ["--resume"]), (tmp_path / "whole.h5", [])):
        result = CliRunner().invoke(main, [*args, "--out", str(out), *resume])
        assert result.exit_code == 0, result.output
    assert helpers.episode_digests(path) == helpers.episode_digests(tmp_path / "whole.h5")
    for out in (path, tmp_path / "whole.h5"):
        with open_dataset(out) as data:
            assert data.complete and data.metadata["collector"]["steps"] == data.num_steps
