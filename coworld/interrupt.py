"""Ctrl-C and SIGTERM: long jobs stop at a safe point within seconds, say what they kept, and exit 130 / 143.

Python turns SIGINT into a ``KeyboardInterrupt`` raised wherever the main thread happens to be. Raised inside a
callback (an h5py object being freed, a weakref callback) it is printed as "Exception ignored" and lost, so the job
runs on; raised in the middle of a write it leaves the writer half-updated. SIGTERM kills the process outright.

So the CLI installs :func:`handling_signals`: a signal raises :class:`Interrupted` at once, except inside the
:func:`at_safe_points` part of a long command, where it only sets a flag and the long loops call :func:`check`
where stopping leaves their output whole (between environment steps, updates, episodes). If no check comes within
:data:`GRACE_SECONDS` (the main thread waits for worker processes to start, or runs one long update), the signal is
delivered again to the main thread and raises there, interrupting the wait; raised where it cannot propagate (a
weakref callback, of which torch.compile runs many) it is delivered again shortly. Stopping anywhere is safe for the
files: datasets commit whole episodes and checkpoints are renamed into place, as they must be for ``kill -9``. A second
signal stops at once; a third is not caught at all. Once a stop is asked, an error on the way out (worker processes
killed by the same SIGTERM, sent to the whole process group) is part of the stop, and warnings are no longer shown:
not by a filter, which a ``warnings.catch_warnings`` block (torch.compile enters many) puts back as it found it, but
by the hook every warning is shown through.
The CLI prints one line (what was kept, how to resume) and exits with 128 + the signal number.

Worker processes of vector environments ignore SIGINT (:func:`ignored_by_new_processes` around their start): a Ctrl-C
in a terminal reaches the whole process group, and the parent closes its workers itself. They keep SIGTERM, which is
how Gymnasium ends a worker that does not answer.
"""

from __future__ import annotations

import functools
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

SIGNALS = (signal.SIGINT, signal.SIGTERM)
GRACE_SECONDS = 1.5
"""How long a stop waits for the next :func:`check` before it interrupts the main thread wherever it is."""
RETRY_SECONDS = 0.1
"""How soon a stop that was raised where it could not propagate (a weakref callback) is delivered again."""


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
    def __init__(self) -> None:
        self.installed = False
        self.safe_points = 0  # > 0 inside at_safe_points(): a signal waits for check()
        self.requested: int | None = None  # the signal a stop was asked by
        self.raised = False  # Interrupted was raised: the job is cleaning up, no more escalation
        self.escalating = False  # the grace period ran out: the next delivery raises wherever the main thread is
        self.count = 0  # signals received from outside
        self.timer: threading.Timer | None = None
        self.previous_unraisable: Callable[[Any], Any] = sys.__unraisablehook__
        self.previous_show: Callable[[Any], Any] = warnings._showwarnmsg


_state = _State()


def check() -> None:
    """Raise :class:`Interrupted` if SIGINT or SIGTERM arrived since the job started; call it where stopping is safe."""
    if _state.requested is not None:
        _raise(_state.requested)


def requested() -> bool:
    """Whether a stop was asked."""
    return _state.requested is not None


def _raise(signum: int) -> None:
    _state.raised = True
    if _state.timer is not None:
        _state.timer.cancel()
    raise Interrupted(signum)


def _handle(signum: int, frame: Any) -> None:
    if _state.escalating:  # our own delivery, after the grace period
        _state.escalating = False
        _raise(signum)
    _state.count += 1
    if _state.count >= 2:  # the second signal stops at once; a third ends the process the operating system's way
        signal.signal(signum, signal.SIG_DFL)
    first = _state.requested is None
    _state.requested = _state.requested or signum
    if _state.safe_points > 0 and first:
        _state.timer = threading.Timer(GRACE_SECONDS, _escalate, args=(signum,))
        _state.timer.daemon = True
        _state.timer.start()
        return
    _raise(signum)


def _swallowed(args: Any) -> None:
    """``sys.unraisablehook`` while signals are handled: a stop raised inside a weakref callback or a ``__del__``
    (torch.compile runs many) cannot propagate and would be lost, so it is delivered again shortly, wherever the main
    thread is then; anything else goes to the hook that was there before."""
    if isinstance(args.exc_value, Interrupted) and _state.installed:
        _state.raised = False
        _state.timer = threading.Timer(RETRY_SECONDS, _escalate, args=(args.exc_value.signum,))
        _state.timer.daemon = True
        _state.timer.start()
        return
    _state.previous_unraisable(args)


def _show_unless_stopping(message: Any) -> None:
    """``warnings._showwarnmsg`` while signals are handled: once a stop is asked, what is warned about on the way out
    (cleanup code, PyTorch's anomaly mode reporting the stop inside a backward pass as an error) is noise; before,
    each warning is shown as it was."""
    if _state.requested is None:
        _state.previous_show(message)


def _escalate(signum: int) -> None:
    """Runs in the timer thread: no check came in time, so interrupt the main thread where it is."""
    if _state.raised or not _state.installed:
        return
    _state.escalating = True
    signal.pthread_kill(threading.main_thread().ident or 0, signum)


@contextmanager
def handling_signals() -> Iterator[None]:
    """Turn SIGINT and SIGTERM into :class:`Interrupted` while the block runs (main thread only; otherwise a no-op).

    A signal the process was started to ignore (``nohup``, a background job of a script) stays ignored.
    """
    global _state
    if threading.current_thread() is not threading.main_thread() or _state.installed:
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in SIGNALS}
    _state = _State()
    for sig in SIGNALS:
        if previous[sig] is not signal.SIG_IGN:
            signal.signal(sig, _handle)
    _state.previous_unraisable = sys.unraisablehook
    sys.unraisablehook = _swallowed
    _state.previous_show = warnings._showwarnmsg  # the hook catch_warnings leaves alone, unlike the filters
    warnings._showwarnmsg = _show_unless_stopping
    _state.installed = True
    try:
        yield
    finally:
        sys.unraisablehook = _state.previous_unraisable
        warnings._showwarnmsg = _state.previous_show
        if _state.timer is not None:
            _state.timer.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        _state = _State()


def release_held_signals() -> None:
    """Deliver SIGINT and SIGTERM that were blocked while the command started again under tcmalloc
    (:func:`coworld.allocator.exec_with_tcmalloc`); call it inside :func:`handling_signals`, where a pending one
    raises :class:`Interrupted` like any other. Nothing happens where none was blocked."""
    if threading.current_thread() is threading.main_thread():
        signal.pthread_sigmask(signal.SIG_UNBLOCK, SIGNALS)


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
    """On :class:`Interrupted`, fill in its detail with ``describe()`` (what was kept, how to resume).

    An unexpected error after a stop was asked is taken for part of the stop (see the module docstring); errors a
    person can act on (:class:`~coworld.errors.CoworldError`, e.g. a full disk) are reported as themselves.
    """
    from coworld.errors import CoworldError

    try:
        yield
    except Interrupted as stop:
        if not stop.detail:
            stop.detail = _describe(describe)
        raise
    except CoworldError:
        raise
    except Exception as err:
        if _state.requested is None:
            raise
        raise Interrupted(_state.requested, _describe(describe)) from err


def _describe(describe: Callable[[], str]) -> str:
    try:
        return describe()
    except Exception as err:  # the description must never hide the stop itself
        return f"could not tell what was kept ({type(err).__name__})"


def stop_for(err: BaseException) -> Interrupted | None:
    """The stop an error belongs to: the error itself, or any unexpected error raised after a stop was asked."""
    if isinstance(err, Interrupted):
        return err
    if _state.requested is not None and isinstance(err, Exception):
        return Interrupted(_state.requested)
    return None


@contextmanager
def ignored_by_new_processes() -> Iterator[None]:
    """Processes started inside the block ignore SIGINT for life (an ignored signal stays ignored across fork and exec,
    and Python keeps it so); this process handles it as before once the block ends.

    Keep the block short (just the process start): a SIGINT that arrives meanwhile may be lost, since another thread
    of this process can take it while it is ignored (the main thread blocks it). Outside the main thread the block
    changes nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
