"""Windows of episodes in the step convention, from an open dataset or a list of episodes (a replay's, fresh
rollouts): what the open-loop strips and pictures are drawn from."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from coworld.data.schema import STEP_KEYS

__all__ = ["EpisodeSource", "EpisodeStore", "count_episodes", "episode_windows", "evenly_spaced", "get_episodes"]


@runtime_checkable
class EpisodeStore(Protocol):
    """What an open :class:`~coworld.data.reader.Dataset` offers: its episode count and one episode at a time."""

    @property
    def num_episodes(self) -> int: ...

    def episode(self, i: int) -> dict[str, np.ndarray]: ...


EpisodeSource = EpisodeStore | Sequence[Mapping[str, np.ndarray]]
"""Episodes in the step convention: an open dataset, or a list of episodes (a replay's, fresh rollouts)."""


def count_episodes(source: EpisodeSource) -> int:
    return source.num_episodes if isinstance(source, EpisodeStore) else len(source)


def get_episodes(source: EpisodeSource, indices: Sequence[int]) -> list[Mapping[str, np.ndarray]]:
    """Episodes ``indices`` of ``source`` (an index repeated is read once)."""
    read = {i: source.episode(i) if isinstance(source, EpisodeStore) else source[i] for i in set(indices)}
    return [read[i] for i in indices]


def evenly_spaced(total: int, n: int) -> list[int]:
    """``min(n, total)`` distinct indices spread evenly over ``range(total)``, first and last included."""
    if total <= 0 or n <= 0:
        return []
    return sorted({int(round(i)) for i in np.linspace(0, total - 1, min(n, total))})


def episode_windows(
    episodes: Sequence[Mapping[str, np.ndarray]], length: int, starts: Sequence[int] | None = None
) -> dict[str, np.ndarray]:
    """One window of ``length`` steps from each episode (step convention), stacked into a batch ``(B, L, ...)``.

    ``starts`` (default 0) is clipped so each window fits inside its episode; ``length`` is cut to the shortest
    episode. Each window after the first step has ``is_first`` False, so a window that starts mid-episode is
    observed from a zero state (as training windows are).
    """
    length = min([length, *(len(ep["reward"]) for ep in episodes)])
    starts = [0] * len(episodes) if starts is None else list(starts)
    windows = []
    for episode, start in zip(episodes, starts, strict=True):
        start = int(np.clip(start, 0, len(episode["reward"]) - length))
        windows.append({key: np.asarray(episode[key][start : start + length]) for key in STEP_KEYS})
    return {key: np.stack([w[key] for w in windows]) for key in STEP_KEYS}
