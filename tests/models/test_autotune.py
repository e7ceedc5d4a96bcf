"""Choosing the fastest form of an operation: timing once per key, the margin, and the switch that turns it off."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from coworld.models import autotune


class FakeClock:
    """``time.perf_counter`` for :mod:`autotune`: each form advances it by its own cost, so timings are exact."""

    def __init__(self) -> None:
        self.now = 0.0
        self.calls: dict[str, int] = {}

    def __call__(self) -> float:
        return self.now

    def form(self, name: str, cost: float) -> Callable[[], None]:
        def run() -> None:
            self.calls[name] = self.calls.get(name, 0) + 1
            self.now += cost

        return run


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    fake = FakeClock()
    monkeypatch.setattr(autotune.time, "perf_counter", fake)
    monkeypatch.setattr(autotune, "_choices", {})
    monkeypatch.delenv("COWORLD_AUTOTUNE", raising=False)
    return fake


def test_the_faster_form_is_chosen_once_per_key(clock: FakeClock) -> None:
    forms = {"a": clock.form("a", 2.0), "b": clock.form("b", 1.0)}
    assert autotune.fastest("op", forms, default="a") == "b"
    assert clock.calls == {"a": 1 + autotune.REPEATS, "b": 1 + autotune.REPEATS}
    assert autotune.fastest("op", forms, default="a") == "b"  # looked up: no form runs again
    assert clock.calls == {"a": 1 + autotune.REPEATS, "b": 1 + autotune.REPEATS}
    assert autotune.chosen() == {"op": "b"}
    # Another key is timed on its own: here the default is the faster.
    slow_b = {"a": clock.form("a", 1.0), "b": clock.form("b", 3.0)}
    assert autotune.fastest(("op", 2), slow_b, default="a") == "a"
    assert autotune.chosen() == {"op": "b", ("op", 2): "a"}


def test_a_form_within_the_margin_leaves_the_default(clock: FakeClock) -> None:
    near = 1.0 - 0.5 * autotune.MARGIN
    assert autotune.fastest("near", {"a": clock.form("a", 1.0), "b": clock.form("b", near)}, default="a") == "a"
    beyond = 1.0 - 2.0 * autotune.MARGIN
    assert autotune.fastest("beyond", {"a": clock.form("a", 1.0), "b": clock.form("b", beyond)}, default="a") == "b"


def test_coworld_autotune_0_times_nothing_and_takes_the_default(
    clock: FakeClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COWORLD_AUTOTUNE", "0")
    forms = {"a": clock.form("a", 2.0), "b": clock.form("b", 1.0)}
    assert autotune.fastest("op", forms, default="a") == "a"
    assert clock.calls == {} and autotune.chosen() == {}
    monkeypatch.setenv("COWORLD_AUTOTUNE", "1")
    assert autotune.fastest("op", forms, default="a") == "b"


def test_nothing_is_timed_while_torch_compile_traces(clock: FakeClock, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(autotune.torch.compiler, "is_compiling", lambda: True)
    forms = {"a": clock.form("a", 2.0), "b": clock.form("b", 1.0)}
    assert autotune.fastest("op", forms, default="a") == "a"
    assert clock.calls == {} and autotune.chosen() == {}
