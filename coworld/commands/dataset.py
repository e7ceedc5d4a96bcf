"""``coworld dataset``: inspect (info), check (verify), merge, import and export offline datasets."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import click

from coworld import interrupt
from coworld.commands.options import Number, count_type, input_path, output_file, output_folder
from coworld.data import CODECS, QUALITIES, merge_datasets, open_dataset, verify_dataset
from coworld.text import count


@click.group()
def dataset() -> None:
    """Inspect, check, merge, import and export datasets.

    Offline datasets in HDF5, format v1: info, verify, merge, import (V-D4RL), export (Minari, npz episodes).
    Docs: datasets/README.md (the format, field by field), docs/usage.md.
    """


@dataset.command()
@click.argument("path", type=input_path())
@click.option(
    "--discount",
    type=Number(0, 1, min_open=True),
    default=0.99,
    show_default=True,
    help="gamma of the value line: the critic's, actor_critic.discount"
    " (tiny, cpu and cpu-dv2 presets 0.99, paper 0.995).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one JSON object.")
def info(path: Path, discount: float, as_json: bool) -> None:
    """Episodes, steps, returns, rewards, values, normalized score, size on disk and metadata of the dataset at PATH.

    The reward line is a step's reward: CoWorld's value cap pushes a binding state's value down with slope alpha *
    zeta (for a Gaussian critic, as a TD error of that size), so set alpha * zeta beside it (docs/algorithms.md, "When
    the cap binds"). The value line is the discounted return from every step to its episode's end: what a critic of
    the behaviour that collected the data would estimate, to set beside a trained critic's estimates (coworld eval's
    value check).
    """
    with open_dataset(path) as data:
        summary = data.summary(discount)
    if as_json:
        click.echo(json.dumps(summary, indent=2, sort_keys=True))
        return
    for key, value in _info_lines(summary):
        click.echo(f"{key:<12}{value}")
    click.echo(f"{'preview':<12}coworld viz dataset {path} --out preview.png (frames, returns; .mp4 for episodes)")


def _info_lines(s: dict[str, Any]) -> list[tuple[str, str]]:
    ret, length, norm = s["return"], s["length"], s["normalized_score"]
    lines = [
        ("path", s["path"]),
        ("format", f"coworld-dataset v{s['format_version']}"),
        ("task", s["task"]),
        ("quality", s["quality"]),
        ("complete", "yes" if s["complete"] else "no (interrupted or still being written; resume to finish)"),
        ("episodes", f"{s['episodes']:,} ({s['terminated_episodes']:,} terminated, the rest cut by a time limit)"),
        ("steps", f"{s['steps']:,} rows, {s['frames']:,} frames with each episode's final frame"),
        ("return", _stats_text(ret, ".1f")),
        ("length", _stats_text(length, ".0f")),
        ("reward", f"{_stats_text(s['reward'], '.3f')}  (a step)"),
        ("value", f"{_stats_text(s['value'], '.2f')}  (discounted return to the episode's end, gamma {s['discount']})"),
        ("normalized", _stats_text(norm, ".1f") if norm else "unknown (no reference returns in the metadata)"),
    ]
    ratio = s["compression_ratio"]
    lines.append(
        (
            "size",
            f"{_mb(s['file_bytes'])} on disk; frames {_mb(s['frame_bytes_raw'])} raw -> "
            f"{_mb(s['frame_bytes_stored'])} stored ({s['compression']}, ratio {ratio:.1f}x)",
        )
    )
    for key in ("reference", "env_config", "collector", "versions"):
        lines.append((key, json.dumps(s[key], sort_keys=True)))
    lines += [("created", str(s["created"])), ("updated", str(s["updated"]))]
    return lines


def _stats_text(stats: dict[str, float], fmt: str) -> str:
    return "  ".join(f"{name} {stats[name]:{fmt}}" for name in ("mean", "std", "min", "max"))


def _mb(n: int) -> str:
    return f"{n / 2**20:,.1f} MiB"


@dataset.command()
@click.argument("path", type=input_path())
def verify(path: Path) -> None:
    """Check schema, shapes, dtypes, episode boundaries, finite values, checksums and the complete flag.

    Prints 'ok' and exits 0, or lists the problems and exits 1.
    """
    problems = verify_dataset(path, progress=sys.stderr.isatty())
    if not problems:
        click.echo(f"{path}: ok")
        return
    for problem in problems:
        click.echo(f"{path}: {problem}")
    click.echo(f"{path}: {len(problems)} problem{'s' if len(problems) > 1 else ''}")
    sys.exit(1)


@dataset.command()
@click.argument("inputs", nargs=-1, required=True, type=input_path())
@click.option("--out", required=True, type=output_file(), help="The merged dataset to write.")
@click.option(
    "--quality",
    type=click.Choice(QUALITIES),
    help="Quality of the merge (default: the inputs' shared one, or medium-expert for medium(-replay) + expert).",
)
@click.option("--force", is_flag=True, help="Replace --out if it exists (once the merge is whole).")
@click.option("--compression", type=click.Choice(CODECS), default="gzip", show_default=True, help="Frame codec.")
@interrupt.at_safe_points
def merge(inputs: tuple[Path, ...], out: Path, quality: str | None, force: bool, compression: str) -> None:
    """Merge datasets of one task, in order, into a new dataset (e.g. medium-replay + expert = medium-expert).

    The merge is built next to --out and renamed into place once whole: stopped at any point, --out is as it was.
    """
    existed = out.exists()
    untouched = f"{out} is as it was" if existed else f"nothing was written to {out}"
    with interrupt.explain(lambda: f"{untouched}; run the merge again"):
        merge_datasets(
            list(inputs), out, quality=quality, force=force, compression=compression, progress=sys.stderr.isatty()
        )
    with open_dataset(out) as data:
        click.echo(
            f"wrote {out}: {data.quality}, {count(data.num_episodes, 'episode')}, {count(data.num_steps, 'step')}"
        )


@dataset.command("import")
@click.argument("source_format", metavar="FORMAT", type=click.Choice(["vd4rl"]))
@click.argument("path", type=input_path())
@click.option("--task", required=True, help="Our task the data belongs to, e.g. walker_walk (see `coworld tasks`).")
@click.option("--out", type=output_file(), help="Default datasets/<task>-<quality>.h5.")
@click.option(
    "--quality", type=click.Choice(QUALITIES), help="Default: read from V-D4RL's folder name (.../medium_replay/...)."
)
@click.option(
    "--resize",
    type=count_type(1, 4096),
    default=None,
    help="Resize frames to this size (64; area filter), e.g. 84px data.",
)
@click.option("--resume", is_flag=True, help="Continue an interrupted import of the same folder into --out.")
@click.option("--force", is_flag=True, help="Overwrite --out if it exists.")
@click.option("--compression", type=click.Choice(CODECS), default="gzip", show_default=True, help="Frame codec.")
def import_dataset(
    source_format: str,
    path: Path,
    task: str,
    out: Path | None,
    quality: str | None,
    resize: int | None,
    resume: bool,
    force: bool,
    compression: str,
) -> None:
    """Convert a dataset of another format into format v1.

    FORMAT vd4rl: PATH is a V-D4RL folder, its 64px layout (.npz episodes) or its 84px one (.hdf5 shards; needs
    --resize 64).
    """
    from coworld.data.vd4rl import import_vd4rl

    summary = import_vd4rl(
        path,
        out,
        task=task,
        quality=quality,
        resize=resize,
        resume=resume,
        force=force,
        compression=compression,
        progress=sys.stderr.isatty(),
    )
    resumed = f" ({summary.skipped:,} already there)" if summary.skipped else ""
    click.echo(f"wrote {summary.path}: {summary.episodes:,} episodes{resumed}, {summary.steps:,} steps of {task}")


@dataset.command("export")
@click.argument("path", type=input_path())
@click.option("--to", "target", required=True, type=click.Choice(["minari", "npz-episodes"]), help="Output format.")
@click.option("--name", help="Minari dataset id; default coworld/<task>/<quality>-v0.")
@click.option("--out", type=output_folder(), help="npz-episodes: the folder to write.")
@click.option("--force", is_flag=True, help="Replace an existing Minari dataset or folder.")
@click.option("--author", help="Minari metadata: the dataset's author.")
@click.option("--author-email", help="Minari metadata: the author's e-mail.")
@click.option("--code-permalink", help="Minari metadata: a link to the code that made the data.")
@click.option("--incomplete", is_flag=True, help="Export a dataset whose collection did not finish (with a warning).")
def export(
    path: Path,
    target: str,
    name: str | None,
    out: Path | None,
    force: bool,
    author: str | None,
    author_email: str | None,
    code_permalink: str | None,
    incomplete: bool,
) -> None:
    """Export a dataset to Minari or to dreamer-style npz episodes.

    PATH is a dataset file, or a name such as walker_uphill-medium-replay (datasets/<task>-<quality>.h5).

    \b
    --to minari        a Minari dataset in MINARI_DATASETS_PATH (default ~/.minari/datasets)
    --to npz-episodes  one .npz per episode (V-D4RL's 64px layout) in the new folder --out
    """
    from coworld.data.export import export_minari, export_npz_episodes, minari_path
    from coworld.errors import ConfigError

    progress = sys.stderr.isatty()
    checks = {"incomplete": incomplete, "warn": lambda message: click.echo(f"warning: {message}", err=True)}
    if target == "npz-episodes":
        if out is None or name is not None:
            raise ConfigError("--to npz-episodes writes the folder --out FOLDER (and takes no --name)")
        export_npz_episodes(path, out, force=force, progress=progress, **checks)
        click.echo(f"wrote {out}: {len(list(out.glob('*.npz'))):,} episodes as .npz files")
        return
    if out is not None:
        raise ConfigError("--to minari writes into Minari's dataset folder (MINARI_DATASETS_PATH), not --out")
    dataset_id = export_minari(
        path,
        name,
        force=force,
        progress=progress,
        author=author,
        author_email=author_email,
        code_permalink=code_permalink,
        **checks,
    )
    where = minari_path(dataset_id)
    click.echo(f"wrote Minari dataset {dataset_id} in {where}: open it with minari.load_dataset({dataset_id!r})")
