"""Datasets in the wrong state, through the CLI: an unfinished dataset is not exported unless asked, a refused
resumed import leaves its file byte for byte, and the messages name what the user gave."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest

import coworld.data
from coworld.data import DatasetWriter


@pytest.fixture
def unfinished(tmp_path: Path) -> Path:
    """What a collect killed with kill -9 leaves: committed episodes, not marked complete."""
    path = tmp_path / "partial.h5"
    with DatasetWriter(path, task="toy_reach_shifted", env_config={}, quality="random", collector={},
                       action_size=2) as writer:  # fmt: skip
        writer.add_episode(np.zeros((4, 64, 64, 3), np.uint8), np.zeros((3, 2)), np.zeros(3), terminated=False)
    return path


def test_npz_export_of_an_unfinished_dataset_is_refused_unless_asked(unfinished, tmp_path, processes):
    out = tmp_path / "npz"
    done = processes.run_cli("dataset", "export", str(unfinished), "--to", "npz-episodes", "--out", str(out))
    line = processes.last_word(done.stderr, "error: ")
    assert done.returncode == 2 and "is not complete" in line and "--incomplete" in line and not out.exists()
    done = processes.run_cli("dataset", "export", str(unfinished), "--to", "npz-episodes", "--out", str(out),
                             "--incomplete")  # fmt: skip
    assert done.returncode == 0 and "warning: " in done.stderr and len(list(out.glob("*.npz"))) == 1


def test_minari_export_of_an_unfinished_dataset_is_refused(unfinished, tmp_path, processes, monkeypatch):
    pytest.importorskip("minari")
    root = tmp_path / "minari"
    done = processes.run_cli("dataset", "export", str(unfinished), "--to", "minari",
                             env={**os.environ, "MINARI_DATASETS_PATH": str(root)})  # fmt: skip
    assert done.returncode == 2 and "is not complete" in processes.last_word(done.stderr, "error: ")
    assert not any(root.rglob("*.hdf5"))


def test_an_empty_minari_name_is_refused(unfinished, processes):
    done = processes.run_cli("dataset", "export", str(unfinished), "--to", "minari", "--name", "", "--incomplete")
    assert done.returncode == 2 and "--name is empty" in processes.last_word(done.stderr, "error: ")


def test_load_warns_of_an_unfinished_dataset(unfinished):
    with pytest.warns(UserWarning, match="is not complete"):
        coworld.data.load(unfinished)
    with pytest.warns(UserWarning, match="holds the 1 episode committed so far"):
        assert len(list(coworld.data.episodes(unfinished))) == 1


def test_a_missing_dataset_name_is_quoted_as_given(processes):
    done = processes.run_cli("dataset", "export", "walker_nowhere-medium-replay", "--to", "npz-episodes", "--out",
                             "/tmp/never-made-by-this-test")  # fmt: skip
    line = processes.last_word(done.stderr, "error: ")
    assert "'walker_nowhere-medium-replay'" in line and "PosixPath" not in line


def npz_episode(path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 6
    action = rng.uniform(-1, 1, (n, 6)).astype(np.float32)
    action[0] = 0
    reward = np.r_[0.0, rng.uniform(0, 1, n - 1)].astype(np.float32)
    np.savez_compressed(path, image=rng.integers(0, 255, (n, 64, 64, 3), np.uint8), action=action, reward=reward,
                        discount=np.ones(n, np.float32), is_first=np.eye(n, dtype=bool)[0],
                        is_last=np.eye(n, dtype=bool)[-1], is_terminal=np.zeros(n, bool))  # fmt: skip


def test_a_refused_resume_leaves_the_file_byte_for_byte(tmp_path, processes):
    first, second = tmp_path / "first" / "64px", tmp_path / "second" / "64px"
    for folder, seed in ((first, 0), (second, 5)):
        folder.mkdir(parents=True)
        npz_episode(folder / f"ep{seed}.npz", seed)
    out = tmp_path / "walker.h5"
    common = ["--task", "walker_walk", "--quality", "random", "--out", str(out)]
    assert processes.run_cli("dataset", "import", "vd4rl", str(first), *common).returncode == 0
    before = hashlib.sha256(out.read_bytes()).hexdigest()
    done = processes.run_cli("dataset", "import", "vd4rl", str(second), *common, "--resume")
    assert done.returncode == 2 and "imported from other files" in processes.last_word(done.stderr, "error: ")
    assert hashlib.sha256(out.read_bytes()).hexdigest() == before


def test_a_text_file_named_npz_is_not_called_a_pickle(tmp_path, processes):
    folder = tmp_path / "64px"
    folder.mkdir()
    (folder / "ep0.npz").write_text("just text")
    done = processes.run_cli("dataset", "import", "vd4rl", str(folder), "--task", "walker_walk", "--quality",
                             "random", "--out", str(tmp_path / "x.h5"))  # fmt: skip
    line = processes.last_word(done.stderr, "error: ")
    assert done.returncode == 2 and "not an npz archive" in line and "pickle" not in line
    assert not (tmp_path / "x.h5").exists()
