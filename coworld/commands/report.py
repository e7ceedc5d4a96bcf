"""``coworld report``: tables, a CSV and figures from a sweep folder or any folder of run folders."""

from __future__ import annotations

import click

from coworld.commands.options import input_path, output_folder
from coworld.text import count


@click.command()
@click.argument("root", type=input_path(file_okay=False))
@click.option("--out", type=output_folder(), default=None, help="Where to write [default: ROOT].")
def report(root, out) -> None:
    """Tables and figures from a folder of runs.

    Writes report.md, results.csv and PNG figures for every run folder under ROOT. Docs: docs/reproducing.md.

    ROOT is a `coworld sweep` folder (finished or not) or any folder holding runs made by `coworld train`.
    """
    from coworld.report import write_report

    made = write_report(root, out)
    for problem in made.skipped:
        click.echo(f"warning: skipped {problem}", err=True)
    click.echo(f"{count(made.runs, 'run')}, {made.finished} finished")
    for path in made.files:
        click.echo(f"wrote {path}")
