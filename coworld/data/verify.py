"""Full check of a dataset file: every finding, not just the first (``coworld dataset verify``).

Beyond what opening checks (layout, episode boundaries, finite actions and rewards), this reads every frame and
compares each episode's checksum, checks the derived fields (``episode_ids``, ``is_first``, ``episodes/returns``),
the infos, the metadata, rows left past the committed ones by an interrupted writer, and the complete flag.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from coworld.data.reader import open_h5
from coworld.data.schema import JSON_ATTRS, ROW_FIELDS, episode_checksum, structural_problems
from coworld.errors import DatasetError
from coworld.progress import progress_bar

_MAX_LISTED = 10  # per kind of per-episode finding


def verify_dataset(path: str | Path, *, progress: bool = False) -> list[str]:
    """Every problem found in the dataset at ``path``, one line each; an empty list means the file is sound.

    A missing path raises :class:`~coworld.errors.DatasetError`; a file that is not a readable dataset is a finding.
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file")
    try:
        f = open_h5(path)
    except DatasetError as err:
        return [str(err).removeprefix(f"{path}: ")]
    with f:
        try:
            return _problems(f, progress)
        except (OSError, KeyError, ValueError) as err:
            return [f"unreadable while checking ({str(err).strip().splitlines()[0]}); is the file truncated?"]


def _problems(f: h5py.File, progress: bool) -> list[str]:
    problems = structural_problems(f)
    if problems:
        return problems
    attrs = f.attrs
    n, e = int(attrs["num_rows"]), int(attrs["num_episodes"])
    starts, lengths = f["episodes/starts"][:e], f["episodes/lengths"][:e]
    terminated = f["episodes/terminated"][:e]
    ends = starts + lengths - 1
    rows = {name: f[name][:n] for name in ROW_FIELDS if name != "observations"}
    done = rows["terminals"] | rows["timeouts"]
    if not np.array_equal(np.flatnonzero(done), ends):
        problems.append("terminals/timeouts do not mark exactly the last row of each episode")
    if (rows["terminals"] & rows["timeouts"]).any():
        problems.append(f"{int((rows['terminals'] & rows['timeouts']).sum())} rows are both terminal and timeout")
    if e and not np.array_equal(rows["terminals"][ends], terminated):
        problems.append("terminals of the last rows disagree with episodes/terminated")
    if not np.array_equal(rows["episode_ids"], np.repeat(np.arange(e, dtype=np.int32), lengths)):
        problems.append("episode_ids do not number the episodes 0, 1, ... in row order")
    first = np.zeros(n, bool)
    first[starts] = True
    if not np.array_equal(rows["is_first"], first):
        problems.append("is_first does not mark exactly the first row of each episode")
    for name in ("actions", "rewards"):
        bad = int((~np.isfinite(rows[name])).sum())
        if bad:
            problems.append(f"{bad} {name} are NaN or inf")
    if e and np.isfinite(rows["rewards"]).all():
        sums = np.add.reduceat(rows["rewards"].astype(np.float64), starts)
        returns = f["episodes/returns"][:e]
        wrong = np.flatnonzero(~np.isclose(sums, returns, rtol=1e-6, atol=1e-4))
        problems += [f"episode {i}: stored return {returns[i]:g} != sum of rewards {sums[i]:g}" for i in wrong[:3]]
    for name, node in f["infos"].items():
        values = node[:n]
        if values.dtype.kind == "f" and not np.isfinite(values).all():
            problems.append(f"infos/{name}: {int((~np.isfinite(values)).sum())} values are NaN or inf")
    for name in JSON_ATTRS:
        if name not in attrs:
            problems.append(f"missing metadata attribute {name!r}")
    if "collector" in attrs and not isinstance(json.loads(attrs["collector"]), dict):
        problems.append("metadata 'collector' is not a JSON object")
    problems += _checksum_problems(f, starts, lengths, rows, progress)
    extra = {name: f[name].shape[0] - n for name in ROW_FIELDS if f[name].shape[0] > n}
    if extra:
        problems.append(
            f"{max(extra.values())} rows past the last committed episode (a writer was interrupted mid-episode); "
            f"resuming the collection drops them"
        )
    if not bool(attrs["complete"]):
        problems.append("not complete: the collection was interrupted or is still running; resume it to finish")
    return problems


def _checksum_problems(
    f: h5py.File, starts: np.ndarray, lengths: np.ndarray, rows: dict[str, np.ndarray], progress: bool
) -> list[str]:
    """Read every episode's frames (rows + final frame) and compare its CRC-32 with the stored one."""
    stored = f["episodes/checksums"][: len(starts)]
    frames, finals = f["observations"], f["episodes/final_observations"]
    unreadable, mismatched = [], []
    for i in progress_bar(range(len(starts)), desc="verify", unit="episodes", enabled=progress, leave=False):
        s, t = int(starts[i]), int(lengths[i])
        try:
            obs = np.concatenate([frames[s : s + t], finals[i : i + 1]])
        except OSError:
            unreadable.append(i)
            continue
        if episode_checksum(obs, rows["actions"][s : s + t], rows["rewards"][s : s + t]) != int(stored[i]):
            mismatched.append(i)
    problems = []
    for found, what in ((unreadable, "frames cannot be read"), (mismatched, "checksum mismatch (data damaged)")):
        if found:
            listed = ", ".join(map(str, found[:_MAX_LISTED])) + (" ..." if len(found) > _MAX_LISTED else "")
            problems.append(f"{len(found)} episodes: {what}: {listed}")
    return problems
