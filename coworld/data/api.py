"""A D4RL-style Python API: ``load(path_or_name)`` gives the D4RL dict, ``qlearning_dataset(path_or_name)`` the same
with ``next_observations``, ``episodes(path_or_name)`` the episodes.

import coworld.data

data = coworld.data.load("walker_uphill-medium-replay")      # datasets/walker_uphill-medium_replay.h5
data["observations"].shape                                   # (N, 64, 64, 3) uint8
q = coworld.data.qlearning_dataset("walker_uphill-medium-replay")  # the same plus next_observations (N, 64, 64, 3)
for episode in coworld.data.episodes("datasets/walker_uphill-medium_replay.h5"):
    episode.observations.shape                               # (T + 1, 64, 64, 3): o_0 .. o_T
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from coworld.data.collect import default_dataset_path
from coworld.data.reader import Dataset, open_dataset
from coworld.data.schema import QUALITIES
from coworld.errors import DatasetError
from coworld.text import count


@dataclass(frozen=True)
class Episode:
    """One episode with Minari's shapes: T + 1 observations for T actions.

    Attributes:
        index: the episode's number in its dataset (0, 1, ...).
        observations: (T+1, H, W, C) uint8, o_0 .. o_T (o_T is the observation after the last action).
        actions: (T, A) float32, a_t taken at o_t.
        rewards: (T,) float32, r_t earned by a_t.
        terminations: (T,) bool, True at the last step of an episode that ended in a true terminal state.
        truncations: (T,) bool, True at the last step of an episode cut by a time limit.
        infos: per-step extras of the dataset (``success``, ``behavior_log_prob``, ...), each (T, ...).
    """

    index: int
    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    infos: dict[str, np.ndarray]

    @property
    def length(self) -> int:
        """T, the number of actions."""
        return len(self.actions)

    @property
    def terminated(self) -> bool:
        """The episode ended in a true terminal state (else a time limit cut it)."""
        return bool(self.terminations[-1])


def resolve_dataset(path_or_name: str | Path) -> Path:
    """The file a path or a dataset name stands for.

    A name is ``<task>-<quality>`` (``walker_uphill-medium-replay``; underscores in the quality work too) and
    stands for ``datasets/<task>-<quality>.h5`` under the current folder, where ``coworld collect`` writes and
    ``coworld train`` reads by default. Anything else is a path.
    """
    path = Path(path_or_name)
    if path.exists() or path.suffix or len(path.parts) > 1:
        return path
    task, _, quality = str(path_or_name).partition("-")
    quality = quality.replace("_", "-")
    if not task or quality not in QUALITIES:
        raise DatasetError(
            f"'{path_or_name}' is neither a file nor a dataset name; a name is <task>-<quality> "
            f"(quality one of {', '.join(QUALITIES)}), e.g. walker_uphill-medium-replay"
        )
    resolved = default_dataset_path(task, quality)
    if not resolved.exists():
        raise DatasetError(
            f"no dataset named '{path_or_name}': {resolved} does not exist; make it with "
            f"`coworld collect --task {task} --quality {quality} --preset cpu` or pass the file's path"
        )
    return resolved


def load(path_or_name: str | Path) -> dict[str, np.ndarray]:
    """The whole dataset as D4RL's dict (every frame in memory).

    Keys: ``observations`` (N, 64, 64, 3) uint8, ``actions`` (N, A) float32, ``rewards`` (N,) float32,
    ``terminals`` and ``timeouts`` (N,) bool (the last row of each episode has exactly one of them), and
    ``infos/<key>`` (N, ...) for the dataset's per-step extras. ``path_or_name``: see :func:`resolve_dataset`.
    """
    with open_dataset(resolve_dataset(path_or_name)) as data:
        warn_incomplete(data)
        return data.to_d4rl()


def qlearning_dataset(path_or_name: str | Path) -> dict[str, np.ndarray]:
    """The dataset as D4RL's ``qlearning_dataset`` dict: :func:`load`'s keys plus ``next_observations``
    (N, 64, 64, 3) uint8, the observation each row's action led to (at an episode's last row, its final frame, which
    the file keeps, so no transition is dropped where D4RL drops each timed-out episode's last). The file stores
    every frame once; this dict holds two copies in memory, as D4RL's does."""
    with open_dataset(resolve_dataset(path_or_name)) as data:
        warn_incomplete(data)
        return data.to_qlearning()


def episodes(path_or_name: str | Path) -> Iterator[Episode]:
    """Each episode of the dataset in order, one at a time (only the current one's frames are in memory)."""
    with open_dataset(resolve_dataset(path_or_name)) as data:
        warn_incomplete(data)
        for i in range(data.num_episodes):
            yield episode_record(data, i)


def incomplete_text(data: Dataset) -> str:
    """What to say of a dataset whose collection did not finish."""
    return (
        f"{data.path} is not complete (its collection was interrupted or is still running): it holds the"
        f" {count(data.num_episodes, 'episode')} committed so far; finish it with `coworld collect ... --resume`"
    )


def warn_incomplete(data: Dataset) -> None:
    """A Python warning (as the library's way to say it) when ``data`` is not complete."""
    if not data.complete:
        import warnings

        warnings.warn(incomplete_text(data), UserWarning, stacklevel=3)


def episode_record(data: Dataset, i: int) -> Episode:
    """Episode ``i`` of an open dataset as an :class:`Episode`."""
    step = data.episode(i)
    last = step["is_last"][1:]
    terminated = bool(step["is_terminal"][-1])
    return Episode(
        index=i,
        observations=step["image"],
        actions=step["action"][1:],
        rewards=step["reward"][1:],
        terminations=last & terminated,
        truncations=last & (not terminated),
        infos={name: step[name][1:] for name in data.infos_keys},
    )
