"""Export a dataset to the formats other offline-RL code reads: Minari, and dreamer-style npz episodes.

* Minari 0.5 (Farama's successor of D4RL): ``<MINARI_DATASETS_PATH>/<namespace>/<name>-v<N>/data/`` holding
  ``metadata.json`` and ``main_data.hdf5``, one group ``episode_<id>`` per episode with ``observations`` (T+1, ...),
  ``actions`` (T, ...), ``rewards``, ``terminations``, ``truncations`` (T,) and ``infos/``. Written with Minari's
  own storage class and JPEG encoding off, so the frames stay bit-exact. ``minari.load_dataset(name)`` opens it.
* npz episodes: one ``np.savez_compressed`` file per episode with V-D4RL's 64px keys (``image``, ``action``,
  ``reward``, ``discount``, ``is_first``, ``is_last``, ``is_terminal``, T+1 entries each, entry 0 the reset with a
  zero action and reward), named ``<time>-<index>-<T+1>.npz`` so ``sorted()`` gives the dataset's episode order and
  the last field is the entry count, as in V-D4RL's released files.

Both are built under a temporary name next to their destination and renamed into place when whole.
"""

from __future__ import annotations

import io
import os
import shutil
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from coworld.data.api import episode_record, incomplete_text, resolve_dataset
from coworld.data.reader import Dataset, open_dataset
from coworld.errors import CoworldError, DatasetError
from coworld.progress import progress_bar

MINARI_HINT = "pip install 'coworld[minari]' (or: pip install minari)"
EXPORT_FORMATS = ("minari", "npz-episodes")


def default_minari_name(task: str, quality: str) -> str:
    """``coworld/<task>/<quality>-v0``, e.g. ``coworld/walker_uphill/medium-replay-v0``."""
    return f"coworld/{task}/{quality}-v0"


def step_episode(data: Dataset, i: int) -> dict[str, np.ndarray]:
    """Episode ``i`` in V-D4RL's npz layout: T+1 entries of ``image``, ``action``, ``reward``, ``discount``,
    ``is_first``, ``is_last``, ``is_terminal`` (discount 0 only at the final entry of a terminated episode)."""
    step = data.episode(i)
    return {
        "image": step["image"],
        "action": step["action"],
        "reward": step["reward"],
        "discount": np.where(step["is_terminal"], 0.0, 1.0).astype(np.float32),
        "is_first": step["is_first"],
        "is_last": step["is_last"],
        "is_terminal": step["is_terminal"],
    }


# -- npz episodes --------------------------------------------------------------------------------------------


def export_npz_episodes(
    path_or_name: str | Path,
    out: str | Path,
    *,
    force: bool = False,
    progress: bool = False,
    incomplete: bool = False,
    warn: Callable[[str], None] | None = None,
) -> Path:
    """Write every episode of a dataset as a dreamer-style npz file into the new folder ``out``; returns ``out``.

    A dataset whose collection did not finish is refused unless ``incomplete`` (then ``warn`` is told)."""
    out = Path(out)
    with open_dataset(resolve_dataset(path_or_name)) as data:
        check_complete(data, incomplete, warn)
        _check_destination(out, force, "folder")
        _remove_stale_temporaries(out)
        tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
        width = max(6, len(str(data.num_episodes - 1)))
        try:
            for i in progress_bar(range(data.num_episodes), desc="export", unit="episodes", enabled=progress):
                episode = step_episode(data, i)
                buffer = io.BytesIO()
                np.savez_compressed(buffer, **episode)
                (tmp / f"{stamp}-{i:0{width}d}-{len(episode['reward'])}.npz").write_bytes(buffer.getvalue())
            _replace(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return out


# -- Minari --------------------------------------------------------------------------------------------------


def import_minari() -> Any:
    """The ``minari`` package, or one line saying how to install it."""
    try:
        import minari
    except ImportError:
        raise CoworldError(f"exporting to Minari needs the minari package: {MINARI_HINT}") from None
    return minari


def export_minari(
    path_or_name: str | Path,
    name: str | None = None,
    *,
    force: bool = False,
    progress: bool = False,
    author: str | None = None,
    author_email: str | None = None,
    code_permalink: str | None = None,
    incomplete: bool = False,
    warn: Callable[[str], None] | None = None,
) -> str:
    """Write a dataset as the Minari dataset ``name`` (default ``coworld/<task>/<quality>-v0``); returns the name.

    The dataset lands in Minari's root (``MINARI_DATASETS_PATH``, default ``~/.minari/datasets``). Its metadata
    holds Gymnasium spaces (``Box(0, 255, (64, 64, 3), uint8)`` frames, ``Box(-1, 1, (A,), float32)`` actions),
    ``ref_min_score`` / ``ref_max_score`` from our reference returns (so ``minari.get_normalized_score`` works),
    ``env_spec`` and ``eval_env_spec`` = ``coworld/<task>-v0`` for a registered task (so
    ``recover_environment()`` makes it, with or without ``eval_env=True``), and everything of ours under ``coworld``
    (task, quality, env config, collector, reference, versions, source file). Each episode carries its return and
    reward statistics (``rewards_sum``, ``rewards_mean``, ... as Minari's data collector records them). Infos are
    padded to T+1 entries as Minari records them (entry 0, the reset's, is zero; entry j is the info of the step
    taken by a_{j-1}).
    """
    minari = import_minari()
    import gymnasium as gym
    from minari.data_collector import EpisodeBuffer
    from minari.data_collector.callbacks import EpisodeMetadataCallback
    from minari.dataset.minari_dataset import parse_dataset_id
    from minari.dataset.minari_storage import MinariStorage
    from minari.namespace import create_namespace, list_local_namespaces, validate_namespace

    if name is not None and not name.strip():
        raise CoworldError("--name is empty; give a Minari dataset id such as coworld/walker_walk/medium-replay-v0")
    source = resolve_dataset(path_or_name)
    with open_dataset(source) as data:
        check_complete(data, incomplete, warn)
        name = name or default_minari_name(data.task, data.quality)
        try:
            namespace, _, _ = parse_dataset_id(name)
            validate_namespace(namespace)
        except (ValueError, TypeError):
            raise CoworldError(
                f"bad Minari dataset name {name!r}: write it as namespace/name-v<version>, "
                f"e.g. {default_minari_name(data.task, data.quality)}"
            ) from None
        final = minari_path(name)
        _check_destination(final, force, "Minari dataset", f", or remove it first with `minari delete {name}`")
        if namespace is not None and namespace not in list_local_namespaces():
            create_namespace(namespace)
        _remove_stale_temporaries(final)
        tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        try:
            storage = MinariStorage.new(
                tmp / "data",
                observation_space=gym.spaces.Box(0, 255, data.image_shape, np.uint8),
                action_space=gym.spaces.Box(-1.0, 1.0, (data.action_size,), np.float32),
                jpeg_encoding=False,
            )
            storage.update_metadata(
                _minari_metadata(data, name, minari.__version__, author, author_email, code_permalink)
            )
            episode_stats, summarize = [], EpisodeMetadataCallback()
            for i in progress_bar(range(data.num_episodes), desc="export", unit="episodes", enabled=progress):
                episode = episode_record(data, i)
                infos = {
                    key: np.concatenate([np.zeros((1, *value.shape[1:]), value.dtype), value])
                    for key, value in episode.infos.items()
                }
                buffer = EpisodeBuffer(
                    observations=episode.observations,
                    actions=episode.actions,
                    rewards=episode.rewards,
                    terminations=episode.terminations,
                    truncations=episode.truncations,
                    infos=infos,
                )
                storage.update_episodes([buffer])
                episode_stats.append(summarize({"rewards": episode.rewards}))
            storage.update_episode_metadata(episode_stats)  # what Minari's DataCollector adds: rewards_sum, ...
            _replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return name


def minari_path(name: str) -> Path:
    """The folder of the Minari dataset ``name`` (in ``MINARI_DATASETS_PATH``, default ``~/.minari/datasets``)."""
    from minari.storage.datasets_root_dir import get_dataset_path

    return Path(get_dataset_path(name))


def _minari_metadata(
    data: Dataset,
    name: str,
    minari_version: str,
    author: str | None,
    author_email: str | None,
    code_permalink: str | None,
) -> dict[str, Any]:
    """The dataset-level fields ``minari.create_dataset_from_buffers`` records, plus ours under ``coworld``."""
    import gymnasium as gym

    from coworld.envs.gym_registration import env_id

    meta = data.metadata
    collector = meta.get("collector") or {}
    reference = data.reference
    fields: dict[str, Any] = {
        "dataset_id": name,
        "minari_version": minari_version,
        "algorithm_name": str(collector.get("algorithm", "unknown")),
        "description": (
            f"coworld {data.quality} dataset of the pixel task {data.task}: {data.num_episodes} episodes, "
            f"{data.num_steps} steps, {data.image_shape[0]} x {data.image_shape[1]} RGB observations"
        ),
        "coworld": {
            "task": data.task,
            "quality": data.quality,
            "format_version": meta.get("format_version"),
            "env_config": meta.get("env_config"),
            "collector": collector,
            "reference": reference,
            "versions": meta.get("versions"),
            "created": meta.get("created"),
            "source": str(data.path.resolve()),
        },
    }
    if "random_return" in reference and "reference_return" in reference:
        fields["ref_min_score"] = float(reference["random_return"])
        fields["ref_max_score"] = float(reference["reference_return"])
    if env_id(data.task) in gym.registry:  # the task the data came from, and the one to evaluate in
        fields["env_spec"] = fields["eval_env_spec"] = gym.spec(env_id(data.task)).to_json()
    optional = {"author": author and {author}, "author_email": author_email and {author_email}}
    fields.update({key: value for key, value in optional.items() if value})
    if code_permalink:
        fields["code_permalink"] = code_permalink
    return fields


# -- writing safely ------------------------------------------------------------------------------------------


def check_complete(data: Dataset, incomplete: bool, warn: Callable[[str], None] | None) -> None:
    """Refuse a dataset whose collection did not finish, unless ``incomplete`` asks for it (then warn)."""
    if data.complete:
        return
    if not incomplete:
        raise DatasetError(f"{incomplete_text(data)}, or pass --incomplete to export those episodes")
    if warn is not None:
        warn(f"{incomplete_text(data)}; exporting those episodes (--incomplete)")


def _check_destination(path: Path, force: bool, what: str, hint: str = "") -> None:
    if path.exists() and not force:
        raise DatasetError(f"{path} already exists; pass --force to replace the {what}{hint}")
    if path.exists() and not path.is_dir():
        raise DatasetError(f"{path} exists and is not a folder; choose another destination")


def _replace(tmp: Path, final: Path) -> None:
    """Move the finished folder ``tmp`` to ``final``, replacing an old one only once the new one is whole."""
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.{os.getpid()}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _remove_stale_temporaries(final: Path) -> None:
    """Delete temporary folders that exports of ``final`` killed before they finished left behind."""
    for leftover in final.parent.glob(f".{final.name}.*.tmp"):
        pid = leftover.name.rsplit(".", 2)[-2]
        if not (pid.isdigit() and psutil.pid_exists(int(pid))):
            shutil.rmtree(leftover, ignore_errors=True)
