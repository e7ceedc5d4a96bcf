"""Options shared by the commands that run torch models."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import click

F = TypeVar("F", bound=Callable[..., Any])


def _set_threads(ctx: click.Context, param: click.Parameter, value: int | None) -> None:
    if value is not None:
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
        help="CPU threads torch uses [default: torch's choice, one per core]. See the README on busy machines.",
    )(command)
