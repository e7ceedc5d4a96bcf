"""Import V-D4RL datasets (Lu et al., TMLR 2023, the standard offline pixel benchmark) into format v1.

V-D4RL ships every dataset (``vd4rl_data/main/<env>/<quality>/{64px,84px}``) in two layouts:

* ``64px``: one ``.npz`` per episode (written with ``np.savez_compressed``), T+1 entries per key: ``image``
  (T+1, 64, 64, 3) uint8, ``action`` (T+1, A), ``reward``, ``discount`` (T+1,), ``is_first``, ``is_last``,
  ``is_terminal`` (T+1,) bool. Read in ``sorted()`` file-name order, as V-D4RL's loaders do.
* ``84px``: HDF5 shards (``*.hdf5``, gzip) of episodes back to back: ``observation`` (N, 3, 84, 84) uint8
  (channels first), ``action`` (N, A), ``reward``, ``discount`` (N,) and ``step_type`` (N,): 0 first, 1 mid,
  2 last (dm_env's). Shards are read in natural order (``2.hdf5`` before ``10.hdf5``) and an episode may run on
  from one shard into the next.

Both follow DreamerV2's / DrQ-v2's step convention: entry j of an episode holds the frame o_j, the action a_{j-1}
that led to it and the reward r_{j-1} it earned; entry 0 is the reset, with a zero action and a zero reward. Our
row i is (o_i, a_i, r_i), so row i takes ``image[i]``, ``action[i + 1]`` and ``reward[i + 1]``, and ``image[T]`` is
the episode's final frame. An episode ended in a true terminal state when its last entry says so (``is_terminal``;
in the shards, dm_env's rule: a last step with discount 0); any other last entry is a time limit.

Frames must be 64 x 64; 84 x 84 frames are resized only when asked (``resize=64``), with OpenCV's area filter.
"""

from __future__ import annotations

import hashlib
import json
import re
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from coworld.data.collect import default_dataset_path, new_dataset
from coworld.data.schema import IMAGE_SHAPE
from coworld.errors import ConfigError, DatasetError
from coworld.progress import progress_bar

# V-D4RL's folder names of its qualities, and the environments it covers.
VD4RL_QUALITIES = {
    "random": "random",
    "medium_replay": "medium-replay",
    "medium": "medium",
    "medium_expert": "medium-expert",
    "expert": "expert",
}
VD4RL_ENVS = ("walker_walk", "cheetah_run", "humanoid_walk")
NPZ_KEYS = ("image", "action", "reward", "is_first", "is_last")
SHARD_KEYS = ("observation", "action", "reward", "discount", "step_type")
RESIZE_FILTER = "cv2.INTER_AREA"
# Largest |action| accepted: V-D4RL's actions come from a tanh-squashed policy in DMC's [-1, 1] box.
_ACTION_BOUND = 1.0 + 1e-6


@dataclass(frozen=True)
class SourceEpisode:
    """Where one V-D4RL episode lies: ``(file, start, stop)`` entry ranges (one per npz file or shard crossed)."""

    segments: tuple[tuple[Path, int, int], ...]
    terminated: bool

    @property
    def length(self) -> int:
        """T, the transitions of the episode (its entries minus the reset entry)."""
        return sum(stop - start for _, start, stop in self.segments) - 1


@dataclass(frozen=True)
class VD4RLSource:
    """A scanned V-D4RL dataset folder: its layout, files, frame size, action size and episodes (no frame read)."""

    path: Path
    layout: str
    """``npz-episodes`` (V-D4RL's 64px folders) or ``hdf5-shards`` (its 84px folders)."""
    files: tuple[Path, ...]
    image_size: int
    action_size: int
    episodes: tuple[SourceEpisode, ...]

    @property
    def num_steps(self) -> int:
        return sum(ep.length for ep in self.episodes)

    def fingerprint(self) -> str:
        """A short hash of the layout and of every file's name and size: tells a resumed import it reads the same
        data."""
        listing = [self.layout, *[(f.name, f.stat().st_size) for f in self.files]]
        return hashlib.sha256(json.dumps(listing).encode()).hexdigest()[:16]

    def described_by_path(self) -> dict[str, str | None]:
        """V-D4RL's environment and quality named by the folder path (``.../walker_walk/medium_replay/64px``)."""
        parts = self.path.resolve().parts
        env = next((part for part in reversed(parts) if part in VD4RL_ENVS), None)
        quality = next((VD4RL_QUALITIES[part] for part in reversed(parts) if part in VD4RL_QUALITIES), None)
        return {"env": env, "quality": quality}


@dataclass(frozen=True)
class ImportSummary:
    """What an import left on disk."""

    path: Path
    episodes: int
    steps: int
    skipped: int
    """Episodes already in the file from an interrupted import (resume), not converted again."""


# -- scanning ------------------------------------------------------------------------------------------------


def scan_vd4rl(path: str | Path) -> VD4RLSource:
    """Find the layout of the V-D4RL folder ``path`` and every episode in it, checking the structure.

    Reads only the small arrays (and the npz frame headers); raises :class:`DatasetError` with one line naming
    the file and the problem when the folder is not laid out as V-D4RL's code writes it.
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(
            f"{path}: not a folder; point at a V-D4RL dataset folder such as .../walker_walk/random/64px"
        )
    npz, shards = sorted(path.glob("*.npz")), sorted(path.glob("*.hdf5"), key=_natural_key)
    if npz and shards:
        raise DatasetError(f"{path}: holds both .npz episodes and .hdf5 shards; point at a folder with one layout")
    if npz:
        return _scan_npz(path, npz)
    if shards:
        return _scan_shards(path, shards)
    inside = sorted(child.name for child in path.iterdir() if child.is_dir() and child.name in ("64px", "84px"))
    hint = f"; it has {' and '.join(inside)}: point at one of them" if inside else ""
    raise DatasetError(f"{path}: no V-D4RL episodes (.npz) or shards (.hdf5) in this folder{hint}")


def _natural_key(file: Path) -> list[Any]:
    return [int(token) if token.isdigit() else token for token in re.split(r"(\d+)", file.name)]


def _scan_npz(path: Path, files: list[Path]) -> VD4RLSource:
    episodes, sizes = [], _Sizes()
    for file in files:
        if not zipfile.is_zipfile(file):  # np.load would speak of pickles
            raise DatasetError(f"{file}: not an npz archive (a zip of .npy arrays, as np.savez writes); remove it")
        try:
            with np.load(file, allow_pickle=False) as data:
                missing = [key for key in NPZ_KEYS if key not in data.files]
                if "is_terminal" not in data.files and "discount" not in data.files:
                    missing.append("is_terminal (or discount)")
                if missing:
                    raise DatasetError(f"{file}: not a V-D4RL episode: no {', '.join(missing)}")
                action, reward = data["action"], data["reward"]
                first, last = data["is_first"].astype(bool), data["is_last"].astype(bool)
                # As V-D4RL's own loader: a file without is_terminal ends in a terminal state where discount is 0.
                terminal = data["is_terminal"] if "is_terminal" in data.files else data["discount"] == 0
            shape, dtype = _npy_header(file, "image")
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as err:
            raise DatasetError(f"{file}: unreadable npz ({_first_line(err)})") from None
        entries = len(action)
        if len(shape) != 4 or shape[0] != entries or shape[1] != shape[2] or shape[3] != 3 or dtype != np.uint8:
            raise DatasetError(f"{file}: image is {shape} {dtype}; V-D4RL episodes hold ({entries}, S, S, 3) uint8")
        if not (action.ndim == 2 and reward.shape == first.shape == last.shape == np.shape(terminal) == (entries,)):
            raise DatasetError(f"{file}: action must be ({entries}, A) and every other key ({entries},)")
        if entries < 2 or not (first[0] and last[-1] and first.sum() == 1 and last.sum() == 1):
            raise DatasetError(
                f"{file}: is_first must mark only entry 0 and is_last only the final entry "
                f"(one episode of at least one transition per file, as V-D4RL writes them)"
            )
        if np.asarray(terminal, bool)[:-1].any():
            raise DatasetError(f"{file}: is_terminal is set before the final entry")
        _check_entries(file, action, reward, np.array([0]))
        sizes.update(file, shape[1], action.shape[1])
        episodes.append(SourceEpisode(((file, 0, entries),), bool(np.asarray(terminal, bool)[-1])))
    return VD4RLSource(path, "npz-episodes", tuple(files), sizes.image, sizes.action, tuple(episodes))


def _npy_header(file: Path, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of one array of an npz archive, without decompressing its data."""
    with zipfile.ZipFile(file) as archive, archive.open(f"{key}.npy") as member:
        version = np.lib.format.read_magic(member)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(member)
    return tuple(shape), np.dtype(dtype)


def _scan_shards(path: Path, files: list[Path]) -> VD4RLSource:
    episodes, sizes = [], _Sizes()
    carried: list[tuple[Path, int, int]] = []  # segments of an episode still open at the end of a shard
    for file in files:
        try:
            with h5py.File(file, "r") as f:
                missing = [key for key in SHARD_KEYS if not isinstance(f.get(key), h5py.Dataset)]
                if missing:
                    raise DatasetError(f"{file}: not a V-D4RL shard: no dataset {', '.join(missing)}")
                shape, dtype = f["observation"].shape, f["observation"].dtype
                action, reward, discount, step_type = (f[key][:] for key in SHARD_KEYS[1:])
        except OSError as err:
            raise DatasetError(f"{file}: not a readable HDF5 file ({_first_line(err)})") from None
        n = shape[0]
        if len(shape) != 4 or shape[1] != 3 or shape[2] != shape[3] or dtype != np.uint8:
            raise DatasetError(f"{file}: observation is {shape} {dtype}; V-D4RL shards hold (N, 3, S, S) uint8")
        if not (action.ndim == 2 and len(action) == n and reward.shape == discount.shape == step_type.shape == (n,)):
            raise DatasetError(f"{file}: action must be ({n}, A) and reward, discount, step_type ({n},)")
        if not np.isin(step_type, (0, 1, 2)).all():
            raise DatasetError(f"{file}: step_type holds values other than 0 (first), 1 (mid) and 2 (last)")
        sizes.update(file, shape[2], action.shape[1])
        start = 0 if carried else None  # first entry, in this shard, of the episode in progress
        next_row = 0  # the row after the last episode that ended in this shard
        for row in map(int, np.flatnonzero(step_type != 1)):
            if step_type[row] == 0:
                if start is not None:
                    begun = carried[0][:2] if carried else (file, start)
                    raise DatasetError(
                        f"{file} row {row}: an episode starts (step_type 0) before the one begun at "
                        f"{begun[0].name} row {begun[1]} has ended (step_type 2)"
                    )
                if row != next_row:
                    raise DatasetError(f"{file} rows {next_row}..{row - 1}: step_type 1 outside any episode")
                start = row
                continue
            if start is None:
                raise DatasetError(f"{file} row {row}: an episode ends (step_type 2) that never began (step_type 0)")
            segments = (*carried, (file, start, row + 1))
            if sum(stop - begin for _, begin, stop in segments) < 2:
                raise DatasetError(f"{file} row {row}: an episode of one entry (the reset) and no transition")
            episodes.append(SourceEpisode(segments, bool(discount[row] == 0)))  # dm_env: LAST with discount 0
            carried, start, next_row = [], None, row + 1
        if start is not None:
            carried.append((file, start, n))
        elif next_row < n:
            raise DatasetError(f"{file} rows {next_row}..{n - 1}: outside any episode (no step_type 0 begins them)")
        _check_entries(file, action, reward, np.flatnonzero(step_type == 0))
    if carried:
        raise DatasetError(f"{carried[0][0]} row {carried[0][1]}: the last episode never ends (no step_type 2)")
    if not episodes:
        raise DatasetError(f"{path}: the shards hold no episode")
    return VD4RLSource(path, "hdf5-shards", tuple(files), sizes.image, sizes.action, tuple(episodes))


class _Sizes:
    """Frame side and action size, which every file of a dataset must share."""

    def __init__(self) -> None:
        self._image: int | None = None
        self._action: int | None = None

    def update(self, file: Path, image: int, action: int) -> None:
        if self._image is None:
            self._image, self._action = int(image), int(action)
        elif (image, action) != (self._image, self._action):
            raise DatasetError(
                f"{file}: {image} x {image} frames and {action}-d actions, but earlier files have "
                f"{self._image} x {self._image} and {self._action}-d; one dataset per folder"
            )

    @property
    def image(self) -> int:
        assert self._image is not None
        return self._image

    @property
    def action(self) -> int:
        assert self._action is not None
        return self._action


def _check_entries(file: Path, action: np.ndarray, reward: np.ndarray, first_rows: np.ndarray) -> None:
    """Finite actions in [-1, 1] and rewards; the reset entries of episodes carry a zero action and reward."""
    if not (np.isfinite(action).all() and np.isfinite(reward).all()):
        raise DatasetError(f"{file}: actions or rewards are NaN or inf")
    if action.size and np.abs(action).max() > _ACTION_BOUND:
        raise DatasetError(f"{file}: actions reach {np.abs(action).max():g}, outside DMC's [-1, 1] box")
    bad = first_rows[(action[first_rows] != 0).any(axis=1) | (reward[first_rows] != 0)]
    if len(bad):
        raise DatasetError(
            f"{file} entry {int(bad[0])}: the first entry of an episode has a non-zero action or reward; V-D4RL's "
            f"first entry is the reset (zero action, zero reward), so this is not its step layout"
        )


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


# -- reading episodes ----------------------------------------------------------------------------------------


def iter_episodes(
    source: VD4RLSource, *, skip: int = 0, resize: int | None = None
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, bool]]:
    """Episodes ``skip, skip + 1, ...`` of ``source`` in our row convention.

    Yields ``(observations (T+1, S, S, 3) uint8, actions (T, A) float32, rewards (T,) float32, terminated)``:
    entry 0's zero action and reward are dropped, so row i is (image[i], action[i + 1], reward[i + 1]).
    ``resize`` (64) resizes every frame with OpenCV's area filter.
    """
    handles: dict[Path, h5py.File] = {}
    try:
        for episode in source.episodes[skip:]:
            parts = [_read_segment(source.layout, handles, *segment) for segment in episode.segments]
            frames, action, reward = (np.concatenate(arrays) for arrays in zip(*parts, strict=True))
            if resize is not None and frames.shape[1] != resize:
                frames = resize_frames(frames, resize)
            yield frames, action[1:].astype(np.float32), reward[1:].astype(np.float32), episode.terminated
    finally:
        for handle in handles.values():
            handle.close()


def _read_segment(
    layout: str, handles: dict[Path, h5py.File], file: Path, start: int, stop: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames (k, S, S, 3), actions (k, A) and rewards (k,) of entries ``start:stop`` of one file."""
    try:
        if layout == "npz-episodes":
            with np.load(file, allow_pickle=False) as data:
                return data["image"][start:stop], data["action"][start:stop], data["reward"][start:stop]
        if file not in handles:
            handles[file] = h5py.File(file, "r")
        f = handles[file]
        frames = f["observation"][start:stop].transpose(0, 2, 3, 1)  # channels last, as our frames are stored
        return np.ascontiguousarray(frames), f["action"][start:stop], f["reward"][start:stop]
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise DatasetError(f"{file}: cannot read entries {start}..{stop - 1} ({_first_line(err)})") from None


def resize_frames(frames: np.ndarray, size: int) -> np.ndarray:
    """(T, H, W, 3) uint8 frames resized to (T, size, size, 3) with OpenCV's area filter (averages source pixels)."""
    import cv2

    out = np.empty((len(frames), size, size, frames.shape[3]), np.uint8)
    for i, frame in enumerate(frames):
        out[i] = cv2.resize(frame, (size, size), interpolation=cv2.INTER_AREA)
    return out


# -- converting ----------------------------------------------------------------------------------------------


def _check_resumable(out: Path, task: str, fingerprint: str) -> None:
    """Refuse to resume ``out`` from other files or for another task, reading it only: a refused resume leaves the
    file byte for byte as it was (opening it for writing already changes its header)."""
    from coworld.data.reader import open_dataset

    with open_dataset(out) as data:
        theirs = data.metadata.get("collector") or {}
        if data.task != task:
            raise DatasetError(f"cannot resume {out}: it holds task {data.task}, not {task}; choose another --out")
        if data.num_episodes and theirs.get("source_fingerprint") != fingerprint:
            raise DatasetError(
                f"cannot resume {out}: it was imported from other files ({theirs.get('source_path')}); "
                f"pass --force to start over"
            )


def import_vd4rl(
    path: str | Path,
    out: str | Path | None = None,
    *,
    task: str,
    quality: str | None = None,
    resize: int | None = None,
    resume: bool = False,
    force: bool = False,
    compression: str = "gzip",
    progress: bool = False,
) -> ImportSummary:
    """Convert the V-D4RL dataset folder ``path`` into a format-v1 dataset of our task ``task``.

    Args:
        path: a V-D4RL folder of ``.npz`` episodes (its 64px layout) or ``.hdf5`` shards (its 84px layout).
        out: the dataset to write; default ``datasets/<task>-<quality>.h5``.
        task: our task the data belongs to (e.g. ``walker_walk``); its action size must match the data's.
        quality: the dataset's quality; default read from V-D4RL's folder name (``.../medium_replay/...``).
        resize: 64 resizes frames of another size to 64 x 64 (area filter); without it they are refused.
        resume: continue an interrupted import of the same folder into ``out`` (episodes are converted in a fixed
            order, so the ones already committed are skipped).
        force: replace an existing ``out``.
        compression: frame codec of the new file (see :data:`~coworld.data.schema.CODECS`).
        progress: show a progress bar.

    The provenance goes into the ``collector`` metadata (``algorithm: import`` and the ``source_*`` fields).
    """
    from coworld.envs import task_spec

    spec = task_spec(task)
    source = scan_vd4rl(path)
    if source.action_size != spec.action_size:
        raise DatasetError(
            f"{path}: actions have {source.action_size} dimensions but {task} takes {spec.action_size}; "
            f"pass the --task the data was recorded in (V-D4RL's walker_walk and cheetah_run have 6)"
        )
    side = IMAGE_SHAPE[0]
    if resize is not None and resize != side:
        raise ConfigError(f"--resize takes {side} (the frame size of coworld datasets), got {resize}")
    if source.image_size != side and resize is None:
        raise DatasetError(
            f"{path}: frames are {source.image_size} x {source.image_size} but coworld datasets hold {side} x {side}; "
            f"pass --resize {side} to resize them (area filter)"
        )
    named = source.described_by_path()
    quality = quality or named["quality"]
    if quality is None:
        raise ConfigError(f"{path}: its folder names no V-D4RL quality; say which with --quality")
    out = Path(out) if out is not None else default_dataset_path(task, quality)
    if resume and not force and out.exists():
        _check_resumable(out, task, source.fingerprint())
    resized = source.image_size != side
    collector = {
        "algorithm": "import",
        "source_format": f"vd4rl-{source.layout}",
        "source_path": str(source.path.resolve()),
        "source_env": named["env"],
        "source_files": len(source.files),
        "source_fingerprint": source.fingerprint(),
        "source_image_size": source.image_size,
        "resize": {"from": source.image_size, "to": side, "filter": RESIZE_FILTER} if resized else None,
        "steps": source.num_steps,
    }
    with new_dataset(
        out,
        task,
        quality=quality,
        collector=collector,
        action_size=spec.action_size,
        resume=resume,
        force=force,
        compression=compression,
    ) as writer:
        skip = writer.num_episodes
        if skip:
            theirs = writer.metadata.get("collector") or {}
            if theirs.get("source_fingerprint") != collector["source_fingerprint"]:
                raise DatasetError(
                    f"cannot resume {out}: it was imported from other files ({theirs.get('source_path')}); "
                    f"pass --force to start over"
                )
        episodes = iter_episodes(source, skip=skip, resize=side if resized else None)
        total = len(source.episodes)
        with progress_bar(total=total, initial=skip, desc="import", unit="episodes", enabled=progress) as bar:
            for frames, actions, rewards, terminated in episodes:
                writer.add_episode(frames, actions, rewards, terminated)
                bar.update()
        writer.close(complete=True)
    return ImportSummary(out, len(source.episodes), source.num_steps, skip)
