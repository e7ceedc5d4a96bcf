"""Ctrl-C and SIGTERM: long jobs stop at a safe point, say what they kept, and exit 130 / 143.

Python turns SIGINT into a ``KeyboardInterrupt`` raised wherever the main thread happens to be. Raised inside a
callback (an h5py object being freed, a weakref callback) it is printed as "Exception ignored" and lost, so the job
runs on; raised in the middle of a write it leaves the writer half-updated. SIGTERM kills the process outright.

So the CLI installs :func:`handling_signals`: a signal raises :class:`Interrupted` at once, except inside the
:func:`at_safe_points` part of a long command, where it only sets a flag and the long loops call :func:`check`
where stopping leaves their output whole (between environment steps, updates, episodes). A second signal during
such a wait stops at once; a third is not caught at all. The CLI prints one line (what was kept, how to resume) and
exits with 128 + the signal number.

Worker processes of vector environments ignore both signals (:func:`ignored_by_new_processes` around their
creation): a Ctrl-C in a terminal reaches the whole process group, and the parent closes its workers itself.
"""

from __future__ import annotations

import functools
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(BaseException):
    """A stop asked by SIGINT or SIGTERM. A BaseException, like KeyboardInterrupt: ``except Exception`` lets it by.

    ``detail`` is filled in on the way out by the command that knows what its output holds (:func:`explain`).
    """

    def __init__(self, signum: int, detail: str = "") -> None:
        super().__init__(signum)
        self.signum = signum
        self.detail = detail

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        """128 + the signal number, as a shell reports a process ended by it: 130 for SIGINT, 143 for SIGTERM."""
        return 128 + self.signum

    def __str__(self) -> str:
        text = f"stopped by {self.signal_name}"
        return f"{text}: {self.detail}" if self.detail else text


class _State:
    installed = False
    safe_points = 0  # > 0 inside at_safe_points(): signals wait for check()
    requested: int | None = None  # the signal waiting for a check()
    count = 0  # signals received


_state = _State()


def check() -> None:
    """Raise :class:`Interrupted` if SIGINT or SIGTERM arrived since the job started; call it where stopping is safe."""
    if _state.requested is not None:
        raise Interrupted(_state.requested)


def requested() -> bool:
    """Whether a stop is waiting for the next :func:`check`."""
    return _state.requested is not None


def _handle(signum: int, frame: Any) -> None:
    _state.count += 1
    if _state.count >= 2:  # the second signal stops at once; the third ends the process the operating system's way
        signal.signal(signum, signal.SIG_DFL)
    if _state.safe_points > 0 and _state.count == 1:
        _state.requested = signum
        return
    _state.requested = signum
    raise Interrupted(signum)


@contextmanager
def handling_signals() -> Iterator[None]:
    """Turn SIGINT and SIGTERM into :class:`Interrupted` while the block runs (main thread only; otherwise a no-op).

    A signal the process was started to ignore (``nohup``, a background job of a script) stays ignored.
    """
    if threading.current_thread() is not threading.main_thread() or _state.installed:
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in SIGNALS}
    for sig in SIGNALS:
        if previous[sig] is not signal.SIG_IGN:
            signal.signal(sig, _handle)
    _state.installed, _state.requested, _state.count = True, None, 0
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        _state.installed, _state.requested, _state.count, _state.safe_points = False, None, 0, 0


@contextmanager
def safe_points() -> Iterator[None]:
    """Inside this block a signal only sets the flag that :func:`check` raises on (the block's loops must call it)."""
    _state.safe_points += 1
    try:
        yield
    finally:
        _state.safe_points -= 1


def at_safe_points(command: F) -> F:
    """Decorate a long command whose loops call :func:`check`: signals wait for the next safe point."""

    @functools.wraps(command)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with safe_points():
            return command(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


@contextmanager
def explain(describe: Callable[[], str]) -> Iterator[None]:
    """On :class:`Interrupted`, fill in its detail with ``describe()`` (what was kept, how to resume)."""
    try:
        yield
    except Interrupted as stop:
        if not stop.detail:
            try:
                stop.detail = describe()
            except Exception as err:  # the description must never hide the stop itself
                stop.detail = f"could not tell what was kept ({type(err).__name__})"
        raise


@contextmanager
def ignored_by_new_processes() -> Iterator[None]:
    """Processes started inside the block ignore SIGINT and SIGTERM for life (an ignored signal stays ignored across
    fork and exec, and Python keeps it so); this process handles them as before once the block ends.

    The signals are blocked meanwhile (Linux never discards a blocked signal), so one that arrives during the block
    is delivered to this process when it ends. Outside the main thread the block changes nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
