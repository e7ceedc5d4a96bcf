"""Merge datasets of one task into a new one (e.g. medium-expert = medium-replay + expert).

The merge is written to ``<out>.merging`` next to ``out`` and renamed over ``out`` only once it is whole, flushed and
marked complete: a kill, a Ctrl-C or a full disk at any moment leaves ``out`` as it was (absent, or the file that
``--force`` is replacing). ``out`` is locked for the whole merge, so no other writer touches it meanwhile.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from coworld import interrupt
from coworld.data.lock import WriterLock
from coworld.data.reader import Dataset, open_dataset
from coworld.data.writer import DatasetWriter
from coworld.errors import DatasetError, StorageError
from coworld.progress import progress_bar
from coworld.storage import check_writable, fsync_path


def merged_quality(qualities: Sequence[str]) -> str | None:
    """The quality of a merge when it is unambiguous: the shared one, or medium-expert for medium(-replay) + expert."""
    kinds = set(qualities)
    if len(kinds) == 1:
        return qualities[0]
    if "expert" in kinds and kinds <= {"medium", "medium-replay", "expert"}:
        return "medium-expert"
    return None


def merging_path(out: str | Path) -> Path:
    """Where a merge into ``out`` is built before it is renamed into place."""
    out = Path(out)
    return out.with_name(f"{out.name}.merging")


def merge_datasets(
    inputs: Sequence[str | Path],
    out: str | Path,
    *,
    quality: str | None = None,
    force: bool = False,
    compression: str = "gzip",
    progress: bool = False,
) -> Path:
    """Write the episodes of every input, in order, to a new dataset ``out`` and return its path.

    Inputs must be distinct, complete and agree on task, action size, image shape and env config. Infos keys present in
    every input are kept. ``quality`` defaults to :func:`merged_quality` of the inputs (required when that is
    ambiguous). An existing ``out`` is replaced only with ``force``, and only once the merge is whole.
    """
    out = Path(out)
    _check_paths([Path(path) for path in inputs], out, force)
    datasets: list[Dataset] = []
    try:
        for path in inputs:
            datasets.append(open_dataset(path))
        first = datasets[0]
        for data in datasets:
            if not data.complete:
                raise DatasetError(f"{data.path} is not complete; finish it (collect --resume) before merging")
            mine = (data.task, data.action_size, data.image_shape, data.metadata.get("env_config"))
            theirs = (first.task, first.action_size, first.image_shape, first.metadata.get("env_config"))
            if mine != theirs:
                raise DatasetError(
                    f"cannot merge {data.path} (task {data.task}, action size {data.action_size}) with "
                    f"{first.path} (task {first.task}, action size {first.action_size}): task and env config must match"
                )
        quality = quality or merged_quality([data.quality for data in datasets])
        if quality is None:
            kinds = ", ".join(data.quality for data in datasets)
            raise DatasetError(f"inputs have qualities {kinds}; say which quality the merge has with --quality")
        check_writable(out.parent, "--out")
        lock = WriterLock(out)  # no collection or other merge writes to out meanwhile
        try:
            _merge_into(datasets, out, quality, compression, progress)
        finally:
            lock.release()
    finally:
        for data in datasets:
            data.close()
    return out


def _check_paths(inputs: list[Path], out: Path, force: bool) -> None:
    if len(inputs) < 2:
        raise DatasetError("merge needs at least two input datasets")
    if out.is_dir():
        raise DatasetError(f"--out {out} is a folder; name the merged dataset file, e.g. {out / 'merged.h5'}")
    if out.exists() and _identity(out) in {_identity(path) for path in inputs}:
        raise DatasetError(f"the output {out} is also an input; write the merge to a new file")
    seen: dict[object, Path] = {}
    for path in inputs:
        key = _identity(path)
        if key in seen:
            raise DatasetError(f"{path} is given twice (as {seen[key]} and {path}); list each input once")
        seen[key] = path
    if out.exists() and not force:
        raise DatasetError(
            f"{out} already exists; choose another --out, or pass --force to replace it once the merge is whole"
        )


def _identity(path: Path) -> object:
    """The same file under any name (links, relative paths); a missing file by its absolute path."""
    try:
        stat = path.stat()
        return (stat.st_dev, stat.st_ino)
    except OSError:
        return path.resolve()


def _merge_into(datasets: list[Dataset], out: Path, quality: str, compression: str, progress: bool) -> None:
    first = datasets[0]
    keep = set.intersection(*(set(data.infos_keys) for data in datasets))
    sources = [
        {
            "path": str(data.path),
            "quality": data.quality,
            "episodes": data.num_episodes,
            "steps": data.num_steps,
            "collector": data.metadata.get("collector"),
        }
        for data in datasets
    ]
    tmp = merging_path(out)
    existed = out.exists()
    try:
        writer = DatasetWriter(
            tmp,
            task=first.task,
            env_config=first.metadata.get("env_config") or {},
            quality=quality,
            collector={"algorithm": "merge", "sources": sources},
            action_size=first.action_size,
            image_shape=first.image_shape,
            force=True,  # what a killed merge left behind
            reference=first.reference,
            compression=compression,
        )
        total = sum(data.num_episodes for data in datasets)
        with writer, progress_bar(total=total, desc="merge", unit="episodes", enabled=progress) as bar:
            for data in datasets:
                for i in range(data.num_episodes):
                    interrupt.check()
                    ep = data.episode(i)
                    writer.add_episode(
                        ep["image"],
                        ep["action"][1:],
                        ep["reward"][1:],
                        bool(ep["is_terminal"][-1]),
                        {name: ep[name][1:] for name in sorted(keep)},
                    )
                    bar.update()
            writer.close(complete=True)
        fsync_path(tmp)
        os.replace(tmp, out)
    except StorageError as err:
        tmp.unlink(missing_ok=True)
        untouched = f"{out} is as it was" if existed else f"nothing was written to {out}"
        raise StorageError(f"cannot write the merge next to {out}: {err.reason}; {untouched}", err.reason) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
