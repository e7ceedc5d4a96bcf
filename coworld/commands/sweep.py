"""``coworld sweep``: a grid of collect -> train -> eval runs, on local worker processes or a Ray cluster."""

from __future__ import annotations

import sys

import click

from coworld import interrupt
from coworld.algorithms import ALGOS
from coworld.commands.options import MAX_THREADS, Number, capped_jobs, count_type, input_path, output_folder
from coworld.errors import CoworldError
from coworld.sweep.grid import MAX_SEEDS, TABLES


@click.command()
@click.option("--dir", "root", required=True, type=output_folder(), help="Sweep folder (resumed if it exists).")
@click.option(
    "--table", type=click.Choice(sorted(set(TABLES) - {"ablation"})), help="A named grid: the paper's tables."
)
@click.option(
    "--ablation", is_flag=True, help="Figure 4(a): CoWorld with each term off in turn (alone, or on a --table)."
)
@click.option(
    "--grid", "grid_file", type=input_path(dir_okay=False), help="A TOML grid file (see docs/reproducing.md)."
)
@click.option(
    "--pairs",
    help="SOURCE:TARGET[,SOURCE:TARGET...], e.g. walker_walk:walker_uphill; SOURCE+SOURCE:TARGET lets CoWorld choose"
    " its source (e.g. walker_walk+cheetah_run:walker_uphill).",
)
@click.option("--algos", help=f"Comma-separated algorithms: {','.join(ALGOS)}.")
@click.option("--seeds", type=count_type(1, MAX_SEEDS), help="Seeds 0..N-1 of every run.")
@click.option("--preset", help="Config preset of every run: paper, cpu or tiny, optionally +SETTINGS (see train).")
@click.option(
    "--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Config override of every run (repeatable)."
)
@click.option("--eval-episodes", type=count_type(), help="Episodes of each run's final evaluation.")
@click.option("--data-dir", type=output_folder(), help="Where the datasets are [default: DIR/datasets].")
@click.option(
    "--jobs", type=count_type(), default=1, show_default=True, help="Local runs at once (capped at the cores)."
)
@click.option("--threads", type=count_type(1, MAX_THREADS), default=1, show_default=True, help="Torch threads per run.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None, help="Device of every run.")
@click.option("--ray", "ray_address", metavar="ADDRESS", help="Run on Ray: a cluster's address, 'auto', or 'local'.")
@click.option("--gpus-per-run", type=Number(0, 64), default=0.0, help="GPUs per Ray task (0.5: two share).")
@click.option(
    "--dry-run", is_flag=True, help="List the datasets to collect and the runs with their state; run nothing."
)
@click.option("--progress/--no-progress", default=None, help="Progress view [default: bar on a terminal, else lines].")
@click.option("--interval", type=Number(1, 86_400), default=60.0, show_default=True, help="Seconds between lines.")
def sweep(
    root,
    table,
    ablation,
    grid_file,
    pairs,
    algos,
    seeds,
    preset,
    overrides,
    eval_episodes,
    data_dir,
    jobs,
    threads,
    device,
    ray_address,
    gpus_per_run,
    dry_run,
    progress,
    interval,
) -> None:
    """Run a paper table or a grid of runs.

    A grid of runs (pairs x algorithms x seeds), each collect -> train -> eval, in --dir. Docs:
    docs/reproducing.md (the tables, Ray, grid files).

    \b
    coworld sweep --table toy --dir sweeps/toy --jobs 2              # the CPU table, 27 runs at tiny sizes
    coworld sweep --table dmc --dir sweeps/dmc --jobs 4 --threads 4  # Table 1 on a GPU machine
    coworld sweep --table dmc --dir /shared/dmc --ray auto --gpus-per-run 0.5
    coworld sweep --table dmc-me --dir sweeps/dmc-me --jobs 4       # the later paper's Table 9 (medium-expert)
    coworld sweep --pairs walker_walk:walker_uphill --algos coworld,dreamerv2 --seeds 3 --preset tiny --dir D

    Rerunning the same command skips finished runs and resumes the others. The exit code is 0 when every run is
    finished, 1 when some failed (their logs are in DIR/logs), 2 on bad options.
    """
    from coworld.sweep import grid as grids
    from coworld.sweep.runner import Execution, check_execution, preview, run_sweep

    if grid_file is not None and table is not None:
        raise CoworldError(
            f"--grid and --table are not combined: name the table in {grid_file} (table = {table!r} there) and pass"
            " --grid alone, or pass --table alone"
        )
    options = grids.read_grid_file(grid_file) if grid_file else {}
    if table is not None:
        options["table"] = table
    if ablation:
        options["ablation"] = True
    if pairs is not None:
        options["pairs"] = grids.parse_pairs(pairs)
    if algos is not None:
        options["algos"] = grids.parse_list(algos)
    if seeds is not None:
        options["seeds"] = grids.seeds_from(seeds)
    if preset is not None:
        options["preset"] = preset
    if eval_episodes is not None:
        options["eval_episodes"] = eval_episodes
    options["overrides"] = (*options.get("overrides", ()), *overrides)
    spec = grids.build_spec(**options)
    if ray_address is None:
        jobs, note = capped_jobs(jobs, threads)
        if note:
            click.echo(f"note: {note}", err=True)
    execution = Execution(
        jobs=jobs,
        threads=threads,
        device=device,
        ray=ray_address,
        gpus_per_run=gpus_per_run,
        progress=progress,
        interval=interval,
    )
    if dry_run:
        check_execution(execution)
        click.echo(preview(spec, root, execution, data_dir=data_dir))
        return

    def announce(plan) -> None:
        todo = len(plan.runs) - len(plan.finished)
        datasets = sum(job.kind == "collect" for job in plan.jobs)
        where = f"Ray ({ray_address})" if ray_address else f"{jobs} local job{'s' * (jobs > 1)}"
        click.echo(
            f"sweep {root}: {len(plan.runs)} runs, {len(plan.finished)} finished, {todo} to run,"
            f" {datasets} dataset{'s' * (datasets != 1)} to collect; on {where}, {threads} thread(s) each",
            err=True,
        )

    with interrupt.explain(lambda: f"finished runs are kept; rerun the same command to resume {root}"):
        outcome = run_sweep(spec, root, execution, data_dir=data_dir, on_plan=announce)
    done = outcome.runs - sum(1 for name, _ in outcome.failed if not name.startswith("collect-"))
    click.echo(f"sweep {root}: {done}/{outcome.runs} runs finished")
    for name, log in outcome.failed:
        click.echo(f"failed: {name} (log: {log})")
    if not outcome.ok:
        sys.exit(1)
    click.echo(f"report: coworld report {root}")
