"""`coworld dataset import vd4rl`: hand-made V-D4RL folders in both layouts, written the way V-D4RL's code writes them.

Every entry j of source episode e carries known values: its frame is the constant ``10 * e + j + 1`` (a constant
frame stays exact through an area resize), its action ``action_value(e, j)`` and its reward ``100 * e + j`` (entry
0, the reset, has a zero action and reward). So the converted rows must be: frame of entry i, action and reward of
entry i + 1.
"""

from __future__ import annotations

import datetime
import io
import subprocess
import sys
import uuid
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from coworld.cli import main
from coworld.data import DatasetWriter, import_vd4rl, open_dataset, verify_dataset
from coworld.data.vd4rl import scan_vd4rl
from coworld.errors import CoworldError
from coworld.training.logger import read_metrics

COWORLD = [sys.executable, "-c", "from coworld.cli import run; run()"]
A = 6  # V-D4RL's walker_walk and cheetah_run


def action_value(e: int, j: int) -> np.ndarray:
    """The action stored at entry j >= 1 of episode e (in [-1, 1], different in every entry and dimension)."""
    return (np.arange(A) / 10 + 0.03 * j - 0.2 * e - 0.4).clip(-1, 1).astype(np.float32)


def source_episode(e: int, length: int, terminated: bool, size: int = 64) -> dict[str, np.ndarray]:
    """Episode e of ``length`` transitions in V-D4RL's step layout: ``length + 1`` entries, entry 0 the reset."""
    j = np.arange(length + 1)
    action = np.stack([np.zeros(A, np.float32) if k == 0 else action_value(e, k) for k in j])
    last = j == length
    return {
        "image": np.broadcast_to((10 * e + j + 1).astype(np.uint8)[:, None, None, None], (length + 1, size, size, 3)),
        "action": action,
        "reward": np.where(j == 0, 0.0, 100.0 * e + j).astype(np.float32),
        "discount": np.where(last & terminated, 0.0, 1.0).astype(np.float32),
        "is_first": j == 0,
        "is_last": last,
        "is_terminal": last & terminated,
    }


def write_npz_episodes(folder: Path, episodes: list[dict[str, np.ndarray]]) -> Path:
    """V-D4RL's 64px layout as its scripts write it: ``<time>-<uuid>-<entries>.npz`` via np.savez_compressed."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, episode in enumerate(episodes):
        stamp = (datetime.datetime(2022, 1, 1) + datetime.timedelta(seconds=i)).strftime("%Y%m%dT%H%M%S")
        name = f"{stamp}-{uuid.uuid4().hex}-{len(episode['action'])}.npz"
        with io.BytesIO() as buffer:
            np.savez_compressed(buffer, **{key: np.ascontiguousarray(value) for key, value in episode.items()})
            (folder / name).write_bytes(buffer.getvalue())
    return folder


def write_shards(folder: Path, shards: list[list[dict[str, np.ndarray]]], cut: int | None = None) -> Path:
    """V-D4RL's 84px layout as its scripts write it: gzip HDF5 shards of episodes back to back, frames channels
    first, ``step_type`` 0/1/2, reward and discount as float64 (gather_offline_data's np.array of floats).

    ``cut`` moves the last ``cut`` rows of each shard to the front of the next one (what np.array_split of
    split_hdf5_shards.py can do), so an episode runs on across a shard boundary.
    """
    folder.mkdir(parents=True, exist_ok=True)
    tables = []
    for episodes in shards:
        step_type = [np.where(ep["is_first"], 0, np.where(ep["is_last"], 2, 1)) for ep in episodes]
        tables.append(
            {
                "observation": np.concatenate([ep["image"].transpose(0, 3, 1, 2) for ep in episodes]),
                "action": np.concatenate([ep["action"] for ep in episodes]),
                "reward": np.concatenate([ep["reward"] for ep in episodes]).astype(np.float64),
                "discount": np.concatenate([ep["discount"] for ep in episodes]).astype(np.float64),
                "step_type": np.concatenate(step_type).astype(np.int64),
            }
        )
    if cut:
        for a, b in zip(tables, tables[1:], strict=False):
            for key in a:
                a[key], b[key] = a[key][:-cut], np.concatenate([a[key][-cut:], b[key]])
    for i, table in enumerate(tables):
        with h5py.File(folder / f"shard_{i + 1}_reward_0.hdf5", "w") as f:
            for key, value in table.items():
                f.create_dataset(key, data=value, compression="gzip")
    return folder


LENGTHS, TERMINATED = [5, 3, 7, 4], [False, True, False, True]


def known_episodes(size: int = 64) -> list[dict[str, np.ndarray]]:
    return [source_episode(e, t, d, size) for e, (t, d) in enumerate(zip(LENGTHS, TERMINATED, strict=True))]


def assert_matches_source(path: Path, sources: list[dict[str, np.ndarray]]) -> None:
    """The converted file holds exactly the known rows, boundaries, terminals and time limits."""
    with open_dataset(path) as data:
        assert data.num_episodes == len(sources) and data.task == "walker_walk"
        np.testing.assert_array_equal(data.lengths, LENGTHS)
        np.testing.assert_array_equal(data.starts, np.concatenate([[0], np.cumsum(LENGTHS)[:-1]]))
        np.testing.assert_array_equal(data.terminated, TERMINATED)
        d4rl = data.to_d4rl()
        ends = np.cumsum(LENGTHS) - 1
        np.testing.assert_array_equal(np.flatnonzero(d4rl["terminals"]), ends[np.array(TERMINATED)])
        np.testing.assert_array_equal(np.flatnonzero(d4rl["timeouts"]), ends[~np.array(TERMINATED)])
        for e, (t, source) in enumerate(zip(LENGTHS, sources, strict=True)):
            s = int(data.starts[e])
            # row i = (frame of entry i, action and reward of entry i + 1)
            np.testing.assert_array_equal(d4rl["observations"][s : s + t, 0, 0, 0], 10 * e + np.arange(t) + 1)
            np.testing.assert_array_equal(d4rl["rewards"][s : s + t], 100 * e + np.arange(1, t + 1))
            np.testing.assert_array_equal(d4rl["actions"][s : s + t], [action_value(e, j) for j in range(1, t + 1)])
            assert data.returns[e] == sum(100 * e + j for j in range(1, t + 1))
            # the step convention of sequence models is V-D4RL's own: the source arrays come back unchanged
            step = data.episode(e)
            for key in ("image", "action", "reward", "is_first", "is_last", "is_terminal"):
                np.testing.assert_array_equal(step[key], source[key], err_msg=key)
    assert verify_dataset(path) == []


def test_npz_episodes_convert_with_known_rows_boundaries_and_terminals(tmp_path: Path) -> None:
    sources = known_episodes()
    folder = write_npz_episodes(tmp_path / "vd4rl_data/main/walker_walk/medium_replay/64px", sources)
    out = tmp_path / "ww.h5"
    result = CliRunner().invoke(main, ["dataset", "import", "vd4rl", str(folder), "--task", "walker_walk",
                                       "--out", str(out)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert f"wrote {out}: 4 episodes, 19 steps of walker_walk" in result.stdout
    assert_matches_source(out, sources)
    with open_dataset(out) as data:
        assert data.quality == "medium-replay" and data.complete  # quality read from V-D4RL's folder name
        collector = data.metadata["collector"]
        assert collector["algorithm"] == "import" and collector["source_format"] == "vd4rl-npz-episodes"
        assert collector["source_path"] == str(folder.resolve()) and collector["source_env"] == "walker_walk"
        assert collector["source_files"] == 4 and collector["resize"] is None and collector["steps"] == 19
        assert data.metadata["env_config"]["action_repeat"] == 2 and data.reference["random_return"] == 41.7


def test_npz_without_is_terminal_ends_in_a_terminal_state_where_discount_is_zero(tmp_path: Path) -> None:
    """V-D4RL's loader: older files have no is_terminal, and discount 0 marks the terminal step."""
    sources = known_episodes()
    older = [{key: value for key, value in ep.items() if key != "is_terminal"} for ep in sources]
    folder = write_npz_episodes(tmp_path / "64px", older)
    summary = import_vd4rl(folder, tmp_path / "ww.h5", task="walker_walk", quality="medium")
    assert summary.episodes == 4 and summary.steps == 19
    assert_matches_source(summary.path, sources)


def test_84px_shards_are_refused_without_resize(tmp_path: Path) -> None:
    folder = write_shards(tmp_path / "walker_walk/expert/84px", [known_episodes(size=84)])
    out = tmp_path / "ww.h5"
    result = CliRunner().invoke(main, ["dataset", "import", "vd4rl", str(folder), "--task", "walker_walk",
                                       "--out", str(out)])  # fmt: skip
    assert result.exit_code == 2 and len(result.stderr.splitlines()) == 1, result.output
    assert "frames are 84 x 84" in result.stderr and "--resize 64" in result.stderr
    assert not out.exists()


def test_84px_shards_resize_with_an_area_filter_and_episodes_cross_shards(tmp_path: Path) -> None:
    sources = known_episodes(size=84)
    # one bright pixel in the corner of a frame of value 1: the area filter averages the 1.3125 x 1.3125 source
    # pixels under an output pixel (weights 1, 0.3125, 0.3125, 0.3125**2 here), so the corner becomes
    # (255 + 0.72) / 1.72 = 148.4 -> 148 (nearest would give 255, bilinear 255 too)
    sources[0]["image"] = sources[0]["image"].copy()
    sources[0]["image"][0, 83, 83] = 255
    # two shards of two episodes; 3 rows of episode 1 move into the second shard, so it crosses the boundary
    folder = write_shards(tmp_path / "walker_walk/medium/84px", [sources[:2], sources[2:]], cut=3)
    with h5py.File(folder / "shard_2_reward_0.hdf5", "r") as f:
        assert list(f["step_type"][:4]) == [1, 1, 2, 0]  # the shard starts inside an episode
    out = tmp_path / "ww.h5"
    result = CliRunner().invoke(main, ["dataset", "import", "vd4rl", str(folder), "--task", "walker_walk",
                                       "--out", str(out), "--resize", "64"])  # fmt: skip
    assert result.exit_code == 0, result.output
    expected = [dict(ep, image=np.broadcast_to(ep["image"][:, :64, :64], (len(ep["image"]), 64, 64, 3))) for ep in
                sources]  # fmt: skip
    expected[0]["image"] = expected[0]["image"].copy()
    expected[0]["image"][0, 63, 63] = 148
    assert_matches_source(out, expected)
    with open_dataset(out) as data:
        collector = data.metadata["collector"]
        assert collector["source_format"] == "vd4rl-hdf5-shards" and collector["source_image_size"] == 84
        assert collector["resize"] == {"from": 84, "to": 64, "filter": "cv2.INTER_AREA"}
        assert data.quality == "medium"


def test_shards_with_float_step_types_and_64px_frames_need_no_resize(tmp_path: Path) -> None:
    """npz_to_hdf5.py writes step_type as float64 (np.ones); 64px shards come from gather_offline_data --pixel_hw 64."""
    folder = write_shards(tmp_path / "64px_shards", [known_episodes()])
    with h5py.File(folder / "shard_1_reward_0.hdf5", "r+") as f:
        step_type = f["step_type"][:].astype(np.float64)
        del f["step_type"]
        f.create_dataset("step_type", data=step_type, compression="gzip")
    summary = import_vd4rl(folder, tmp_path / "ww.h5", task="walker_walk", quality="expert")
    assert_matches_source(summary.path, known_episodes())


def _npz_case(tmp_path: Path, change: str) -> Path:
    episodes = known_episodes()
    if change == "reset reward":
        episodes[1]["reward"] = episodes[1]["reward"].copy()
        episodes[1]["reward"][0] = 1.0
    elif change == "no is_last":
        del episodes[0]["is_last"]
    elif change == "two episodes in a file":
        episodes[0]["is_first"] = episodes[0]["is_first"].copy()
        episodes[0]["is_first"][3] = True
    elif change == "early terminal":
        episodes[2]["is_terminal"] = episodes[2]["is_terminal"].copy()
        episodes[2]["is_terminal"][2] = True
    elif change == "action out of range":
        episodes[0]["action"] = episodes[0]["action"] * 3
    return write_npz_episodes(tmp_path / "walker_walk/medium/64px", episodes)


def _shard_case(tmp_path: Path, change: str) -> Path:
    folder = write_shards(tmp_path / "walker_walk/medium/84px", [known_episodes(size=84)])
    with h5py.File(folder / "shard_1_reward_0.hdf5", "r+") as f:
        step_type = f["step_type"][:]
        if change == "end without start":
            step_type[0] = 1
        elif change == "start inside an episode":
            step_type[3] = 0
        elif change == "last episode never ends":
            step_type[-1] = 1
        del f["step_type"]
        f.create_dataset("step_type", data=step_type)
    return folder


@pytest.mark.parametrize(
    ("make", "args", "message"),
    [
        (lambda p: _npz_case(p, "reset reward"), [], "first entry of an episode has a non-zero action or reward"),
        (lambda p: _npz_case(p, "no is_last"), [], "not a V-D4RL episode: no is_last"),
        (lambda p: _npz_case(p, "two episodes in a file"), [], "is_first must mark only entry 0"),
        (lambda p: _npz_case(p, "early terminal"), [], "is_terminal is set before the final entry"),
        (lambda p: _npz_case(p, "action out of range"), [], "outside DMC's [-1, 1] box"),
        (
            lambda p: _shard_case(p, "end without start"),
            ["--resize", "64"],
            "an episode ends (step_type 2) that never began",
        ),
        (lambda p: _shard_case(p, "start inside an episode"), ["--resize", "64"], "an episode starts (step_type 0)"),
        (lambda p: _shard_case(p, "last episode never ends"), ["--resize", "64"], "the last episode never ends"),
        (lambda p: _npz_case(p, ""), ["--task", "mw_window_close"], "actions have 6 dimensions but mw_window_close"),
        (lambda p: _npz_case(p, ""), ["--task", "walker_wlak"], "unknown task 'walker_wlak'"),
        (lambda p: _npz_case(p, ""), ["--resize", "84"], "--resize takes 64"),
        (lambda p: _npz_case(p, "").parent, [], "it has 64px: point at one of them"),
        (lambda p: write_npz_episodes(p / "mine", known_episodes()), [], "names no V-D4RL quality; say which"),
        (lambda p: p / "missing", [], "not a folder"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path: Path, make, args: list[str], message: str) -> None:
    folder = make(tmp_path)
    out = tmp_path / "out.h5"
    task = [] if "--task" in args else ["--task", "walker_walk"]
    result = CliRunner().invoke(main, ["dataset", "import", "vd4rl", str(folder), *task, *args, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert len(result.stderr.splitlines()) == 1 and message in result.stderr, result.stderr
    assert "Traceback" not in result.output and not out.exists()


def test_an_interrupted_import_resumes_where_it_stopped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sources = known_episodes()
    folder = write_npz_episodes(tmp_path / "walker_walk/medium_replay/64px", sources)
    out = tmp_path / "ww.h5"
    real_add = DatasetWriter.add_episode
    calls = []

    def add_then_die(self, *args, **kwargs):  # the process is interrupted while writing the third episode
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        real_add(self, *args, **kwargs)

    monkeypatch.setattr(DatasetWriter, "add_episode", add_then_die)
    with pytest.raises(KeyboardInterrupt):
        import_vd4rl(folder, out, task="walker_walk")
    monkeypatch.setattr(DatasetWriter, "add_episode", real_add)
    with open_dataset(out) as data:
        assert data.num_episodes == 2 and not data.complete
    with pytest.raises(CoworldError, match="already exists; pass --resume"):
        import_vd4rl(folder, out, task="walker_walk")
    other = write_npz_episodes(tmp_path / "other/medium_replay/64px", sources[:3])
    with pytest.raises(CoworldError, match="imported from other files"):
        import_vd4rl(other, out, task="walker_walk", resume=True)
    summary = import_vd4rl(folder, out, task="walker_walk", resume=True)
    assert summary.skipped == 2 and summary.episodes == 4
    assert_matches_source(out, sources)


def test_scan_reads_frame_headers_only(tmp_path: Path) -> None:
    folder = write_npz_episodes(tmp_path / "64px", known_episodes())
    source = scan_vd4rl(folder)
    assert (source.layout, source.image_size, source.action_size) == ("npz-episodes", 64, 6)
    assert [ep.length for ep in source.episodes] == LENGTHS and [ep.terminated for ep in source.episodes] == TERMINATED


@pytest.fixture(scope="module")
def imported_walker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three 60-step V-D4RL walker_walk episodes of textured frames, imported through the real CLI."""
    tmp = tmp_path_factory.mktemp("imported")
    episodes = [source_episode(e, 60, False) for e in range(3)]
    rng = np.random.default_rng(0)
    for ep in episodes:  # textured frames, so the encoder sees something
        ep["image"] = rng.integers(0, 256, ep["image"].shape, dtype=np.uint8)
    folder = write_npz_episodes(tmp / "walker_walk/medium_replay/64px", episodes)
    dataset = tmp / "walker_walk-medium_replay.h5"
    done = subprocess.run([*COWORLD, "dataset", "import", "vd4rl", str(folder), "--task", "walker_walk",
                           "--out", str(dataset)], capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return dataset


@pytest.mark.parametrize(
    ("algo", "schedule"),
    [
        ("dreamerv2", ["--set", "offline.updates=3", "--set", "offline.checkpoint_every=3"]),
        ("drq-bc", ["--set", "drqbc.updates=3", "--set", "drqbc.eval_every=3", "--set", "drqbc.checkpoint_every=3"]),
        pytest.param(
            "curl-cql",
            ["--set", "curl.updates=3", "--set", "curl.eval_every=3", "--set", "curl.checkpoint_every=3"],
            marks=pytest.mark.slow,
        ),
    ],
)
def test_imported_dataset_trains(imported_walker: Path, tmp_path: Path, algo: str, schedule: list[str]) -> None:
    """`coworld train` takes the converted file like one of ours (tiny preset, 3 updates, one evaluation episode)."""
    run = tmp_path / algo
    proc = subprocess.run([*COWORLD, "train", "--algo", algo, "--target", "walker_walk", "--dataset",
                           str(imported_walker), "--preset", "tiny", "--device", "cpu", "--threads", "1",
                           "--no-progress", "--set", "train.eval_episodes=1", "--set", "curl.eval_episodes=1",
                           "--set", "drqbc.eval_episodes=1",
                           *schedule, "--logdir", str(run)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"done: {run}" in proc.stdout
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["updates"] == 3 and state["kind"] == {"dreamerv2": "dreamerv2-offline"}.get(algo, algo)
    evaluations = [record for record in read_metrics(run) if "eval/return" in record]
    assert evaluations and evaluations[-1]["step"] == 3  # evaluated in walker_walk after its last update
