"""`coworld dataset export`: Minari (loaded back with Minari itself) and dreamer-style npz episodes (round trip)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from gymnasium.envs.registration import EnvSpec

from coworld.cli import main
from coworld.data import DatasetWriter, export_minari, export_npz_episodes, import_vd4rl, open_dataset
from coworld.data.collect import dataset_fields
from coworld.errors import CoworldError

COWORLD = [sys.executable, "-c", "from coworld.cli import run; run()"]
README = Path(__file__).parents[2] / "datasets" / "README.md"
LENGTHS, TERMINATED = [6, 3, 9, 4, 5], [False, True, False, True, False]


def make_episodes(seed: int = 0) -> list[dict[str, Any]]:
    """walker_walk-shaped episodes (6-d actions) with tagged frames, random actions and rewards, and infos."""
    rng = np.random.default_rng(seed)
    episodes = []
    for e, (t, terminated) in enumerate(zip(LENGTHS, TERMINATED, strict=True)):
        frames = rng.integers(0, 256, (t + 1, 64, 64, 3), dtype=np.uint8)
        frames[:, 0, 0, 0], frames[:, 0, 0, 1] = np.arange(t + 1), e
        episodes.append(
            {
                "observations": frames,
                "actions": rng.uniform(-1, 1, (t, 6)).astype(np.float32),
                "rewards": rng.normal(size=t).astype(np.float32),
                "terminated": terminated,
                "infos": {"success": rng.random(t) < 0.5, "behavior_log_prob": rng.normal(size=t).astype(np.float32)},
            }
        )
    return episodes


def write(path: Path, episodes: list[dict[str, Any]], quality: str = "medium-replay") -> Path:
    fields = dataset_fields("walker_walk")
    collector = {"algorithm": "dreamerv2", "preset": "tiny", "seed": 3, "steps": 27}
    with DatasetWriter(path, task="walker_walk", quality=quality, collector=collector, action_size=6, **fields) as w:
        for ep in episodes:
            w.add_episode(ep["observations"], ep["actions"], ep["rewards"], ep["terminated"], ep["infos"])
        w.close(complete=True)
    return path


@pytest.fixture
def episodes() -> list[dict[str, Any]]:
    return make_episodes()


@pytest.fixture
def source(tmp_path: Path, episodes: list[dict[str, Any]]) -> Path:
    return write(tmp_path / "walker_walk-medium_replay.h5", episodes)


@pytest.fixture
def minari_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


# -- Minari --------------------------------------------------------------------------------------------------


def test_minari_export_loads_back_in_minari_and_matches_every_episode(
    source: Path, episodes: list[dict[str, Any]], minari_root: Path
) -> None:
    import gymnasium as gym
    import minari

    result = CliRunner().invoke(main, ["dataset", "export", str(source), "--to", "minari", "--author", "Ada"])
    assert result.exit_code == 0, result.output
    name = "coworld/walker_walk/medium-replay-v0"  # the default name: coworld/<task>/<quality>-v0
    assert f"wrote Minari dataset {name} in {minari_root / name}:" in result.stdout  # where it went, too
    data_dir = minari_root / name / "data"
    assert sorted(p.name for p in data_dir.iterdir()) == ["main_data.hdf5", "metadata.json"]
    assert not list((minari_root / "coworld/walker_walk").glob(".*"))  # no temporary folder left

    dataset = minari.load_dataset(name)
    assert name in minari.list_local_datasets()
    assert dataset.total_episodes == len(episodes) and dataset.total_steps == sum(LENGTHS)
    assert dataset.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert dataset.action_space == gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
    for ep, got in zip(episodes, dataset.iterate_episodes(), strict=True):
        t = len(ep["rewards"])
        np.testing.assert_array_equal(got.observations, ep["observations"])  # bit-exact: no JPEG
        np.testing.assert_array_equal(got.actions, ep["actions"])
        np.testing.assert_array_equal(got.rewards, ep["rewards"])
        np.testing.assert_array_equal(got.terminations, (np.arange(t) == t - 1) & ep["terminated"])
        np.testing.assert_array_equal(got.truncations, (np.arange(t) == t - 1) & (not ep["terminated"]))
        for key, values in ep["infos"].items():  # Minari's infos have T + 1 entries, the reset's first
            np.testing.assert_array_equal(got.infos[key], np.concatenate([[0], values]).astype(values.dtype))
    meta = dataset.storage.metadata
    assert meta["jpeg_encoding"] is False and meta["author"] == {"Ada"} and meta["algorithm_name"] == "dreamerv2"
    ours = meta["coworld"]
    assert (ours["task"], ours["quality"]) == ("walker_walk", "medium-replay")
    assert ours["collector"] == {"algorithm": "dreamerv2", "preset": "tiny", "seed": 3, "steps": 27}
    assert ours["env_config"]["action_repeat"] == 2 and ours["source"] == str(source.resolve())
    returns = np.array([ep["rewards"].astype(np.float64).sum() for ep in episodes])
    stats = list(dataset.storage.get_episode_metadata(range(len(episodes))))  # as Minari's DataCollector adds them
    np.testing.assert_allclose([s["rewards_sum"] for s in stats], returns, rtol=1e-5)
    np.testing.assert_allclose([s["rewards_max"] for s in stats], [ep["rewards"].max() for ep in episodes])
    with open_dataset(source) as data:
        np.testing.assert_allclose(100 * minari.get_normalized_score(dataset, returns), data.normalized_scores())
    with h5py.File(data_dir / "main_data.hdf5", "r") as f:
        assert f["episode_2/observations"].dtype == np.uint8 and f["episode_2/observations"].shape == (10, 64, 64, 3)
    # the evaluation env is our registered task, made by Gymnasium from the spec stored in the metadata
    assert EnvSpec.from_json(meta["eval_env_spec"]).id == "coworld/walker_walk-v0"
    for eval_env in (True, False):  # the data's env is the same registered task: Minari's default recovers it too
        env = dataset.recover_environment(eval_env=eval_env)
        assert env.unwrapped.task.name == "walker_walk" and env.reset(seed=0)[0].shape == (64, 64, 3)
        env.close()
    assert EnvSpec.from_json(meta["env_spec"]) == EnvSpec.from_json(meta["eval_env_spec"])


def test_minari_export_refuses_to_overwrite_without_force(source: Path, minari_root: Path, tmp_path: Path) -> None:
    import minari

    name = "coworld/ww/test-v1"
    assert export_minari(source, name) == name
    runner = CliRunner()
    result = runner.invoke(main, ["dataset", "export", str(source), "--to", "minari", "--name", name])
    assert result.exit_code == 2 and len(result.stderr.splitlines()) == 1
    assert "already exists; pass --force" in result.stderr
    fewer = write(tmp_path / "fewer.h5", make_episodes(seed=1)[:2], quality="expert")
    result = runner.invoke(main, ["dataset", "export", str(fewer), "--to", "minari", "--name", name, "--force"])
    assert result.exit_code == 0, result.output
    assert minari.load_dataset(name).total_episodes == 2
    assert not [p for p in (minari_root / "coworld/ww").iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--to", "minari", "--name", "no version"], "bad Minari dataset name 'no version'"),
        (["--to", "minari", "--name", "coworld/-v0"], "bad Minari dataset name 'coworld/-v0'"),
        (["--to", "minari", "--name", "/x-v0"], "bad Minari dataset name '/x-v0'"),
        (["--to", "minari", "--out", "x"], "not --out"),
        (["--to", "npz-episodes"], "--to npz-episodes writes the folder --out FOLDER"),
        (["--to", "parquet"], "Invalid value for '--to'"),
    ],
)
def test_export_bad_options_are_one_line(source: Path, minari_root: Path, args: list[str], message: str) -> None:
    result = CliRunner().invoke(main, ["dataset", "export", str(source), *args])
    assert result.exit_code == 2 and message in result.stderr, result.output
    assert not minari_root.exists() or not list(minari_root.rglob("main_data.hdf5"))


def test_minari_missing_gives_the_install_hint(source: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "minari", None)  # `import minari` raises ImportError
    with pytest.raises(CoworldError, match=re.escape("needs the minari package: pip install 'coworld[minari]'")):
        export_minari(source)


def test_readme_minari_snippet_runs(source: Path, minari_root: Path) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    [snippet] = [block for block in blocks if "minari.load_dataset" in block]
    name = re.search(r'load_dataset\("([^"]+)"\)', snippet).group(1)
    with open_dataset(source) as data:
        assert name == f"coworld/{data.task}/{data.quality}-v0"
    export_minari(source)
    scope: dict[str, Any] = {}
    exec(snippet, scope)
    assert scope["episode"].observations.shape == (LENGTHS[0] + 1, 64, 64, 3)
    assert scope["env"].unwrapped.task.name == "walker_walk"
    scope["env"].close()


# -- npz episodes --------------------------------------------------------------------------------------------


def test_npz_episodes_have_vd4rl_keys_order_and_names(source: Path, episodes: list[dict[str, Any]]) -> None:
    out = source.parent / "npz"
    result = CliRunner().invoke(main, ["dataset", "export", str(source), "--to", "npz-episodes", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"wrote {out}: 5 episodes" in result.stdout
    files = sorted(out.glob("*.npz"))  # sorted() is the order dreamer-style loaders read them in
    assert len(files) == len(episodes) and not list(source.parent.glob(".npz*"))
    for i, (file, ep) in enumerate(zip(files, episodes, strict=True)):
        t = len(ep["rewards"])
        stamp, index, entries = file.stem.split("-")
        assert re.fullmatch(r"\d{8}T\d{6}", stamp) and int(index) == i and int(entries) == t + 1
        with np.load(file, allow_pickle=False) as got:
            assert sorted(got.files) == sorted(
                ["image", "action", "reward", "discount", "is_first", "is_last", "is_terminal"]
            )
            assert got["image"].dtype == np.uint8 and got["action"].dtype == np.float32
            np.testing.assert_array_equal(got["image"], ep["observations"])
            np.testing.assert_array_equal(got["action"], np.concatenate([np.zeros((1, 6)), ep["actions"]]))
            np.testing.assert_array_equal(got["reward"], np.concatenate([[0], ep["rewards"]]).astype(np.float32))
            last = np.arange(t + 1) == t
            np.testing.assert_array_equal(got["is_first"], np.arange(t + 1) == 0)
            np.testing.assert_array_equal(got["is_last"], last)
            np.testing.assert_array_equal(got["is_terminal"], last & ep["terminated"])
            np.testing.assert_array_equal(got["discount"], np.where(last & ep["terminated"], 0, 1))


def test_import_of_the_export_gives_the_dataset_back(source: Path, episodes: list[dict[str, Any]]) -> None:
    folder = export_npz_episodes(source, source.parent / "vd4rl")
    summary = import_vd4rl(folder, source.parent / "back.h5", task="walker_walk", quality="medium-replay")
    with open_dataset(source) as before, open_dataset(summary.path) as after:
        assert after.num_episodes == before.num_episodes and after.num_steps == before.num_steps
        for i in range(before.num_episodes):
            a, b = before.episode(i), after.episode(i)
            for key in ("image", "action", "reward", "is_first", "is_last", "is_terminal"):
                np.testing.assert_array_equal(b[key], a[key], err_msg=f"episode {i} {key}")
        np.testing.assert_array_equal(after.returns, before.returns)


def test_npz_export_refuses_an_existing_folder_unless_forced(source: Path) -> None:
    out = source.parent / "npz"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(CoworldError, match="already exists; pass --force"):
        export_npz_episodes(source, out)
    assert (out / "keep.txt").read_text() == "mine"
    export_npz_episodes(source, out, force=True)
    assert len(list(out.glob("*.npz"))) == 5 and not (out / "keep.txt").exists()


def test_export_as_a_real_process_by_dataset_name(source: Path, tmp_path: Path) -> None:
    """PATH may be a dataset name, resolved under ./datasets like `coworld train` does."""
    (tmp_path / "datasets").mkdir()
    source.rename(tmp_path / "datasets" / source.name)
    out = tmp_path / "npz"
    done = subprocess.run([*COWORLD, "dataset", "export", "walker_walk-medium-replay", "--to", "npz-episodes",
                           "--out", str(out)], capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert len(list(out.glob("*.npz"))) == 5
    missing = subprocess.run([*COWORLD, "dataset", "export", "walker_walk-expert", "--to", "npz-episodes",
                              "--out", str(out)], capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1 and "no dataset named" in missing.stderr
    assert "Traceback" not in missing.stderr
