"""Options shared by the commands: torch threads, and the types that check numbers and paths while parsing."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

F = TypeVar("F", bound=Callable[..., Any])


DEFAULT_THREADS = 1
"""torch's CPU threads when neither ``--threads`` nor ``OMP_NUM_THREADS`` says otherwise. A second thread speeds
a tiny update up on an idle machine but more than halves its speed when another process holds a core (OpenMP
threads wait for each other at every parallel region), and ``OMP_WAIT_POLICY=PASSIVE`` avoids the collapse only by
losing the gain; one thread never falls off that cliff (docs/performance.md; benchmarks/RESULTS.md, "Threads")."""


MAX_THREADS = 1024
"""The most torch threads a command takes (more than any machine's cores)."""


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
        type=click.IntRange(1, MAX_THREADS),
        default=None,
        expose_value=False,
        callback=_set_threads,
        help=f"CPU threads torch uses [default: OMP_NUM_THREADS if set, else {DEFAULT_THREADS}: safe on a busy"
        " machine; see docs/performance.md before raising it].",
    )(command)


# -- values checked while the options are parsed: every command's numbers and paths ---------------------------------

SEED = click.IntRange(0, 2**32 - 1)
"""A seed: what NumPy and torch accept from every command."""

MAX_COUNT = 10**9
"""The upper bound of a count without a tighter one of its own (episodes, steps): far beyond any real run, and still
a number every counter holds; ``tests/commands/test_option_table.py`` requires every integer option to have one."""


def count_type(low: int = 1, high: int = MAX_COUNT) -> click.IntRange:
    """A whole number in ``[low, high]``: a count, a size or a rate, always with an upper bound."""
    return click.IntRange(low, high)


class Number(click.FloatRange):
    """A finite number in a range (click's FloatRange lets ``nan`` and ``inf`` through)."""

    name = "number"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return number


class CheckedPath(click.Path):
    """A path option that is never empty; for an ``output``, one that can be made: its nearest existing folder is a
    folder (not a file) that this process may write in. Checked while the options are parsed, before any work.

    ``output``: 'file' (a file the command writes; its folder is made), 'folder' (a folder it writes into), or ''
    (an input, read only).
    """

    def __init__(self, *, output: str = "", **kwargs: Any) -> None:
        if output == "file":
            kwargs.setdefault("dir_okay", False)
        elif output == "folder":
            kwargs.setdefault("file_okay", False)
        super().__init__(path_type=Path, **kwargs)
        self.output = output

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and not value.strip():
            self.fail("an empty path; give a file or folder name.", param, ctx)
        if self.output:
            check_output(Path(os.fsdecode(value)), self.output, _option_name(param))
        return super().convert(value, param, ctx)


def _option_name(param: click.Parameter | None) -> str:
    if isinstance(param, click.Option):
        return max(param.opts, key=len)
    return param.human_readable_name if param is not None else "path"


def check_output(path: Path, kind: str, option: str) -> None:
    """Raise one CoworldError line unless ``path`` (a 'file' or a 'folder' the command writes, given as ``option``)
    can be made: its nearest existing folder is a folder, not a file, and this process may write in it."""
    from coworld.errors import ConfigError
    from coworld.storage import check_writable

    if kind == "file" and path.is_dir():
        raise ConfigError(f"{path} is a folder, not a file; choose another {option}")
    if kind == "folder" and path.exists() and not path.is_dir():
        raise ConfigError(f"{path} is a file, not a folder; choose another {option}")
    folder = path if kind == "folder" else path.parent
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{option} {path}: {existing} is a file, not a folder; choose another {option}")
    check_writable(folder, option)


def input_path(**kwargs: Any) -> CheckedPath:
    """A path the command reads (never empty)."""
    return CheckedPath(**kwargs)


def output_file(**kwargs: Any) -> CheckedPath:
    """A file the command writes: not a folder, its folder can be made and written."""
    return CheckedPath(output="file", **kwargs)


def output_folder(**kwargs: Any) -> CheckedPath:
    """A folder the command writes into: not a file, and it can be made and written."""
    return CheckedPath(output="folder", **kwargs)


def distinct_outputs(paths: dict[str, Path | None]) -> None:
    """Refuse two outputs of one command that name the same file (``--out a.png --json a.png``), in one line."""
    from coworld.errors import ConfigError

    seen: dict[Path, str] = {}
    for option, path in paths.items():
        if path is None:
            continue
        key = Path(os.path.abspath(path))
        if key in seen:
            raise ConfigError(f"{seen[key]} and {option} both name {path}; give each output its own file")
        seen[key] = option


def capped_jobs(requested: int, threads: int, option: str = "--jobs") -> tuple[int, str]:
    """``requested`` processes of ``threads`` threads each capped at the cores available, and a note when capped."""
    from coworld.envs.vector import available_cores

    cores = available_cores()
    most = max(1, cores // threads)
    if requested <= most:
        return requested, ""
    per = f" of {threads} threads each" if threads > 1 else ""
    return most, f"{option} {requested} capped to {most}: one run{per} per CPU core ({cores} available)"
