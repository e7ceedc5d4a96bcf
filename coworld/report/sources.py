"""The report's "Source choice" section: for each run that chose among several sources (``--source A,B,...``), the
candidates' distances to the target and the one it chose (``source_choice.json``,
:mod:`coworld.training.multi_source`)."""

from __future__ import annotations

from pathlib import Path

from coworld.errors import CoworldError
from coworld.report.results import RunResult, shown_path
from coworld.training.chosen_source import read_choice


def choice_lines(results: list[RunResult], problems: list[str], folder: Path) -> list[str]:
    """One Markdown line per run with a source choice (the chosen in bold), naming the run relative to the report's
    ``folder``; a damaged record goes to ``problems``."""
    lines = []
    for r in results:
        try:
            choice = read_choice(Path(r.run_dir), fix="the report leaves this run's source choice out")
        except CoworldError as err:
            problems.append(str(err))
            continue
        if choice is None:
            continue
        listed = ", ".join(
            f"**{name}** {choice.distances[name]:.4g}"
            if name == choice.chosen
            else f"{name} {choice.distances[name]:.4g}"
            for name in choice.candidates
        )
        lines.append(f"- `{shown_path(r.run_dir, folder)}` ({r.target}, seed {r.seed}): {listed}")
    return lines
