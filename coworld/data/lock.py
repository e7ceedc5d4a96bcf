"""A lock file that lets one writer at a time touch a dataset, and recognises locks left by killed writers.

The lock is ``<dataset>.lock``, a small JSON file naming the host, PID and start time of the holder. It is created
atomically (written to a private temporary file, then hard-linked into place, which fails if the lock exists). A lock
whose holder is gone (on this host: no such PID, or a PID reused by a process started at another time) is stale and
is taken over; any other lock stops the second writer with a :class:`~coworld.errors.DatasetError`.
"""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path
from typing import Any

import psutil

from coworld.errors import DatasetError, StorageError
from coworld.storage import WRITE_ERRNOS, failure_reason


def lock_path(path: Path) -> Path:
    """The lock file of the dataset at ``path``."""
    return path.with_name(path.name + ".lock")


def read_lock(path: Path) -> dict[str, Any] | None:
    """The holder recorded in the lock of dataset ``path``, or None if there is no lock."""
    try:
        return json.loads(lock_path(path).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {}  # unreadable: treated as held, the error message says how to remove it


def process_record(pid: int) -> dict[str, Any]:
    """What identifies a process across PID reuse: host, PID and start time."""
    return {"host": socket.gethostname(), "pid": pid, "started": psutil.Process(pid).create_time()}


def holder_alive(holder: dict[str, Any]) -> bool:
    """Whether the process recorded in a lock still runs (locks from other hosts count as alive)."""
    if holder.get("host") != socket.gethostname():
        return True
    try:
        process = psutil.Process(int(holder["pid"]))
        return abs(process.create_time() - float(holder["started"])) < 1.0
    except (psutil.NoSuchProcess, KeyError, TypeError, ValueError):
        return False


class WriterLock:
    """Exclusive write access to one dataset file; acquire on construction, :meth:`release` when done."""

    def __init__(self, path: Path) -> None:
        self.path = lock_path(path)
        self._dataset = path
        self._record = process_record(os.getpid())
        for _ in range(3):
            try:
                created = self._try_create()
            except OSError as err:
                if err.errno not in WRITE_ERRNOS:
                    raise
                reason = failure_reason(err)
                raise StorageError(f"cannot write {path}: {reason}", reason) from None
            if created:
                return
            holder = read_lock(path)
            if holder is None:
                continue  # released between our attempt and the read
            if holder and not holder_alive(holder):
                self._remove_stale(holder)
                continue
            who = f"process {holder['pid']} on {holder['host']}" if holder else "another process"
            raise DatasetError(
                f"{path} is locked by {who} (lock file {self.path}); wait for that writer to finish, "
                f"or delete the lock file if it is no longer running"
            )
        raise DatasetError(f"could not take the lock {self.path}: other writers keep taking it; try again")

    def _try_create(self) -> bool:
        tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.tmp")
        try:
            tmp.write_text(json.dumps(self._record))
            os.link(tmp, self.path)
            return True
        except FileExistsError:
            return False
        finally:
            tmp.unlink(missing_ok=True)

    def _remove_stale(self, holder: dict[str, Any]) -> None:
        # Remove the lock only if it still names the dead holder (another writer may have replaced it meanwhile).
        if read_lock(self._dataset) == holder:
            self.path.unlink(missing_ok=True)

    def release(self) -> None:
        """Remove the lock file if it is still ours (one left on a location that became read-only is stale later)."""
        if read_lock(self._dataset) == self._record:
            try:
                self.path.unlink(missing_ok=True)
            except OSError as err:
                if err.errno not in WRITE_ERRNOS:
                    raise
