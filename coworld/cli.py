"""The ``coworld`` command line: a thin click group.

Each command lives in ``coworld/commands/<name>.py`` and is imported only when it runs, so ``--help`` and
``coworld tasks`` stay fast (no torch import). Any :class:`~coworld.errors.CoworldError`, and an output location
the system refuses to write (full, read-only, no permission), becomes one line on stderr and exit code 2. SIGINT and
SIGTERM stop a command with one line and exit code 130 / 143 (:mod:`coworld.interrupt`).
"""

from __future__ import annotations

import atexit
import importlib
import os
import signal
import sys
from typing import Any

import click

from coworld import __version__, allocator, interrupt
from coworld.errors import CoworldError
from coworld.storage import WRITE_ERRNOS, os_error_text

# command name -> "module:attribute"
COMMANDS = {
    "tasks": "coworld.commands.tasks:tasks",
    "render": "coworld.commands.tasks:render",
    "collect": "coworld.commands.collect:collect",
    "dataset": "coworld.commands.dataset:dataset",
    "train": "coworld.commands.train:train",
    "eval": "coworld.commands.evaluate:evaluate",
    "config": "coworld.commands.config:config",
    "viz": "coworld.commands.viz:viz",
    "sweep": "coworld.commands.sweep:sweep",
    "report": "coworld.commands.report:report",
}


SUMMARIES = {
    "tasks": "List the tasks, their returns and the source -> target pairs.",
    "render": "Save one random episode's frames as PNG files.",
    "collect": "Collect an offline dataset in a task.",
    "dataset": "Inspect, check, merge, import and export datasets.",
    "train": "Train CoWorld or a baseline on a dataset.",
    "eval": "Evaluate a trained run: return, value and reward checks.",
    "config": "Print the resolved config as JSON.",
    "viz": "Pictures of predictions, latents and datasets.",
    "sweep": "Run a paper table or a grid of runs.",
    "report": "Tables and figures from a folder of runs.",
}
"""Each command's first line, as `coworld --help` lists it without importing the commands (and torch)."""


class _LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        with formatter.section("Commands"):
            formatter.write_dl([(name, SUMMARIES[name]) for name in self.list_commands(ctx)])

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name].split(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as err:
            if err.name and err.name.startswith("coworld."):
                return None  # a command not built yet is simply absent
            raise

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except CoworldError as err:
            click.echo(f"error: {err}", err=True)
            sys.exit(2)
        except OSError as err:
            if err.errno not in WRITE_ERRNOS:
                raise
            click.echo(f"error: {os_error_text(err)}", err=True)
            sys.exit(2)

    def main(self, *args: Any, **kwargs: Any) -> Any:
        allocator.keep_freed_memory()  # glibc's malloc keeps freed tensors' memory (a no-op under tcmalloc)
        with interrupt.handling_signals():  # from the start: importing a command can take seconds
            try:
                interrupt.release_held_signals()  # a Ctrl-C while the command started again under tcmalloc
                return super().main(*args, **kwargs)
            except (interrupt.Interrupted, Exception) as err:
                stop = interrupt.stop_for(err)
                if stop is None:
                    raise
                click.echo(f"\n{stop}" if sys.stderr.isatty() else str(stop), err=True)  # after the ^C
                sys.exit(stop.exit_code)


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="coworld")
def main() -> None:
    """Offline visual RL across domains: datasets, CoWorld and baselines, evaluation, the paper's tables.

    Start with README.md; each command's details are in docs/usage.md, the algorithms in docs/algorithms.md,
    the paper's tables in docs/reproducing.md (paths in the coworld repository).
    """


STOP_CODES = (128 + signal.SIGINT, 128 + signal.SIGTERM)


def run() -> None:
    """The ``coworld`` command: :func:`main` in a process with tcmalloc preloaded where it is installed (the
    command starts over with it; :mod:`coworld.allocator`), else with glibc's malloc tuned.

    A command stopped by a signal has written and closed all it keeps by the time :func:`main` exits; the process
    then runs the exit functions Python registered and ends without the rest of the teardown, in which native thread
    pools that torch started for an update on another thread (``train.background_updates``) can abort it after its
    one line ("terminate called ...")."""
    allocator.exec_with_tcmalloc()
    try:
        main()
    except SystemExit as done:
        if done.code not in STOP_CODES:
            raise
        atexit._run_exitfuncs()  # what Python runs at exit (multiprocessing's clean-up among them), not C++'s
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(done.code)


if __name__ == "__main__":  # `python -m coworld.cli ...`, as the benchmarks run a checkout without installing it
    run()
