"""Writes the system refuses: a full disk, a read-only location, missing permission.

Commands check their output location before any work (:func:`check_writable`), and the writers turn a refused write
into one line (:func:`write_failure`) naming the file and the system's reason, taken from the ``OSError`` or from
the HDF5 error text, which carries the errno of the failed ``write``.
"""

from __future__ import annotations

import errno
import json
import os
import re
import resource
import shutil
import tempfile
from pathlib import Path
from typing import Any

from coworld.errors import CoworldError, StorageError

WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG})
"""The errors of a write that a person fixes outside the program (free space, another folder, permissions)."""

_HDF5_ERRNO = re.compile(r"errno = (\d+)")


def failure_reason(err: BaseException) -> str:
    """The system's reason for a failed write: ``No space left on device``, ``Read-only file system``, ...

    h5py raises RuntimeError or OSError whose text holds the failed call's ``errno = N``; torch raises RuntimeError
    without one (then the text's first line is the reason).
    """
    number = failure_errno(err)
    if number is not None:
        return os.strerror(number)  # h5py's OSError carries HDF5's text as strerror
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return text[:160]


def failure_errno(err: BaseException) -> int | None:
    """The errno of a failed write (from the OSError or the HDF5 error text), or None."""
    if isinstance(err, OSError) and err.errno is not None:
        return err.errno
    found = _HDF5_ERRNO.search(str(err))
    return int(found.group(1)) if found else None


def room_problem(path: str | os.PathLike[str], needed: int) -> OSError | None:
    """Why the file at ``path`` cannot grow by ``needed`` bytes, as the OSError a write would meet, or None.

    Checked: the free space of its file system and this process's file size limit (RLIMIT_FSIZE). Asking first
    matters: HDF5 extends a file to its allocated size when it closes it, which a size limit also refuses, and
    such a file no longer opens.
    """
    path = Path(path)
    size = path.stat().st_size if path.exists() else 0
    free = shutil.disk_usage(path.parent).free
    if free < needed:
        return OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({_mib(needed)} needed, {_mib(free)} free)")
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and size + needed > limit:
        return OSError(errno.EFBIG, f"{os.strerror(errno.EFBIG)} (the file size limit is {_mib(limit)})")
    return None


def _mib(n: int) -> str:
    return f"{n / 2**20:,.1f} MiB"


def os_error_text(err: OSError) -> str:
    """One line for an OSError of a refused write: what could not be written and why."""
    where = f" {err.filename}" if err.filename else ""
    fix = "free space" if err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) else "make it writable"
    return f"cannot write{where}: {failure_reason(err)}; {fix} or choose another location, then rerun"


def check_writable(folder: str | os.PathLike[str], option: str) -> None:
    """Raise StorageError unless files can be made in ``folder`` (or, while it does not exist, in its nearest existing
    parent, where it would be made), for the output ``option``. Nothing is left behind.

    Creating (and removing) a probe file is the only test that also holds for root on a read-only mount.
    """
    folder = Path(folder)
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    try:
        with tempfile.TemporaryFile(dir=existing, prefix=".coworld-probe-"):
            pass
    except OSError as err:  # whatever the system's reason, the place takes no files (``/proc`` says ENOENT)
        reason = failure_reason(err)
        raise StorageError(f"cannot write to {folder} ({reason}); choose another {option}", reason) from None


def write_text_atomically(path: str | os.PathLike[str], text: str) -> None:
    """Write a whole text file under a temporary name in its folder, then rename it into place: a failed write
    (or a kill) leaves the previous file, or none, never half of one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        fsync_path(tmp)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise OSError(err.errno, err.strerror, str(path)) from None  # the user's path, not the temporary one
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def copy_file_atomically(source: str | os.PathLike[str], path: str | os.PathLike[str]) -> None:
    """Copy ``source`` to ``path`` under a temporary name in its folder, then rename it into place; a refused write
    is one StorageError line naming ``path``, and leaves the previous file, or none."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        shutil.copyfile(source, tmp)
        fsync_path(tmp)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        if failure_errno(err) not in WRITE_ERRNOS:
            raise
        reason = failure_reason(err)
        raise StorageError(f"cannot write {path}: {reason}", reason) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def fsync_path(path: str | os.PathLike[str]) -> None:
    """Flush a closed file's data to the disk (before renaming it into place)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_json_object(path: Path, fix: str = "") -> dict[str, Any]:
    """The JSON object in ``path``; bytes that are not UTF-8, text that is not JSON, or JSON of another shape raise
    one CoworldError line naming the file."""
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        raise CoworldError(damaged(path, "not UTF-8 text", fix)) from None
    except json.JSONDecodeError as err:
        raise CoworldError(damaged(path, f"not JSON: {err}", fix)) from None
    if not isinstance(data, dict):
        raise CoworldError(damaged(path, f"JSON {type(data).__name__}, not an object", fix))
    return data


def damaged(path: Path, why: str, fix: str) -> str:
    """The line that says ``path`` is damaged, why, and ``fix`` (what to do); without one, that coworld cannot read
    it."""
    return f"{path} is damaged ({why})" + (f"; {fix}" if fix else "; it is not a run folder coworld can read")
