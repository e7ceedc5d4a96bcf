"""CoWorld's own diagnostics, read from its runs' logs: what each domain-collaborative term did.

* Eq. 3, alignment: the KL between the source and the target posteriors on target frames
  (``target/coworld/align_kl``), at the first and the last log;
* Eqs. 4-5, relabelling: the source reward head's loss on relabelled target rewards
  (``source/coworld/relabel_reward_loss``), first and last;
* Eq. 6, the max-min value regulariser: how often it binds (``target/coworld/maxmin_active``, the fraction of the
  target agent's imagined states where ``zeta * v_T > v_S``, so the source critic caps the target critic), over the
  whole run and at the last log; where it would bind at ``zeta`` 2, 3, 5 and 10 (``target/coworld/binds_zeta_Z``,
  measured without effect), over the whole run; and the two critics' mean values on those states
  (``target/coworld/target_value``, ``target/coworld/source_value``), with the cap itself: the capping critic's
  value over the run's ``zeta`` (:attr:`RunResult.zeta`), the level the term holds the target critic under, and the
  target critic's value as a fraction of that cap (:func:`under_cap`): where the cap acts, the critic settles just
  under it and the term binds on few states all the same, so the binding share alone does not show whether it acts.

A term that is switched off logs nothing and shows as a dash.

Beside them, every world-model run's target agent over its updates on the target dataset: its world model
(:func:`world_model_table`: image and reward losses and KL), where what Eq. 3's alignment costs the model of the
target frames shows against offline DreamerV2's; and its actor-critic (:func:`actor_critic_table`: the critic's
value, the actor's entropy and the return scale its loss divides by), where a cap on the values shows against an
uncapped critic's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coworld.algorithms import is_collaborative
from coworld.report.results import RunResult, read_run_metrics
from coworld.report.tables import label_order

ALIGN = "target/coworld/align_kl"
RELABEL = "source/coworld/relabel_reward_loss"
MAXMIN = "target/coworld/maxmin_active"
TARGET_VALUE = "target/coworld/target_value"
SOURCE_VALUE = "target/coworld/source_value"
PROBES = ("2", "3", "5", "10")
"""The ``zeta`` at which each target update measures where Eq. 6's term would bind (``binds_zeta_Z``)."""


@dataclass(frozen=True)
class Series:
    """One logged metric over a run: its first and last value and its mean over every log."""

    first: float
    last: float
    mean: float
    count: int

    def scaled(self, factor: float) -> Series:
        return Series(self.first * factor, self.last * factor, self.mean * factor, self.count)


def series(records: Sequence[Mapping[str, Any]], key: str) -> Series | None:
    """``key``'s finite values in ``records``, in order, summarised; None when the run never logged it."""
    return _summary([float(r[key]) for r in records if _finite(r.get(key))])


def _summary(values: Sequence[float]) -> Series | None:
    if not values:
        return None
    return Series(first=values[0], last=values[-1], mean=sum(values) / len(values), count=len(values))


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _arrow(s: Series | None) -> str:
    return "–" if s is None else f"{s.first:.3g} → {s.last:.3g}"


def _share(s: Series | None) -> str:
    return "–" if s is None else f"{100 * s.mean:.1f}% ({100 * s.last:.1f}%)"


def _percent(s: Series | None) -> str:
    return "–" if s is None else f"{100 * s.mean:.1f}%"


def _value(s: Series | None) -> str:
    return "–" if s is None else f"{s.mean:.3g} ({s.last:.3g})"


def diagnostics_table(results: Sequence[RunResult]) -> str:
    """A markdown table, one row per CoWorld run; '' when there is none."""
    coworld = [r for r in results if is_collaborative(r.algo)]
    order = {label: i for i, label in enumerate(label_order(coworld))}
    runs = sorted(coworld, key=lambda r: (r.pair, order[r.label], r.seed))
    if not runs:
        return ""
    lines = [
        "| pair | algorithm | seed | alignment KL, first → last | relabelled reward loss, first → last"
        " | max-min binds: run (last) | would bind at zeta 2 / 3 / 5 / 10 | target critic: run (last)"
        " | the cap's critic: run (last) | the cap, its critic / zeta: run (last)"
        " | target critic / the cap: last 3/4 of the run, min-max (last) |",
        "|---|---|---:|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        records = read_run_metrics(Path(r.run_dir))
        capping = series(records, SOURCE_VALUE)
        cells = [
            _arrow(series(records, ALIGN)),
            _arrow(series(records, RELABEL)),
            _share(series(records, MAXMIN)),
            " / ".join(_percent(series(records, f"target/coworld/binds_zeta_{z}")) for z in PROBES),
            _value(series(records, TARGET_VALUE)),
            _value(capping),
            _value(None if capping is None or r.zeta is None else capping.scaled(1 / r.zeta)),
            _fraction(None if r.zeta is None else under_cap(records, r.zeta)),
        ]
        lines.append(f"| {r.source} → {r.target} | {r.label} | {r.seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


WORLD_MODEL_TERMS = (("wm/image", "image loss"), ("wm/reward", "reward loss"), ("wm/kl", "KL"))
"""The world model's logged terms the world-model table shows, with their titles."""
ACTOR_CRITIC_TERMS = (
    ("critic/value", "critic value"),
    ("actor/entropy", "actor entropy"),
    ("actor/return_scale", "return scale"),
)
"""The actor-critic's logged terms the actor-critic table shows, with their titles."""
TARGET_UNITS = ("update", "target_update")
"""The units of the logs of updates on the target dataset (an offline run's, a CoWorld run's target phases)."""


def target_curve(records: Sequence[Mapping[str, Any]], name: str) -> list[tuple[int, float]]:
    """(update, value) of the target agent's ``name`` (``wm/image``, ``critic/value``, ...) at each log of a run's
    updates on the target dataset (CoWorld logs its target agent's under ``target/``; a source's pretraining, logged by
    env step, is left out); [] where not logged."""
    logs = [r for r in records if r.get("unit") in TARGET_UNITS]
    for key in (f"target/{name}", name):
        curve = [(int(r["step"]), float(r[key])) for r in logs if _finite(r.get(key))]
        if curve:
            return curve
    return []


def on_target(records: Sequence[Mapping[str, Any]], name: str) -> Series | None:
    """:func:`target_curve`'s values summarised; None where not logged."""
    return _summary([value for _, value in target_curve(records, name)])


def target_table(results: Sequence[RunResult], terms: Sequence[tuple[str, str]]) -> str:
    """A markdown table of ``terms`` (:func:`on_target`), one row per run that logged any; '' when there is none."""
    runs = [r for r in results if not r.online]
    order = {label: i for i, label in enumerate(label_order(runs))}
    rows = []
    for r in sorted(runs, key=lambda r: (r.target, order[r.label], r.seed)):
        records = read_run_metrics(Path(r.run_dir))
        found = [on_target(records, name) for name, _ in terms]
        if any(found):
            pair = f"{r.source} → {r.target}" if r.source else r.target
            cells = [f"{_arrow(t)} ({t.mean:.3g})" if t else "–" for t in found]
            rows.append(f"| {pair} | {r.label} | {r.seed} | " + " | ".join(cells) + " |")
    if not rows:
        return ""
    names = " | ".join(f"{title}: first → last (run)" for _, title in terms)
    return "\n".join([f"| pair | algorithm | seed | {names} |", "|---|---|---:|" + "---|" * len(terms), *rows])


def world_model_table(results: Sequence[RunResult]) -> str:
    """Each run's target world model: :data:`WORLD_MODEL_TERMS` over its updates on the target dataset."""
    return target_table(results, WORLD_MODEL_TERMS)


def actor_critic_table(results: Sequence[RunResult]) -> str:
    """Each run's target actor-critic: :data:`ACTOR_CRITIC_TERMS` over its updates on the target dataset."""
    return target_table(results, ACTOR_CRITIC_TERMS)


def under_cap(records: Sequence[Mapping[str, Any]], zeta: float) -> tuple[float, float, float] | None:
    """The target critic's value as a fraction of the cap (:func:`cap_curve`) at each log of the last three quarters
    of the run, after the critic's first climb: (lowest, highest, last); None without a log where the cap is above 0."""
    curve = [(step, critic / cap) for step, critic, cap in cap_curve(records, zeta) if cap > 0]
    if not curve:
        return None
    fractions = [fraction for step, fraction in curve if step >= curve[-1][0] / 4]
    return min(fractions), max(fractions), fractions[-1]


def _fraction(span: tuple[float, float, float] | None) -> str:
    return "–" if span is None else f"{span[0]:.2f}-{span[1]:.2f} ({span[2]:.2f})"


def cap_curve(records: Sequence[Mapping[str, Any]], zeta: float) -> list[tuple[int, float, float]]:
    """(target update, target critic, cap) at each log where both critics' values on the imagined target states were
    logged: the cap is the capping critic's value over ``zeta``, the level Eq. 6 holds the target critic under."""
    return [
        (int(r["step"]), float(r[TARGET_VALUE]), float(r[SOURCE_VALUE]) / zeta)
        for r in records
        if _finite(r.get(TARGET_VALUE)) and _finite(r.get(SOURCE_VALUE))
    ]
