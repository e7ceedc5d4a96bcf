"""A run's description (``run.json``): what was trained, on what; read without torch, so `coworld report` starts
without it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from coworld.errors import CoworldError

EARLIER_RELEASE = "coworld 0.1.0 at commit 81d62fb"
"""The last coworld that reads checkpoints and run folders written before this release's formats."""


def collector_run_info(task: str, preset: str) -> dict[str, Any]:
    """The run description of the online DreamerV2 agent that ``coworld collect --policy dreamerv2`` trains: a
    dreamerv2 run like any other (``online`` says it learned in its environment, not from a dataset)."""
    return {"algo": "dreamerv2", "source": None, "target": task, "task": task, "preset": preset, "online": True}


def run_description(info: Any, path: str | Path) -> Any:
    """A run description as read from ``path`` (``run.json``), as it is; a collector's description from before
    this release (its ``task`` and ``quality``, no ``algo``) is refused in one CoworldError line."""
    if isinstance(info, dict) and "algo" not in info and "task" in info and "quality" in info:
        raise CoworldError(
            f"{path} was written by an earlier coworld's collector (no 'algo' entry), which this one does not read:"
            f" collect the dataset again, or read the folder with {EARLIER_RELEASE}"
        )
    return info
