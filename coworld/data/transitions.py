"""Seeded sampler of frame-stacked transitions ``(s, a, r, s', not_done)`` for the model-free baselines.

CURL and CURL+CQL learn from single transitions whose observation is a stack of the last ``k`` frames. The sampler
works in the dataset's *step space* (see :mod:`coworld.data.reader`): every episode's ``T + 1`` frames, final frame
included, laid back to back, ``M = num_steps + num_episodes`` steps. Frames are held in RAM once (the same array
:meth:`~coworld.data.reader.Dataset.load_frames` caches for the sequence sampler; 1M frames of 64 x 64 x 3 are
12.3 GB) and stacks are gathered by index, so no frame is stored ``k`` times.

Stacking, for transition ``t`` of an episode with frames ``o_0 .. o_T`` (``T`` transitions):

* ``obs``      = ``o_{t-k+1} .. o_t``, oldest first; indices before 0 repeat ``o_0`` (CURL's reset fills the
  stack with the first frame);
* ``next_obs`` = ``o_{t-k+2} .. o_{t+1}``; at ``t = T - 1`` it ends with the episode's final frame ``o_T``;
* no stack ever holds a frame of another episode.

``not_done`` is 0 only where the episode *terminated* at ``o_{t+1}``; an episode cut by a time limit
(``timeouts``) still bootstraps from its last frame.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from coworld.data.reader import Dataset
from coworld.errors import DatasetError

__all__ = ["TransitionSampler"]


class TransitionSampler:
    """Uniform random batches of frame-stacked transitions, reproducible from ``seed``.

    Args:
        image: ``(M, H, W, C) uint8`` every step's frame, episodes back to back.
        action: ``(M, A)``, the action that led to each step (row of a first step unused).
        reward: ``(M,)``, the reward received on arriving at each step.
        is_first: ``(M,) bool``, first step of each episode (step 0 must be one).
        is_last: ``(M,) bool``, final frame of each episode.
        is_terminal: ``(M,) bool``, final frame of an episode that truly terminated.
        batch_size: transitions per batch ``B``.
        frame_stack: frames per observation ``k``.
        seed: seed of the sampler's own generator.

    Batches (:meth:`sample`, or ``next(sampler)``) are dicts of NumPy arrays:
    ``obs (B, k*C, H, W) uint8``, ``action (B, A) float32``, ``reward (B,) float32``,
    ``next_obs (B, k*C, H, W) uint8``, ``not_done (B,) float32``. Channels are frame-major: channels
    ``[j*C, (j+1)*C)`` hold frame ``j`` of the stack, oldest first.
    """

    def __init__(
        self,
        *,
        image: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        is_first: np.ndarray,
        is_last: np.ndarray,
        is_terminal: np.ndarray,
        batch_size: int,
        frame_stack: int,
        seed: int = 0,
    ) -> None:
        if batch_size < 1 or frame_stack < 1:
            raise ValueError(f"batch_size and frame_stack must be >= 1, got {batch_size} and {frame_stack}")
        M = len(image)
        if image.ndim != 4 or image.dtype != np.uint8:
            raise DatasetError(f"frames must be uint8 (M, H, W, C), got {image.dtype} {image.shape}")
        for name, value in (("reward", reward), ("is_first", is_first), ("is_last", is_last)):
            if value.shape != (M,):
                raise DatasetError(f"{name} must have one entry per frame ({M},), got {value.shape}")
        if action.ndim != 2 or len(action) != M or is_terminal.shape != (M,):
            raise DatasetError(f"action must be (M, A) and is_terminal (M,) for M = {M} frames")
        if M == 0 or not is_first[0] or not is_last[-1]:
            raise DatasetError("steps must hold whole episodes: is_first on the first step, is_last on the last")
        self.batch_size = batch_size
        self.frame_stack = frame_stack
        self._image = image
        self._action = np.asarray(action, dtype=np.float32)
        self._reward = np.asarray(reward, dtype=np.float32)
        self._not_done = 1.0 - np.asarray(is_terminal, dtype=np.float32)
        is_first, is_last = np.asarray(is_first, dtype=bool), np.asarray(is_last, dtype=bool)
        steps = np.arange(M)
        # Transition t leaves step j = t's step and arrives at j + 1: every step but an episode's final frame.
        self._source = np.flatnonzero(~is_last)  # (N,)
        if (is_first[self._source + 1]).any():
            raise DatasetError("an episode ends without is_last on its final frame")
        self._episode_start = np.maximum.accumulate(np.where(is_first, steps, 0))  # (M,) first step of j's episode
        if len(self._source) == 0:
            raise DatasetError("the dataset holds no transition (every episode has fewer than 2 frames)")
        self.rng = np.random.default_rng(seed)

    @classmethod
    def from_episodes(
        cls, episodes: Sequence[Mapping[str, np.ndarray]], *, batch_size: int, frame_stack: int, seed: int = 0
    ) -> TransitionSampler:
        """Sample from in-memory episodes in the step convention (:meth:`Dataset.episode`'s dicts: ``image (T+1,
        H, W, C)``, ``action (T+1, A)``, ``reward (T+1,)``, ``is_terminal (T+1,)``; first/last are implied)."""
        if not episodes:
            raise DatasetError("no episodes to sample from")
        lengths = [len(episode["image"]) for episode in episodes]
        first = np.concatenate([np.arange(n) == 0 for n in lengths])
        last = np.concatenate([np.arange(n) == n - 1 for n in lengths])
        return cls(
            image=np.concatenate([np.asarray(episode["image"]) for episode in episodes]),
            action=np.concatenate([np.asarray(episode["action"], dtype=np.float32) for episode in episodes]),
            reward=np.concatenate([np.asarray(episode["reward"], dtype=np.float32) for episode in episodes]),
            is_first=first,
            is_last=last,
            is_terminal=np.concatenate([np.asarray(episode["is_terminal"], dtype=bool) for episode in episodes]),
            batch_size=batch_size,
            frame_stack=frame_stack,
            seed=seed,
        )

    @classmethod
    def from_dataset(cls, dataset: Dataset, *, batch_size: int, frame_stack: int, seed: int = 0) -> TransitionSampler:
        """Sample from a :class:`~coworld.data.reader.Dataset`, its frames loaded into RAM once (shared with its
        sequence sampler's "ram" mode, and with later samplers of the same Dataset object, as a resumed or
        re-seeded run builds); a dataset too large for the free memory raises DatasetError."""
        if not dataset.fits_in_ram():
            gigabytes = dataset.num_frames * int(np.prod(dataset.image_shape)) / 2**30
            raise DatasetError(
                f"{dataset.path}: the transition sampler keeps all frames in RAM ({gigabytes:.1f} GiB), more than"
                " half the free memory; free memory or train on a smaller dataset (`coworld dataset merge` subsets)"
            )
        steps = dataset.step_arrays()
        return cls(
            image=dataset.load_frames(),
            action=steps.action,
            reward=steps.reward,
            is_first=steps.is_first,
            is_last=steps.is_last,
            is_terminal=steps.is_terminal,
            batch_size=batch_size,
            frame_stack=frame_stack,
            seed=seed,
        )

    @property
    def num_transitions(self) -> int:
        """Transitions ``N`` (steps minus one per episode)."""
        return len(self._source)

    @property
    def num_episodes(self) -> int:
        return int(len(self._image) - len(self._source))

    @property
    def action_size(self) -> int:
        return self._action.shape[1]

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """``(H, W, C)`` of one frame."""
        _, H, W, C = self._image.shape
        return H, W, C

    def stack_steps(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Steps of the ``obs`` and ``next_obs`` stacks of transitions ``index``.

        Args:
            index: ``(B,)`` transition indices in ``[0, N)``.

        Returns:
            ``(obs_steps (B, k), next_steps (B, k))``, oldest first, clamped to each episode's first step.
        """
        source = self._source[index]
        back = np.arange(-(self.frame_stack - 1), 1, dtype=np.int64)  # (k,) -k+1 .. 0
        start = self._episode_start[source][:, None]
        current = source[:, None] + back
        return np.maximum(current, start), np.maximum(current + 1, start)

    def sample(self, batch_size: int | None = None) -> dict[str, np.ndarray]:
        """One batch of ``batch_size`` (default :attr:`batch_size`) transitions drawn uniformly with replacement.

        ``obs`` and ``next_obs`` share ``k - 1`` frames, so the ``k + 1`` frames of both are gathered once and the
        two stacks are views of one ``(B, (k+1)*C, H, W)`` array (strided along the batch axis).
        """
        B = batch_size or self.batch_size
        index = self.rng.integers(0, self.num_transitions, size=B)
        obs_steps, next_steps = self.stack_steps(index)
        window = np.concatenate([obs_steps, next_steps[:, -1:]], axis=1)  # (B, k+1): obs = [:k], next = [1:]
        _, H, W, C = self._image.shape
        k = self.frame_stack
        frames = self._image[window]  # (B, k+1, H, W, C)
        stacked = np.ascontiguousarray(frames.transpose(0, 1, 4, 2, 3)).reshape(B, (k + 1) * C, H, W)
        arrive = self._source[index] + 1
        return {
            "obs": stacked[:, : k * C],
            "action": self._action[arrive],
            "reward": self._reward[arrive],
            "next_obs": stacked[:, C:],
            "not_done": self._not_done[arrive],
        }

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        return self

    def __next__(self) -> dict[str, np.ndarray]:
        return self.sample()

    def state_dict(self) -> dict[str, Any]:
        """The generator's state (plain ints and strings: safe for ``torch.load(weights_only=True)``)."""
        return {"rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Resume the sequence of batches saved by :meth:`state_dict`."""
        self.rng.bit_generator.state = dict(state["rng"])
