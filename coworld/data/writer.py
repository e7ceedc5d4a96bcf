"""Crash-safe, append-only dataset writer.

Episodes are appended whole. Each :meth:`DatasetWriter.add_episode` writes the rows, flushes the file, then bumps the
committed counters (``num_rows``, ``num_episodes``) and flushes again, so a ``kill -9`` at any moment loses at most
the episode being written: readers trust only the committed counters, and a resumed writer drops the rows past them.
A lock file (:mod:`coworld.data.lock`) keeps a second writer out.

A write the system refuses (a full disk, a read-only location) raises :class:`~coworld.errors.StorageError` and
leaves the file as the last commit left it. Before each episode the writer asks whether the file has room for it
(:func:`~coworld.storage.room_problem`), so a full disk is usually met before anything is written. A write that fails
anyway (another process filled the disk meanwhile) must fail at once: HDF5 keeps chunks in a per-dataset cache that
it writes when the dataset is closed, and h5py cannot raise from the deallocator of a short-lived dataset object, so
with the cache on, a failed write would print only "Exception ignored" while the counters were committed over data
that never reached the disk. So the chunk cache is off (each write reaches the file in the call that makes it, and
raises there), and the datasets stay open for the writer's life. After a refused write the writer touches the file
no more (even shrinking it back can drop committed chunks from HDF5's index) and never marks it complete; a resumed
writer drops the uncommitted rows.
"""

from __future__ import annotations

import glob
import json
import os
import platform
from collections.abc import Mapping
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType
from typing import Any

import h5py
import numpy as np

from coworld.data.lock import WriterLock
from coworld.data.schema import (
    CODECS,
    EPISODE_CHUNK,
    EPISODE_FIELDS,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAME_CHUNK,
    IMAGE_SHAPE,
    PLUGIN_CODECS,
    QUALITIES,
    ROW_CHUNK,
    ROW_FIELDS,
    STEP_KEYS,
    decode_attrs,
    episode_checksum,
    frame_filter,
    import_hdf5plugin,
    structural_problems,
)
from coworld.errors import ConfigError, DatasetError, StorageError
from coworld.storage import WRITE_ERRNOS, failure_errno, failure_reason, room_problem
from coworld.text import count

_VERSIONED_PACKAGES = ("coworld", "numpy", "h5py", "torch", "gymnasium", "mujoco", "dm-control", "metaworld", "pillow")
_SMALL_FILTER: dict[str, Any] = {}


def package_versions() -> dict[str, str]:
    """Versions of Python, HDF5 and the installed packages that shape the data (absent packages are skipped)."""
    versions = {"python": platform.python_version(), "hdf5": h5py.version.hdf5_version}
    for name in _VERSIONED_PACKAGES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            pass
    return versions


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


class DatasetWriter:
    """Append whole episodes to a dataset file, safely against crashes and concurrent writers.

    ``resume=True`` continues an existing file (a missing one is created); it must hold the same task, action size
    and image shape, and rows left by an interrupted episode are dropped. A file marked complete can be resumed too:
    it is marked incomplete again as soon as an episode is added (callers that know their target, like
    ``coworld collect``, refuse to resume a complete dataset that already holds it). An existing file is replaced
    only with ``force=True``. Use as a context manager, and call ``close(complete=True)`` once the target is reached.

    Args:
        path: the ``.h5`` file to write; parent folders are created.
        task: task name, e.g. ``walker_walk``.
        env_config: the full environment config (action repeat, image size, camera, modification, ...).
        quality: one of ``random, medium-replay, medium, medium-expert, expert``.
        collector: how the data was made (algorithm, preset, steps, seed, last_eval_return, ...).
        action_size: A, the width of ``actions``.
        image_shape: (H, W, C) of the frames.
        resume: continue an existing file instead of refusing to touch it.
        force: delete an existing file and start over.
        reference: returns that define the normalized score: ``{"random_return": r0, "reference_return": r1}``.
        compression: frame codec of a new file, one of ``gzip`` (default, stock h5py), ``none``, ``zstd``, ``lz4``
            (the last two need hdf5plugin); a resumed file keeps its own.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        task: str,
        env_config: Mapping[str, Any],
        quality: str,
        collector: Mapping[str, Any],
        action_size: int,
        image_shape: tuple[int, int, int] = IMAGE_SHAPE,
        resume: bool = False,
        force: bool = False,
        reference: Mapping[str, Any] | None = None,
        compression: str = "gzip",
    ) -> None:
        if quality not in QUALITIES:
            raise ConfigError(f"unknown dataset quality {quality!r}; choose one of: {', '.join(QUALITIES)}")
        if compression not in CODECS:
            raise ConfigError(f"unknown compression {compression!r}; choose one of: {', '.join(CODECS)}")
        if resume and force:
            raise ConfigError("resume and force exclude each other: resume continues a dataset, force replaces it")
        if int(action_size) < 1 or len(image_shape) != 3:
            raise ConfigError(f"bad dataset shape: action_size {action_size}, image_shape {image_shape}")
        self.path = Path(path)
        self.task = task
        self.action_size = int(action_size)
        self.image_shape = tuple(int(x) for x in image_shape)
        self._file: h5py.File | None = None
        self._nodes: dict[str, h5py.Dataset] = {}
        self._infos: dict[str, tuple[np.dtype, tuple[int, ...]]] | None = None
        self._marked_incomplete = False
        self._failure: StorageError | None = None
        if self.path.is_dir():
            raise DatasetError(
                f"{self.path} is a folder, not a dataset file; name a file such as {self.path / 'data.h5'}"
            )
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise self._refused(err, opening=True) from None
        self._lock = WriterLock(self.path)
        try:
            if self.path.exists() and not resume:
                if not force:
                    raise DatasetError(
                        f"{self.path} already exists; pass --resume to continue it or --force to overwrite it"
                    )
                self.path.unlink()
            if self.path.exists():
                self._file = self._open_existing()
            else:
                self._file = self._create(env_config, quality, collector, reference or {}, compression)
            self._open_nodes()
        except BaseException:
            if self._file is not None:
                _close_quietly(self._file)
            self._lock.release()
            raise

    # -- opening ---------------------------------------------------------------------------------------------

    def _create(
        self,
        env_config: Mapping[str, Any],
        quality: str,
        collector: Mapping[str, Any],
        reference: Mapping[str, Any],
        compression: str,
    ) -> h5py.File:
        # Built under a temporary name and renamed into place: the path never names a half-made file. A process
        # killed between the two left its temporary file (``<name>.<pid>.tmp``): this one replaces what it made.
        for leftover in self.path.parent.glob(f"{glob.escape(self.path.name)}.*.tmp"):
            if leftover.name[len(self.path.name) + 1 : -len(".tmp")].isdigit():
                leftover.unlink(missing_ok=True)
        tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.tmp")
        try:
            self._build(tmp, env_config, quality, collector, reference, compression)
            os.replace(tmp, self.path)
        except BaseException as err:
            tmp.unlink(missing_ok=True)
            if isinstance(err, (OSError, RuntimeError)) and failure_errno(err) in WRITE_ERRNOS:
                raise self._refused(err, opening=True) from None
            raise
        self._marked_incomplete = True
        return h5py.File(self.path, "r+", rdcc_nbytes=0)

    def _build(
        self,
        tmp: Path,
        env_config: Mapping[str, Any],
        quality: str,
        collector: Mapping[str, Any],
        reference: Mapping[str, Any],
        compression: str,
    ) -> None:
        """Create every dataset (empty, resizable, chunked) and the metadata in a new file at ``tmp``."""
        frames = frame_filter(compression)
        # fs_strategy "none": space freed when a compressed chunk is rewritten is never reused, so data that
        # the on-disk chunk index still points to is never overwritten before the index itself is flushed.
        with h5py.File(tmp, "w", fs_strategy="none") as f:
            h, w, c = self.image_shape
            for name, dtype in ROW_FIELDS.items():
                if name == "observations":
                    shape, chunks, kwargs = (h, w, c), (FRAME_CHUNK, h, w, c), frames
                else:
                    shape = (self.action_size,) if name == "actions" else ()
                    chunks, kwargs = (ROW_CHUNK, *shape), _SMALL_FILTER
                f.create_dataset(name, (0, *shape), dtype, maxshape=(None, *shape), chunks=chunks, **kwargs)
            episodes = f.create_group("episodes")
            for name, dtype in EPISODE_FIELDS.items():
                if name == "final_observations":  # one frame per chunk: an append or a read touches only its own
                    shape, chunks, kwargs = (h, w, c), (1, h, w, c), frames
                else:
                    shape, chunks, kwargs = (), (EPISODE_CHUNK,), _SMALL_FILTER
                episodes.create_dataset(name, (0, *shape), dtype, maxshape=(None, *shape), chunks=chunks, **kwargs)
            f.create_group("infos")
            created = _now()
            f.attrs.update(
                {
                    "format": FORMAT_NAME,
                    "format_version": FORMAT_VERSION,
                    "task": self.task,
                    "quality": quality,
                    "complete": False,
                    "num_rows": 0,
                    "num_episodes": 0,
                    "action_size": self.action_size,
                    "image_shape": np.asarray(self.image_shape, np.int64),
                    "compression": compression,
                    "created": created,
                    "updated": created,
                    "env_config": _to_json(env_config, "env_config"),
                    "collector": _to_json(collector, "collector"),
                    "reference": _to_json(reference, "reference"),
                    "versions": json.dumps(package_versions(), sort_keys=True),
                }
            )

    def _open_existing(self) -> h5py.File:
        try:
            f = h5py.File(self.path, "r+", rdcc_nbytes=0)
        except OSError as err:
            if failure_errno(err) in WRITE_ERRNOS:
                raise self._refused(err, opening=True) from None
            if "unable to lock file" in str(err) or "already open" in str(err):
                raise DatasetError(
                    f"cannot resume {self.path}: it is open elsewhere (a reader holds HDF5's file lock); "
                    f"close it and retry"
                ) from None
            raise DatasetError(f"cannot resume {self.path}: not a readable HDF5 file ({_first_line(err)})") from None
        try:
            if f.attrs.get("compression") in PLUGIN_CODECS:
                import_hdf5plugin(str(f.attrs["compression"]))
            problems = structural_problems(f)
            if problems:
                raise DatasetError(f"cannot resume {self.path}: {problems[0]}")
            meta = decode_attrs(f.attrs)
            theirs = (meta["task"], int(meta["action_size"]), tuple(meta.get("image_shape", IMAGE_SHAPE)))
            ours = (self.task, self.action_size, self.image_shape)
            if theirs != ours:
                raise DatasetError(
                    f"cannot resume {self.path}: it holds task {theirs[0]} with action size {theirs[1]} and images "
                    f"{theirs[2]}, not task {ours[0]} with action size {ours[1]} and images {ours[2]}; "
                    f"choose another --out or pass --force to overwrite it"
                )
            try:
                self._drop_uncommitted(f)
            except (OSError, RuntimeError) as err:
                if failure_errno(err) not in WRITE_ERRNOS:
                    raise
                raise self._refused(err, opening=True) from None
            infos = {name: (node.dtype, node.shape[1:]) for name, node in f["infos"].items()}
            # An empty dataset has not fixed its infos keys yet; one with rows has (possibly to none).
            self._infos = infos if infos or int(f.attrs["num_rows"]) > 0 else None
        except BaseException:
            f.close()
            raise
        return f

    def _open_nodes(self) -> None:
        """Open every dataset once, for the writer's whole life (see the module docstring)."""
        f = self._handle()
        self._nodes = {name: f[name] for name in ROW_FIELDS}
        self._nodes.update({f"episodes/{name}": f["episodes"][name] for name in EPISODE_FIELDS})
        self._nodes.update({f"infos/{name}": node for name, node in f["infos"].items()})

    def _bytes_needed(self, obs: np.ndarray, act: np.ndarray, extras: dict[str, np.ndarray]) -> int:
        """An upper bound of the bytes an episode adds to the file: its raw data, a rewritten partial chunk of each
        frame dataset (rows and final frames), and room for HDF5's own records."""
        frame = int(np.prod(self.image_shape))
        raw = obs.nbytes + act.nbytes + len(act) * 16 + sum(value.nbytes for value in extras.values())
        return raw + (FRAME_CHUNK + 1) * frame + 2**20

    def _refused(self, err: BaseException, *, opening: bool = False) -> StorageError:
        """The one-line error of a write the system refused; after it the writer writes nothing more."""
        reason = failure_reason(err)
        text = reason  # or the refusal of room_problem, which says how much room there was
        if isinstance(err, OSError) and err.strerror and err.strerror.startswith(reason):
            text = err.strerror
        if opening:
            return StorageError(f"cannot write {self.path}: {text}", reason)
        committed = self.num_episodes
        kept = f"{count(committed, 'committed episode')} {'is' if committed == 1 else 'are'} intact"
        self._failure = StorageError(f"cannot write {self.path}: {text}; {kept}", reason)
        return self._failure

    @staticmethod
    def _drop_uncommitted(f: h5py.File) -> None:
        """Shrink every dataset to the committed counts (undoes an episode a killed writer left half-written)."""
        n, e = int(f.attrs["num_rows"]), int(f.attrs["num_episodes"])
        for name in ROW_FIELDS:
            if f[name].shape[0] != n:
                f[name].resize(n, axis=0)
        for node in f["infos"].values():
            if node.shape[0] != n:
                node.resize(n, axis=0)
        for name in EPISODE_FIELDS:
            if f["episodes"][name].shape[0] != e:
                f["episodes"][name].resize(e, axis=0)
        f.flush()

    # -- writing ---------------------------------------------------------------------------------------------

    @property
    def num_steps(self) -> int:
        """Committed rows (transitions)."""
        return int(self._handle().attrs["num_rows"])

    @property
    def num_episodes(self) -> int:
        """Committed episodes."""
        return int(self._handle().attrs["num_episodes"])

    @property
    def complete(self) -> bool:
        """The file's complete flag as it stands."""
        return bool(self._handle().attrs["complete"])

    @property
    def metadata(self) -> dict[str, Any]:
        """The file's root attributes as plain values (JSON fields such as ``collector`` parsed)."""
        return decode_attrs(self._handle().attrs)

    def returns(self) -> np.ndarray:
        """Returns of the committed episodes, shape (E,) float64."""
        return self._handle()["episodes/returns"][: self.num_episodes]

    def add_episode(
        self,
        observations: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        terminated: bool,
        infos: Mapping[str, np.ndarray] | None = None,
        collector: Mapping[str, Any] | None = None,
    ) -> None:
        """Append one whole episode of T transitions and commit it.

        Args:
            observations: (T+1, H, W, C) uint8, o_0 .. o_T including the final frame.
            actions: (T, A), a_t taken at o_t.
            rewards: (T,), r_t earned by a_t.
            terminated: the episode ended in a true terminal state (else it was cut by a time limit).
            infos: optional per-step extras, each (T, ...) (e.g. ``success``, ``behavior_log_prob``); every episode
                of a dataset must carry the same keys.
            collector: fields merged into the ``collector`` record in the episode's commit, so that a count it keeps
                of the episodes (a random collection's ``steps``) is never behind them, whenever the writer stops.
        """
        f = self._handle()
        obs = np.asarray(observations)
        t = obs.shape[0] - 1
        if obs.dtype != np.uint8 or obs.shape[1:] != self.image_shape or t < 1:
            raise DatasetError(
                f"observations must be (T+1, {', '.join(map(str, self.image_shape))}) uint8 with T >= 1, "
                f"got {obs.shape} {obs.dtype}"
            )
        act = np.asarray(actions, dtype=np.float32)
        rew = np.asarray(rewards, dtype=np.float32)
        if act.shape != (t, self.action_size) or rew.shape != (t,):
            raise DatasetError(
                f"an episode of {t + 1} frames needs actions ({t}, {self.action_size}) and rewards ({t},), "
                f"got {act.shape} and {rew.shape}"
            )
        if not (np.isfinite(act).all() and np.isfinite(rew).all()):
            raise DatasetError("episode has non-finite actions or rewards; refusing to store it")
        extras = self._check_infos(infos or {}, t)
        record = None if collector is None else _to_json({**json.loads(f.attrs["collector"]), **collector}, "collector")
        n, e = self.num_steps, self.num_episodes
        problem = room_problem(self.path, self._bytes_needed(obs, act, extras))
        if problem is not None:  # refused before a byte is written: the file stays as the last commit left it
            raise self._refused(problem) from None
        try:
            self._write_episode(f, n, e, obs, act, rew, bool(terminated), extras, record)
        except (OSError, RuntimeError) as err:
            if failure_errno(err) not in WRITE_ERRNOS:
                raise
            raise self._refused(err) from None

    def _write_episode(
        self,
        f: h5py.File,
        n: int,
        e: int,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        terminated: bool,
        extras: dict[str, np.ndarray],
        record: str | None = None,
    ) -> None:
        """Write the rows and the episode record at rows ``n ..`` and episode ``e``, flush, then commit (with the
        ``collector`` record ``record``, where given)."""
        t = len(act)
        if not self._marked_incomplete:
            f.attrs["complete"] = False
            self._marked_incomplete = True
        last = np.zeros(t, bool)
        last[-1] = True
        rows: dict[str, np.ndarray] = {
            "observations": obs[:-1],
            "actions": act,
            "rewards": rew,
            "terminals": last & bool(terminated),
            "timeouts": last & (not terminated),
            "episode_ids": np.full(t, e, np.int32),
            "is_first": np.arange(t) == 0,
        }
        for name, value in rows.items():
            _append(self._nodes[name], n, value)
        for name, value in extras.items():
            _append(self._nodes[f"infos/{name}"], n, value)
        episode = {
            "starts": np.array([n], np.int64),
            "lengths": np.array([t], np.int64),
            "returns": np.array([rew.sum(dtype=np.float64)]),
            "terminated": np.array([terminated], bool),
            "final_observations": obs[-1:],
            "checksums": np.array([episode_checksum(obs, act, rew)], np.uint32),
        }
        for name, value in episode.items():
            _append(self._nodes[f"episodes/{name}"], e, value)
        f.flush()  # the data is on disk before the counters say it is there
        f.attrs["num_rows"] = n + t
        f.attrs["num_episodes"] = e + 1
        if record is not None:
            f.attrs["collector"] = record
        f.attrs["updated"] = _now()
        f.flush()

    def _check_infos(self, infos: Mapping[str, np.ndarray], t: int) -> dict[str, np.ndarray]:
        arrays = {name: np.asarray(value) for name, value in infos.items()}
        for name, value in arrays.items():
            if name in STEP_KEYS or "/" in name:
                raise DatasetError(f"infos key {name!r} is reserved or contains '/'")
            if value.ndim < 1 or value.shape[0] != t:
                raise DatasetError(f"infos[{name!r}] must have {t} rows (one per action), got shape {value.shape}")
            if value.dtype.kind == "f" and not np.isfinite(value).all():
                raise DatasetError(f"infos[{name!r}] has non-finite values; refusing to store it")
        if self._infos is None:  # the first episode fixes the keys
            f = self._handle()
            for name, value in arrays.items():
                shape = value.shape[1:]
                self._nodes[f"infos/{name}"] = f["infos"].create_dataset(
                    name, (0, *shape), value.dtype, maxshape=(None, *shape), chunks=(ROW_CHUNK, *shape), **_SMALL_FILTER
                )
            self._infos = {name: (value.dtype, value.shape[1:]) for name, value in arrays.items()}
        if set(arrays) != set(self._infos):
            raise DatasetError(
                f"episode infos keys {sorted(arrays)} differ from the dataset's {sorted(self._infos)}; "
                f"every episode must carry the same infos"
            )
        return {name: value.astype(self._infos[name][0], copy=False) for name, value in arrays.items()}

    def keep_episodes(self, episodes: int) -> None:
        """Keep the first ``episodes`` committed episodes and drop the rest, as a resumed writer drops a killed one's
        uncommitted rows (a two-phase run's source replay cut back to its agent's checkpoint)."""
        f = self._handle()
        if not 0 <= episodes <= self.num_episodes:
            raise ValueError(f"cannot keep {episodes} of {self.num_episodes} episodes")
        if episodes == self.num_episodes:
            return
        rows = int(self._nodes["episodes/starts"][episodes])
        try:
            f.attrs["num_rows"] = rows
            f.attrs["num_episodes"] = episodes
            f.attrs["updated"] = _now()
            self._drop_uncommitted(f)
        except (OSError, RuntimeError) as err:
            if failure_errno(err) not in WRITE_ERRNOS:
                raise
            raise self._refused(err) from None

    def update_metadata(self, **collector_fields: Any) -> None:
        """Merge fields into the ``collector`` record (e.g. ``last_eval_return=512.0``, ``stop_reason="steps"``)."""
        f = self._handle()
        collector = json.loads(f.attrs["collector"])
        collector.update(collector_fields)
        try:
            f.attrs["collector"] = _to_json(collector, "collector")
            f.attrs["updated"] = _now()
            f.flush()
        except (OSError, RuntimeError) as err:
            if failure_errno(err) not in WRITE_ERRNOS:
                raise
            raise self._refused(err) from None

    # -- closing ---------------------------------------------------------------------------------------------

    def close(self, complete: bool | None = None) -> None:
        """Set the complete flag (None keeps it), flush, close the file and release the lock. Idempotent.

        The flag is set only once everything before it is on disk; after a refused write it is never set, and the
        file is closed as it is (HDF5 may still report the buffered data it cannot write; that is ignored).
        """
        if self._file is None:
            return
        f, self._nodes = self._file, {}
        try:
            if self._failure is not None:
                _close_quietly(f)
                return
            try:
                f.flush()
                if complete is not None:
                    f.attrs["complete"] = bool(complete)
                    f.attrs["updated"] = _now()
                    f.flush()
            except (OSError, RuntimeError) as err:
                if failure_errno(err) not in WRITE_ERRNOS:
                    raise
                error = self._refused(err)
                _close_quietly(f)
                raise error from None
            f.close()
        finally:
            self._file = None
            self._lock.release()

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _handle(self) -> h5py.File:
        if self._failure is not None:
            raise self._failure
        if self._file is None:
            raise DatasetError(f"the writer of {self.path} is closed")
        return self._file


def _append(node: h5py.Dataset, at: int, value: np.ndarray) -> None:
    """Write ``value`` (k, ...) at rows ``at .. at+k`` of a resizable dataset, growing it (one contiguous write)."""
    node.resize(at + len(value), axis=0)
    node[at : at + len(value)] = value


def _close_quietly(f: h5py.File) -> None:
    """Close a file whose writes have failed; HDF5 reports the data it still cannot write, which is known."""
    try:
        f.close()
    except (OSError, RuntimeError):
        pass


def _to_json(value: Mapping[str, Any], name: str) -> str:
    try:
        return json.dumps(dict(value), sort_keys=True, default=_json_default)
    except (TypeError, ValueError) as err:
        raise DatasetError(f"{name} must be JSON-serialisable: {err}") from None


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON-serialisable")


def _first_line(err: BaseException) -> str:
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
