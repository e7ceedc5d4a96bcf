"""The report's tables: Table-1-style results (mean ± std over seeds, best per row in bold), the aggregate row,
the ablation and the value check, as markdown.

The aggregate is the interquartile mean (IQM) of normalized scores over every run of every task, with a 95%
stratified-bootstrap confidence interval (Agarwal et al., 2021: runs are resampled with replacement within each
task, the tasks kept). It is computed with SciPy's ``bootstrap``, one sample per task, which resamples each sample
independently: the stratified bootstrap of ``rliable``'s ``get_interval_estimates`` (percentile intervals) with
``scipy.stats.trim_mean(scores, 0.25)`` as the IQM, as ``rliable.metrics.aggregate_iqm`` computes it, and unlike
rliable's runs x tasks matrix it allows a different number of runs per task (a partial sweep).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from coworld.algorithms import by_column
from coworld.errors import CoworldError
from coworld.report.results import RunResult


def require_scipy() -> Any:
    """``scipy.stats``, or CoworldError with the install hint."""
    try:
        from scipy import stats
    except ModuleNotFoundError:
        raise CoworldError("the report's statistics need SciPy: pip install 'coworld[report]'") from None
    return stats


def iqm(scores: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50% (25% trimmed from each end)."""
    return require_scipy().trim_mean(scores, 0.25, axis=axis)


@dataclass(frozen=True)
class Interval:
    point: float
    low: float
    high: float
    runs: int
    tasks: int


def iqm_interval(
    scores_per_task: Sequence[Sequence[float]], *, confidence: float = 0.95, resamples: int = 10_000, seed: int = 0
) -> Interval:
    """IQM over all runs of all tasks and its stratified-bootstrap confidence interval (percentile method).

    Args:
        scores_per_task: the normalized scores of each task's runs (at least one run per task).
    """
    stats = require_scipy()
    tasks = [np.asarray(scores, dtype=np.float64) for scores in scores_per_task if len(scores)]
    if not tasks:
        raise ValueError("no scores")
    everything = np.concatenate(tasks)
    point = float(iqm(everything))
    varied = [t for t in tasks if len(t) > 1]  # a task of one run resamples to itself: a constant
    fixed = np.concatenate([t for t in tasks if len(t) == 1] or [np.empty(0)])
    if not varied:
        return Interval(point, point, point, len(everything), len(tasks))

    def statistic(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
        batch = samples[0].shape[:-1]
        constant = np.broadcast_to(fixed, (*batch, len(fixed)))
        return iqm(np.concatenate([*samples, constant], axis=-1), axis=-1)

    result = stats.bootstrap(
        varied,
        statistic,
        n_resamples=resamples,
        confidence_level=confidence,
        method="percentile",
        vectorized=True,
        rng=np.random.default_rng(seed),
    )
    ci = result.confidence_interval
    return Interval(point, float(ci.low), float(ci.high), len(everything), len(tasks))


def label_order(results: Iterable[RunResult]) -> list[str]:
    """The runs' labels in the tables' order: the algorithms in their records' column order
    (:func:`coworld.algorithms.by_column`), each followed by its variants in natural order (an algorithm's
    label first, then "coworld (zeta3)" before "coworld (zeta10)")."""
    results = list(results)

    def natural(label: str) -> list[Any]:
        return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", label)]

    return [
        label
        for algo in by_column({r.algo for r in results})
        for label in sorted({r.label for r in results if r.algo == algo}, key=natural)
    ]


def _rows(results: Sequence[RunResult]) -> list[str]:
    return list(dict.fromkeys(r.target for r in results))


def _pair_label(results: Sequence[RunResult], target: str) -> str:
    sources = sorted({r.source for r in results if r.target == target and r.source})
    return f"{'/'.join(sources)} → {target}" if sources else target


def _fmt(value: float) -> str:
    return f"{value:.1f}"


def _mean_std(values: Sequence[float], *, count: bool = False) -> str:
    """``mean ± std``, with ``(n=k)`` when ``count``; a single value has no spread to show, so it is written alone,
    always with ``(n=1)``."""
    if len(values) == 1:
        return f"{_fmt(float(values[0]))} (n=1)"
    text = f"{_fmt(float(np.mean(values)))} ± {_fmt(float(np.std(values)))}"
    return f"{text} (n={len(values)})" if count else text


def _cell(values: Sequence[float], seeds_expected: int) -> str:
    return _mean_std(values, count=len(values) != seeds_expected)


def results_table(results: Sequence[RunResult], *, variants: bool = False) -> str:
    """Rows = pairs (by target), columns = algorithms: mean ± std of the final return over seeds, best in bold.

    Only finished runs (with eval.json) count. ``variants=False`` takes the algorithms as configured (variant '')
    and adds the IQM aggregate row; ``variants=True`` gives each algorithm that has variants (an ablation's CoWorld
    with a term off, a study's other settings) beside its runs as configured, one column per variant.
    """
    finished = [r for r in results if r.final_return is not None]
    if variants:
        varied = {r.algo for r in finished if r.variant}
        chosen = [r for r in finished if r.algo in varied]
    else:
        chosen = [r for r in finished if not r.variant]  # their label is the algorithm's name
    columns = label_order(chosen)
    if not chosen:
        return ""
    cells: dict[tuple[str, str], list[float]] = {}
    for r in chosen:
        cells.setdefault((r.target, r.label), []).append(float(r.final_return))  # type: ignore[arg-type]
    seeds = max(len(v) for v in cells.values())
    lines = [
        "| pair | " + " | ".join(columns) + " |",
        "|---|" + "---:|" * len(columns),
    ]
    for target in _rows(chosen):
        means = {c: float(np.mean(cells[(target, c)])) for c in columns if (target, c) in cells}
        best = max(means.values()) if len(means) > 1 else None
        row = []
        for c in columns:
            if (target, c) not in cells:
                row.append("—")
                continue
            text = _cell(cells[(target, c)], seeds)
            row.append(f"**{text}**" if best is not None and means[c] == best else text)
        lines.append(f"| {_pair_label(results, target)} | " + " | ".join(row) + " |")
    if not variants:
        row = []
        for c in columns:
            per_task = [
                [r.normalized_score for r in chosen if r.algo == c and r.target == t and r.normalized_score is not None]
                for t in _rows(chosen)
            ]
            per_task = [scores for scores in per_task if scores]
            if not per_task:
                row.append("—")
                continue
            ci = iqm_interval(per_task)
            row.append(f"{ci.point:.1f} [{ci.low:.1f}, {ci.high:.1f}]")
        lines.append("| IQM normalized score [95% CI] | " + " | ".join(row) + " |")
    return "\n".join(lines)


def seed_table(results: Sequence[RunResult]) -> str:
    """Each finished run's final return by seed, one row per pair and label (variants too), one column per seed: so
    a study's arms can be set against its baselines within each seed. '' unless some label has two seeds or more."""
    finished = [r for r in results if r.final_return is not None]
    by_seed: dict[tuple[str, str], dict[int, float]] = {}
    for r in finished:
        by_seed.setdefault((r.target, r.label), {})[r.seed] = float(r.final_return)  # type: ignore[arg-type]
    if not by_seed or max(len(returns) for returns in by_seed.values()) < 2:
        return ""
    seeds = sorted({seed for returns in by_seed.values() for seed in returns})
    lines = [
        "| pair | algorithm | " + " | ".join(f"seed {seed}" for seed in seeds) + " |",
        "|---|---|" + "---:|" * len(seeds),
    ]
    for target in _rows(finished):
        for label in label_order(r for r in finished if r.target == target):
            returns = by_seed[(target, label)]
            cells = [_fmt(returns[seed]) if seed in returns else "—" for seed in seeds]
            lines.append(f"| {_pair_label(results, target)} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def value_table(results: Sequence[RunResult]) -> str:
    """Figure 4(b)'s check as a table: mean critic estimate against the true discounted return, per pair,
    algorithm and variant (finished runs that measured it), with what CoWorld's cap (the critic Eq. 6 caps the
    target critic with) says of the same states where it was measured, and the reward check: the world model's
    predicted reward a step for the same states against the reward received on arriving there."""
    measured = [r for r in results if r.value_estimate is not None and r.value_true is not None]
    if not measured:
        return ""
    lines = [
        "| pair | algorithm | value estimate | true discounted return | the cap's critic"
        " | reward a step: predicted / received | runs |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for target in _rows(measured):
        here = [r for r in measured if r.target == target]
        for label in label_order(here):
            runs = [r for r in here if r.label == label]
            estimate = float(np.mean([r.value_estimate for r in runs]))
            true = float(np.mean([r.value_true for r in runs]))
            capping = [r.value_source for r in runs if r.value_source is not None]
            cap = f"{np.mean(capping):.2f}" if capping else "–"
            checked = [r for r in runs if r.reward_estimate is not None and r.reward_true is not None]
            reward = (
                f"{np.mean([r.reward_estimate for r in checked]):.3f} / {np.mean([r.reward_true for r in checked]):.3f}"
                if checked
                else "–"
            )
            lines.append(
                f"| {_pair_label(results, target)} | {label} | {estimate:.2f} | {true:.2f} | {cap} | {reward}"
                f" | {len(runs)} |"
            )
    return "\n".join(lines)


def paper_table(results: Sequence[RunResult]) -> str:
    """Ours beside the later CoWorld paper's number (:mod:`coworld.report.paper`), one row per pair and algorithm
    whose finished runs (as configured) have one: the same algorithm, pair and target-dataset quality."""
    finished = [r for r in results if r.final_return is not None and r.paper is not None]
    if not finished:
        return ""
    lines = ["| pair | algorithm | dataset | ours | paper | paper's table |", "|---|---|---|---:|---:|---|"]
    for target in _rows(finished):
        here = [r for r in finished if r.target == target]
        for algo in by_column({r.algo for r in here}):
            runs = [r for r in here if r.algo == algo]
            ours = [float(r.final_return) for r in runs]  # type: ignore[arg-type]
            number = runs[0].paper
            assert number is not None
            lines.append(
                f"| {_pair_label(results, target)} | {algo} | {runs[0].dataset_quality} | "
                f"{_mean_std(ours, count=True)} | "
                f"{number.mean:.0f} ± {number.std:.0f} | {number.where} |"
            )
    return "\n".join(lines)
