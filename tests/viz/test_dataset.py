"""Dataset previews: the frames shown are the dataset's own, every episode's return is on the histogram."""

from __future__ import annotations

import numpy as np

from coworld.data import open_dataset
from coworld.data.windows import evenly_spaced
from coworld.viz.dataset import dataset_grid, dataset_video, returns_histogram

from .conftest import contains


def test_evenly_spaced_known_values():
    assert evenly_spaced(10, 4) == [0, 3, 6, 9]
    assert evenly_spaced(3, 8) == [0, 1, 2]
    assert evenly_spaced(5, 1) == [0] and evenly_spaced(0, 3) == []


def test_grid_shows_frames_of_evenly_spaced_episodes(target_dataset):
    with open_dataset(target_dataset) as data:
        grid = dataset_grid(data, episodes=3, frames=4)
        for i in (0, 2, 3):  # evenly spaced over 4 episodes
            images = data.episode(i)["image"]
            for t in evenly_spaced(len(images), 4):
                assert contains(grid, images[t][20:])  # the frame below its step label, pixel for pixel
        assert not contains(grid, data.episode(1)["image"][-1][20:])  # episode 1 is not shown


def test_video_holds_whole_episodes_one_after_another(target_dataset):
    with open_dataset(target_dataset) as data:
        video = dataset_video(data, episodes=2, scale=2)
        picked = [0, 3]
        assert len(video) == sum(int(data.lengths[i]) + 1 for i in picked)
        last = data.episode(3)["image"][-1]
        assert contains(video[-1], last.repeat(2, 0).repeat(2, 1))


def test_histogram_counts_every_episode(target_dataset):
    with open_dataset(target_dataset) as data:
        figure = returns_histogram(data)
        ax = figure.axes[0]
        assert sum(patch.get_height() for patch in ax.patches) == data.num_episodes
        lo = min(patch.get_x() for patch in ax.patches)
        hi = max(patch.get_x() + patch.get_width() for patch in ax.patches)
        assert np.isclose(lo, data.returns.min()) and np.isclose(hi, data.returns.max())
