"""What every task family's env shares: frames as observations, actions in a box, episodes cut by a time limit."""

from __future__ import annotations

from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np

if TYPE_CHECKING:
    from coworld.envs.spec import EnvSettings, TaskSpec


class PixelEnv(gym.Env[np.ndarray, np.ndarray]):
    """A task seen as ``(S, S, 3)`` uint8 RGB frames (``S`` = ``settings.image_size``), acting in ``[-1, 1]^A``,
    truncated after ``settings.episode_length`` agent steps and never terminated.

    A family's env draws its frames and steps its simulator; this class keeps the episode's count and seed, refuses a
    step before ``reset()`` (at the start and after a truncation) and an action of the wrong shape, and renders the
    latest frame.

    Every episode has a seed that seeds all of its randomness (:meth:`_episode_seed`): the one ``reset`` is given,
    else the next of a chain that starts at the env's own seed. So an episode is a function of its seed and its
    actions, whatever ran before it: an online run resumes its running episodes exactly by replaying their actions
    from their seeds (:mod:`coworld.training.online`).

    Attributes:
        task: the :class:`~coworld.envs.registry.TaskSpec`; ``settings``: the resolved overrides.
    """

    metadata = {"render_modes": ["rgb_array"]}
    render_mode = "rgb_array"

    def __init__(self, task: TaskSpec, settings: EnvSettings, action_size: int, seed: int) -> None:
        self.task = task
        self.settings = settings
        size = settings.image_size
        self.observation_space = gym.spaces.Box(0, 255, (size, size, 3), np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (action_size,), np.float32)
        self._steps = 0
        self._needs_reset = True
        self._frame = np.zeros(self.observation_space.shape, np.uint8)
        self.episode_seed: int | None = None
        """The seed of the running (or last) episode; None before the first ``reset``."""
        self._next_seed = int(seed)

    def _episode_seed(self, seed: int | None) -> int:
        """Called first by ``reset(seed=seed)``: the seed of the episode it starts, ``seed`` where given, else the
        next of the chain (the env's seed for its first episode)."""
        self.episode_seed = int(seed) if seed is not None else self._next_seed
        self._next_seed = next_seed(self.episode_seed)
        return self.episode_seed

    def _start_episode(self) -> None:
        """Called by ``reset()``: the episode's first step is next."""
        self._steps = 0
        self._needs_reset = False

    def _checked(self, action: np.ndarray, dtype: type = np.float64) -> np.ndarray:
        """``action`` as an array of ``dtype``, once an episode is running and the shape is the action space's."""
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (at the start and after each truncated episode)")
        action = np.asarray(action, dtype)
        if action.shape != self.action_space.shape:
            raise ValueError(f"{self.task.name} takes actions of shape {self.action_space.shape}, got {action.shape}")
        return action

    def _count_step(self) -> bool:
        """Count one agent step; whether it ends the episode (the time limit: truncated)."""
        self._steps += 1
        self._needs_reset = self._steps >= self.settings.episode_length
        return self._needs_reset

    def render(self) -> np.ndarray:
        """The latest observation (``rgb_array``)."""
        return self._frame.copy()


def next_seed(seed: int) -> int:
    """The seed of the episode after one seeded ``seed`` (a ``reset()`` without a seed)."""
    return int(np.random.SeedSequence(seed).generate_state(1)[0])
