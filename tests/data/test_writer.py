"""DatasetWriter: round trip, D4RL layout and boundaries, existing files, resume, locks, bad episodes, a full disk."""

from __future__ import annotations

import errno
import json
import os
import re
import socket
from datetime import datetime
from pathlib import Path
from types import ModuleType
from typing import Any

import h5py
import numpy as np
import psutil
import pytest

from coworld.data import DatasetWriter, open_dataset, verify_dataset
from coworld.data.lock import lock_path
from coworld.errors import ConfigError, DatasetError, StorageError


def test_round_trip_gives_back_every_episode(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    with open_dataset(dataset_path) as data:
        assert data.num_episodes == len(episodes)
        assert data.num_steps == sum(len(ep["rewards"]) for ep in episodes)
        assert data.num_frames == data.num_steps + data.num_episodes
        assert data.task == "fake_task" and data.action_size == 3 and data.complete
        for i, ep in enumerate(episodes):
            got = data.episode(i)
            t = len(ep["rewards"])
            np.testing.assert_array_equal(got["image"], ep["observations"])
            np.testing.assert_array_equal(got["action"][1:], ep["actions"])
            np.testing.assert_array_equal(got["reward"][1:], ep["rewards"])
            assert not got["action"][0].any() and got["reward"][0] == 0
            assert got["is_first"].tolist() == [True] + [False] * t
            assert got["is_last"].tolist() == [False] * t + [True]
            assert got["is_terminal"].tolist() == [False] * t + [ep["terminated"]]
            np.testing.assert_array_equal(got["success"][1:], ep["infos"]["success"])
            np.testing.assert_array_equal(got["behavior_log_prob"][1:], ep["infos"]["behavior_log_prob"])
        np.testing.assert_allclose(data.returns, [ep["rewards"].astype(np.float64).sum() for ep in episodes])
        np.testing.assert_array_equal(data.lengths, [len(ep["rewards"]) for ep in episodes])


def test_metadata_is_recorded(dataset_path: Path) -> None:
    with open_dataset(dataset_path) as data:
        meta = data.metadata
    assert meta["format"] == "coworld-dataset" and meta["format_version"] == 1
    assert meta["quality"] == "random"
    assert meta["env_config"] == {"action_repeat": 2, "image_size": 64, "camera": "tracking"}
    assert meta["collector"] == {"algorithm": "random", "seed": 0}
    assert meta["reference"] == {"random_return": 0.0, "reference_return": 10.0}
    assert meta["versions"]["h5py"] == h5py.__version__ and meta["versions"]["numpy"] == np.__version__
    assert datetime.fromisoformat(meta["created"]) <= datetime.fromisoformat(meta["updated"])
    assert meta["complete"] is True


def test_top_level_is_d4rl_with_boundaries(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    lengths = [len(ep["rewards"]) for ep in episodes]
    ends = np.cumsum(lengths) - 1
    with h5py.File(dataset_path, "r") as f:  # plain h5py: what a user without coworld sees
        np.testing.assert_array_equal(
            f["observations"][:], np.concatenate([ep["observations"][:-1] for ep in episodes])
        )
        np.testing.assert_array_equal(f["actions"][:], np.concatenate([ep["actions"] for ep in episodes]))
        np.testing.assert_array_equal(f["episodes/final_observations"][:], [ep["observations"][-1] for ep in episodes])
        terminals, timeouts = f["terminals"][:], f["timeouts"][:]
        assert f["observations"].dtype == np.uint8 and f["actions"].dtype == np.float32
        assert f["rewards"].dtype == np.float32 and terminals.dtype == bool and timeouts.dtype == bool
        np.testing.assert_array_equal(np.flatnonzero(terminals | timeouts), ends)
        np.testing.assert_array_equal(terminals[ends], [ep["terminated"] for ep in episodes])
        np.testing.assert_array_equal(timeouts[ends], [not ep["terminated"] for ep in episodes])
        np.testing.assert_array_equal(f["episode_ids"][:], np.repeat(np.arange(len(episodes)), lengths))
        np.testing.assert_array_equal(np.flatnonzero(f["is_first"][:]), ends - np.array(lengths) + 1)
        np.testing.assert_array_equal(
            f["infos/success"][:], np.concatenate([ep["infos"]["success"] for ep in episodes])
        )
        assert f["observations"].compression == "gzip"  # stock filter: opens without plugins


def test_to_d4rl_matches_the_rows(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    with open_dataset(dataset_path) as data:
        d4rl = data.to_d4rl()
    assert set(d4rl) == {"observations", "actions", "rewards", "terminals", "timeouts", "infos/success",
                         "infos/behavior_log_prob"}  # fmt: skip
    np.testing.assert_array_equal(d4rl["rewards"], np.concatenate([ep["rewards"] for ep in episodes]))
    np.testing.assert_array_equal(d4rl["observations"][-1], episodes[-1]["observations"][-2])


def test_existing_file_is_never_overwritten_without_force(
    dataset_path: Path, helpers: ModuleType, episodes: list[dict[str, Any]]
) -> None:
    before = helpers.file_state(dataset_path)
    with pytest.raises(DatasetError, match="already exists.*--resume.*--force"):
        DatasetWriter(dataset_path, quality="random", **helpers.WRITER_ARGS)
    assert helpers.file_state(dataset_path) == before
    assert not lock_path(dataset_path).exists()  # the refused writer released its lock
    with DatasetWriter(dataset_path, quality="expert", force=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 0
        ep = episodes[0]
        writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], False, ep["infos"])
        writer.close(complete=True)
    with open_dataset(dataset_path) as data:
        assert data.num_episodes == 1 and data.quality == "expert"


def test_a_new_file_replaces_the_temporary_files_that_killed_writers_left(tmp_path: Path, helpers: ModuleType) -> None:
    path = tmp_path / "m.h5"
    left = [tmp_path / "m.h5.17902.tmp", tmp_path / "m.h5.3.tmp"]  # a kill between building and renaming
    kept = [tmp_path / "m.h5.lock.17903.tmp", tmp_path / "other.h5.17902.tmp", tmp_path / "m.h5x.1.tmp"]
    for file in left + kept:
        file.write_bytes(b"partial")
    with DatasetWriter(path, quality="random", **helpers.WRITER_ARGS) as writer:
        writer.close(complete=True)
    assert not any(file.exists() for file in left)
    assert all(file.exists() for file in kept)  # another writer's lock in the making, other datasets' files


def test_resume_continues_a_partial_dataset(
    tmp_path: Path, helpers: ModuleType, episodes: list[dict[str, Any]]
) -> None:
    path = helpers.write_dataset(tmp_path / "part.h5", episodes[:3], complete=False)
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert (writer.num_episodes, writer.num_steps) == (3, sum(len(ep["rewards"]) for ep in episodes[:3]))
        for ep in episodes[3:]:
            writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        writer.close(complete=True)
    with open_dataset(path) as data:
        assert data.num_episodes == len(episodes) and data.complete
        np.testing.assert_array_equal(data.episode(4)["image"], episodes[4]["observations"])


def test_resume_of_a_missing_file_starts_fresh(tmp_path: Path, helpers: ModuleType) -> None:
    path = tmp_path / "sub" / "new.h5"
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 0 and writer.num_steps == 0
    assert path.exists()


def test_resume_of_a_complete_dataset_reopens_it_only_when_written(dataset_path: Path, helpers: ModuleType) -> None:
    with DatasetWriter(dataset_path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.complete  # nothing added: the flag stays
    with open_dataset(dataset_path) as data:
        assert data.complete
    ep = helpers.make_episodes([4], seed=9)[0]
    with DatasetWriter(dataset_path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], False, ep["infos"])
        assert not writer.complete  # more data: no longer the finished dataset
    with open_dataset(dataset_path) as data:
        assert not data.complete and data.num_episodes == 8


@pytest.mark.parametrize(
    ("override", "message"),
    [({"task": "other_task"}, "task other_task"), ({"action_size": 4}, "action size 4")],
)
def test_resume_refuses_a_dataset_of_another_task_or_shape(
    dataset_path: Path, helpers: ModuleType, override: dict[str, Any], message: str
) -> None:
    args = {**helpers.WRITER_ARGS, **override}
    with pytest.raises(DatasetError, match=f"cannot resume .*, not .*{message}"):
        DatasetWriter(dataset_path, quality="random", resume=True, **args)
    assert not lock_path(dataset_path).exists()


def test_update_metadata_merges_collector_fields(tmp_path: Path, helpers: ModuleType) -> None:
    with DatasetWriter(tmp_path / "m.h5", quality="medium-replay", **helpers.WRITER_ARGS) as writer:
        writer.update_metadata(last_eval_return=512.5, stop_reason="medium level reached")
        assert writer.metadata["collector"] == {
            "algorithm": "random",
            "seed": 0,
            "last_eval_return": 512.5,
            "stop_reason": "medium level reached",
        }
    with h5py.File(tmp_path / "m.h5", "r") as f:
        assert json.loads(f.attrs["collector"])["last_eval_return"] == 512.5


def test_collector_fields_are_committed_with_their_episode(tmp_path: Path, helpers: ModuleType) -> None:
    good, bad = helpers.make_episodes([5, 4])
    with DatasetWriter(tmp_path / "c.h5", quality="random", **helpers.WRITER_ARGS) as writer:
        writer.add_episode(good["observations"], good["actions"], good["rewards"], False, good["infos"], {"steps": 5})
        with pytest.raises(DatasetError, match="non-finite"):  # refused: neither the episode nor its count goes in
            rewards = np.full(4, np.nan, np.float32)
            writer.add_episode(bad["observations"], bad["actions"], rewards, False, bad["infos"], {"steps": 9})
    with h5py.File(tmp_path / "c.h5", "r") as f:
        assert json.loads(f.attrs["collector"]) == {"algorithm": "random", "seed": 0, "steps": 5}
        assert int(f.attrs["num_rows"]) == 5


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"rewards": np.array([0.0, np.nan, 1.0, 0.0], np.float32)}, "non-finite"),
        ({"actions": np.zeros((4, 2), np.float32)}, "needs actions"),
        ({"observations": np.zeros((5, 32, 32, 3), np.uint8)}, "observations must be"),
        ({"observations": np.zeros((5, 64, 64, 3), np.float32)}, "observations must be"),
        ({"infos": {"other": np.zeros(4)}}, "infos keys"),
        ({"infos": {"success": np.zeros(3, bool), "behavior_log_prob": np.zeros(4)}}, "must have 4 rows"),
    ],
)
def test_bad_episodes_are_refused_and_nothing_is_committed(
    dataset_path: Path, helpers: ModuleType, change: dict[str, Any], message: str
) -> None:
    ep = {**helpers.make_episodes([4], seed=3)[0], **change}
    with DatasetWriter(dataset_path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        before = (writer.num_episodes, writer.num_steps)
        with pytest.raises(DatasetError, match=message):
            writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], False, ep["infos"])
        assert (writer.num_episodes, writer.num_steps) == before


def test_bad_writer_arguments(tmp_path: Path, helpers: ModuleType) -> None:
    with pytest.raises(ConfigError, match="unknown dataset quality 'great'"):
        DatasetWriter(tmp_path / "q.h5", quality="great", **helpers.WRITER_ARGS)
    with pytest.raises(ConfigError, match="unknown compression 'brotli'"):
        DatasetWriter(tmp_path / "q.h5", quality="random", compression="brotli", **helpers.WRITER_ARGS)
    with pytest.raises(ConfigError, match="exclude each other"):
        DatasetWriter(tmp_path / "q.h5", quality="random", resume=True, force=True, **helpers.WRITER_ARGS)
    assert not (tmp_path / "q.h5").exists()


def test_a_second_writer_is_stopped_by_the_lock(tmp_path: Path, helpers: ModuleType) -> None:
    path = tmp_path / "locked.h5"
    with DatasetWriter(path, quality="random", **helpers.WRITER_ARGS):
        with pytest.raises(DatasetError, match=rf"locked by process {os.getpid()} .*lock file .*locked\.h5\.lock"):
            DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS)
        assert lock_path(path).exists()  # the refused writer did not remove the holder's lock
    assert not lock_path(path).exists()
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 0


def test_a_stale_lock_is_taken_over_but_a_live_one_is_not(tmp_path: Path, helpers: ModuleType) -> None:
    path = helpers.write_dataset(tmp_path / "stale.h5", helpers.make_episodes([5]), complete=False)
    dead = psutil.Popen(["true"])
    dead.wait()
    host = socket.gethostname()
    lock_path(path).write_text(json.dumps({"host": host, "pid": dead.pid, "started": dead.create_time()}))
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 1
        assert json.loads(lock_path(path).read_text())["pid"] == os.getpid()
    parent = psutil.Process(os.getppid())
    lock_path(path).write_text(json.dumps({"host": host, "pid": parent.pid, "started": parent.create_time()}))
    with pytest.raises(DatasetError, match=f"locked by process {parent.pid}"):
        DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS)
    # the same PID started at another time is a reused PID: the lock is stale
    lock_path(path).write_text(json.dumps({"host": host, "pid": parent.pid, "started": parent.create_time() - 100}))
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        assert writer.num_episodes == 1


@pytest.mark.parametrize("codec", ["none", "zstd", "lz4"])
def test_other_codecs_round_trip(tmp_path: Path, helpers: ModuleType, codec: str) -> None:
    pytest.importorskip("hdf5plugin")
    eps = helpers.make_episodes([6, 9])
    path = helpers.write_dataset(tmp_path / f"{codec}.h5", eps, compression=codec)
    with open_dataset(path) as data:
        assert data.metadata["compression"] == codec
        np.testing.assert_array_equal(data.episode(1)["image"], eps[1]["observations"])


def test_resume_while_a_reader_has_the_file_open_says_so(dataset_path: Path, helpers: ModuleType) -> None:
    with open_dataset(dataset_path) as data:
        data.episode(0)
        with pytest.raises(DatasetError, match="it is open elsewhere"):
            DatasetWriter(dataset_path, quality="random", resume=True, **helpers.WRITER_ARGS)
    assert not lock_path(dataset_path).exists()


def test_a_write_refused_after_the_room_check_keeps_the_commits_and_resumes(
    small_disk, helpers: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills between the room check and the write (another process wrote meanwhile): the write's own error
    stops the writer at once, the commits before stay whole, and a resumed writer continues once there is room."""
    import coworld.data.writer as writer_module

    monkeypatch.setattr(writer_module, "room_problem", lambda path, needed: None)
    disk = small_disk(3 * 2**20)
    if not disk.mounted:  # without root there is no small disk to fill: the fourth episode's first write is refused
        real_append, calls = writer_module._append, []

        def append(node: Any, at: int, value: Any) -> None:
            calls.append(node.name)
            if len(calls) > 3 * 15:  # 15 appends per episode: 7 row fields, 2 infos, 6 episode fields
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real_append(node, at, value)

        monkeypatch.setattr(writer_module, "_append", append)
    path, episodes = disk.path / "w.h5", helpers.make_episodes([60] * 20)
    with pytest.raises(
        StorageError, match=r"No space left on device; (\d+) committed episodes? (is|are) intact"
    ) as err:
        with DatasetWriter(path, quality="random", compression="none", **helpers.WRITER_ARGS) as writer:
            for ep in episodes:
                writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
    kept = int(re.search(r"(\d+) committed", str(err.value)).group(1))
    helpers.assert_unfinished_but_sound(path)
    assert helpers.assert_whole_prefix(path, episodes) == kept > 0

    monkeypatch.undo()
    disk.grow(64 * 2**20)
    with DatasetWriter(path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        for ep in episodes[writer.num_episodes :]:
            writer.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        writer.close(complete=True)
    assert helpers.assert_whole_prefix(path, episodes) == 20 and verify_dataset(path) == []
