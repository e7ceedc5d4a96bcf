"""One logger with pluggable outputs: console, JSON lines and TensorBoard.

Keys are namespaced (``wm/``, ``actor/``, ``critic/``, ``coworld/``, ``eval/``, ...). Every call to
:meth:`Logger.log` writes one record at one step to every output; :meth:`Logger.log_image` writes a picture to
TensorBoard (e.g. the open-loop prediction strips, ``openl/<task>``).
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import tqdm

OUTPUTS = ("console", "jsonl", "tensorboard")

CONSOLE_KEYS = ("eval/", "/loss", "perf/", "coworld/")
"""Metrics whose key contains one of these go to the console too (all go to the files)."""


class Logger:
    """Writes scalar metrics to ``logdir/metrics.jsonl``, TensorBoard event files and the console.

    Args:
        logdir: run folder.
        outputs: any of ``console``, ``jsonl``, ``tensorboard``.
    """

    def __init__(self, logdir: str | Path, *, outputs: Sequence[str] = OUTPUTS) -> None:
        unknown = set(outputs) - set(OUTPUTS)
        if unknown:
            raise ValueError(f"unknown logger outputs {sorted(unknown)}; choose from {OUTPUTS}")
        self.logdir = Path(logdir)
        self.logdir.mkdir(parents=True, exist_ok=True)
        self._console = "console" in outputs
        self._jsonl = open(self.logdir / "metrics.jsonl", "a") if "jsonl" in outputs else None
        self._tb = None
        if "tensorboard" in outputs:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.logdir / "tb"))
        self._start = time.time()

    def log(self, metrics: Mapping[str, Any], step: int, unit: str = "step") -> None:
        """Record scalar ``metrics`` at ``step``, which counts ``unit`` (``env_step``, ``update``,
        ``target_update``, ...); non-finite values are kept (as null in JSON).

        Files get every metric; the console gets one line of the headline ones (:data:`CONSOLE_KEYS`),
        labelled with what the step counts, e.g. ``[target_update 2,000] eval/return 312.4 ...``.
        """
        scalars = {key: float(value) for key, value in metrics.items()}
        if self._jsonl is not None:
            record: dict[str, Any] = {"step": step, "unit": unit, "time": round(time.time() - self._start, 3)}
            record.update({k: (v if math.isfinite(v) else None) for k, v in scalars.items()})
            self._jsonl.write(json.dumps(record) + "\n")
            self._jsonl.flush()
        if self._tb is not None:
            for key, value in scalars.items():
                self._tb.add_scalar(key, value, step)
            self._tb.flush()
        shown = {k: v for k, v in scalars.items() if any(part in k for part in CONSOLE_KEYS)}
        if self._console and shown:
            text = "  ".join(f"{k} {v:.4g}" for k, v in sorted(shown.items()))
            tqdm.tqdm.write(f"[{unit} {step:,}] {text}", file=sys.stderr)

    def log_image(self, tag: str, image: Any, step: int) -> None:
        """Record a uint8 ``(H, W, 3)`` picture at ``step`` (TensorBoard only; the other outputs take scalars)."""
        if self._tb is not None:
            self._tb.add_image(tag, image, step, dataformats="HWC")
            self._tb.flush()

    def close(self) -> None:
        if self._jsonl is not None:
            self._jsonl.close()
            self._jsonl = None
        if self._tb is not None:
            self._tb.close()
            self._tb = None

    def __enter__(self) -> Logger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_metrics(logdir: str | Path) -> list[dict[str, Any]]:
    """The records of ``logdir/metrics.jsonl``, in order; a line cut short by a kill is skipped."""
    path = Path(logdir) / "metrics.jsonl"
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except ValueError:
            continue
    return records


class Rate:
    """Counts per second between successive calls (e.g. updates/s over one log window)."""

    def __init__(self, count: int = 0) -> None:
        self._count, self._time = count, time.perf_counter()

    def __call__(self, count: int) -> float:
        """The rate since the previous call (or construction), then restart the window at ``count``."""
        now = time.perf_counter()
        rate = (count - self._count) / max(now - self._time, 1e-9)
        self._count, self._time = count, now
        return rate
