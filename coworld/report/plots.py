"""The report's figures (matplotlib, written as PNG without a display).

* learning curves, one figure per pair: evaluation return against target updates, the mean over seeds as a line
  and mean ± one standard deviation as a band, one line per algorithm (and CoWorld variant); beside it each run
  against its training hours;
* the value check (Figure 4(b)): per pair, the critic's mean estimate next to the true discounted return, per
  algorithm and variant, and for CoWorld what the critic that caps its target critic says of the same states;
* the ablation (Figure 4(a)), when the runs have CoWorld variants: mean ± std of the final return per variant;
* the cap, for CoWorld's runs: the target critic's mean value on imagined target states against the level Eq. 6
  holds it under (the capping critic's value there over zeta), against target updates.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from coworld.algorithms import is_collaborative
from coworld.errors import CoworldError
from coworld.report.diagnostics import cap_curve, target_curve
from coworld.report.results import RunResult, learning_curve, read_run_metrics, wall_clock_curve
from coworld.report.tables import label_order
from coworld.text import count


def require_matplotlib() -> Any:
    """matplotlib's ``Figure`` class, or CoworldError with the install hint."""
    try:
        from matplotlib.figure import Figure
    except ModuleNotFoundError:
        raise CoworldError("the report's plots need matplotlib: pip install 'coworld[report]'") from None
    return Figure


def _figure(width: float, height: float) -> Any:
    return require_matplotlib()(figsize=(width, height), layout="constrained")


def label_style(i: int) -> tuple[dict[str, str], str]:
    """The ``i``-th label's line colour and style, and its marker: matplotlib's ten cycle colours, solid with circles,
    then again dashed with squares and dotted with triangles, so a figure of up to 30 labels draws no two alike (the
    report's cap study has 11)."""
    tens = i // 10 % 3
    return {"color": f"C{i % 10}", "linestyle": ("-", "--", ":")[tens]}, "os^"[tens]


def mean_band(curves: Sequence[Sequence[tuple[int, float]]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(steps, mean, std) over runs at each step that any run evaluated (a run counts where it has a value)."""
    by_step: dict[int, list[float]] = {}
    for curve in curves:
        for step, value in curve:
            by_step.setdefault(step, []).append(value)
    steps = np.array(sorted(by_step))
    mean = np.array([np.mean(by_step[s]) for s in steps])
    std = np.array([np.std(by_step[s]) for s in steps])
    return steps, mean, std


def curve_runs(results: Sequence[RunResult], target: str) -> tuple[list[RunResult], str]:
    """The runs whose curves share a figure of ``target``, and its x-axis: the training runs against target updates;
    where there are none, the online DreamerV2 runs of ``coworld collect`` against env steps (they count those)."""
    runs = [r for r in results if r.target == target]
    trained = [r for r in runs if not r.online]
    return (trained, "target updates") if trained else (runs, "env steps")


def learning_curves(results: Sequence[RunResult], target: str, path: Path) -> bool:
    """Plot the learning curves of the runs on ``target``; False (nothing written) when none has evaluations.

    Left: the mean ± std over seeds against target updates (env steps for collectors). Right: each run against its
    training hours, where a two-phase run's source learning counts too.
    """
    runs, x_label = curve_runs(results, target)
    fig = _figure(13.5, 4.0)  # two plots and the legend beside them
    by_updates, by_clock = fig.subplots(1, 2)
    drawn = 0  # labels drawn so far
    for label in label_order(runs):
        labelled = [r for r in runs if r.label == label]
        records = {r.run_dir: read_run_metrics(Path(r.run_dir)) for r in labelled}  # one read serves both axes
        curves = [c for c in (learning_curve(Path(r.run_dir), r.algo, records[r.run_dir]) for r in labelled) if c]
        if not curves:
            continue
        style, marker = label_style(drawn)
        steps, mean, std = mean_band(curves)
        by_updates.plot(
            steps,
            mean,
            label=f"{label} ({count(len(curves), 'run')})",
            marker=marker if len(steps) < 12 else None,
            **style,
        )
        by_updates.fill_between(steps, mean - std, mean + std, alpha=0.2, color=style["color"], linewidth=0)
        for r in labelled:
            clock = wall_clock_curve(Path(r.run_dir), r.algo, records[r.run_dir])
            if clock:
                hours, values = zip(*clock, strict=True)
                by_clock.plot(hours, values, alpha=0.7, linewidth=1.0, **style)
        drawn += 1
    if not drawn:
        return False
    sources = sorted({r.source for r in runs if r.source})
    fig.suptitle(f"{'/'.join(sources)} → {target}" if sources else target)
    by_updates.set_xlabel(x_label)
    by_updates.set_ylabel("evaluation return (mean ± std over seeds)")
    fig.legend(*by_updates.get_legend_handles_labels(), loc="outside right upper", fontsize="small")  # off the curves
    by_clock.set_xlabel("training hours (each run)")
    by_clock.set_ylabel("evaluation return")
    for ax in (by_updates, by_clock):
        ax.grid(alpha=0.3)
    fig.savefig(path, dpi=120)
    return True


def value_check(results: Sequence[RunResult], path: Path) -> bool:
    """Figure 4(b): critic estimate against true discounted return, per pair (subplot) and algorithm (and variant),
    with the estimate of the critic that caps CoWorld's target critic where it was measured."""
    measured = [r for r in results if r.value_estimate is not None and r.value_true is not None]
    targets = list(dict.fromkeys(r.target for r in measured))
    if not targets:
        return False
    labels_of = {target: label_order(r for r in measured if r.target == target) for target in targets}
    widths = [1.2 + 0.7 * len(labels_of[target]) for target in targets]
    fig = _figure(max(4.0, sum(widths)), 3.8)  # each subplot as wide as its three bars a run label need
    axes = fig.subplots(1, len(targets), squeeze=False, gridspec_kw={"width_ratios": widths})[0]
    for ax, target in zip(axes, targets, strict=True):
        runs = [r for r in measured if r.target == target]
        labels = labels_of[target]
        x = np.arange(len(labels))
        estimate = [np.mean([r.value_estimate for r in runs if r.label == label]) for label in labels]
        true = [np.mean([r.value_true for r in runs if r.label == label]) for label in labels]
        capping = [
            [r.value_source for r in runs if r.label == label and r.value_source is not None] for label in labels
        ]
        ax.bar(x - 0.27, estimate, 0.27, label="value estimate")
        ax.bar(x, true, 0.27, label="true discounted return")
        if any(capping):  # CoWorld's runs: what the critic of Eq. 6's cap says of the same states
            ax.bar(x + 0.27, [np.mean(v) if v else np.nan for v in capping], 0.27, label="the cap's critic")
        ax.set_xticks(x, labels, rotation=30, ha="right", fontsize="small")
        ax.set_title(target, fontsize="small")
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("value (mean over seeds)")
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside upper center", ncols=len(names), fontsize="small")  # off the bars
    fig.savefig(path, dpi=120)
    return True


def ablation_bars(results: Sequence[RunResult], path: Path) -> bool:
    """Figure 4(a): final return (mean ± std over seeds) of each CoWorld variant, per pair, with the other
    algorithms as configured on the same target as dashed lines (their mean)."""
    finished = [r for r in results if r.final_return is not None]
    runs = [r for r in finished if is_collaborative(r.algo)]
    if len({r.variant for r in runs}) < 2:
        return False
    targets = list(dict.fromkeys(r.target for r in runs))
    fig = _figure(max(4.0, 3.6 * len(targets)), 3.6)
    axes = fig.subplots(1, len(targets), squeeze=False)[0]
    for ax, target in zip(axes, targets, strict=True):
        labels = label_order(r for r in runs if r.target == target)
        values = [[r.final_return for r in runs if r.target == target and r.label == label] for label in labels]
        x = np.arange(len(labels))
        colors = ["C0" if label == "coworld" else "C7" for label in labels]
        ax.bar(x, [np.mean(v) for v in values], yerr=[np.std(v) for v in values], capsize=4, color=colors)
        others = [r for r in finished if r.target == target and not is_collaborative(r.algo) and not r.variant]
        for i, label in enumerate(label_order(others)):
            mean = np.mean([r.final_return for r in others if r.label == label])
            ax.axhline(mean, color=f"C{i + 1}", linestyle="--", linewidth=1, label=label)
        if others:
            ax.legend(fontsize="small")
        ticks = [label.removeprefix("coworld (").removesuffix(")") for label in labels]
        ax.set_xticks(x, ticks, rotation=30, ha="right")
        ax.set_ylabel("final return")
        ax.set_title(target, fontsize="small")
        ax.grid(axis="y", alpha=0.3)
    fig.savefig(path, dpi=120)
    return True


def _greys(count: int) -> list[str]:
    """``count`` greys from black, lighter each, none too light to see."""
    return [str(round(0.7 * i / max(1, count - 1), 3)) if i else "black" for i in range(count)]


def _two_three_five(value: float, _position: int) -> str:
    """A log axis's minor tick label at 2, 3 and 5 times a power of ten only, so labels stay apart."""
    return f"{value:g}" if round(value / 10 ** np.floor(np.log10(value))) in (2, 3, 5) else ""


def _labelled_log_ticks(low: float, high: float) -> int:
    """How many ticks a log axis from ``low`` to ``high`` would label (powers of ten, and 2, 3 and 5 times them: see
    :func:`_two_three_five`); under two, a log axis tells no value, and a linear one is drawn instead."""
    powers = range(int(np.floor(np.log10(low))), int(np.ceil(np.log10(high))) + 1)
    return sum(low <= k * 10.0**p <= high for p in powers for k in (1, 2, 3, 5))


def cap_curves(results: Sequence[RunResult], path: Path) -> bool:
    """Per target (subplot), each CoWorld label's target critic (solid) and the cap on it, the capping critic's value
    over the run's zeta (dashed), and the uncapped critics, offline DreamerV2's and those of CoWorld runs without the
    cap (black and greys, one per label), each mean over seeds at each log; False (nothing written) when no CoWorld
    run logged its critics. Past ten CoWorld labels, colours repeat with markers (squares, then triangles)."""
    runs = [r for r in results if is_collaborative(r.algo)]
    curves = {}
    for r in runs:
        curve = cap_curve(read_run_metrics(Path(r.run_dir)), r.zeta) if r.zeta else []
        if curve:
            curves[r.run_dir] = curve
    targets = list(dict.fromkeys(r.target for r in runs if r.run_dir in curves))
    if not targets:
        return False
    uncapped = {}
    for r in results:
        if r.target not in targets or not (r.algo == "dreamerv2" or (is_collaborative(r.algo) and r.zeta is None)):
            continue
        curve = target_curve(read_run_metrics(Path(r.run_dir)), "critic/value")  # an uncapped critic
        if curve:
            uncapped[r.run_dir] = curve
    fig = _figure(5.5 * len(targets) + 2.5, 4.2)  # + the legend beside the last subplot
    axes = fig.subplots(1, len(targets), squeeze=False)[0]
    for ax, target in zip(axes, targets, strict=True):
        here = [r for r in runs if r.target == target and r.run_dir in curves]
        values = [v for r in here for c in curves[r.run_dir] for v in c[1:]]
        for i, label in enumerate(label_order(here)):
            mine = [curves[r.run_dir] for r in here if r.label == label]
            look, marker = label_style(i)
            marker = marker if i >= 10 else "None"  # solid and dashed say critic and cap: past ten colours, marks
            for column, style in ((1, "-"), (2, "--")):  # the target critic, then the cap
                steps, mean, _ = mean_band([[(c[0], c[column]) for c in curve] for curve in mine])
                name = f"{label}: target critic" if column == 1 else None
                ax.plot(steps, mean, style, color=look["color"], marker=marker, markersize=3, label=name, linewidth=1.2)
        offline = [r for r in results if r.target == target and r.run_dir in uncapped]
        labels = label_order(offline)
        for shade, label in zip(_greys(len(labels)), labels, strict=True):
            steps, mean, _ = mean_band([uncapped[r.run_dir] for r in offline if r.label == label])
            ax.plot(steps, mean, color=shade, label=f"{label}: critic, no cap", linewidth=1.2)
            values.extend(mean)
        ax.plot([], [], "--", color="0.45", label="dashed: the cap (capping critic / zeta)", linewidth=1.2)
        if min(values) > 0 and _labelled_log_ticks(min(values), max(values)) >= 2:  # values apart by a factor of zeta
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter("{x:g}")
            ax.yaxis.set_minor_formatter(_two_three_five)
            ax.tick_params(axis="y", which="minor", labelsize="x-small")
        ax.set_xlabel("target updates")
        ax.set_title(target, fontsize="small")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize="x-small", loc="upper left", bbox_to_anchor=(1.0, 1.0))  # beside the lines, not on them
    axes[0].set_ylabel("value on imagined target states")
    fig.savefig(path, dpi=120)
    return True
