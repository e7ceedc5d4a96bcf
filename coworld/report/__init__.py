"""``coworld report``: the results of a sweep (or of any run folders) as a table, a CSV and figures.

:func:`write_report` writes into ``out`` (default: the folder itself):

* ``results.csv`` -- one row per run (:mod:`coworld.report.results`);
* ``report.md`` -- the Table-1-style table with the aggregate row, ours beside the later CoWorld paper's published
  numbers (:mod:`coworld.report.paper`), the variants, by-seed and value-check tables, CoWorld's own diagnostics
  (:mod:`coworld.report.diagnostics`), the figures, and which runs are not finished (:mod:`coworld.report.tables`);
* ``curves-<target>.png``, ``value_check.png``, ``ablation.png``, ``cap.png`` (:mod:`coworld.report.plots`).

It works on what exists: a partial sweep reports its finished runs and draws the curves of all. The files name run
folders relative to ``out`` (and the sweep by its folder's name), so a report committed with its runs names no
folder of the machine that made it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from coworld.report.results import RunResult, learning_curve, load_results, shown_path, to_csv
from coworld.storage import check_writable, write_text_atomically
from coworld.text import count


@dataclass(frozen=True)
class Report:
    results: list[RunResult]
    files: list[Path]
    skipped: list[str]
    """One line per file that could not be read (the report was written without it)."""

    @property
    def finished(self) -> int:
        return sum(r.final_return is not None for r in self.results)

    @property
    def runs(self) -> int:
        """Runs, without the dataset collectors nobody evaluated (they are not runs that are still to finish)."""
        return _run_count(self.results)


def _run_count(results: list[RunResult]) -> int:
    return len(results) - len(_collectors(results))


def _collectors(results: list[RunResult]) -> list[RunResult]:
    """The online DreamerV2 agents of ``coworld collect --policy dreamerv2`` that have no final evaluation."""
    return [r for r in results if r.online and r.final_return is None]


def write_report(root: str | Path, out: str | Path | None = None) -> Report:
    """Read every run under ``root`` and write the report files into ``out`` (default ``root``)."""
    from coworld.report import plots, tables

    root = Path(os.path.abspath(root))  # every path read, and so every skipped file's line, starts with it
    out = Path(os.path.abspath(out)) if out is not None else root
    skipped: list[str] = []
    results = load_results(root, skipped)
    skipped += [problem for r in results for problem in r.problems]
    tables.require_scipy()  # the optional dependencies, before anything is written
    plots.require_matplotlib()
    check_writable(out, "--out")
    out.mkdir(parents=True, exist_ok=True)
    files = []

    csv_path = out / "results.csv"
    write_text_atomically(csv_path, to_csv(results, out))
    files.append(csv_path)

    figures: list[tuple[str, str]] = []
    for target in dict.fromkeys(r.target for r in results):
        path = out / f"curves-{target}.png"
        if plots.learning_curves(results, target, path):
            figures.append((f"Learning curves, {target}", path.name))
    if plots.value_check(results, out / "value_check.png"):
        figures.append(("Value check (Figure 4(b))", "value_check.png"))
    if plots.ablation_bars(results, out / "ablation.png"):
        figures.append(("CoWorld's variants (Figure 4(a))", "ablation.png"))
    if plots.cap_curves(results, out / "cap.png"):
        figures.append(("The target critic under Eq. 6's cap", "cap.png"))
    files += [out / name for _, name in figures]

    md_path = out / "report.md"
    write_text_atomically(md_path, _markdown(root, out, results, figures, skipped))
    files.insert(1, md_path)
    return Report(results, files, skipped)


def _markdown(
    root: Path, out: Path, results: list[RunResult], figures: list[tuple[str, str]], skipped: list[str]
) -> str:
    from coworld.report import tables
    from coworld.report.diagnostics import actor_critic_table, diagnostics_table, world_model_table

    finished = [r for r in results if r.final_return is not None]
    collectors = _collectors(results)
    lines = [
        f"# Results: {root.name}",
        "",
        f"{count(_run_count(results), 'run')}, {len(finished)} finished (with eval.json). Final return: mean ± std"
        " over seeds of each run's final evaluation; best mean per row in bold; (n=k) where a cell has fewer seeds"
        " than the others, and a single seed's return alone with (n=1). Aggregate: interquartile mean of normalized"
        " scores, 100 (R - random) / (reference - random) per target task, over all runs of all tasks, with its 95%"
        " stratified-bootstrap confidence interval.",
        "",
    ]
    main, varied = tables.results_table(results), tables.results_table(results, variants=True)
    if not main:
        main = (
            "No run as configured has finished yet; the finished variants are below."
            if varied
            else "No finished runs yet."
        )
    lines += ["## Results", "", main, ""]
    published = tables.paper_table(results)
    if published:
        lines += [
            "## Beside the published numbers",
            "",
            "Ours (mean ± std over seeds) beside the later CoWorld paper's (NeurIPS 2024, arXiv 2305.15260 v4; mean ±"
            " std of 10 episodes over 3 seeds) for the same pair, algorithm and target-dataset quality. Its columns"
            " map to our algorithms as `coworld/report/paper.py` says (its Offline DV2 is `dreamerv2-penalty`).",
            "",
            published,
            "",
        ]
    if varied:
        lines += [
            "## Variants",
            "",
            "Each algorithm that has variants beside its runs as configured: the settings a sweep's variant names (the"
            " ablation's `no-*` switch one of CoWorld's terms off, Figure 4(a)).",
            "",
            varied,
            "",
        ]
    by_seed = tables.seed_table(results)
    if by_seed:
        lines += [
            "## By seed",
            "",
            "Each finished run's final return by seed, so that each arm can be set against the others within a seed.",
            "",
            by_seed,
            "",
        ]
    from coworld.report.sources import choice_lines

    choices = choice_lines(results, skipped, out)
    if choices:
        lines += [
            "## Source choice",
            "",
            "Runs that chose among several sources: each candidate's distance to the target (Eq. 3's KL between its"
            " latents and the target's on target frames; `coworld.training.multi_source`), the chosen one in bold.",
            "",
            *choices,
            "",
        ]
    values = tables.value_table(results)
    if values:
        lines += [
            "## Value check",
            "",
            "Critic's mean estimate over the evaluation's steps against the discounted return actually received"
            " from the same steps (Figure 4(b)).",
            "",
            values,
            "",
        ]
    terms = diagnostics_table(results)
    if terms:
        lines += [
            "## CoWorld's terms",
            "",
            "From each CoWorld run's logs: the alignment KL between source and target posteriors on target frames"
            " (Eq. 3), the source reward head's loss on relabelled target rewards (Eqs. 4-5), the share of imagined"
            " target states where the source critic caps the target critic (Eq. 6's max-min term binds), and the two"
            " critics' mean values there; over the run's logs, the last log in brackets.",
            "",
            terms,
            "",
        ]
    models = world_model_table(results)
    if models:
        lines += [
            "## Target world models",
            "",
            "Each world-model run's model of the target dataset over its updates there: the image and reward"
            " losses (negative log-likelihoods) and the KL between posterior and prior; first → last log, the run's"
            " mean in brackets. CoWorld's alignment (Eq. 3) pulls its target latents toward the source's: what"
            " that costs its model of the target frames shows against offline DreamerV2's.",
            "",
            models,
            "",
        ]
    actor_critics = actor_critic_table(results)
    if actor_critics:
        lines += [
            "## Target actor-critics",
            "",
            "Each run's actor-critic over its updates on the target dataset: the critic's mean value on imagined"
            " states, the actor's entropy and the return scale its loss divides by; first → last log, the run's mean"
            " in brackets. Eq. 6 caps CoWorld's critic: its level, and what the actor makes of it, show against"
            " offline DreamerV2's.",
            "",
            actor_critics,
            "",
        ]
    if figures:
        lines += ["## Figures", ""]
        lines += [f"![{title}]({name})" for title, name in figures]
        lines.append("")
    if skipped:
        lines += ["## Files skipped", "", "These could not be read; the report was made without them:", ""]
        lines += [f"- {_relative_line(problem, root, out)}" for problem in skipped]
        lines.append("")
    if collectors:
        lines += [
            "## Dataset collectors",
            "",
            "The online DreamerV2 agents that made the datasets (`coworld eval --ckpt FOLDER` evaluates one):",
            "",
        ]
        for r in collectors:
            curve = learning_curve(Path(r.run_dir), r.algo)
            last = f"last evaluation while learning {curve[-1][1]:.1f} at env step {curve[-1][0]:,}" if curve else ""
            shown = shown_path(r.run_dir, out)
            lines.append(f"- `{shown}` ({r.target}, seed {r.seed}): {last or 'no evaluation logged yet'}")
        lines.append("")
    unfinished = [r for r in results if r.final_return is None and r not in collectors]
    if unfinished:
        lines += ["## Not finished", "", "Runs without eval.json (training, failed, or never evaluated):", ""]
        for r in unfinished:
            lines.append(f"- `{shown_path(r.run_dir, out)}` ({r.label}, seed {r.seed}): {_progress(r)}")
        lines.append("")
    return "\n".join(lines)


def _progress(r: RunResult) -> str:
    """How far an unfinished run has logged: its target updates, else its source agent's env steps."""
    if r.updates is not None:
        return f"{r.updates} updates logged"
    if r.source_steps is None:
        return "nothing logged yet"
    return f"pretraining its source, {r.source_steps:,} env steps logged"


def _relative_line(problem: str, root: Path, out: Path) -> str:
    """A skipped file's line, which starts with the file's path under ``root``, with that path relative to ``out``."""
    prefix, folder = str(root) + os.sep, shown_path(root, out)
    if not problem.startswith(prefix):
        return problem
    return problem[len(prefix) :] if folder == os.curdir else os.path.join(folder, problem[len(prefix) :])
