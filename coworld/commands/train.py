"""``coworld train``: CoWorld or a baseline (offline DreamerV2 and its variants, LOMPO, CURL, CURL+CQL, DrQ+BC) on
a target dataset."""

from __future__ import annotations

from pathlib import Path

import click

from coworld import interrupt
from coworld.algorithms import ALGOS, algorithm, names
from coworld.commands.options import SEED, input_path, output_folder, threads_option
from coworld.errors import StorageError

RESUME = "rerun the same command to resume"


@click.command()
@click.option("--target", required=True, help="Offline target task (its dataset is the training data).")
@click.option(
    "--source",
    default=None,
    help=f"Online source task ({', '.join(names(needs_source=True))} only; the others ignore it), e.g. walker_walk;"
    " for coworld also several, A,B,... or A+B+... (as sweep pairs and run folder names write them): it pretrains each"
    " and keeps the one whose latents lie closest to the target's.",
)
@click.option(
    "--dataset",
    type=input_path(dir_okay=False),
    default=None,
    help="Target dataset; default datasets/<target>-medium_replay.h5.",
)
@click.option("--algo", type=click.Choice(ALGOS), default="coworld", show_default=True)
@click.option(
    "--preset",
    default="paper",
    show_default=True,
    help="paper (Table 3, GPU), cpu (learning on 2 cores) or tiny (CPU minutes, tests); +SETTINGS picks a version of"
    " CoWorld's settings: +table3 (the default), +later-dmc, +later-metaworld or +release (`coworld config`).",
)
@click.option(
    "--logdir",
    type=output_folder(),
    default=None,
    help="Run folder; default runs/<algo>-<source>-<target>-s<seed>. An existing one is resumed.",
)
@click.option("--seed", type=SEED, default=None, help="Seed (default: config seed, 0).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None, help="Default auto.")
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY=VALUE",
    help="Config override, e.g. --set coworld.align=false (repeatable).",
)
@threads_option
@click.option(
    "--force",
    is_flag=True,
    help="Start the run folder over: what training wrote there (checkpoint, metrics, logs) is removed first.",
)
@click.option(
    "--keep-pretrained",
    is_flag=True,
    help="coworld: keep a copy of the run folder as source pretraining leaves it (<logdir>/pretrained), for runs"
    " started with --pretrained-from.",
)
@click.option(
    "--pretrained-from",
    "pretrained_from",
    multiple=True,
    type=input_path(file_okay=False),
    metavar="DIR",
    help="coworld: a run folder whose source pretraining this run shares (its config may differ only in the target"
    " phases' settings; docs/usage.md); a new run starts from the first that kept one, else pretrains (repeatable).",
)
@click.option("--progress/--no-progress", default=True, help="Progress bars.")
@interrupt.at_safe_points
def train(
    target,
    source,
    dataset,
    algo,
    preset,
    logdir,
    seed,
    device,
    overrides,
    force,
    keep_pretrained,
    pretrained_from,
    progress,
) -> None:
    """Train CoWorld or a baseline on a dataset.

    Learns from a fixed target dataset (CoWorld, dreamerv2-finetune and dreamerv2-finetune-ewc also learn online
    in --source).
    Rerunning the same command on the same --logdir resumes from the last checkpoint (also after Ctrl-C, SIGTERM,
    a kill or a full disk). Docs: docs/algorithms.md (what each algorithm computes), docs/usage.md.
    """
    from coworld.storage import check_writable
    from coworld.training.train import check_job, run_job

    if source is not None and not algorithm(algo).needs_source:
        click.echo(f"note: --source is not used by {algo}: it learns from the target dataset alone", err=True)
        source = None
    job = check_job(
        algo=algo,
        source=source,
        target=target,
        dataset=dataset,
        preset=preset,
        logdir=logdir,
        seed=seed,
        device=device,
        overrides=overrides,
        force=force,
        keep_pretrained=keep_pretrained,
        pretrained_from=pretrained_from,
    )
    check_writable(job.logdir, "--logdir")
    for warning in job.warnings:
        click.echo(f"warning: {warning}", err=True)
    kind = f"with source {source}" if algorithm(algo).needs_source else "offline on the dataset alone"
    click.echo(f"train {algo} on {job.dataset} ({target}, {kind}); run folder {job.logdir}")
    if job.resume and (job.logdir / "checkpoint.pt").exists():
        click.echo(f"resuming from {job.logdir / 'checkpoint.pt'}")
    if job.start_over and job.logdir.exists():
        click.echo(f"--force: starting {job.logdir} over")
    try:
        with interrupt.explain(lambda: f"{_kept(job.logdir)}; {RESUME}"):
            summary = run_job(job, progress=progress)
    except StorageError as err:
        fix = "free space" if err.disk_full else "make it writable"
        raise StorageError(f"{err}; {fix}, then {RESUME}", err.reason) from None
    last = summary.get("last_eval_return")
    click.echo(f"done: {job.logdir}" + (f" (last evaluation return {last:.1f})" if last is not None else ""))


def _kept(logdir: Path) -> str:
    """What a stopped run folder holds: how far its last checkpoint got."""
    import torch

    path = logdir / "checkpoint.pt"
    if not path.exists():
        if (logdir / "source" / "checkpoint.pt").exists():  # pretraining its source agent (CoWorld, fine-tuning)
            return f"{logdir} keeps the source agent's pretraining checkpoint and experience"
        if (logdir / "sources").is_dir():  # CoWorld choosing among several sources
            return f"{logdir} keeps the candidate sources' pretraining and the distances measured so far"
        return f"{logdir} holds no checkpoint yet"
    state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    if "progress" in state:  # CoWorld
        progress = state["progress"]
        return f"{logdir} keeps its checkpoint from iteration {progress['iteration']}, {progress['phase']} phase"
    return f"{logdir} keeps its checkpoint at update {int(state['updates']):,}"
