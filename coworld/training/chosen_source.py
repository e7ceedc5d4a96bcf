"""The record of CoWorld's automatic source choice in a run folder (made by :mod:`coworld.training.multi_source`),
read by ``train`` (resuming), ``report`` and ``eval`` alike: which candidates, each one's distance to the target, the
chosen."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coworld.errors import CheckpointError
from coworld.storage import damaged, read_json_object
from coworld.training.job import START_OVER

CHOICE_FILE = "source_choice.json"
"""The choice and every candidate's distance, in the run folder."""


@dataclass(frozen=True)
class SourceChoice:
    """What :func:`coworld.training.multi_source.choose_source` decided: the candidates in the order given, each one's
    distance, the chosen."""

    candidates: tuple[str, ...]
    distances: dict[str, float]
    chosen: str
    align_on: str
    batches: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "candidates": list(self.candidates),
            "distances": self.distances,
            "chosen": self.chosen,
            "rule": "the candidate whose latents on target frames lie closest to the target's (Eq. 3's KL)",
            "align_on": self.align_on,
            "batches": self.batches,
        }


def candidate_dir(run_dir: str | Path, task: str) -> Path:
    """Where a candidate source's pretraining lives until the choice."""
    return Path(run_dir) / "sources" / task


MEASURED_FILE = Path("selection") / "distances.json"
"""The distances measured so far, candidate by candidate, until the choice is made (in the run folder)."""


def read_choice(
    run_dir: str | Path, candidates: Sequence[str] | None = None, fix: str | None = None
) -> SourceChoice | None:
    """The choice written in ``run_dir``; None before it is made, when the distances measured so far are checked too
    if the run's ``candidates`` are given (:func:`read_distances`). A damaged record, or one naming other candidates
    than ``candidates``, is one CheckpointError line ending with ``fix``: what the calling command offers, by
    default ``train``'s (a new --logdir, or --force)."""
    fix = START_OVER if fix is None else fix
    path = Path(run_dir) / CHOICE_FILE
    if not path.exists():
        if candidates is not None:
            read_distances(run_dir, candidates)
        return None
    data = read_json_object(path, fix)
    try:
        names = tuple(str(c) for c in data["candidates"])
        choice = SourceChoice(
            candidates=names,
            distances=_distances(data["distances"], names),
            chosen=str(data["chosen"]),
            align_on=str(data["align_on"]),
            batches=int(data["batches"]),
        )
        if choice.chosen not in names:
            raise ValueError(f"it chose {choice.chosen}, which is not among its candidates {names}")
        if set(choice.distances) != set(names):
            raise ValueError(f"it has distances of {tuple(choice.distances)} but its candidates are {names}")
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise CheckpointError(damaged(path, str(err), fix)) from None
    if candidates is not None and tuple(candidates) != names:
        raise CheckpointError(
            f"{path} chose among {', '.join(names)}, not this run's {', '.join(candidates)}: it was copied from"
            f" another run; {fix}"
        )
    return choice


def read_distances(run_dir: str | Path, candidates: Sequence[str]) -> dict[str, float]:
    """The distances measured so far in ``run_dir`` (none before the first), checked before a run goes on measuring:
    a JSON object of this run's ``candidates`` and numbers. Anything else is one CheckpointError line saying to
    delete the file, which measures the candidates again from their kept pretraining."""
    path = Path(run_dir) / MEASURED_FILE
    if not path.exists():
        return {}
    fix = f"delete it to measure the candidates again (their pretraining is kept), or {START_OVER}"
    data = read_json_object(path, fix)
    try:
        return _distances(data, candidates)
    except ValueError as err:
        raise CheckpointError(damaged(path, str(err), fix)) from None


def _distances(data: Any, candidates: Sequence[str]) -> dict[str, float]:
    """``{candidate: distance}`` read from JSON: an object of candidates and numbers (a non-finite distance, which
    the choice passes over, included); anything else raises ValueError saying what is amiss."""
    if not isinstance(data, Mapping):
        raise ValueError(f"distances {data!r} are not an object of candidates and numbers")
    for name, value in data.items():
        if name not in candidates:
            raise ValueError(f"{name} is not a candidate of this run ({', '.join(candidates)})")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"the distance of {name} is {value!r}, not a number")
    return {name: float(value) for name, value in data.items()}


def trained_source(run_dir: str | Path, info: Mapping[str, Any], fix: str | None = None) -> str | None:
    """The source task a run's source agent learned in: the one chosen where it chose among several (None before
    the choice), else the one it names. ``fix``: what the calling command offers where the choice is damaged
    (:func:`read_choice`)."""
    source = info.get("source")
    if not isinstance(source, str):
        return None
    if "," not in source:
        return source
    choice = read_choice(run_dir, fix=fix)
    return choice.chosen if choice is not None else None
