"""In-memory replay of an online run, sampled in the same step convention as the dataset sampler.

Each vectorised environment fills its own running episode; a finished episode is stored whole. Windows of
``seq_len`` consecutive steps are drawn uniformly over all valid start positions of the stored episodes, so
every step is equally likely. Step ``j`` of an episode holds the image ``o_j``, the action that led to it,
the reward received on arriving, and the ``is_first`` / ``is_last`` / ``is_terminal`` flags.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

import numpy as np

from coworld.data.schema import STEP_KEYS as KEYS


class Replay:
    """Finished episodes in RAM, dropped oldest-first past ``capacity`` steps.

    Args:
        capacity: most steps held (0 = unbounded).
        seed: seed of the window sampler.
    """

    def __init__(self, *, capacity: int = 0, seed: int = 0) -> None:
        self.capacity = capacity
        self.episodes: list[dict[str, np.ndarray]] = []
        self._running: dict[int, dict[str, list[np.ndarray]]] = {}
        self._rng = np.random.default_rng(seed)
        self.num_steps = 0

    # -- filling ---------------------------------------------------------------------------------------------------
    def add_step(self, env_index: int, step: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        """Append one step of environment ``env_index``; return the episode when ``step`` ends it."""
        if step["is_first"]:
            self._running[env_index] = {key: [] for key in KEYS}
        running = self._running[env_index]
        for key in KEYS:
            running[key].append(np.asarray(step[key]))
        if not step["is_last"]:
            return None
        episode = {key: np.stack(values) for key, values in running.items()}
        del self._running[env_index]
        self.add_episode(episode)
        return episode

    def add_episode(self, episode: Mapping[str, np.ndarray]) -> None:
        """Store a finished episode given as arrays of T+1 steps."""
        episode = {key: np.asarray(episode[key]) for key in KEYS}
        self.episodes.append(episode)
        self.num_steps += len(episode["reward"])
        while self.capacity and self.num_steps > self.capacity and len(self.episodes) > 1:
            self.num_steps -= len(self.episodes.pop(0)["reward"])

    @property
    def sampler_state(self) -> dict:
        """The window sampler's random state (a checkpoint's entry; set it to continue the same draws)."""
        return self._rng.bit_generator.state

    @sampler_state.setter
    def sampler_state(self, state: dict) -> None:
        self._rng.bit_generator.state = state

    # -- sampling --------------------------------------------------------------------------------------------------
    def sample(self, batch_size: int, seq_len: int) -> dict[str, np.ndarray]:
        """A batch of ``batch_size`` windows of ``seq_len`` steps, each inside one episode when it is long enough.

        Returns:
            dict of arrays (B, L, ...) with the keys of :data:`KEYS`.
        """
        if not self.episodes:
            raise RuntimeError("the replay is empty: collect at least one whole episode before sampling")
        lengths = np.array([len(ep["reward"]) for ep in self.episodes])
        starts = np.maximum(lengths - seq_len + 1, 1)
        which = self._rng.choice(len(self.episodes), size=batch_size, p=starts / starts.sum())
        windows = [self._window(int(i), int(self._rng.integers(starts[i])), seq_len) for i in which]
        batch = {key: np.stack([w[key] for w in windows]) for key in KEYS}
        batch["is_first"][:, 0] = True  # a window starts from a fresh latent, with no previous action (DreamerV2)
        return batch

    def _window(self, index: int, start: int, seq_len: int) -> dict[str, np.ndarray]:
        # An episode shorter than seq_len continues into the following ones, with is_first marking the seams.
        parts, need = [], seq_len
        while need > 0:
            episode = self.episodes[index % len(self.episodes)]
            part = {key: value[start : start + need] for key, value in episode.items()}
            parts.append(part)
            need -= len(part["reward"])
            index, start = index + 1, 0
        return {key: np.concatenate([p[key] for p in parts]) for key in KEYS}

    def iterate(self, batch_size: int, seq_len: int) -> Iterator[dict[str, np.ndarray]]:
        while True:
            yield self.sample(batch_size, seq_len)
