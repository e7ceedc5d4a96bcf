"""Seeded sequence sampler: batches of B windows of L consecutive steps, from RAM or streamed from disk.

Window starts are drawn uniformly from every start that keeps the window inside one episode; an episode shorter
than L contributes one window that starts at its first step (or earlier, if the data ends first) and runs on into
the following episode, where ``is_first`` marks the boundary. No window runs past the end of the data. Both modes
draw the same starts from the same seed, so they yield identical batches.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from coworld.errors import ConfigError, DatasetError

SAMPLER_MODES = ("auto", "ram", "stream")


class StepSource(Protocol):
    """What the sampler reads of a dataset (:class:`coworld.data.reader.Dataset` is one)."""

    path: Path
    num_frames: int
    lengths: np.ndarray
    step_starts: np.ndarray
    image_shape: tuple[int, int, int]

    def fits_in_ram(self) -> bool: ...

    def step_arrays(self) -> Any: ...

    def load_frames(self) -> np.ndarray: ...

    def read_steps(self, start: int, out: np.ndarray) -> None: ...


class SequenceSampler:
    """Endless iterator of batches in the DreamerV2 step convention.

    Each batch holds ``image`` (B, L, H, W, C) uint8, ``action`` (B, L, A) float32, ``reward`` (B, L) float32 and
    ``is_first``, ``is_last``, ``is_terminal`` (B, L) bool (see :mod:`coworld.data.reader` for their meaning;
    ``is_first`` is also set on every window's first step, so each window starts from a fresh latent).

    The sampler pickles (for DataLoader workers): the file is reopened in each process, and a sampler running in a
    PyTorch DataLoader worker seeds itself from ``(seed, worker id)`` so workers draw different windows. In "ram"
    mode the frames are loaded when the sampler is built, so forked workers share them.

    Args:
        dataset: an opened dataset.
        batch_size: B.
        seq_len: L, at most the number of steps in the dataset.
        seed: seeds the window starts.
        mode: "ram", "stream" or "auto" (ram when the frames fit in half the available memory).
    """

    def __init__(self, dataset: StepSource, batch_size: int, seq_len: int, seed: int = 0, mode: str = "auto") -> None:
        if mode not in SAMPLER_MODES:
            raise ConfigError(f"unknown sampler mode {mode!r}; choose one of: {', '.join(SAMPLER_MODES)}")
        if batch_size < 1 or seq_len < 1:
            raise ConfigError(f"batch_size and seq_len must be >= 1, got {batch_size} and {seq_len}")
        if seq_len > dataset.num_frames:
            raise DatasetError(
                f"{dataset.path}: seq_len {seq_len} is longer than the whole dataset ({dataset.num_frames} steps)"
            )
        self.dataset = dataset
        self.batch_size = int(batch_size)
        self.seq_len = int(seq_len)
        self.seed = int(seed)
        self.mode = ("ram" if dataset.fits_in_ram() else "stream") if mode == "auto" else mode
        self.steps = dataset.step_arrays()
        # Window starts: episode e offers `count[e]` starts beginning at step `base[e]`.
        steps_per_episode = dataset.lengths + 1
        self._count = np.maximum(steps_per_episode - self.seq_len + 1, 1)
        self._base = np.minimum(dataset.step_starts, dataset.num_frames - self.seq_len)
        self._cum = np.cumsum(self._count)
        self._offsets = np.arange(self.seq_len)
        self._rng: np.random.Generator | None = None
        self._rng_pid: int | None = None
        if self.mode == "ram":
            dataset.load_frames()

    def __iter__(self) -> SequenceSampler:
        return self

    def __next__(self) -> dict[str, np.ndarray]:
        return self.gather(self.sample_starts(self._generator()))

    def skip(self, batches: int) -> None:
        """Draw and drop the window starts of the next ``batches`` batches without reading their frames: the
        iterator then yields what it would have yielded after that many ``next`` calls."""
        rng = self._generator()
        for _ in range(batches):
            self.sample_starts(rng)

    def sample_starts(self, rng: np.random.Generator) -> np.ndarray:
        """(B,) int64 first steps of B windows, uniform over the allowed starts."""
        pick = rng.integers(0, self._cum[-1], size=self.batch_size)
        episode = np.searchsorted(self._cum, pick, side="right")
        return self._base[episode] + pick - (self._cum[episode] - self._count[episode])

    def gather(self, starts: np.ndarray) -> dict[str, np.ndarray]:
        """The batch of windows beginning at ``starts`` (B,)."""
        index = starts[:, None] + self._offsets  # (B, L)
        if self.mode == "ram":
            image = np.take(self.dataset.load_frames(), index, axis=0)
        else:
            image = np.empty((len(starts), self.seq_len, *self.dataset.image_shape), np.uint8)
            for b in np.argsort(starts, kind="stable"):  # file order: neighbouring windows share cached chunks
                self.dataset.read_steps(int(starts[b]), image[b])
        s = self.steps
        is_first = s.is_first[index]
        is_first[:, 0] = True  # a window starts from a fresh latent, with no previous action (DreamerV2)
        return {
            "image": image,
            "action": s.action[index],
            "reward": s.reward[index],
            "is_first": is_first,
            "is_last": s.is_last[index],
            "is_terminal": s.is_terminal[index],
        }

    def _generator(self) -> np.random.Generator:
        if self._rng is None or self._rng_pid != os.getpid():
            entropy = [self.seed]
            worker = _dataloader_worker_id()
            if worker is not None:
                entropy.append(worker)
            self._rng = np.random.default_rng(entropy)
            self._rng_pid = os.getpid()
        return self._rng


def _dataloader_worker_id() -> int | None:
    """The PyTorch DataLoader worker id of this process, or None (torch is not imported here for this)."""
    data = sys.modules.get("torch.utils.data")
    info = data.get_worker_info() if data is not None else None
    return None if info is None else int(info.id)
