"""Batches made one ahead on a background thread: the next is drawn and laid out while the current update runs.

Sampling a batch and rearranging its images (:meth:`coworld.models.world_model.WorldModel.prepare`) read no
weight, so on a machine with a core to spare they can overlap the update that uses the batch before. The update
itself still runs on the caller's thread with its own torch threads; PyTorch and NumPy release the GIL in their
kernels, so the two threads work at once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

__all__ = ["Prefetcher", "prefetched", "stop_prefetch"]

T = TypeVar("T")


class Prefetcher(Generic[T]):
    """The items of ``source`` passed through ``prepare``, each made on a background thread while the caller works
    on the one before.

    The same items in the same order as ``map(prepare, source)``; the source is drawn from one thread only, one
    item ahead of the caller (never more: a batch waiting is the only extra memory). An error raised while making
    an item is raised by the ``next`` that would have returned it; the source's end ends the iteration. Call
    :meth:`close` (or use it as a context manager) when done: it waits for the item being made, then stops the
    thread.
    """

    def __init__(self, source: Iterator[Any], prepare: Callable[[Any], T] | None = None) -> None:
        self._source = source
        self._prepare = prepare
        self._executor: ThreadPoolExecutor | None = ThreadPoolExecutor(1, thread_name_prefix="coworld-prefetch")
        self._next: Future[T] | None = self._executor.submit(self._make)

    def _make(self) -> T:
        item = next(self._source)
        return item if self._prepare is None else self._prepare(item)

    def __iter__(self) -> Prefetcher[T]:
        return self

    def __next__(self) -> T:
        made = self._next
        if made is None:  # closed
            raise StopIteration
        try:
            item = made.result()
        except BaseException:  # the source's end (StopIteration) or its error: nothing more to make
            self.close()
            raise
        assert self._executor is not None  # open while a next item was pending
        self._next = self._executor.submit(self._make)
        return item

    def close(self) -> None:
        """Stop the thread after the item it is making (idempotent); later ``next`` calls end the iteration."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None
            self._next = None

    def __enter__(self) -> Prefetcher[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def prefetched(source: Iterator[Any], prepare: Callable[[Any], Any] | None, ahead: bool) -> Iterator[Any]:
    """The batch stream a trainer reads: ``source`` made ahead through ``prepare`` (a :class:`Prefetcher`) where
    ``ahead`` (``train.prefetch``), else ``source`` itself, each batch drawn when the update asks for it (whose own
    code then does what ``prepare`` would). Pass it to :func:`stop_prefetch` when done."""
    return Prefetcher(source, prepare) if ahead else source


def stop_prefetch(batches: Iterator[Any] | None) -> None:
    """Stop the thread of a :class:`Prefetcher` (any other iterator has none)."""
    if isinstance(batches, Prefetcher):
        batches.close()
