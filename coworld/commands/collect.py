"""``coworld collect``: build an offline dataset by running a behaviour policy in a task.

The policy is pluggable: ``--policy`` picks an entry of :data:`COLLECTORS`, each a function taking the parsed
options. ``random`` (uniform actions) makes a ``random``-quality dataset.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from coworld import interrupt
from coworld.commands.options import SEED, Number, count_type, output_file, threads_option
from coworld.data import CODECS
from coworld.errors import CoworldError, StorageError
from coworld.text import count

RESUME = "rerun the same command with --resume to continue"


def _collect_random(options: dict[str, Any]) -> None:
    from coworld.data import collect_random
    from coworld.data.collect import default_dataset_path
    from coworld.envs.vector import sensible_workers
    from coworld.storage import check_writable

    workers, note = sensible_workers(options["workers"], options["episodes"])
    if note:
        click.echo(f"note: {note}", err=True)
    out = options["out"] or default_dataset_path(options["task"], "random")
    check_writable(out.parent, "--out")
    with _resumable(out):
        summary = collect_random(
            options["task"],
            out,
            episodes=options["episodes"],
            max_steps=options["max_steps"],
            seed=options["seed"],
            workers=workers,
            resume=options["resume"],
            force=options["force"],
            compression=options["compression"],
            progress=not options["quiet"],
        )
    rate = summary.env_steps / summary.seconds if summary.seconds > 0 else 0.0
    click.echo(
        f"wrote {summary.path}: {count(summary.episodes, 'episode')}, {count(summary.steps, 'step')}, mean return "
        f"{summary.mean_return:.1f} ({count(summary.env_steps, 'env step')} in {summary.seconds:.0f} s,"
        f" {rate:,.0f} steps/s)"
    )


def _collect_dreamerv2(options: dict[str, Any]) -> None:
    from coworld.data.collect import default_dataset_path
    from coworld.storage import check_writable
    from coworld.training.collect import collect_dreamerv2

    if options["workers"] != 1:
        raise CoworldError("--workers sets random collection; for dreamerv2 use --set train.envs=N")
    quality = options["quality"] or "medium-replay"
    out = options["out"] or default_dataset_path(options["task"], quality)
    check_writable(out.parent, "--out")
    with _resumable(out, agent=True):
        summary = collect_dreamerv2(
            options["task"],
            out,
            quality=quality,
            preset=options["preset"],
            overrides=options["overrides"],
            max_steps=options["max_steps"],
            stop_return=options["stop_return"],
            episodes=options["episodes"] or 10,
            seed=options["seed"],
            device=options["device"],
            resume=options["resume"],
            force=options["force"],
            compression=options["compression"],
            progress=not options["quiet"],
            warn=lambda message: click.echo(f"warning: {message}", err=True),
        )
    last = "none" if summary.last_eval_return is None else f"{summary.last_eval_return:.1f}"
    click.echo(
        f"wrote {summary.path}: {count(summary.episodes, 'episode')}, {count(summary.steps, 'step')} ({quality});"
        f" stopped on {summary.stop_reason}; last evaluation return {last}"
    )


@contextmanager
def _resumable(out: Path, agent: bool = False) -> Iterator[None]:
    """Complete the line of a stop (Ctrl-C, SIGTERM) or a refused write: what ``out`` keeps, how to continue."""
    try:
        with interrupt.explain(lambda: f"{_kept(out, agent)}; {RESUME}"):
            yield
    except StorageError as err:
        fix = "free space" if err.disk_full else "make it writable"
        raise StorageError(f"{err}; {fix}, then {RESUME}", err.reason) from None


def _kept(out: Path, agent: bool) -> str:
    """What a stopped collection left: the whole episodes in the dataset (and the agent's checkpoint)."""
    from coworld.data import open_dataset

    if out.exists():
        with open_dataset(out) as data:
            kept = f"{out} keeps {count(data.num_episodes, 'whole episode')} ({count(data.num_steps, 'step')})"
    else:
        kept = f"no episode was finished, so {out} was not made"
    if agent:
        run = out.with_name(out.name.removesuffix(".h5") + ".run")
        has = (run / "checkpoint.pt").exists()
        kept += f"; the agent's last checkpoint is in {run}" if has else "; the agent has no checkpoint yet"
    return kept


# --policy name -> collector
COLLECTORS: dict[str, Callable[[dict[str, Any]], None]] = {
    "random": _collect_random,
    "dreamerv2": _collect_dreamerv2,
}


@click.command()
@click.option("--task", required=True, help="Task name (see `coworld tasks`).")
@click.option(
    "--policy",
    type=click.Choice(sorted(COLLECTORS)),
    default="dreamerv2",
    show_default=True,
    help="dreamerv2: train DreamerV2 online and record it (medium-replay etc.); random: uniform actions.",
)
@click.option(
    "--quality",
    type=click.Choice(["medium-replay", "medium-expert", "medium", "expert"]),
    default=None,
    help="dreamerv2 only: medium-replay (all it experienced while learning, to the medium level; default),"
    " medium-expert (the same, on to the expert level) or episodes of the trained policy (medium, expert;"
    " --episodes of them).",
)
@click.option(
    "--preset",
    default="paper",
    show_default=True,
    help="dreamerv2 only: paper (Table 3, GPU), cpu (learning on 2 cores) or tiny (CPU minutes, tests).",
)
@click.option(
    "--stop-return",
    type=Number(-1e9, 1e9),
    default=None,
    help="dreamerv2 only: stop training once evaluation reaches this [default: 1/3 of the task's reference; the"
    " reference for --quality medium-expert; none for expert].",
)
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="dreamerv2 only: config override.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
@click.option("--episodes", type=count_type(), help="Collect exactly this many episodes.")
@click.option("--max-steps", type=count_type(), help="Collect exactly this many steps (rows).")
@click.option("--out", type=output_file(), help="Dataset file [default: datasets/<task>-<quality>.h5].")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seeds the environments and policy.")
@click.option("--workers", type=count_type(), default=1, show_default=True, help="Parallel environments.")
@click.option("--resume", is_flag=True, help="Continue a partial dataset at --out up to the requested amount.")
@click.option("--force", is_flag=True, help="Overwrite an existing dataset at --out.")
@click.option("--compression", type=click.Choice(CODECS), default="gzip", show_default=True, help="Frame codec.")
@threads_option
@click.option("--quiet", is_flag=True, help="No progress bar.")
@interrupt.at_safe_points
def collect(**options: Any) -> None:
    """Collect an offline dataset in a task.

    Each episode of TASK is written as soon as it ends.

    By default DreamerV2 learns online in TASK and everything it experiences becomes a medium-replay dataset,
    until its evaluation return reaches --stop-return or --max-steps rows exist. With --policy random, uniform
    actions make a random-quality dataset. Stopped (Ctrl-C, SIGTERM, a kill, a full disk), rerun with --resume to
    continue. Docs: datasets/README.md (the format), docs/usage.md.
    """
    if options["policy"] == "random" and options["quality"] is not None:
        raise CoworldError("--quality is for --policy dreamerv2; random collection makes a 'random' dataset")
    COLLECTORS[options["policy"]](options)
