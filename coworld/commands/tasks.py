"""``coworld tasks`` (the task table and the paper's source -> target pairs) and ``coworld render`` (PNG frames)."""

from __future__ import annotations

from pathlib import Path

import click

from coworld import algorithms
from coworld.commands.options import SEED, count_type, output_folder
from coworld.envs.registry import PAIRS, TASKS, task_spec
from coworld.errors import ConfigError


@click.command("tasks")
def tasks() -> None:
    """List the tasks, their returns and the source -> target pairs.

    Every task (with its reference return and medium level), the source -> target pairs, and which algorithms need
    a source task. Docs: docs/usage.md, "Tasks".
    """
    header = ("task", "family", "actions", "episode", "repeat", "random", "reference", "medium", "modification")
    rows = [
        (
            t.name,
            t.family,
            str(t.action_size),
            str(t.episode_length),
            str(t.action_repeat),
            _number(t.random_return),
            _number(t.reference_return),
            _number(t.medium_return),
            t.modification or "-",
        )
        for t in TASKS.values()
    ]
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header) - 1)]
    for row in [header, *rows]:
        click.echo("  ".join(cell.ljust(width) for cell, width in zip(row[:-1], widths, strict=True)) + "  " + row[-1])
    click.echo("\nepisode: agent steps per episode; repeat: simulator steps per agent step.")
    click.echo("random: mean return of uniform random actions; reference: best return known to be reachable;")
    click.echo(
        "medium: a third of it (a third of the way from random where that is higher), where `coworld collect` stops"
        " a medium-replay dataset (--stop-return overrides)."
    )
    click.echo("\nwhere the references come from:")
    sources: dict[str, list[str]] = {}
    for t in TASKS.values():
        sources.setdefault(t.reference_source, []).append(t.name)
    for source, names in sources.items():
        click.echo(f"  {', '.join(names)}: {source}")
    click.echo("\nsource -> target pairs:")
    width = max(len(source) for source, _ in PAIRS)
    for source, target in PAIRS:
        click.echo(f"  {source.ljust(width)} -> {target}")
    online, offline = algorithms.names(needs_source=True), algorithms.names(needs_source=False)
    click.echo("\nalgorithms (`coworld train --algo`):")
    click.echo(f"  need --source (they also learn online in the source task): {', '.join(online)}")
    click.echo(f"  learn from the target dataset alone: {', '.join(offline)}")


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


@click.command("render")
@click.option("--task", "task_name", required=True, help="Task name (see `coworld tasks`).")
@click.option("--out", "out_dir", required=True, type=output_folder(), help="Folder.")
@click.option(
    "--frames",
    default=50,
    show_default=True,
    type=count_type(1, 100_000),
    help="Frames to save (the first is the reset).",
)
@click.option("--seed", default=0, show_default=True, type=SEED, help="Seed of the env and the random actions.")
@click.option("--image-size", default=64, show_default=True, type=count_type(8, 1024), help="Frame side in pixels.")
def render(task_name: str, out_dir: Path, frames: int, seed: int, image_size: int) -> None:
    """Save one random episode's frames as PNG files.

    The files are <task>_<step>.png under --out. Docs: docs/usage.md, "Tasks".
    """
    import imageio.v3 as iio

    from coworld.envs import make

    spec = task_spec(task_name)
    if not 1 <= frames <= spec.episode_length + 1:
        raise ConfigError(f"--frames must be between 1 and {spec.episode_length + 1} (one {task_name} episode)")
    env = make(task_name, seed=seed, image_size=image_size)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        frame, _ = env.reset()
        for step in range(frames):
            if step:
                frame, *_ = env.step(env.action_space.sample())
            iio.imwrite(out_dir / f"{task_name}_{step:04d}.png", frame)
    finally:
        env.close()
    click.echo(f"wrote {frames} frames of {task_name} to {out_dir}")
