"""Merge datasets of one task into a new one (e.g. medium-expert = medium-replay + expert)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from tqdm import tqdm

from coworld.data.reader import Dataset, open_dataset
from coworld.data.writer import DatasetWriter
from coworld.errors import DatasetError


def merged_quality(qualities: Sequence[str]) -> str | None:
    """The quality of a merge when it is unambiguous: the shared one, or medium-expert for medium(-replay) + expert."""
    kinds = set(qualities)
    if len(kinds) == 1:
        return qualities[0]
    if "expert" in kinds and kinds <= {"medium", "medium-replay", "expert"}:
        return "medium-expert"
    return None


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

    Inputs must be complete and agree on task, action size, image shape and env config. Infos keys present in every
    input are kept. ``quality`` defaults to :func:`merged_quality` of the inputs (required when that is ambiguous).
    """
    out = Path(out)
    if len(inputs) < 2:
        raise DatasetError("merge needs at least two input datasets")
    for path in inputs:
        if Path(path).resolve() == out.resolve():
            raise DatasetError(f"the output {out} is also an input; write the merge to a new file")
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
        writer = DatasetWriter(
            out,
            task=first.task,
            env_config=first.metadata.get("env_config") or {},
            quality=quality,
            collector={"algorithm": "merge", "sources": sources},
            action_size=first.action_size,
            image_shape=first.image_shape,
            force=force,
            reference=first.reference,
            compression=compression,
        )
        total = sum(data.num_episodes for data in datasets)
        with writer, tqdm(total=total, unit="episode", desc="merging", disable=not progress) as bar:
            for data in datasets:
                for i in range(data.num_episodes):
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
    finally:
        for data in datasets:
            data.close()
    return out
