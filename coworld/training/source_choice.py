"""The record of CoWorld's automatic source choice in a run folder (made by :mod:`coworld.training.choice`), read by
``train`` (resuming), ``report`` and ``eval`` alike: which candidates, each one's distance to the target, the chosen."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coworld.errors import CheckpointError

CHOICE_FILE = "source_choice.json"
"""The choice and every candidate's distance, in the run folder."""


@dataclass(frozen=True)
class SourceChoice:
    """What :func:`coworld.training.choice.choose_source` decided: the candidates in the order given, each one's
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


def read_choice(run_dir: str | Path, candidates: Sequence[str] | None = None) -> SourceChoice | None:
    """The choice written in ``run_dir`` (None before it is made); a damaged file, or one naming other candidates
    than ``candidates``, is one CheckpointError line."""
    path = Path(run_dir) / CHOICE_FILE
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
        choice = SourceChoice(
            candidates=tuple(str(c) for c in data["candidates"]),
            distances={str(k): float(v) for k, v in data["distances"].items()},
            chosen=str(data["chosen"]),
            align_on=str(data["align_on"]),
            batches=int(data["batches"]),
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise CheckpointError(f"{path} is damaged ({err}); remove the run folder's training with --force") from None
    if choice.chosen not in choice.candidates or (candidates is not None and tuple(candidates) != choice.candidates):
        raise CheckpointError(
            f"{path} chose among {', '.join(choice.candidates)}, not this run's {', '.join(candidates or ())};"
            " it was copied from another run: pass another --logdir, or --force to start over"
        )
    return choice


def trained_source(run_dir: str | Path, info: Mapping[str, Any]) -> str | None:
    """The source task a run's source agent learned in: the one chosen where it chose among several (None before
    the choice), else the one it names."""
    source = info.get("source")
    if not isinstance(source, str):
        return None
    if "," not in source:
        return source
    choice = read_choice(run_dir)
    return choice.chosen if choice is not None else None


DISTANCES_FILE = "selection/distances.json"
"""The candidates' distances measured so far, in the run folder, until the choice is written."""


def read_distances(run_dir: str | Path, candidates: Sequence[str]) -> dict[str, float]:
    """The distances measured so far in ``run_dir`` (``{}`` before the first), each of one of ``candidates``; a damaged
    file is one CheckpointError line saying how to measure again."""
    path = Path(run_dir) / DISTANCES_FILE
    if not path.exists():
        return {}
    fix = f"delete {path} to measure the candidates again, or pass --force to start the run over"
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise CheckpointError(f"{path} is damaged ({type(err).__name__}); {fix}") from None
    if not isinstance(data, dict):
        raise CheckpointError(f"{path} is damaged (not a JSON object of distances); {fix}")
    for name, value in data.items():
        if name not in candidates:
            sources = ", ".join(candidates)
            raise CheckpointError(f"{path} names {name!r}, not one of this run's sources {sources}; {fix}")
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise CheckpointError(f"{path} is damaged ({name}'s distance is {value!r}, not a number); {fix}")
    return {name: float(value) for name, value in data.items()}
