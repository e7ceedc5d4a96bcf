"""User-facing errors.

Anything a person can fix (a bad task name, a corrupt dataset, an unknown config key, a missing checkpoint)
raises :class:`CoworldError` with one line saying what is wrong and what to do. The CLI prints that line and
exits with code 2; library users catch the exception.
"""

from __future__ import annotations


class CoworldError(Exception):
    """A problem with the user's input, described in one actionable line."""


class UnknownTaskError(CoworldError, KeyError):
    """A task name that is not in the registry."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


class ConfigError(CoworldError):
    """An unknown config key, a value of the wrong type, or an unknown preset."""


class DatasetError(CoworldError):
    """A dataset that is missing, unreadable, of the wrong task or shape, or locked by another writer."""


class CheckpointError(CoworldError):
    """A checkpoint that is missing, corrupt or made by an incompatible run."""


class StorageError(CoworldError):
    """A write the system refused (disk full, read-only location, no permission); what was committed before is
    intact. ``reason`` is the system's word for it (``No space left on device``)."""

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason

    @property
    def disk_full(self) -> bool:
        """The disk (or the user's quota, or the file size limit) has no room: freeing space lets a rerun continue."""
        import errno
        import os

        return self.reason in {os.strerror(e) for e in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)}


class TrainingDiverged(CoworldError):
    """A loss, an action or a weight stopped being a number: the run stops rather than train on, naming the phase,
    what to lower and the last good checkpoint, which stays as it was (:mod:`coworld.training.divergence`)."""


class NonFiniteCheckpoint(TrainingDiverged):
    """A checkpoint refused because ``entry`` (a path into its state, ``agent/world_model/...``) holds ``value``
    (``nan``, ``inf`` or ``-inf``); the checkpoint at ``path`` is as it was."""

    def __init__(self, message: str, *, path: str, entry: str, value: str) -> None:
        super().__init__(message)
        self.path, self.entry, self.value = path, entry, value
