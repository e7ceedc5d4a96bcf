"""``coworld eval``: evaluate a trained agent in its target environment."""

from __future__ import annotations

from pathlib import Path

import click

from coworld.commands.options import threads_option


@click.command("eval")
@click.option("--ckpt", "ckpt", required=True, type=click.Path(), help="Run folder or its checkpoint.pt.")
@click.option("--episodes", type=int, default=10, show_default=True)
@click.option("--workers", type=int, default=1, show_default=True, help="Environments stepped in parallel.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--video", type=click.Path(dir_okay=False), default=None, help="Write the first episodes as MP4/GIF.")
@click.option("--video-episodes", type=int, default=1, show_default=True)
@click.option(
    "--out", type=click.Path(dir_okay=False), default=None, help="Results JSON; default <run folder>/eval.json."
)
@click.option("--task", default=None, help="Evaluate in another task than the run's target (same action size).")
@threads_option
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
def evaluate(ckpt, episodes, workers, seed, video, video_episodes, out, task, device) -> None:
    """Mean ± std return (and success rate on Meta-World) of a trained policy, plus the value check."""
    from coworld.errors import CoworldError
    from coworld.training.evaluate import evaluate as run_eval
    from coworld.training.evaluate import load_trained_agent, write_video
    from coworld.training.run import seed_everything

    if episodes < 1 or workers < 1:
        raise CoworldError("--episodes and --workers must be at least 1")
    agent, info, config = load_trained_agent(Path(ckpt), device=device)
    seed_everything(seed)  # the agents sample latents (and some actions): the same --seed gives the same result
    task = task or info["target"]
    discount = config.actor_critic.discount if hasattr(agent, "value") else None
    result, frames = run_eval(
        agent,
        task,
        episodes=episodes,
        workers=workers,
        seed=seed,
        discount=discount,
        video_episodes=video_episodes if video else 0,
        progress=True,
    )
    result.extra.update(algo=info["algo"], checkpoint=str(ckpt), seed=seed)
    run_dir = Path(ckpt) if Path(ckpt).is_dir() else Path(ckpt).parent
    out_path = Path(out) if out else run_dir / "eval.json"
    result.to_json(out_path)
    click.echo(result.summary())
    if video:
        write_video(video, frames)
        click.echo(f"video: {video}")
    click.echo(f"results: {out_path}")
