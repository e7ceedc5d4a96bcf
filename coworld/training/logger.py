"""One logger with pluggable outputs: console, JSON lines and TensorBoard.

Keys are namespaced (``wm/``, ``actor/``, ``critic/``, ``coworld/``, ``eval/``, ...). Every call to
:meth:`Logger.log` writes one record at one step to every output; :meth:`Logger.log_image` writes a picture to
TensorBoard (e.g. the open-loop prediction strips, ``openl/<task>``).

A checkpoint keeps :meth:`Logger.mark` (``metrics.jsonl``'s length and digest, and each TensorBoard event file's
length, as the checkpoint is written); a run resumed from it redoes the updates that followed, so it first cuts the
files back there (:meth:`Logger.rewind`) and logs each record once, as an uninterrupted run does. The event files are
cut at record boundaries (every write is flushed), and those an earlier process began after the mark are removed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import sys
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import tqdm

OUTPUTS = ("console", "jsonl", "tensorboard")

CONSOLE_KEYS = ("eval/", "/loss", "perf/", "coworld/")
"""Metrics whose key contains one of these go to the console too (all go to the files)."""

METRICS_MARK = "metrics_mark"
"""The checkpoint entry holding :meth:`Logger.mark` (absent from checkpoints written before it was kept)."""
EMPTY_MARK = {"bytes": 0, "sha256": hashlib.sha256(b"").hexdigest(), "tensorboard": {}}
"""The mark of a file before any record: a run starting over from nothing rewinds to it."""


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
        self._earlier_events: set[str] = set()
        """The event files that earlier processes wrote in ``tb/`` (this one's own is new)."""
        if "tensorboard" in outputs:
            from torch.utils.tensorboard import SummaryWriter

            _quiet_event_writer_threads()
            self._earlier_events = {path.name for path in self._event_files()}
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
            with self._naming_the_log():
                self._jsonl.write(json.dumps(record) + "\n")
                self._jsonl.flush()
        if self._tb is not None:
            with self._tensorboard_writes():
                for key, value in scalars.items():
                    self._tb.add_scalar(key, value, step)
                self._tb.flush()
        shown = {k: v for k, v in scalars.items() if any(part in k for part in CONSOLE_KEYS)}
        if self._console and shown:
            text = "  ".join(f"{k} {v:.4g}" for k, v in sorted(shown.items()))
            tqdm.tqdm.write(f"[{unit} {step:,}] {text}", file=sys.stderr)

    def mark(self) -> dict[str, Any] | None:
        """Where the logs stand now, for a checkpoint to keep: ``metrics.jsonl``'s length in bytes and the SHA-256 of
        those bytes (which tells this file from another run's, e.g. a pretraining moved here), and with TensorBoard
        the length of each event file in ``tb/``; None without the jsonl output."""
        if self._jsonl is None:
            return None
        self._jsonl.flush()
        data = (self.logdir / "metrics.jsonl").read_bytes()
        mark: dict[str, Any] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
        if self._tb is not None:
            with self._tensorboard_writes():
                self._tb.flush()
            mark["tensorboard"] = {path.name: path.stat().st_size for path in self._event_files()}
        return mark

    def rewind(self, mark: Mapping[str, Any] | None) -> None:
        """Cut the logs back to ``mark`` (a checkpoint's :meth:`mark`), dropping the records a run resumed from that
        checkpoint logs again: ``metrics.jsonl`` to its length then, and the event files earlier processes wrote to
        theirs (removing those begun after it). Everything is left as it is where ``mark`` is None (a checkpoint from
        before marks were kept) or does not describe the start of ``metrics.jsonl`` (another run's; a file already
        shorter); the event files too where the mark has no lengths of theirs (a checkpoint from before they were
        kept, or written without TensorBoard)."""
        if self._jsonl is None or mark is None:
            return
        self._jsonl.flush()
        path, size = self.logdir / "metrics.jsonl", int(mark["bytes"])
        with open(path, "rb") as f:
            kept = f.read(size)
        if len(kept) != size or hashlib.sha256(kept).hexdigest() != mark["sha256"]:
            return
        os.truncate(path, size)  # the file is open for appending: the next record goes at the new end
        if self._tb is not None and "tensorboard" in mark:
            self._rewind_events({str(name): int(length) for name, length in mark["tensorboard"].items()})

    def _rewind_events(self, lengths: Mapping[str, int]) -> None:
        """Cut the earlier processes' event files to ``lengths`` (name: bytes), removing those not named."""
        for name in sorted(self._earlier_events):
            path = self.logdir / "tb" / name
            if name not in lengths:
                path.unlink(missing_ok=True)
                self._earlier_events.discard(name)
            elif path.exists() and path.stat().st_size > lengths[name]:
                os.truncate(path, lengths[name])

    def _event_files(self) -> list[Path]:
        """The TensorBoard event files in ``tb/``, this process's own among them once it has one."""
        return sorted((self.logdir / "tb").glob("events.out.tfevents.*"))

    def log_image(self, tag: str, image: Any, step: int) -> None:
        """Record a uint8 ``(H, W, 3)`` picture at ``step`` (TensorBoard only; the other outputs take scalars)."""
        if self._tb is not None:
            with self._tensorboard_writes():
                self._tb.add_image(tag, image, step, dataformats="HWC")
                self._tb.flush()

    @contextlib.contextmanager
    def _naming_the_log(self) -> Iterator[None]:
        """A refused write to the open log (a full disk) as an OSError naming the file, which a file object's own
        write and close errors do not."""
        try:
            yield
        except OSError as err:
            raise OSError(err.errno, err.strerror, str(self.logdir / "metrics.jsonl")) from None

    def close(self) -> None:
        if self._jsonl is not None:
            jsonl, self._jsonl = self._jsonl, None
            with self._naming_the_log():
                jsonl.close()
        if self._tb is not None:
            tb, self._tb = self._tb, None
            with self._tensorboard_writes():
                tb.close()

    @contextlib.contextmanager
    def _tensorboard_writes(self) -> Iterator[None]:
        """A write TensorBoard's writer thread could not make (a full disk) as one StorageError line naming the
        folder; other errors as they are."""
        from coworld.errors import StorageError
        from coworld.storage import WRITE_ERRNOS, failure_errno, failure_reason

        try:
            yield
        except OSError as err:
            if failure_errno(err) not in WRITE_ERRNOS:
                raise
            reason = failure_reason(err)
            raise StorageError(f"cannot write TensorBoard events in {self.logdir / 'tb'}: {reason}", reason) from None

    def __enter__(self) -> Logger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _quiet_event_writer_threads() -> None:
    """Keep TensorBoard's writer thread from printing a traceback for a write the system refused: the writer raises
    the same error in the main thread at its next write or flush, where :class:`Logger` turns it into one line.
    Installed once, around whatever ``threading.excepthook`` was; every other thread's error is shown as before."""
    if getattr(threading.excepthook, "_coworld_quiet", False):
        return
    previous = threading.excepthook

    def hook(args: threading.ExceptHookArgs) -> None:
        from coworld.storage import WRITE_ERRNOS, failure_errno

        writer_thread = type(args.thread).__name__ == "_AsyncWriterThread"
        if writer_thread and isinstance(args.exc_value, OSError) and failure_errno(args.exc_value) in WRITE_ERRNOS:
            return
        previous(args)

    hook._coworld_quiet = True  # type: ignore[attr-defined]
    threading.excepthook = hook


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
