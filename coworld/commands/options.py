"""Options shared by the commands that run torch models."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar

import click

F = TypeVar("F", bound=Callable[..., Any])


DEFAULT_THREADS = 1
"""torch's CPU threads when neither ``--threads`` nor ``OMP_NUM_THREADS`` says otherwise. Measured on 2 cores
(benchmarks/RESULTS.md, "Threads"): a second thread makes a tiny update 1.4x faster on an idle machine but 2.6x
slower when another process holds a core (OpenMP threads wait for each other at every parallel region), and
``OMP_WAIT_POLICY=PASSIVE`` avoids the collapse only by losing the gain; one thread never falls off that cliff."""


def _set_threads(ctx: click.Context, param: click.Parameter, value: int | None) -> None:
    if value is None:
        if os.environ.get("OMP_NUM_THREADS"):
            return  # the user's own setting, which torch already follows
        value = DEFAULT_THREADS
    import torch

    torch.set_num_threads(value)


def threads_option(command: F) -> F:
    """``--threads N``: torch's CPU threads for this command (applied while the options are parsed)."""
    return click.option(
        "--threads",
        type=click.IntRange(min=1),
        default=None,
        expose_value=False,
        callback=_set_threads,
        help=f"CPU threads torch uses [default: OMP_NUM_THREADS if set, else {DEFAULT_THREADS}: safe on a busy"
        " machine; see the README's 'Measured' before raising it].",
    )(command)
