"""The sweep's progress view: runs done / running / failed / pending, and the latest evaluation of each running run.

On a terminal it is a tqdm bar over the runs with the counts and the running runs' latest ``eval/return`` after
it; otherwise (a log file, CI) one plain line every ``interval`` seconds. Finished and failed runs are announced
on a line of their own either way.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TextIO

import tqdm

STATES = ("done", "running", "failed", "pending")

_TAIL_BYTES = 65536


def latest_eval(run_dir: Path | None, algo: str = "") -> float | None:
    """The target agent's last ``eval/return`` in ``run_dir/metrics.jsonl`` (reads only the file's tail), or None."""
    from coworld.report.results import target_eval_return

    if run_dir is None:
        return None
    path = run_dir / "metrics.jsonl"
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - _TAIL_BYTES))
            lines = f.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        if '"eval/return"' not in line:
            continue
        try:
            value = target_eval_return(json.loads(line), algo)
        except ValueError:
            continue  # the first, cut line of the tail, or a line being written
        if value is not None:
            return value
    return None


class ProgressView:
    """Shows the state of a sweep's runs.

    Args:
        total: number of runs in the sweep.
        enabled: False shows nothing but the per-run lines.
        interval: seconds between plain lines when ``stream`` is not a terminal.
    """

    def __init__(self, total: int, *, enabled: bool = True, interval: float = 60.0, stream: TextIO | None = None):
        self.stream = stream or sys.stderr
        self.total = total
        self.interval = interval
        self.enabled = enabled
        self._tty = enabled and self.stream.isatty()
        self._bar = (
            tqdm.tqdm(total=total, unit="run", desc="sweep", file=self.stream, dynamic_ncols=True)
            if self._tty
            else None
        )
        self._last_line = 0.0
        self._last_counts: dict[str, int] | None = None

    def update(self, states: Mapping[str, str], running: Mapping[str, float | None], collecting: int = 0) -> None:
        """``states``: run name -> one of :data:`STATES`; ``running``: running run -> latest eval return;
        ``collecting``: datasets being collected."""
        counts = {state: 0 for state in STATES}
        for state in states.values():
            counts[state] += 1
        text = summary_line(counts, running, collecting)
        if self._bar is not None:
            self._bar.n = counts["done"]
            self._bar.set_postfix_str(text.split(" done, ", 1)[1], refresh=True)  # the bar shows the done count
        elif self.enabled and (time.time() - self._last_line >= self.interval or self._last_counts is None):
            print(text, file=self.stream, flush=True)
            self._last_line = time.time()
        self._last_counts = counts

    def event(self, text: str) -> None:
        """One line about one job (finished, failed)."""
        if self._bar is not None:
            self._bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def summary_line(counts: Mapping[str, int], running: Mapping[str, float | None], collecting: int = 0) -> str:
    """e.g. ``sweep: 3/12 done, 2 running, 0 failed, 7 pending | coworld-...-s0 eval 30.4, curl-...-s1 eval -``."""
    total = sum(counts.values())
    text = (
        f"sweep: {counts['done']}/{total} done, {counts['running']} running, {counts['failed']} failed,"
        f" {counts['pending']} pending"
    )
    if collecting:
        text += f", {collecting} dataset{'s' * (collecting > 1)} collecting"
    if running:
        shown = [f"{name} eval {'-' if value is None else f'{value:.1f}'}" for name, value in running.items()]
        text += " | " + ", ".join(shown)
    return text
