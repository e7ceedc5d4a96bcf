"""``coworld collect``: build an offline dataset by running a behaviour policy in a task.

The policy is pluggable: ``--policy`` picks an entry of :data:`COLLECTORS`, each a function taking the parsed
options. ``random`` (uniform actions) makes a ``random``-quality dataset.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from coworld.data import CODECS
from coworld.errors import CoworldError


def _collect_random(options: dict[str, Any]) -> None:
    from coworld.data import collect_random

    summary = collect_random(
        options["task"],
        options["out"],
        episodes=options["episodes"],
        max_steps=options["max_steps"],
        seed=options["seed"],
        workers=options["workers"],
        resume=options["resume"],
        force=options["force"],
        compression=options["compression"],
        progress=not options["quiet"],
    )
    rate = summary.env_steps / summary.seconds if summary.seconds > 0 else 0.0
    click.echo(
        f"wrote {summary.path}: {summary.episodes:,} episodes, {summary.steps:,} steps, mean return "
        f"{summary.mean_return:.1f} ({summary.env_steps:,} env steps in {summary.seconds:.0f} s, {rate:,.0f} steps/s)"
    )


def _collect_dreamerv2(options: dict[str, Any]) -> None:
    raise CoworldError("--policy dreamerv2 is not available yet; use --policy random")


# --policy name -> collector
COLLECTORS: dict[str, Callable[[dict[str, Any]], None]] = {
    "random": _collect_random,
    "dreamerv2": _collect_dreamerv2,
}


@click.command()
@click.option("--task", required=True, help="Task name (see `coworld tasks`).")
@click.option(
    "--policy", type=click.Choice(sorted(COLLECTORS)), default="random", show_default=True, help="Behaviour policy."
)
@click.option("--episodes", type=click.IntRange(min=1), help="Collect exactly this many episodes.")
@click.option("--max-steps", type=click.IntRange(min=1), help="Collect exactly this many steps (rows).")
@click.option("--out", type=click.Path(path_type=Path), help="Dataset file [default: datasets/<task>-<quality>.h5].")
@click.option("--seed", type=int, default=0, show_default=True, help="Seeds the environments and the policy.")
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True, help="Parallel environments.")
@click.option("--resume", is_flag=True, help="Continue a partial dataset at --out up to the requested amount.")
@click.option("--force", is_flag=True, help="Overwrite an existing dataset at --out.")
@click.option("--compression", type=click.Choice(CODECS), default="gzip", show_default=True, help="Frame codec.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def collect(**options: Any) -> None:
    """Collect an offline dataset of TASK with a behaviour policy; each episode is written as soon as it ends."""
    COLLECTORS[options["policy"]](options)
