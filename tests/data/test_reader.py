"""open_dataset: bad files fail with one clear line and stay untouched; summaries; pickling."""

from __future__ import annotations

import pickle
import shutil
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import h5py
import numpy as np
import pytest

from coworld.data import DatasetWriter, normalized_score, open_dataset
from coworld.errors import DatasetError


def _not_hdf5(path: Path) -> None:
    path.write_text("observations,actions\n1,2\n")


def _truncated(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _missing_key(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        del f["actions"]


def _wrong_shape(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        actions = f["actions"][:]
        del f["actions"]
        f["actions"] = np.concatenate([actions, actions], axis=1)


def _nan_rewards(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        f["rewards"][3] = np.nan


def _bad_boundaries(path: Path) -> None:
    with h5py.File(path, "r+") as f:
        f["timeouts"][0] = True


def _not_coworld(path: Path) -> None:
    with h5py.File(path, "w") as f:
        f["observations"] = np.zeros((2, 64, 64, 3), np.uint8)


BAD_FILES: dict[str, tuple[Callable[[Path], None], str]] = {
    "not hdf5": (_not_hdf5, "not a readable HDF5 file"),
    "truncated": (_truncated, "truncated"),
    "missing key": (_missing_key, "missing dataset 'actions'"),
    "wrong shape": (_wrong_shape, r"actions has shape \(\d+, 6\), expected \(N, 3\)"),
    "nan rewards": (_nan_rewards, "1 rewards are NaN or inf"),
    "bad boundaries": (_bad_boundaries, "terminals/timeouts do not mark exactly the last row"),
    "not coworld": (_not_coworld, "not a coworld-dataset file"),
}


@pytest.fixture(params=sorted(BAD_FILES))
def bad_file(request: pytest.FixtureRequest, tmp_path: Path, dataset_path: Path) -> tuple[Path, str]:
    """A damaged copy of the small dataset, and the words its error must contain."""
    damage, message = BAD_FILES[request.param]
    path = tmp_path / "bad.h5"
    shutil.copy(dataset_path, path)
    damage(path)
    return path, message


def test_bad_files_fail_with_one_clear_line_and_stay_untouched(bad_file: tuple[Path, str], helpers: ModuleType) -> None:
    path, message = bad_file
    before = helpers.file_state(path)
    with pytest.raises(DatasetError, match=message) as err:
        open_dataset(path)
    text = str(err.value)
    assert "\n" not in text and text.startswith(str(path))
    assert helpers.file_state(path) == before


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such file"):
        open_dataset(tmp_path / "nope.h5")
    with pytest.raises(DatasetError, match="is a directory"):
        open_dataset(tmp_path)


def test_a_dataset_without_episodes_is_refused(tmp_path: Path, helpers: ModuleType) -> None:
    with DatasetWriter(tmp_path / "empty.h5", quality="random", **helpers.WRITER_ARGS):
        pass
    with pytest.raises(DatasetError, match="holds no episodes yet"):
        open_dataset(tmp_path / "empty.h5")


def test_episode_index_counts_from_both_ends(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    with open_dataset(dataset_path) as data:
        np.testing.assert_array_equal(data.episode(-1)["image"], episodes[-1]["observations"])
        with pytest.raises(IndexError, match="episode 7 out of range"):
            data.episode(7)


def test_summary_reports_counts_returns_and_scores(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    returns = np.array([ep["rewards"].astype(np.float64).sum() for ep in episodes])
    with open_dataset(dataset_path) as data:
        summary = data.summary()
    assert summary["episodes"] == 7 and summary["steps"] == sum(len(ep["rewards"]) for ep in episodes)
    assert summary["terminated_episodes"] == 3
    assert summary["return"]["mean"] == pytest.approx(returns.mean())
    assert summary["return"]["max"] == pytest.approx(returns.max())
    # reference: random 0, reference 10 -> score = 10 * return
    assert summary["normalized_score"]["mean"] == pytest.approx(10 * returns.mean())
    assert summary["frame_bytes_raw"] == (summary["steps"] + 7) * 64 * 64 * 3
    assert summary["compression_ratio"] == pytest.approx(summary["frame_bytes_raw"] / summary["frame_bytes_stored"])
    assert summary["compression_ratio"] > 2  # frames are mostly flat: gzip must shrink them


def test_normalized_score_needs_both_references() -> None:
    assert normalized_score(55.0, {"random_return": 10.0, "reference_return": 100.0}) == pytest.approx(50.0)
    assert normalized_score(55.0, {"reference_return": 100.0}) is None


def test_a_pickled_dataset_reopens_its_file(dataset_path: Path, episodes: list[dict[str, Any]]) -> None:
    with open_dataset(dataset_path) as data:
        data.episode(0)  # opens the handle
        copy = pickle.loads(pickle.dumps(data))
    np.testing.assert_array_equal(copy.episode(2)["image"], episodes[2]["observations"])
    copy.close()


def test_rows_past_the_committed_ones_are_ignored_reported_and_dropped_on_resume(
    dataset_path: Path, episodes: list[dict[str, Any]], helpers: ModuleType
) -> None:
    from coworld.data import verify_dataset

    n = sum(len(ep["rewards"]) for ep in episodes)
    with h5py.File(dataset_path, "r+") as f:  # what a writer killed inside add_episode can leave
        for name in ("observations", "actions", "rewards", "terminals", "timeouts", "episode_ids", "is_first"):
            f[name].resize(n + 5, axis=0)
        f["rewards"][n:] = 99.0
    with open_dataset(dataset_path) as data:
        assert data.num_steps == n and data.to_d4rl()["rewards"].max() < 99.0
    assert any("5 rows past the last committed episode" in p for p in verify_dataset(dataset_path))
    with DatasetWriter(dataset_path, quality="random", resume=True, **helpers.WRITER_ARGS) as writer:
        writer.close(complete=True)
    with h5py.File(dataset_path, "r") as f:
        assert f["rewards"].shape == (n,) and f["observations"].shape[0] == n
    assert verify_dataset(dataset_path) == []
