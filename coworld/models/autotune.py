"""The fastest of equivalent forms of one computation on this machine, chosen by timing them once per key.

Some operations of the update have forms that compute the same numbers (to float rounding) at speeds that depend on
the CPU: summing a convolution's output gradient for its bias ran 1.6-4.8x faster as a matrix-vector product than
as PyTorch's reduction at some of the tiny preset's widths on one Intel Xeon, and 1.3-10x slower on one AMD EPYC
(benchmarks/RESULTS.md, "Eighth pass" and "Eleventh pass"); on that AMD EPYC a linear layer's forward and input
gradient at the authors' sizes ran faster as oneDNN's 1 x 1 convolutions than as the BLAS matrix product, and at the
tiny preset's widths mostly not (:func:`coworld.models.networks.linear`; "Thirteenth pass").
As cuDNN's benchmark mode does for convolutions, :func:`fastest` times each form on the first call with a new key
(the operation and its input's shape) and returns the same choice for that key for the rest of the process.

The forms differ in summation order only, so two processes that choose differently compute numbers that differ in
their last bits. ``COWORLD_AUTOTUNE=0`` in the environment times nothing and takes every default form, for runs
that must repeat bit for bit from one process to the next.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Hashable, Mapping

import torch

__all__ = ["chosen", "enabled", "fastest"]

MARGIN = 0.1
"""Another form replaces the default only when its best time is at least this fraction faster: forms within it are
left to the default, so that timing noise between equal forms does not flip the choice from one process to the
next."""

REPEATS = 3
"""Timed calls of each form (after one untimed call), alternating; each form's best call counts."""

_choices: dict[Hashable, str] = {}
_lock = threading.Lock()


def enabled() -> bool:
    """Whether :func:`fastest` times forms (``COWORLD_AUTOTUNE`` unset or not ``0``)."""
    return os.environ.get("COWORLD_AUTOTUNE", "1") != "0"


def fastest(key: Hashable, forms: Mapping[str, Callable[[], object]], default: str) -> str:
    """The name of the fastest of ``forms`` (name -> a call of that form on the inputs at hand) for ``key``.

    The first call with ``key`` runs every form ``1 + REPEATS`` times and keeps the result; later calls only look it
    up. ``default`` is the form taken unless another is :data:`MARGIN` faster, when timing is off (:func:`enabled`),
    and while ``torch.compile`` traces (timing a trace measures nothing)."""
    choice = _choices.get(key)
    if choice is not None:
        return choice
    if not enabled() or torch.compiler.is_compiling():
        return default
    with _lock:  # one thread times at a time, so that two timings do not share the core
        if key not in _choices:
            _choices[key] = _time_forms(forms, default)
        return _choices[key]


def chosen() -> dict[Hashable, str]:
    """A copy of the choices made so far in this process, key -> form name."""
    return dict(_choices)


def _time_forms(forms: Mapping[str, Callable[[], object]], default: str) -> str:
    best = dict.fromkeys(forms, float("inf"))
    for form in forms.values():
        form()
    for _ in range(REPEATS):
        for name, form in forms.items():
            start = time.perf_counter()
            form()
            best[name] = min(best[name], time.perf_counter() - start)
    winner = min(best, key=best.__getitem__)
    return winner if best[winner] < (1.0 - MARGIN) * best[default] else default
