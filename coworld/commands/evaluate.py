"""``coworld eval``: evaluate a trained agent in its target environment."""

from __future__ import annotations

import json
from pathlib import Path

import click

from coworld import interrupt
from coworld.commands.options import SEED, count_type, distinct_outputs, input_path, output_file, threads_option


@click.command("eval")
@click.option("--ckpt", "ckpt", required=True, type=input_path(), help="Run folder or its checkpoint.pt.")
@click.option("--episodes", type=count_type(), default=10, show_default=True)
@click.option("--workers", type=count_type(), default=1, show_default=True, help="Environments stepped in parallel.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Episode e is seeded by (seed, e).")
@click.option("--video", type=output_file(), default=None, help="Write the first episodes as MP4/GIF.")
@click.option("--video-episodes", type=count_type(0), default=1, show_default=True)
@click.option("--out", type=output_file(), default=None, help="Results JSON; default <run folder>/eval.json.")
@click.option("--task", default=None, help="Evaluate in another task than the run's target (same action size).")
@click.option("--force", is_flag=True, help="Replace the results file (--out) if it holds an earlier evaluation.")
@threads_option
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
@interrupt.at_safe_points
def evaluate(ckpt, episodes, workers, seed, video, video_episodes, out, task, force, device) -> None:
    """Evaluate a trained run: return, value and reward checks.

    Mean ± std return (and success rate on Meta-World) of a trained policy, plus the value and reward checks. The
    results are printed before they are written: a location that cannot be written loses nothing. Docs:
    docs/usage.md, "Evaluation".
    """
    from coworld.envs.vector import sensible_workers
    from coworld.errors import CoworldError
    from coworld.storage import check_writable, write_text_atomically
    from coworld.training.evaluate import evaluate as run_eval
    from coworld.training.evaluate import load_trained_agent, write_video
    from coworld.viz.media import VIDEO_SUFFIXES, output_kind

    workers, note = sensible_workers(workers, episodes)
    if note:
        click.echo(f"note: {note}", err=True)
    run_dir = Path(ckpt) if Path(ckpt).is_dir() else Path(ckpt).parent
    out_path = Path(out) if out else run_dir / "eval.json"
    check_writable(out_path.parent, "--out")
    if out_path.exists() and not force:
        raise CoworldError(
            f"{out_path} holds an earlier evaluation ({_held(out_path)}); kept. Pass --force to replace it,"
            " or --out FILE to write this one elsewhere"
        )
    if video:  # everything the end of the evaluation writes is checked before it starts
        distinct_outputs({"--out": out_path, "--video": Path(video)})
        output_kind(video, VIDEO_SUFFIXES)
        check_writable(Path(video).parent, "--video")
    with interrupt.explain(lambda: "no results were written (an evaluation does not resume); rerun the same command"):
        agent, info, config = load_trained_agent(Path(ckpt), device=device)
        if task is not None:
            from coworld.envs import task_spec

            trained, asked = task_spec(info["target"]), task_spec(task)
            if asked.action_size != trained.action_size:
                raise CoworldError(
                    f"{task} takes {asked.action_size}-d actions but this agent was trained on {info['target']}"
                    f" ({trained.action_size}-d); evaluate it on a task of the same action size"
                )
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
    click.echo(result.summary())
    try:
        write_text_atomically(out_path, json.dumps(result.to_dict(), indent=2) + "\n")
    except OSError as err:
        click.echo(json.dumps(result.to_dict()))  # the record the file would have held
        raise _refused(err, f"the results to {out_path}", "printed above instead") from None
    if video:
        try:
            write_video(video, frames)
        except OSError as err:
            raise _refused(err, f"the video to {video}", f"the results are in {out_path}") from None
        click.echo(f"video: {video}")
    click.echo(f"results: {out_path}")


def _held(path: Path) -> str:
    """What an earlier results file holds, in a few words (for the refusal to replace it)."""
    try:
        returns = json.loads(path.read_text())["returns"]
        return f"{len(returns)} episodes" if isinstance(returns, list) else "unreadable"
    except (OSError, ValueError, KeyError, TypeError):
        return "unreadable"


def _refused(err: OSError, what: str, instead: str) -> Exception:
    """The one-line error of a write the system refused (others are re-raised: they are bugs)."""
    from coworld.errors import StorageError
    from coworld.storage import WRITE_ERRNOS, failure_reason

    if err.errno not in WRITE_ERRNOS:
        return err
    reason = failure_reason(err)
    return StorageError(f"cannot write {what}: {reason}; {instead}", reason)
