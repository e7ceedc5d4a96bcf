"""Progress bars that suit where the output goes.

On a terminal, a tqdm bar redrawn in place. When stderr is a file or a pipe (a batch job's log, ``2> log``), the
same tqdm bar writes one plain line every ``PLAIN_EVERY_S`` seconds instead of carriage-return redraws, each
saying what its numbers count, e.g. ``collect: 12,000/100,000 env steps (12%) [05:01<36:50, 39.8 env steps/s]``.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import Any, TextIO

import tqdm

PLAIN_EVERY_S = 30.0
"""Seconds between the plain progress lines written when stderr is not a terminal."""

_PLAIN_FORMAT = "{desc}: {n_fmt}/{total_fmt}{unit} ({percentage:.0f}%) [{elapsed}<{remaining}, {rate_fmt}{postfix}]"


class _Lines:
    """A file for tqdm that turns each in-place redraw into one line of its own."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        text = text.replace("\r", "").strip()
        if text:
            self.stream.write(text + "\n")

    def flush(self) -> None:
        self.stream.flush()


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    total: int | None = None,
    desc: str,
    unit: str,
    enabled: bool = True,
    **kwargs: Any,
) -> tqdm.tqdm:
    """A tqdm bar over ``iterable`` or ``total`` items counted in ``unit`` (plural, e.g. "env steps"); disabled
    when not ``enabled``. See the module docstring for what it writes to a terminal and elsewhere."""
    if not enabled:
        return tqdm.tqdm(iterable, total=total, disable=True, **kwargs)
    if sys.stderr.isatty():
        return tqdm.tqdm(iterable, total=total, desc=desc, unit=f" {unit}", dynamic_ncols=True, **kwargs)
    return tqdm.tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=f" {unit}",
        file=_Lines(sys.stderr),
        mininterval=PLAIN_EVERY_S,
        maxinterval=PLAIN_EVERY_S,
        bar_format=_PLAIN_FORMAT,
        **kwargs,
    )
