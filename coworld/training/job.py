"""A training request, checked: what ``coworld train`` hands to an algorithm's loop.

Pure data, imported by every loop and by the commands alike; the checks that build a :class:`TrainJob`
are :func:`coworld.training.train.check_job`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coworld import envs
from coworld.algorithms import algorithm
from coworld.config import Config, canonical_preset
from coworld.errors import CoworldError

START_OVER = "pass a new --logdir, or --force to start this one over"
"""How ``coworld train`` starts a run folder of other settings over; the collector names its own options."""


def default_logdir(algo: str, source: str | None, target: str, seed: int) -> Path:
    sources = "+".join(parse_sources(source)) if source else None  # a list of sources is written a+b in names
    pair = f"{sources}-{target}" if sources and algorithm(algo).needs_source else target
    return Path("runs") / f"{algo}-{pair}-s{seed}"


def parse_sources(text: str) -> tuple[str, ...]:
    """``--source``: one task, or several (CoWorld's automatic choice) separated by ``,`` (or ``+``, as sweep pairs
    and run folder names write them); each a known task, none twice. One CoworldError line otherwise."""
    names = [part.strip() for part in text.replace("+", ",").split(",")]
    if not all(names):
        raise CoworldError(f"source list {text!r} has an empty name; write TASK or TASK,TASK,... (see `coworld tasks`)")
    for name in names:
        envs.task_spec(name)
    repeated = next((name for i, name in enumerate(names) if name in names[:i]), None)
    if repeated is not None:
        raise CoworldError(f"source list {text!r} names {repeated} twice; give each candidate source once")
    return tuple(names)


@dataclass(frozen=True)
class TrainJob:
    """A checked request to train."""

    algo: str
    source: str | None
    target: str
    dataset: Path
    logdir: Path
    config: Config
    preset: str
    resume: bool = False
    """The run folder already holds this run: training continues from its checkpoint."""
    start_over: bool = False
    """``--force``: what training wrote in the run folder is removed first, and the run starts afresh."""
    warnings: tuple[str, ...] = ()
    """Things worth telling the user before a long run starts (one line each)."""
    keep_pretrained: bool = False
    """CoWorld: keep a copy of the run folder as source pretraining leaves it (:mod:`coworld.training.pretrained`)."""
    pretrained_from: tuple[Path, ...] = ()
    """CoWorld: run folders whose pretraining this run's is; a new run starts from the first that kept one."""

    def info(self) -> dict[str, Any]:
        return {
            "algo": self.algo,
            "source": self.source,
            "target": self.target,
            "dataset": str(self.dataset),
            "preset": canonical_preset(self.preset),
        }
