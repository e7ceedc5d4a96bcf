"""What is in a dataset: a grid of frames from evenly spaced episodes, whole episodes as a video, and a histogram
of episode returns. Every episode shown carries its index and return."""

from __future__ import annotations

from typing import Any

import numpy as np

from coworld.data.windows import evenly_spaced
from coworld.pictures import labelled_grid, put_text, stack_frames, upscale

__all__ = ["dataset_grid", "dataset_video", "returns_histogram"]


def dataset_grid(dataset: Any, *, episodes: int = 8, frames: int = 8, scale: int = 1) -> np.ndarray:
    """One row per episode (evenly spaced through the file), ``frames`` evenly spaced frames of it per row.

    Each row is labelled with the episode's index and return, each frame with its step. Returns uint8 (H, W, 3).
    """
    picked = evenly_spaced(dataset.num_episodes, episodes)
    cells, labels = [], []
    for i in picked:
        length = int(dataset.lengths[i]) + 1  # steps: rows plus the final frame
        steps = evenly_spaced(length, frames)
        images = dataset.episode(i)["image"]
        row = []
        for t in steps:
            cell = upscale(images[t], scale).copy()
            put_text(cell, str(t), 1, 1, colour=(255, 255, 255), box=True)
            row.append(cell)
        cells.append(row)
        labels.append(f"ep {i}: return {dataset.returns[i]:.1f}")
    title = (
        f"{dataset.task} ({dataset.quality}): {dataset.num_episodes} episodes, return"
        f" {dataset.returns.mean():.1f} +- {dataset.returns.std():.1f}; numbers = step"
    )
    return labelled_grid(cells, row_labels=labels, title=title)


def dataset_video(dataset: Any, *, episodes: int = 3, scale: int = 4) -> np.ndarray:
    """Whole episodes (evenly spaced through the file) one after another, each frame titled with the episode's
    index, return and step. Returns uint8 (T, H, W, 3), T = the chosen episodes' steps in all."""
    out = []
    for i in evenly_spaced(dataset.num_episodes, episodes):
        images = dataset.episode(i)["image"]
        for t, image in enumerate(images):
            title = f"ep {i}  return {dataset.returns[i]:.1f}  step {t}/{len(images) - 1}"
            out.append(labelled_grid([[image]], title=title, scale=scale))
    return stack_frames(out)


def returns_histogram(dataset: Any, bins: int = 30) -> Any:
    """Matplotlib figure: the histogram of episode returns, its mean marked."""
    from matplotlib.figure import Figure

    returns = np.asarray(dataset.returns, np.float64)
    fig = Figure(figsize=(5.0, 3.2))
    ax = fig.subplots()
    ax.hist(returns, bins=min(bins, max(1, len(returns))), color="tab:blue", alpha=0.8)
    ax.axvline(returns.mean(), color="black", linestyle="--", linewidth=1, label=f"mean {returns.mean():.1f}")
    ax.set_xlabel("episode return")
    ax.set_ylabel("episodes")
    ax.set_title(f"{dataset.task} ({dataset.quality}): {len(returns)} episodes", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
