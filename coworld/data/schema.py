"""Dataset format v1: names, dtypes, chunking, compression and the structural checks shared by reader and verifier.

A dataset is one HDF5 file. Row ``i`` of the D4RL-style top level is the transition ``(o_i, a_i, r_i)``: action
``a_i`` was taken at observation ``o_i`` and earned reward ``r_i``. Episodes are stored back to back; episode ``e``
covers rows ``starts[e] : starts[e] + lengths[e]`` and its final frame ``o_T`` (the observation after the last
action) lives once in ``episodes/final_observations[e]``, so no frame is stored twice. Root attributes carry the
metadata; ``num_rows`` / ``num_episodes`` count what was committed (a writer killed mid-episode may leave rows past
``num_rows``, which readers ignore). ``datasets/README.md`` documents every field.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Mapping
from typing import Any

import h5py
import numpy as np

from coworld.errors import ConfigError, DatasetError

FORMAT_NAME = "coworld-dataset"
FORMAT_VERSION = 1
QUALITIES = ("random", "medium-replay", "medium", "medium-expert", "expert")
IMAGE_SHAPE = (64, 64, 3)

# Frames per chunk of `observations`: a 50-step window touches 4-5 chunks (see datasets/README.md, "Compression").
FRAME_CHUNK = 16
# Rows per chunk of the small per-step arrays (actions, rewards, flags, infos); these are read whole at open.
ROW_CHUNK = 4096
# Episodes per chunk of the per-episode arrays (starts, lengths, returns, ...).
EPISODE_CHUNK = 1024
# Stock HDF5 filters open everywhere; "zstd" and "lz4" need `pip install hdf5plugin` to write and to read.
CODECS = ("gzip", "none", "zstd", "lz4")
PLUGIN_CODECS = ("zstd", "lz4")

# Per-row datasets at the top level: name -> dtype (shape (N,) or (N, A) or (N, H, W, C)).
ROW_FIELDS: dict[str, np.dtype] = {
    "observations": np.dtype(np.uint8),
    "actions": np.dtype(np.float32),
    "rewards": np.dtype(np.float32),
    "terminals": np.dtype(bool),
    "timeouts": np.dtype(bool),
    "episode_ids": np.dtype(np.int32),
    "is_first": np.dtype(bool),
}
# Per-episode datasets in the `episodes/` group: name -> dtype (shape (E,) or (E, H, W, C)).
EPISODE_FIELDS: dict[str, np.dtype] = {
    "starts": np.dtype(np.int64),
    "lengths": np.dtype(np.int64),
    "returns": np.dtype(np.float64),
    "terminated": np.dtype(bool),
    "final_observations": np.dtype(np.uint8),
    "checksums": np.dtype(np.uint32),
}
REQUIRED_ATTRS = ("format", "format_version", "task", "quality", "complete", "num_rows", "num_episodes", "action_size")
JSON_ATTRS = ("env_config", "collector", "reference", "versions")
# Keys of the step-convention dicts (sampler batches, Dataset.episode); infos may not reuse them.
STEP_KEYS = ("image", "action", "reward", "is_first", "is_last", "is_terminal")


def frame_filter(codec: str) -> dict[str, Any]:
    """h5py ``create_dataset`` keyword arguments that compress frames with ``codec`` (one of :data:`CODECS`)."""
    if codec == "gzip":
        return {"compression": "gzip", "compression_opts": 4}
    if codec == "none":
        return {}
    if codec in PLUGIN_CODECS:
        hdf5plugin = import_hdf5plugin(codec)
        if codec == "zstd":
            return dict(hdf5plugin.Zstd(clevel=3))
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.NOSHUFFLE))
    raise ConfigError(f"unknown compression {codec!r}; choose one of: {', '.join(CODECS)}")


def import_hdf5plugin(codec: str) -> Any:
    """Import ``hdf5plugin`` (registers the zstd / lz4 filters with HDF5) or fail with an install hint."""
    try:
        import hdf5plugin
    except ImportError:
        raise DatasetError(f"compression {codec!r} needs the hdf5plugin package: pip install hdf5plugin") from None
    return hdf5plugin


def episode_checksum(observations: np.ndarray, actions: np.ndarray, rewards: np.ndarray) -> int:
    """CRC-32 of one episode's bytes: frames ``(T+1, H, W, C)`` uint8 incl. the final one, actions, rewards."""
    crc = zlib.crc32(np.ascontiguousarray(observations, dtype=np.uint8))
    crc = zlib.crc32(np.ascontiguousarray(actions, dtype="<f4"), crc)
    return zlib.crc32(np.ascontiguousarray(rewards, dtype="<f4"), crc)


def decode_attrs(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Root attributes as plain Python values: JSON attributes parsed, NumPy scalars unwrapped."""
    out: dict[str, Any] = {}
    for key, value in attrs.items():
        if isinstance(value, bytes):
            value = value.decode()
        if key in JSON_ATTRS and isinstance(value, str):
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                pass  # structural_problems reports it
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, np.generic):
            value = value.item()
        out[key] = value
    return out


def structural_problems(f: h5py.File) -> list[str]:
    """Everything wrong with the layout of an open dataset file, cheaply (no frame is read).

    Checks the format attributes, the presence, dtype and shape of every dataset, and that the per-episode index
    (starts, lengths) tiles the committed rows. Later checks are skipped when an earlier one makes them meaningless.
    """
    attrs = f.attrs
    if attrs.get("format") != FORMAT_NAME:
        return [f"not a {FORMAT_NAME} file (root attribute 'format' is {attrs.get('format')!r})"]
    version = int(attrs.get("format_version", -1))
    if version > FORMAT_VERSION:
        return [f"format version {version} is newer than this coworld reads ({FORMAT_VERSION}); upgrade coworld"]
    problems = [f"missing root attribute {name!r}" for name in REQUIRED_ATTRS if name not in attrs]
    for name in JSON_ATTRS:
        if name in attrs:
            try:
                json.loads(attrs[name])
            except (TypeError, ValueError):
                problems.append(f"root attribute {name!r} is not valid JSON")
    if problems:
        return problems
    quality = attrs["quality"]
    if quality not in QUALITIES:
        problems.append(f"quality {quality!r} is not one of {', '.join(QUALITIES)}")
    n, e, a = int(attrs["num_rows"]), int(attrs["num_episodes"]), int(attrs["action_size"])
    image_shape = tuple(int(x) for x in attrs.get("image_shape", IMAGE_SHAPE))
    expected = {
        "observations": (n, *image_shape),
        "actions": (n, a),
        **{name: (n,) for name in ("rewards", "terminals", "timeouts", "episode_ids", "is_first")},
    }
    for name, dtype in ROW_FIELDS.items():
        problems += _dataset_problems(f, name, dtype, expected[name])
    for name, dtype in EPISODE_FIELDS.items():
        shape = (e, *image_shape) if name == "final_observations" else (e,)
        problems += _dataset_problems(f, f"episodes/{name}", dtype, shape)
    if "infos" in f:
        for name, node in f["infos"].items():
            if not isinstance(node, h5py.Dataset) or node.ndim < 1 or node.shape[0] < n:
                problems.append(f"infos/{name} must be a dataset with at least num_rows = {n} rows")
            elif name in STEP_KEYS:
                problems.append(f"infos/{name} reuses a reserved step key")
    if problems:
        return problems
    lengths = f["episodes/lengths"][:e]
    starts = f["episodes/starts"][:e]
    if e and lengths.min() < 1:
        problems.append(f"episode {int(np.argmin(lengths))} has length {int(lengths.min())} (must be >= 1)")
    elif int(lengths.sum()) != n:
        problems.append(f"episode lengths sum to {int(lengths.sum())} but num_rows is {n}")
    elif e and not np.array_equal(starts, np.concatenate([[0], np.cumsum(lengths)[:-1]])):
        problems.append("episodes/starts is not the running sum of episodes/lengths")
    return problems


def _dataset_problems(f: h5py.File, name: str, dtype: np.dtype, shape: tuple[int, ...]) -> list[str]:
    """Problems of one dataset: missing, wrong dtype, wrong trailing shape, fewer rows than committed."""
    node = f.get(name)
    if not isinstance(node, h5py.Dataset):
        return [f"missing dataset {name!r}"]
    if node.dtype != dtype:
        return [f"{name} has dtype {node.dtype}, expected {dtype}"]
    if node.shape[1:] != shape[1:] or node.ndim != len(shape):
        want = ", ".join(["N", *map(str, shape[1:])])
        return [f"{name} has shape {node.shape}, expected ({want})"]
    if node.shape[0] < shape[0]:
        return [f"{name} has {node.shape[0]} rows but {shape[0]} are committed"]
    return []
