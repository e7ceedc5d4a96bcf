"""The background batch maker: the same items in the same order, one ahead, its errors raised where they belong."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from coworld.data.prefetch import Prefetcher


class Counting:
    """An iterator of 0..n-1 that records how many items were drawn and from which threads; raises at ``fail_at``."""

    def __init__(self, n: int, fail_at: int | None = None) -> None:
        self.n, self.fail_at = n, fail_at
        self.drawn = 0
        self.threads: set[str] = set()
        self.fourth = threading.Event()

    def __iter__(self) -> Iterator[int]:
        return self

    def __next__(self) -> int:
        self.threads.add(threading.current_thread().name)
        if self.drawn == self.n:
            raise StopIteration
        if self.drawn == self.fail_at:
            raise ValueError(f"item {self.drawn} is corrupt")
        self.drawn += 1
        if self.drawn == 4:
            self.fourth.set()
        return self.drawn - 1


def _prefetch_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("coworld-prefetch")]


def test_the_same_items_in_order_made_on_another_thread_one_ahead() -> None:
    source = Counting(5)
    made_on: list[str] = []

    def prepare(item: int) -> int:
        made_on.append(threading.current_thread().name)
        return 10 * item

    with Prefetcher(source, prepare) as items:
        assert [next(items) for _ in range(3)] == [0, 10, 20]
        assert source.fourth.wait(10)  # the next is made without being asked for
        time.sleep(0.2)
        assert source.drawn == 4  # the three taken and the one made ahead, no more
    assert source.threads == set(made_on) and len(source.threads) == 1
    assert next(iter(source.threads)).startswith("coworld-prefetch")
    assert not _prefetch_threads()
    with pytest.raises(StopIteration):  # closed: the iteration is over
        next(items)
    assert list(Prefetcher(Counting(4))) == [0, 1, 2, 3]  # without `prepare`, to the source's end
    assert not _prefetch_threads()


def test_an_error_is_raised_by_the_next_that_would_have_returned_it() -> None:
    items = Prefetcher(Counting(5, fail_at=2))
    assert next(items) == 0 and next(items) == 1
    with pytest.raises(ValueError, match="item 2 is corrupt"):
        next(items)
    assert not _prefetch_threads()
    with pytest.raises(StopIteration):
        next(items)
    items.close()  # idempotent


def test_an_error_in_prepare_is_raised_the_same_way() -> None:
    def prepare(item: int) -> int:
        if item == 1:
            raise RuntimeError("cannot lay out item 1")
        return item

    items = Prefetcher(Counting(3), prepare)
    assert next(items) == 0
    with pytest.raises(RuntimeError, match="cannot lay out item 1"):
        next(items)
    assert not _prefetch_threads()
