"""The ``coworld`` command line: a thin click group.

Each command lives in ``coworld/commands/<name>.py`` and is imported only when it runs, so ``--help`` and
``coworld tasks`` stay fast (no torch import). Any :class:`~coworld.errors.CoworldError` becomes one line on
stderr and exit code 2.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

import click

from coworld import __version__
from coworld.errors import CoworldError

# command name -> "module:attribute"
COMMANDS = {
    "tasks": "coworld.commands.tasks:tasks",
    "render": "coworld.commands.tasks:render",
    "collect": "coworld.commands.collect:collect",
    "dataset": "coworld.commands.dataset:dataset",
    "train": "coworld.commands.train:train",
    "eval": "coworld.commands.evaluate:evaluate",
    "sweep": "coworld.commands.sweep:sweep",
    "report": "coworld.commands.report:report",
}


class _LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

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


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="coworld")
def main() -> None:
    """Offline visual RL across domains: collect datasets, train CoWorld and baselines, evaluate."""
