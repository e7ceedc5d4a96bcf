"""SequenceSampler: step convention, contiguous windows, episode boundaries, RAM == stream, seeding, workers."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from coworld.data import open_dataset
from coworld.data.sampler import SequenceSampler
from coworld.errors import ConfigError, DatasetError

B, L = 16, 10


def _window_start(batch: dict[str, np.ndarray], b: int, oracle: dict[str, np.ndarray]) -> int:
    """Where window ``b`` starts in step space, read from the (step, episode) tag of its first frame."""
    frame = batch["image"][b, 0, 0, 0]
    episode = int(frame[1]) + 256 * int(frame[2])
    first = np.flatnonzero(oracle["is_first"])[episode]
    return int(first + frame[0])


def test_batches_have_the_contract_shapes_and_dtypes(dataset_path: Path) -> None:
    with open_dataset(dataset_path) as data:
        batch = next(data.sampler(B, L, seed=0))
    assert {k: (v.shape, v.dtype) for k, v in batch.items()} == {
        "image": ((B, L, 64, 64, 3), np.uint8),
        "action": ((B, L, 3), np.float32),
        "reward": ((B, L), np.float32),
        "is_first": ((B, L), bool),
        "is_last": ((B, L), bool),
        "is_terminal": ((B, L), bool),
    }


@pytest.mark.parametrize("mode", ["ram", "stream"])
def test_windows_are_contiguous_slices_of_the_step_space(
    dataset_path: Path, episodes: list[dict[str, Any]], helpers: ModuleType, mode: str
) -> None:
    oracle = helpers.step_space(episodes)
    lengths = np.array([len(ep["rewards"]) + 1 for ep in episodes])  # steps per episode
    with open_dataset(dataset_path) as data:
        sampler = data.sampler(B, L, seed=1, mode=mode)
        for _ in range(10):
            batch = next(sampler)
            for b in range(B):
                k = _window_start(batch, b, oracle)
                assert k + L <= len(oracle["reward"])  # never past the end of the data
                for key, value in batch.items():
                    first = 1 if key == "is_first" else 0  # every window starts as an episode start
                    np.testing.assert_array_equal(value[b, first:], oracle[key][k + first : k + L], err_msg=key)
                assert batch["is_first"][b, 0]
                # a window crosses into another episode only when it started in an episode shorter than L
                if batch["is_first"][b, 1:].any():
                    episode = int(np.searchsorted(np.cumsum(lengths), k, side="right"))
                    assert lengths[episode] < L or k + L == len(oracle["reward"])


def test_windows_stay_inside_long_episodes_and_cover_every_start(
    dataset_path: Path, episodes: list[dict[str, Any]], helpers: ModuleType
) -> None:
    oracle = helpers.step_space(episodes)
    firsts = np.flatnonzero(oracle["is_first"])
    steps = [len(ep["rewards"]) + 1 for ep in episodes]
    allowed = set()
    for first, n in zip(firsts, steps, strict=True):
        allowed |= set(range(first, first + n - L + 1)) if n >= L else {first}
    with open_dataset(dataset_path) as data:
        sampler = data.sampler(B, L, seed=2, mode="ram")
        seen = {_window_start(batch, b, oracle) for batch in (next(sampler) for _ in range(80)) for b in range(B)}
    assert seen == allowed  # 1280 draws over 65 starts: each allowed start appears, nothing else does


def test_the_last_short_episode_is_reached_without_running_past_the_end(tmp_path: Path, helpers: ModuleType) -> None:
    episodes = helpers.make_episodes([20, 4])  # the last episode has 5 steps < L
    path = helpers.write_dataset(tmp_path / "tail.h5", episodes)
    oracle = helpers.step_space(episodes)
    with open_dataset(path) as data:
        batch = next(data.sampler(64, L, seed=0, mode="stream"))
    starts = {_window_start(batch, b, oracle) for b in range(64)}
    total = len(oracle["reward"])
    assert max(starts) == total - L  # the short episode's window is moved back to end with the data
    assert batch["is_last"][:, -1].any()


def test_ram_and_stream_give_identical_batches(dataset_path: Path) -> None:
    with open_dataset(dataset_path, cache_mb=1) as data:
        ram, stream = data.sampler(B, L, seed=7, mode="ram"), data.sampler(B, L, seed=7, mode="stream")
        for _ in range(5):
            a, b = next(ram), next(stream)
            for key in a:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_the_seed_decides_the_windows(dataset_path: Path) -> None:
    with open_dataset(dataset_path) as data:
        first = [next(data.sampler(B, L, seed=3))["image"] for _ in range(2)]
        other = next(data.sampler(B, L, seed=4))["image"]
    np.testing.assert_array_equal(first[0], first[1])
    assert not np.array_equal(first[0], other)


@pytest.mark.parametrize("mode", ["ram", "stream"])
def test_skipping_batches_continues_the_stream_where_drawing_them_would(
    dataset_path: Path, mode: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``skip(n)`` leaves the sampler where ``n`` draws would, without reading a frame (CoWorld's resumed source
    phase skips its target phase's batches this way)."""
    with open_dataset(dataset_path) as data:
        drawn = data.sampler(B, L, seed=3, mode=mode)
        expected = [next(drawn) for _ in range(5)][3:]
        skipped = data.sampler(B, L, seed=3, mode=mode)
        with monkeypatch.context() as patch:
            patch.setattr(SequenceSampler, "gather", lambda *_: pytest.fail("skip read frames"))
            skipped.skip(3)
        for want in expected:
            got = next(skipped)
            assert all(np.array_equal(got[key], want[key]) for key in want)


def test_auto_mode_streams_when_the_frames_do_not_fit(dataset_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import coworld.data.reader as reader

    with open_dataset(dataset_path) as data, monkeypatch.context() as patch:
        patch.setattr(reader, "RAM_FRACTION", 1e-9)
        assert data.sampler(B, L).mode == "stream"
    with open_dataset(dataset_path) as data:
        assert data.sampler(B, L).mode == "ram"
        # Frames already in RAM stay there: a later sampler on the same dataset does not fall back to disk.
        monkeypatch.setattr(reader, "RAM_FRACTION", 1e-9)
        assert data.sampler(B, L).mode == "ram"


def test_bad_sampler_arguments(dataset_path: Path) -> None:
    with open_dataset(dataset_path) as data:
        with pytest.raises(ConfigError, match="unknown sampler mode 'disk'"):
            data.sampler(B, L, mode="disk")
        with pytest.raises(ConfigError, match="must be >= 1"):
            data.sampler(0, L)
        with pytest.raises(DatasetError, match=r"seq_len 500 is longer than the whole dataset \(109 steps\)"):
            data.sampler(B, 500)


def test_dataloader_workers_each_open_the_file_and_draw_their_own_windows(
    dataset_path: Path, episodes: list[dict[str, Any]], helpers: ModuleType
) -> None:
    pytest.importorskip("torch")
    from coworld.data.loader import make_loader

    oracle = helpers.step_space(episodes)
    with open_dataset(dataset_path) as data:
        data.episode(0)  # the parent holds an open handle: workers must not reuse it
        loader = make_loader(data, B, L, seed=5, mode="stream", num_workers=2)
        batches = [{k: v.numpy() for k, v in batch.items()} for batch, _ in zip(loader, range(4), strict=False)]
        del loader
    for batch in batches:
        for b in range(B):
            k = _window_start(batch, b, oracle)
            np.testing.assert_array_equal(batch["image"][b], oracle["image"][k : k + L])
    # batches 0 and 1 come from different workers (round robin): different seeds, different windows
    assert not np.array_equal(batches[0]["image"], batches[1]["image"])


def test_dataset_windows_start_from_a_fresh_latent_even_mid_episode(dataset_path: Path) -> None:
    with open_dataset(dataset_path) as data:
        sampler = SequenceSampler(data, batch_size=64, seq_len=4, seed=0)
        batch = next(sampler)
        starts = sampler.sample_starts(np.random.default_rng(0))
        assert not sampler.steps.is_first[starts].all()  # the data do hold windows that start mid-episode
    assert batch["is_first"][:, 0].all()
