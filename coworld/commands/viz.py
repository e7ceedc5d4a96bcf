"""``coworld viz``: look inside a run's world models (open-loop predictions, latent t-SNE) and at a dataset."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from coworld.commands.options import (
    SEED,
    Number,
    count_type,
    distinct_outputs,
    input_path,
    output_file,
    threads_option,
)
from coworld.training.chosen_source import trained_source

DEVICES = click.Choice(["auto", "cpu", "cuda"])
MAX_SHOWN = 64
"""The most episodes one picture or video shows."""
MAX_STEPS = 10_000
"""The longest sequence (--length, --context): longer than any task's episode."""
MAX_SCALE = 8
"""The largest pixel enlargement: a default prediction strip at scale 8 is already 25,600 x 5,120 pixels."""
MAX_FPS = 120
MAX_LATENT_FRAMES = 5_000
"""The most frames per domain of a t-SNE picture (3 groups of them: t-SNE time grows faster than their number)."""
MAX_PERPLEXITY = 1_000.0


@click.group()
def viz() -> None:
    """Pictures of predictions, latents and datasets.

    What the models predict and encode, and what a dataset holds. Docs: docs/usage.md, "Seeing inside the
    models".
    """


@viz.command()
@click.option("--ckpt", required=True, type=input_path(), help="Run folder (coworld or dreamerv2).")
@click.option("--out", required=True, type=output_file(), help=".mp4, .gif or .png")
@click.option("--episodes", type=count_type(1, MAX_SHOWN), default=2, show_default=True, help="Episodes shown.")
@click.option("--context", type=count_type(1, MAX_STEPS), default=5, show_default=True, help="Observed frames.")
@click.option("--length", type=count_type(2, MAX_STEPS), default=50, show_default=True, help="Steps per sequence.")
@click.option("--start", type=count_type(0, MAX_STEPS), default=0, show_default=True, help="First step shown.")
@click.option("--dataset", type=input_path(), default=None, help="Target episodes from here.")
@click.option("--online", is_flag=True, help="Fresh episodes of the run's target policy instead of dataset ones.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the --online episodes.")
@click.option("--scale", type=count_type(1, MAX_SCALE), default=None, help="Pixel enlargement [png 1, video 2].")
@click.option("--fps", type=count_type(1, MAX_FPS), default=5, show_default=True)
@threads_option
@click.option("--device", type=DEVICES, default="auto", show_default=True)
def predictions(ckpt, out, episodes, context, length, start, dataset, online, seed, scale, fps, device) -> None:
    """Open-loop prediction (Figure 5): observe CONTEXT frames, imagine the rest from the recorded actions.

    Shows truth, each model's frames and |error| over time, for a CoWorld run both the target and the source
    model on the same target episodes, and prints the per-step error (MSE, pixels in [0, 1]).
    """
    from coworld.viz.media import output_kind
    from coworld.viz.predictions import error_table, predict, prediction_strip, prediction_video
    from coworld.viz.runs import load_run_models, prediction_windows, target_episodes

    kind = output_kind(out)
    run = load_run_models(ckpt, device=device)
    chosen, where = target_episodes(run, episodes, dataset=dataset, online=online, seed=seed)
    batch = prediction_windows(chosen, start=start, length=length, context=context)
    pred = predict(run.world_models(), batch, context)
    click.echo(f"{run.run_dir} ({run.algo} run): {where}, steps {start}..{start + batch['image'].shape[1] - 1}")
    click.echo(error_table(pred))
    _save(
        out,
        kind,
        image=lambda: prediction_strip(pred, scale=scale or 1),
        video=lambda: prediction_video(pred, scale=scale or 2),
        fps=fps,
    )


@viz.command()
@click.option("--ckpt", required=True, type=input_path(), help="Run folder (coworld or dreamerv2).")
@click.option("--out", required=True, type=output_file(), help="The picture (.png).")
@click.option(
    "--frames", type=count_type(10, MAX_LATENT_FRAMES), default=500, show_default=True, help="Frames per domain."
)
@click.option("--length", type=count_type(1, MAX_STEPS), default=25, show_default=True, help="Steps per sequence.")
@click.option("--dataset", type=input_path(), default=None, help="Target frames from here.")
@click.option(
    "--source-dataset",
    type=input_path(),
    default=None,
    help="Source frames from here [default: a coworld run's source_replay.h5].",
)
@click.option("--source", default=None, help="Source task for random-action episodes when there is no dataset.")
@click.option("--perplexity", type=Number(1, MAX_PERPLEXITY), default=30.0, show_default=True)
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--json", "json_out", type=output_file(), help="Write the numbers here.")
@threads_option
@click.option("--device", type=DEVICES, default="auto", show_default=True)
def latents(ckpt, out, frames, length, dataset, source_dataset, source, perplexity, seed, json_out, device) -> None:
    """t-SNE of posterior latents by domain and encoder (Figure 6), with the numbers that say the same.

    A CoWorld run: source frames through the source encoder, target frames through the target encoder, and
    target frames through the source encoder. A dreamerv2 run: both domains through its one encoder (pass
    --source-dataset, or --source TASK for random-action episodes).
    """
    import json

    from coworld.viz.latents import NAME_THE_SOURCE, latent_figure, latents_of_run
    from coworld.viz.media import output_kind, require_extra, write_figure, write_text
    from coworld.viz.runs import load_run_models

    output_kind(out, (".png",))
    distinct_outputs({"--out": out, "--json": json_out})
    require_extra("sklearn", "matplotlib")
    run = load_run_models(ckpt, device=device)
    report, where = latents_of_run(
        run,
        frames=frames,
        length=length,
        dataset=dataset,
        source_dataset=source_dataset,
        source=source,
        seed=seed,
        perplexity=perplexity,
    )
    source_task = source or trained_source(run.run_dir, run.info, NAME_THE_SOURCE)
    title = f"{run.algo}: {source_task or 'source'} -> {run.info['target']} ({run.run_dir.name})"
    write_figure(out, latent_figure(report, title))
    click.echo(f"{run.run_dir} ({run.algo} run): {where}; {frames} frames each")
    click.echo(report.summary())
    if json_out is not None:
        write_text(json_out, json.dumps(report.metrics(), indent=2) + "\n")
    click.echo(f"wrote {out}")


@viz.command("dataset")
@click.argument("path", type=input_path())
@click.option("--out", required=True, type=output_file(), help=".png, .mp4 or .gif")
@click.option("--episodes", type=count_type(1, MAX_SHOWN), default=None, help="Episodes shown [png 8, video 3].")
@click.option("--frames", type=count_type(1, MAX_SHOWN), default=8, show_default=True, help="Frames per row (png).")
@click.option(
    "--hist",
    type=output_file(),
    default=None,
    help="Histogram of episode returns [default: <out>-returns.png beside --out].",
)
@click.option("--fps", type=count_type(1, MAX_FPS), default=30, show_default=True)
def dataset_command(path, out, episodes, frames, hist, fps) -> None:
    """A grid of frames of evenly spaced episodes (.png) or whole episodes (.mp4/.gif), each with its return,
    plus a histogram of the returns of all episodes."""
    from coworld.data import open_dataset
    from coworld.viz.dataset import dataset_grid, dataset_video, returns_histogram
    from coworld.viz.media import output_kind, require_extra, write_figure

    kind = output_kind(out)
    hist = hist if hist is not None else out.with_name(f"{out.stem}-returns.png")
    output_kind(hist, (".png",))
    distinct_outputs({"--out": out, "--hist": hist})
    require_extra("matplotlib")
    with open_dataset(path) as data:
        _save(
            out,
            kind,
            image=lambda: dataset_grid(data, episodes=episodes or 8, frames=frames),
            video=lambda: dataset_video(data, episodes=episodes or 3),
            fps=fps,
        )
        write_figure(hist, returns_histogram(data))
        click.echo(f"wrote {hist} (returns of {data.num_episodes} episodes)")


def _save(out: Path, kind: str, *, image: Callable[[], Any], video: Callable[[], Any], fps: int) -> None:
    """Write a picture (``kind`` 'image') or a video of ``out``'s kind, and say what was written."""
    from coworld.viz.media import write_image, write_video

    if kind == "image":
        picture = image()
        write_image(out, picture)
        click.echo(f"wrote {out} ({picture.shape[1]} x {picture.shape[0]} pixels)")
    else:
        frames = video()
        write_video(out, frames, fps=fps)
        click.echo(f"wrote {out} ({len(frames)} frames of {frames.shape[2]} x {frames.shape[1]} pixels)")
