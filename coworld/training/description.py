"""A run's description (``run.json``): what was trained, on what; read without torch, so `coworld report` starts
without it."""

from __future__ import annotations

from typing import Any


def collector_run_info(task: str, preset: str) -> dict[str, Any]:
    """The run description of the online DreamerV2 agent that ``coworld collect --policy dreamerv2`` trains: a
    dreamerv2 run like any other (``online`` says it learned in its environment, not from a dataset)."""
    return {"algo": "dreamerv2", "source": None, "target": task, "task": task, "preset": preset, "online": True}


def run_description(info: Any) -> Any:
    """A run description as read from ``run.json``, with a collector's older description (only its ``task``
    and ``quality``, no ``algo``) completed as the online dreamerv2 run it is; anything else as it is."""
    if isinstance(info, dict) and "algo" not in info and "task" in info and "quality" in info:
        return {**collector_run_info(str(info["task"]), str(info.get("preset", "?"))), **info}
    return info
