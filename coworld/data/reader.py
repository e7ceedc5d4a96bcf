"""Read a dataset: validated on open, episodes in the DreamerV2 step convention, a D4RL view, sequence batches.

Step convention (what sequence models consume): an episode of T rows is T+1 steps. Step j holds ``image`` o_j,
``action`` a_{j-1} (the action that led to o_j; zeros at j = 0), ``reward`` r_{j-1} (zero at j = 0), ``is_first``
(j = 0), ``is_last`` (j = T, the final frame) and ``is_terminal`` (j = T and the episode truly terminated). Episodes
are laid back to back in one "step space" of ``num_steps + num_episodes`` steps; a sampled window is a contiguous
range of it.

The file is opened lazily in each process (h5py handles do not survive pickling or fork), so a :class:`Dataset` and
its samplers can be handed to DataLoader workers.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np
import psutil

from coworld.data.lock import holder_alive, read_lock
from coworld.data.sampler import SequenceSampler
from coworld.data.schema import PLUGIN_CODECS, decode_attrs, import_hdf5plugin, structural_problems
from coworld.data.values import true_values
from coworld.errors import DatasetError

# Share of the currently available memory that mode "auto" lets the frames take before it streams instead.
RAM_FRACTION = 0.5
_FINALS_CACHE = 1024  # final frames kept decoded per process in streaming mode (12 KiB each at 64 x 64 x 3)


@dataclass(frozen=True)
class StepArrays:
    """Everything but the frames, laid out in step space (M = num_steps + num_episodes steps).

    Attributes:
        action: (M, A) float32, the action that led to each step (zeros at first steps).
        reward: (M,) float32, the reward received on arriving at each step (zero at first steps).
        is_first: (M,) bool.
        is_last: (M,) bool, the final frame of each episode.
        is_terminal: (M,) bool, is_last of episodes that truly terminated.
    """

    action: np.ndarray
    reward: np.ndarray
    is_first: np.ndarray
    is_last: np.ndarray
    is_terminal: np.ndarray


def open_dataset(path: str | Path, *, cache_mb: int = 64) -> Dataset:
    """Open and validate the dataset at ``path``; bad files raise :class:`~coworld.errors.DatasetError`.

    ``cache_mb`` bounds HDF5's cache of decoded frame chunks per process (used when streaming from disk).
    """
    return Dataset(path, cache_mb=cache_mb)


def normalized_score(returns: np.ndarray | float, reference: dict[str, Any]) -> np.ndarray | float | None:
    """``100 * (R - random_return) / (reference_return - random_return)``, or None without both references."""
    low, high = reference.get("random_return"), reference.get("reference_return")
    if low is None or high is None or float(high) == float(low):
        return None
    return 100.0 * (np.asarray(returns, np.float64) - float(low)) / (float(high) - float(low))


class Dataset:
    """An opened dataset file. Small per-step arrays live in RAM; frames are read on demand or loaded once.

    Attributes:
        path: the file.
        metadata: root attributes as plain values (task, quality, env_config, collector, reference, versions, ...).
        starts, lengths: (E,) int64, the rows of each episode.
        returns: (E,) float64, the undiscounted return of each episode.
        terminated: (E,) bool, the episode ended in a true terminal state (else a time limit cut it).
    """

    def __init__(self, path: str | Path, *, cache_mb: int = 64) -> None:
        self.path = Path(path)
        self.cache_bytes = int(cache_mb) << 20
        self._file: h5py.File | None = None
        self._pid: int | None = None
        self._ram_images: np.ndarray | None = None
        self._steps: StepArrays | None = None
        self._read_final: Any = None
        f = self._handle()
        try:
            self._load(f)
        except DatasetError:
            self.close()
            raise
        except (OSError, KeyError, ValueError) as err:
            self.close()
            raise DatasetError(self._problem(f"unreadable ({_first_line(err)}); is the file truncated?")) from None

    # -- opening and validation ------------------------------------------------------------------------------

    def _problem(self, what: str) -> str:
        return f"{self.path}: {what}; `coworld dataset verify {self.path}` lists every problem"

    def _handle(self) -> h5py.File:
        """The h5py file of this process, opened on first use (and again after a fork or unpickling)."""
        if self._file is None or self._pid != os.getpid():
            self._file = open_h5(self.path, rdcc_nbytes=self.cache_bytes)
            self._pid = os.getpid()
            self._read_final = functools.lru_cache(maxsize=_FINALS_CACHE)(self._final_frame)
        return self._file

    def _load(self, f: h5py.File) -> None:
        problems = structural_problems(f)
        if problems:
            raise DatasetError(self._problem(problems[0]))
        self.metadata: dict[str, Any] = decode_attrs(f.attrs)
        n, e = int(self.metadata["num_rows"]), int(self.metadata["num_episodes"])
        if e == 0:
            raise DatasetError(f"{self.path}: holds no episodes yet; collect some first")
        self.starts: np.ndarray = f["episodes/starts"][:e]
        self.lengths: np.ndarray = f["episodes/lengths"][:e]
        self.returns: np.ndarray = f["episodes/returns"][:e]
        self.terminated: np.ndarray = f["episodes/terminated"][:e]
        self._actions: np.ndarray = f["actions"][:n]
        self._rewards: np.ndarray = f["rewards"][:n]
        terminals, timeouts = f["terminals"][:n], f["timeouts"][:n]
        ends = self.starts + self.lengths - 1
        if not np.array_equal(np.flatnonzero(terminals | timeouts), ends):
            raise DatasetError(self._problem("terminals/timeouts do not mark exactly the last row of each episode"))
        if (terminals & timeouts).any() or not np.array_equal(terminals[ends], self.terminated):
            raise DatasetError(self._problem("terminals, timeouts and episodes/terminated disagree"))
        if not np.isfinite(self._rewards).all():
            raise DatasetError(self._problem(f"{int((~np.isfinite(self._rewards)).sum())} rewards are NaN or inf"))
        if not np.isfinite(self._actions).all():
            raise DatasetError(self._problem(f"{int((~np.isfinite(self._actions)).sum())} actions are NaN or inf"))
        self.infos_keys: tuple[str, ...] = tuple(f["infos"].keys()) if "infos" in f else ()
        # First step of each episode in step space (each earlier episode adds its final frame).
        self.step_starts: np.ndarray = self.starts + np.arange(e)

    # -- description -----------------------------------------------------------------------------------------

    @property
    def task(self) -> str:
        return str(self.metadata["task"])

    @property
    def quality(self) -> str:
        return str(self.metadata["quality"])

    @property
    def action_size(self) -> int:
        return int(self.metadata["action_size"])

    @property
    def image_shape(self) -> tuple[int, int, int]:
        h, w, c = self.metadata.get("image_shape", (64, 64, 3))
        return int(h), int(w), int(c)

    @property
    def num_episodes(self) -> int:
        """E, committed episodes."""
        return len(self.lengths)

    @property
    def num_steps(self) -> int:
        """N, committed rows (transitions)."""
        return len(self._rewards)

    @property
    def num_frames(self) -> int:
        """M = N + E, frames including each episode's final frame (= steps in step space)."""
        return self.num_steps + self.num_episodes

    @property
    def complete(self) -> bool:
        return bool(self.metadata["complete"])

    @property
    def reference(self) -> dict[str, Any]:
        return dict(self.metadata.get("reference") or {})

    def normalized_scores(self) -> np.ndarray | None:
        """(E,) normalized score of each episode (see :func:`normalized_score`), None without reference returns."""
        scores = normalized_score(self.returns, self.reference)
        return None if scores is None else np.asarray(scores)

    def values(self, discount: float) -> np.ndarray:
        """(N,) the discounted return from every row to its episode's end (:func:`~coworld.data.values.true_values`):
        what a critic of the behaviour that collected the data estimates at each step."""
        return np.concatenate(
            [true_values(self._rewards[s : s + t], discount) for s, t in zip(self.starts, self.lengths, strict=True)]
        )

    def frame_storage(self) -> tuple[int, int]:
        """(raw, stored) bytes of all frames (rows and final frames): raw / stored is the compression ratio."""
        f = self._handle()
        raw = self.num_frames * int(np.prod(self.image_shape))
        stored = f["observations"].id.get_storage_size() + f["episodes/final_observations"].id.get_storage_size()
        return raw, stored

    def summary(self, discount: float = 0.99) -> dict[str, Any]:
        """Counts, return, length, reward (a step) and value statistics (the discounted return from each step, at
        ``discount``), normalized score, storage and metadata, as plain values."""
        raw, stored = self.frame_storage()
        out: dict[str, Any] = {
            "path": str(self.path),
            "format_version": self.metadata.get("format_version"),
            "task": self.task,
            "quality": self.quality,
            "complete": self.complete,
            "episodes": self.num_episodes,
            "steps": self.num_steps,
            "frames": self.num_frames,
            "terminated_episodes": int(self.terminated.sum()),
            "return": _stats(self.returns),
            "length": _stats(self.lengths),
            "reward": _stats(self._rewards),
            "value": _stats(self.values(discount)),
            "discount": discount,
            "normalized_score": None,
            "file_bytes": self.path.stat().st_size,
            "frame_bytes_raw": raw,
            "frame_bytes_stored": stored,
            "compression": self.metadata.get("compression"),
            "compression_ratio": raw / stored if stored else None,
        }
        scores = self.normalized_scores()
        if scores is not None:
            out["normalized_score"] = _stats(scores)
        for name in ("env_config", "collector", "reference", "versions", "created", "updated"):
            out[name] = self.metadata.get(name)
        return out

    # -- reading ---------------------------------------------------------------------------------------------

    def episode(self, i: int) -> dict[str, np.ndarray]:
        """Episode ``i`` in the step convention: T+1 steps for T rows.

        Returns ``image`` (T+1, H, W, C) uint8, ``action`` (T+1, A) float32, ``reward`` (T+1,) float32, ``is_first``,
        ``is_last``, ``is_terminal`` (T+1,) bool, and each infos key (T+1, ...) with step 0 zero/False.
        """
        if not -self.num_episodes <= i < self.num_episodes:
            raise IndexError(f"episode {i} out of range: the dataset has {self.num_episodes} episodes")
        i %= self.num_episodes
        s, t = int(self.starts[i]), int(self.lengths[i])
        f = self._handle()
        image = np.empty((t + 1, *self.image_shape), np.uint8)
        self._read(f["observations"], image[:t], s, s + t)
        image[t] = self._read_final(i)
        out = {
            "image": image,
            "action": np.concatenate([np.zeros((1, self.action_size), np.float32), self._actions[s : s + t]]),
            "reward": np.concatenate([np.zeros(1, np.float32), self._rewards[s : s + t]]),
            "is_first": np.arange(t + 1) == 0,
            "is_last": np.arange(t + 1) == t,
            "is_terminal": (np.arange(t + 1) == t) & bool(self.terminated[i]),
        }
        for name in self.infos_keys:
            values = f["infos"][name][s : s + t]
            out[name] = np.concatenate([np.zeros((1, *values.shape[1:]), values.dtype), values])
        return out

    def to_d4rl(self) -> dict[str, np.ndarray]:
        """All rows as D4RL arrays: observations (N, H, W, C), actions (N, A), rewards, terminals, timeouts (N,),
        plus ``infos/<key>``. Loads every frame into memory."""
        f = self._handle()
        n = self.num_steps
        out = {"observations": np.empty((n, *self.image_shape), np.uint8)}
        self._read(f["observations"], out["observations"], 0, n)
        out["actions"] = self._actions.copy()
        out["rewards"] = self._rewards.copy()
        for name in ("terminals", "timeouts"):
            out[name] = f[name][:n]
        for name in self.infos_keys:
            out[f"infos/{name}"] = f["infos"][name][:n]
        return out

    def to_qlearning(self) -> dict[str, np.ndarray]:
        """:meth:`to_d4rl` plus ``next_observations`` (N, H, W, C), D4RL's ``qlearning_dataset`` key: row ``i``'s
        ``o_{t+1}``, the next row's frame, or at an episode's last row its final frame
        (``episodes/final_observations``). The file holds every frame once; this builds both arrays in memory."""
        out = self.to_d4rl()
        observations = out["observations"]
        following = np.empty_like(observations)
        following[:-1] = observations[1:]
        finals = np.empty((self.num_episodes, *self.image_shape), np.uint8)
        self._read(self._handle()["episodes/final_observations"], finals, 0, self.num_episodes)
        following[self.starts + self.lengths - 1] = finals
        return {**out, "next_observations": following}

    def step_arrays(self) -> StepArrays:
        """The non-frame part of every step, built once (about 4 * A + 7 bytes per step)."""
        if self._steps is None:
            e, m = self.num_episodes, self.num_frames
            arrive = np.arange(self.num_steps) + np.repeat(np.arange(e), self.lengths) + 1  # step reached by row i
            action = np.zeros((m, self.action_size), np.float32)
            action[arrive] = self._actions
            reward = np.zeros(m, np.float32)
            reward[arrive] = self._rewards
            is_first, is_last, is_terminal = np.zeros(m, bool), np.zeros(m, bool), np.zeros(m, bool)
            last = self.step_starts + self.lengths
            is_first[self.step_starts] = True
            is_last[last] = True
            is_terminal[last] = self.terminated
            self._steps = StepArrays(action, reward, is_first, is_last, is_terminal)
        return self._steps

    def fits_in_ram(self) -> bool:
        """Whether all frames are loaded already (:meth:`load_frames`) or take less than half of the memory
        available now."""
        if self._ram_images is not None:
            return True
        need = self.num_frames * int(np.prod(self.image_shape))
        return need < RAM_FRACTION * psutil.virtual_memory().available

    def load_frames(self) -> np.ndarray:
        """Every frame in step space, (M, H, W, C) uint8, read once and kept (what sampler mode "ram" uses)."""
        if self._ram_images is None:
            f = self._handle()
            images = np.empty((self.num_frames, *self.image_shape), np.uint8)
            for i in range(self.num_episodes):  # each episode's rows are one contiguous slice of step space
                k, s, t = int(self.step_starts[i]), int(self.starts[i]), int(self.lengths[i])
                self._read(f["observations"], images[k : k + t], s, s + t)
            finals = np.empty((self.num_episodes, *self.image_shape), np.uint8)
            self._read(f["episodes/final_observations"], finals, 0, self.num_episodes)
            images[self.step_starts + self.lengths] = finals
            self._ram_images = images
        return self._ram_images

    def read_steps(self, start: int, out: np.ndarray) -> None:
        """Frames of steps ``start .. start + len(out)`` into ``out`` (L, H, W, C), from disk.

        The rows of any contiguous step range are one contiguous slice of ``observations`` (final frames sit
        between episodes in step space only), so this is one slice read plus the final frames the window crosses.
        """
        length = len(out)
        first = int(np.searchsorted(self.step_starts, start, side="right")) - 1
        last = int(np.searchsorted(self.step_starts, start + length - 1, side="right")) - 1
        ends = self.step_starts[first : last + 1] + self.lengths[first : last + 1]  # steps holding final frames
        inside = np.flatnonzero((ends >= start) & (ends < start + length))
        row = start - first
        frames = self._handle()["observations"]
        if inside.size == 0:
            self._read(frames, out, row, row + length)
            return
        keep = np.ones(length, bool)
        keep[ends[inside] - start] = False
        rows = np.empty((length - inside.size, *self.image_shape), np.uint8)
        self._read(frames, rows, row, row + len(rows))
        out[keep] = rows
        for j in inside:
            out[ends[j] - start] = self._read_final(first + int(j))

    def _final_frame(self, i: int) -> np.ndarray:
        out = np.empty((1, *self.image_shape), np.uint8)
        self._read(self._handle()["episodes/final_observations"], out, i, i + 1)
        return out[0]

    def _read(self, node: h5py.Dataset, out: np.ndarray, start: int, stop: int) -> None:
        """``node[start:stop]`` into the C-contiguous ``out`` without a temporary copy."""
        if stop <= start:
            return
        try:
            node.read_direct(out, source_sel=np.s_[start:stop])
        except OSError as err:
            raise DatasetError(
                self._problem(f"cannot read {node.name} rows {start}..{stop} ({_first_line(err)}); damaged file")
            ) from None

    def sampler(self, batch_size: int, seq_len: int, seed: int = 0, mode: str = "auto") -> SequenceSampler:
        """An endless, seeded iterator of batches of ``batch_size`` windows of ``seq_len`` steps; see
        :class:`~coworld.data.sampler.SequenceSampler`. ``mode``: ``ram`` loads every frame once, ``stream``
        reads windows from disk with bounded memory, ``auto`` picks ``ram`` when the frames fit in available memory."""
        return SequenceSampler(self, batch_size, seq_len, seed=seed, mode=mode)

    # -- lifetime --------------------------------------------------------------------------------------------

    def close(self) -> None:
        """Close this process's file handle (it reopens on next use); frames loaded into RAM are dropped."""
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file = None
        self._read_final = None
        self._ram_images = None

    def __enter__(self) -> Dataset:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.update(_file=None, _pid=None, _read_final=None)
        return state

    def __repr__(self) -> str:
        return (
            f"Dataset({str(self.path)!r}, task={self.task!r}, quality={self.quality!r}, "
            f"episodes={self.num_episodes}, steps={self.num_steps})"
        )


def open_h5(path: Path, **kwargs: Any) -> h5py.File:
    """Open a dataset file read-only, turning every way that can fail into one :class:`DatasetError` line."""
    if not path.exists():
        raise DatasetError(f"{path}: no such file")
    if path.is_dir():
        raise DatasetError(f"{path}: is a directory, not a dataset file")
    try:
        f = h5py.File(path, "r", **kwargs)
    except OSError as err:
        holder = read_lock(path)
        if holder and holder_alive(holder):
            raise DatasetError(
                f"{path}: is being written by process {holder['pid']}; wait for it to finish and try again"
            ) from None
        raise DatasetError(
            f"{path}: not a readable HDF5 file ({_first_line(err)}); is it truncated or not a dataset?"
        ) from None
    codec = f.attrs.get("compression")
    if codec in PLUGIN_CODECS:
        import_hdf5plugin(str(codec))
    return f


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def _stats(values: np.ndarray) -> dict[str, float]:
    values = np.asarray(values, np.float64)
    return {
        "mean": float(values.mean()),
        "std": float(values.std()),
        "min": float(values.min()),
        "max": float(values.max()),
    }
