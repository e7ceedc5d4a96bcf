"""Read run folders into one tidy record per run, and write them as ``results.csv``.

A run folder is any folder holding a ``run.json`` with an ``algo`` and a ``target`` (what ``coworld train``
writes), inside a sweep or not. Its final result is ``eval.json`` (written by ``coworld eval``); a run without one
is listed with an empty return (still training, or never evaluated) and still has a learning curve. A sweep's
runs also hold ``sweep-run.json`` with their variant name and pair; elsewhere the variant is read from the config
(the CoWorld terms switched off) and the pair is the target alone for the baselines. Runs of one algorithm and
variant that differ in their preset or config (anything but the seed) stay apart, each variant then naming what sets
it apart (:mod:`coworld.report.arms`). An ``eval.json`` or a metrics record holding what is not a finite number is
skipped and named (:func:`evaluation_damage`).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from coworld import envs
from coworld.algorithms import is_collaborative
from coworld.errors import CoworldError, UnknownTaskError
from coworld.report.arms import ABLATION_SWITCHES, Settings, arm_variants, run_settings
from coworld.report.paper import Published, published
from coworld.text import count
from coworld.training.description import run_description
from coworld.training.logger import read_metrics

ONLINE_ALGO = "dreamerv2-online"
"""How a report names the online DreamerV2 agent that a ``coworld collect --policy dreamerv2`` run trained in the
target task itself (its run folder sits beside the dataset): a reference row, not an offline method."""


@dataclass(frozen=True)
class RunResult:
    """One run: what it is and what it measured (None where not measured)."""

    run_dir: str
    algo: str
    variant: str
    """'' for the algorithm as configured; e.g. 'no-align' for CoWorld without Eq. 3, 'zeta3' (a sweep's name),
    'coworld.zeta=10' or 'zeta3, coworld.k=0.5' (what sets the run's arm apart: :mod:`coworld.report.arms`)."""
    source: str | None
    target: str
    seed: int
    final_return: float | None
    """Mean return of the final evaluation (eval.json)."""
    return_std: float | None
    episodes: int | None
    success_rate: float | None
    value_estimate: float | None
    """Critic's mean estimate over the evaluation's steps (Figure 4(b))."""
    value_true: float | None
    """Mean discounted return actually received from the same steps."""
    normalized_score: float | None
    """(final_return - random_return) / (reference_return - random_return) of the target task."""
    updates: int | None
    """Target-agent updates logged."""
    wall_time_s: float | None
    """Training time logged in metrics.jsonl (summed over resumed segments)."""
    problems: tuple[str, ...] = ()
    """One line per file of the run that could not be read (and was skipped), e.g. ``eval.json: not JSON``."""
    dataset_quality: str | None = None
    """Quality of the target dataset it trained on (:func:`dataset_quality`), None where unknown."""
    value_source: float | None = None
    """CoWorld: the mean estimate, over the same steps, of the critic that caps the target critic (Eq. 6)."""
    source_steps: int | None = None
    """The last source env step logged (:func:`source_steps`): how far a run that pretrains its source has come."""
    reward_estimate: float | None = None
    """World-model agents: the reward head's mean prediction for the states the evaluation reached (reward check)."""
    reward_true: float | None = None
    """The mean reward of arriving at the same states, received."""
    zeta: float | None = None
    """CoWorld: Eq. 6's scale on the target critic (``coworld.zeta`` in config.json); None for other algorithms and
    for CoWorld without the cap (``coworld.value_reg`` false)."""

    @property
    def paper(self) -> Published | None:
        """The later CoWorld paper's number for this algorithm, pair and dataset quality (:mod:`.paper`), if any."""
        if self.variant:
            return None
        return published(self.algo, self.source, self.target, self.dataset_quality)

    @property
    def pair(self) -> str:
        return f"{self.source}->{self.target}" if self.source else self.target

    @property
    def label(self) -> str:
        """The column of the run in tables: algorithm, then variant."""
        return f"{self.algo} ({self.variant})" if self.variant else self.algo

    @property
    def online(self) -> bool:
        """The online DreamerV2 agent of a collection (:data:`ONLINE_ALGO`): a reference row, not a trained run."""
        return self.algo == ONLINE_ALGO


CSV_COLUMNS = (
    "pair",
    "source",
    "target",
    "algo",
    "variant",
    "seed",
    "final_return",
    "return_std",
    "episodes",
    "success_rate",
    "value_estimate",
    "value_true",
    "value_source",
    "reward_estimate",
    "reward_true",
    "normalized_score",
    "updates",
    "wall_time_s",
    "run_dir",
    "dataset_quality",
    "paper_return",
    "paper_std",
    "paper_table",
)
"""The columns of ``results.csv``; ``paper_*``: the later CoWorld paper's number for the run's algorithm, pair and
dataset quality, and the table printing it (empty where the paper has none)."""


def find_run_dirs(root: str | Path, problems: list[str] | None = None) -> list[Path]:
    """Every run folder under ``root`` (``root`` itself included), sorted; a ``run.json`` that cannot be read is
    skipped, with a line in ``problems``."""
    root = Path(root)
    if not root.is_dir():
        raise CoworldError(f"{root} is not a folder; pass a sweep folder or a folder of runs made by `coworld train`")
    found = []
    for path in sorted(root.rglob("run.json")):
        info = run_description(_json_object(path, problems if problems is not None else []), path)
        if info is not None and isinstance(info.get("algo"), str) and isinstance(info.get("target"), str):
            found.append(path.parent)  # a training run, or the online dreamerv2 run of a collection
    return found


def target_eval_return(record: Mapping[str, Any], algo: str) -> float | None:
    """The target agent's evaluation return in one metrics record, or None.

    A CoWorld run folder also logs its source agent's evaluations in the source task, under the same
    ``eval/return`` key but without the value check; the target agent's evaluations carry the value check.
    """
    value = record.get("eval/return")
    if not _is_step(value):
        return None
    if is_collaborative(algo) and "eval/value_estimate" not in record:
        return None
    return float(value)


def learning_curve(run_dir: Path, algo: str, records: list[dict[str, Any]] | None = None) -> list[tuple[int, float]]:
    """(target updates, evaluation return) of each evaluation during training, in order."""
    records = _metrics(run_dir, []) if records is None else records  # its problems: load_result reports them
    curve = []
    for record in records:
        value = target_eval_return(record, algo)
        if value is not None and math.isfinite(value):
            curve.append((int(record["step"]), value))
    return curve


def _updates(records: list[dict[str, Any]], algo: str) -> int | None:
    """The last target update logged (a source phase's records, counted in source steps, are left out)."""
    steps = [
        int(r["step"])
        for r in records
        if not str(r.get("unit", "")).startswith("source_")
        and (
            not is_collaborative(algo)
            or any(key.startswith("target/") for key in r)
            or target_eval_return(r, algo) is not None
        )
    ]
    return max(steps) if steps else None


def source_steps(records: list[dict[str, Any]]) -> int | None:
    """The last source env step logged (a source agent's pretraining and source phases); None where there is none."""
    steps = [int(r["step"]) for r in records if r.get("unit") == "source_env_step"]
    return max(steps) if steps else None


def _elapsed(records: list[dict[str, Any]]) -> list[float | None]:
    """Training seconds at each record (summed over a resumed run's segments by :func:`_one_segment`); None for a
    record without a time."""
    return [float(r["time"]) if _is_step(r.get("time")) else None for r in records]


def _wall_time(records: list[dict[str, Any]]) -> float | None:
    """The run's training seconds (:func:`_elapsed` at its last timed record)."""
    times = [t for t in _elapsed(records) if t is not None]
    return times[-1] if times else None


def wall_clock_curve(
    run_dir: Path, algo: str, records: list[dict[str, Any]] | None = None
) -> list[tuple[float, float]]:
    """(training hours, evaluation return) of each evaluation during training: :func:`learning_curve` against the
    clock, which for a two-phase run includes its source agent's online learning."""
    records = _metrics(run_dir, []) if records is None else records
    curve = []
    for record, seconds in zip(records, _elapsed(records), strict=True):
        value = target_eval_return(record, algo)
        if value is not None and seconds is not None and math.isfinite(value):
            curve.append((seconds / 3600, value))
    return curve


def _variant(run_dir: Path, algo: str, config: Mapping[str, Any], problems: list[str]) -> tuple[str, str | None]:
    """(variant, pair source) from sweep-run.json, else the CoWorld switches in the run's config."""
    record = _json_object(run_dir / "sweep-run.json", problems)
    if record is not None:
        source = record.get("source")
        return str(record.get("variant", "")), source if isinstance(source, str) else None
    if not is_collaborative(algo):
        return "", None
    switches = config.get("coworld")
    if not isinstance(switches, dict):
        return "", None
    off = [name for key, name in ABLATION_SWITCHES if switches.get(key) is False]
    return "+".join(off), None


def _json_object(path: Path, problems: list[str]) -> dict[str, Any] | None:
    """The JSON object in ``path``; None when the file is missing, or (with a line in ``problems``) unreadable,
    not JSON, or JSON of another shape."""
    try:
        data = json.loads(path.read_bytes())
    except FileNotFoundError:
        return None
    except OSError as err:
        problems.append(f"{path}: cannot be read ({err.strerror})")
        return None
    except ValueError as err:  # UnicodeDecodeError included
        problems.append(f"{path}: not JSON ({str(err).splitlines()[0][:80]})")
        return None
    if not isinstance(data, dict):
        problems.append(f"{path}: holds a JSON {type(data).__name__}, not an object")
        return None
    return data


def _metrics(run_dir: Path, problems: list[str]) -> list[dict[str, Any]]:
    """The metrics records of a run; none (with a line in ``problems``) when metrics.jsonl cannot be read."""
    try:
        records = read_metrics(run_dir)
    except OSError as err:
        problems.append(f"{run_dir / 'metrics.jsonl'}: cannot be read ({err.strerror})")
        return []
    except UnicodeDecodeError:
        problems.append(f"{run_dir / 'metrics.jsonl'}: not UTF-8 text; no learning curve")
        return []
    good = [r for r in records if isinstance(r, dict) and _is_step(r.get("step"))]
    if len(good) < len(records):
        problems.append(f"{run_dir / 'metrics.jsonl'}: {len(records) - len(good)} records without a step skipped")
    damage = [(r, _record_damage(r)) for r in good]
    damaged = [(r, what) for r, what in damage if what]
    if damaged:
        first, what = damaged[0]
        problems.append(
            f"{run_dir / 'metrics.jsonl'}: {count(len(damaged), 'record')} holding a value that is not a finite"
            f" number skipped (the first at step {first['step']}: {what})"
        )
    return _one_segment([r for r, what in damage if not what])


def _record_damage(record: Mapping[str, Any]) -> str:
    """The first value of a metrics record that is not a finite number (``unit``: not a string), as ``'wm/kl is
    NaN'``; '' where there is none. The logger writes a value that was not finite as null: that record is skipped
    whole, as one holding NaN is, and none of its values is drawn."""
    for key, value in record.items():
        if not (isinstance(value, str) if key == "unit" else _is_step(value)):
            return f"{key} is {_kind(value)}"
    return ""


def _one_segment(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """A resumed run's records as those of one run. The logger's clock restarts with each segment: each record's
    ``time`` becomes the training seconds since the run began, summed over segments. A resume redoes what followed
    its checkpoint and logs it again (the same unit, step and metrics): of those records the last stays."""
    total, last, timed = 0.0, None, []
    for record in records:
        t = record.get("time")
        if _is_step(t):
            if last is not None and t < last:
                total += last
            last = float(t)
            record = {**record, "time": total + last}
        timed.append(record)
    seen, kept = set(), []
    for record in reversed(timed):
        key = (record.get("unit"), record["step"], frozenset(record) - {"time"})
        if key not in seen:
            seen.add(key)
            kept.append(record)
    return kept[::-1]


def read_run_metrics(run_dir: Path) -> list[dict[str, Any]]:
    """The run's metrics records that have a step; none when metrics.jsonl cannot be read (:func:`load_result`
    names that problem)."""
    return _metrics(run_dir, [])


def _is_step(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def normalized(task: str, value: float | None) -> float | None:
    """``100 * (value - random_return) / (reference_return - random_return)`` of ``task``, the scale ``coworld
    eval`` and ``coworld dataset info`` print (:func:`coworld.data.reader.normalized_score`); None when not
    defined."""
    from coworld.data.reader import normalized_score

    if value is None:
        return None
    try:
        spec = envs.task_spec(task)
    except UnknownTaskError:
        return None
    score = normalized_score(value, {"random_return": spec.random_return, "reference_return": spec.reference_return})
    return None if score is None else float(score)


def dataset_quality(path: Any) -> str | None:
    """The quality of the dataset a run trained on (``run.json``'s ``dataset``): what the file says, or where it
    cannot be read (moved, another machine's path), what its name says (``<task>-<quality>.h5``, as ``coworld
    collect`` and a sweep name it); None otherwise."""
    from coworld.data import QUALITIES

    if not isinstance(path, str) or not path:
        return None
    try:
        import h5py

        with h5py.File(path, "r") as f:  # the attribute alone: opening the dataset would read its every row
            quality = f.attrs.get("quality")
        if isinstance(quality, bytes):
            quality = quality.decode()
        if quality in QUALITIES:
            return str(quality)
    except (OSError, ValueError):
        pass
    _, _, quality = Path(path).name.removesuffix(".h5").partition("-")
    quality = quality.replace("_", "-")
    return quality if quality in QUALITIES else None


def _mean(values: Any) -> float | None:
    """The mean of a list of numbers; None for an empty list or None (not measured)."""
    if not values:
        return None
    return float(sum(float(v) for v in values) / len(values))


class UnreadableRun(CoworldError):
    """A run folder the report leaves out: its ``config.json``, which says which seed it is, cannot be read."""


def _config(run_dir: Path) -> tuple[dict[str, Any], int]:
    """The run's config (``config.json``; empty where there is none, as in an older collector's run folder) and its
    seed (-1 there). A config that cannot be read, or has no whole-number seed, raises :class:`UnreadableRun` with
    the line that says so."""
    problems: list[str] = []
    config = _json_object(run_dir / "config.json", problems)
    seed = -1 if config is None else config.get("seed")
    if not problems and not (isinstance(seed, int) and not isinstance(seed, bool)):
        problems.append(f"{run_dir / 'config.json'}: its seed is {seed!r}, not a whole number")
    if problems:
        raise UnreadableRun(f"{problems[0]}; the run is left out (which seed it is, is unknown)")
    return config or {}, seed


def _zeta(config: Mapping[str, Any]) -> float | None:
    """``coworld.zeta`` of a config, where it is a positive number and Eq. 6's cap is on."""
    switches = config.get("coworld")
    if not isinstance(switches, dict) or switches.get("value_reg") is False:
        return None
    value = switches.get("zeta")
    return float(value) if _is_step(value) and value > 0 else None  # a finite number


def _foreign_evaluation(result: Mapping[str, Any] | None, info: Mapping[str, Any]) -> str:
    """Why an ``eval.json`` does not score this run ('' where it does): an evaluation of another algorithm's agent (a
    checkpoint copied in from another run), or in another task than the run's target (``coworld eval --task``)."""
    if result is None:
        return ""
    extra = result.get("extra")
    scored = extra.get("algo") if isinstance(extra, dict) else None
    if scored is not None and scored != info["algo"]:
        return f"an evaluation of a {scored} agent, but the run is {info['algo']}"
    task = result.get("task")
    if task is not None and task != info["target"]:
        return f"an evaluation in {task}, not in the run's target {info['target']}"
    return ""


EPISODE_FIELDS = ("lengths", "successes", "value_estimate", "value_true", "value_source", "reward_estimate",
                  "reward_true")  # fmt: skip
"""eval.json's per-episode lists beside ``returns``, each null where not measured."""


def evaluation_damage(result: Mapping[str, Any]) -> str:
    """What in an eval.json is not what ``coworld eval`` writes, '' where nothing is: ``returns`` must be a
    non-empty list of finite numbers, each of :data:`EPISODE_FIELDS` a list of finite numbers (``successes``: of
    true / false) or null, ``std`` a finite number and ``success_rate`` one or null. E.g. ``returns must be a list of
    finite numbers, got a string``: a string's characters, or a NaN, would otherwise become a result."""
    returns = result.get("returns", _MISSING)
    wrong = "got an empty list" if returns == [] else _not_a_list_of(returns, _is_step)
    if wrong:
        return f"returns must be a list of finite numbers, {wrong}"
    for key in EPISODE_FIELDS:
        value, flags = result.get(key), key == "successes"
        wrong = "" if value is None else _not_a_list_of(value, _is_flag if flags else _is_step)
        if wrong:
            return f"{key} must be a list of {'true / false' if flags else 'finite numbers'} or null, {wrong}"
    if "std" in result and not _is_step(result["std"]):
        return f"std must be a finite number, got {_kind(result['std'])}"
    rate = result.get("success_rate")
    if rate is not None and not _is_step(rate):
        return f"success_rate must be a finite number or null, got {_kind(rate)}"
    return ""


def _is_flag(value: Any) -> bool:
    return isinstance(value, bool) or _is_step(value)


_MISSING = object()
"""A key that is not there (:func:`_kind` says "nothing")."""


def _not_a_list_of(values: Any, fits: Callable[[Any], bool]) -> str:
    """'' where ``values`` is a list whose every item ``fits``, else what it holds: ``got a string``, ``got NaN at
    index 1``."""
    if not isinstance(values, list):
        return f"got {_kind(values)}"
    bad = next((i for i, v in enumerate(values) if not fits(v)), None)
    return "" if bad is None else f"got {_kind(values[bad])} at index {bad}"


def _kind(value: Any) -> str:
    """What a JSON value is, for a line about it: ``NaN``, ``Infinity``, ``a string``, ``an object``, ``null``."""
    if value is _MISSING:
        return "nothing"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a bool"
    if isinstance(value, int | float):
        if math.isnan(value):
            return "NaN"
        return "a number" if math.isfinite(value) else ("Infinity" if value > 0 else "-Infinity")
    names = {str: "a string", list: "a list", dict: "an object"}
    return names.get(type(value), type(value).__name__)


def load_result(run_dir: Path, qualities: dict[str, str | None] | None = None) -> RunResult:
    """The :class:`RunResult` of one run folder; a file of it that cannot be read is skipped and named in
    ``problems`` (a ``config.json`` leaves the whole run out: :class:`UnreadableRun`). ``qualities``: dataset path
    -> quality, read once per dataset of a report. Its variant is the run's name alone (:func:`load_results` adds
    what tells it from the other runs of a report)."""
    return _load(run_dir, qualities)[0]


def _load(run_dir: Path, qualities: dict[str, str | None] | None) -> tuple[RunResult, Settings]:
    """:func:`load_result`, and what made the run (:func:`coworld.report.arms.run_settings`)."""
    problems: list[str] = []
    info = run_description(_json_object(run_dir / "run.json", problems), run_dir / "run.json") or {}
    algo, target = str(info["algo"]), str(info["target"])
    if info.get("online"):
        algo = ONLINE_ALGO  # the agent a `coworld collect --policy dreamerv2` trained in the target task itself
    config, seed = _config(run_dir)
    settings = run_settings(config, info.get("preset"), run_dir / "config.json", problems)
    variant, pair_source = _variant(run_dir, algo, config, problems)
    source = info.get("source") if isinstance(info.get("source"), str) else None
    source = source or pair_source
    final = std = success = estimate = true = capping = predicted = arrived = None
    episodes = None
    result = _json_object(run_dir / "eval.json", problems)
    foreign = _foreign_evaluation(result, info)
    if foreign:
        problems.append(f"{run_dir / 'eval.json'}: {foreign}")
        result = None
    damage = "" if result is None else evaluation_damage(result)
    if damage:
        problems.append(f"{run_dir / 'eval.json'}: not an evaluation record ({damage})")
        result = None
    if result is not None:
        returns = [float(r) for r in result["returns"]]
        final, episodes = _mean(returns), len(returns)
        std = float(result.get("std", 0.0))
        success = None if result.get("success_rate") is None else float(result["success_rate"])
        estimate, true = _mean(result.get("value_estimate")), _mean(result.get("value_true"))
        capping = _mean(result.get("value_source"))
        predicted, arrived = _mean(result.get("reward_estimate")), _mean(result.get("reward_true"))
    records = _metrics(run_dir, problems)
    result = RunResult(
        run_dir=str(run_dir),
        algo=algo,
        variant=variant,
        source=source,
        target=target,
        seed=seed,
        final_return=final,
        return_std=std,
        episodes=episodes,
        success_rate=success,
        value_estimate=estimate,
        value_true=true,
        value_source=capping,
        reward_estimate=predicted,
        reward_true=arrived,
        zeta=_zeta(config) if is_collaborative(algo) else None,
        normalized_score=normalized(target, final),
        updates=_updates(records, algo),
        source_steps=source_steps(records),
        wall_time_s=_wall_time(records),
        problems=tuple(problems),
        dataset_quality=None if info.get("online") else _cached_quality(info.get("dataset"), qualities),
    )
    return result, settings


def _cached_quality(path: Any, qualities: dict[str, str | None] | None) -> str | None:
    if qualities is None or not isinstance(path, str):
        return dataset_quality(path)
    if path not in qualities:
        qualities[path] = dataset_quality(path)
    return qualities[path]


def load_results(root: str | Path, problems: list[str] | None = None) -> list[RunResult]:
    """Every run under ``root``, each variant naming what tells its arm from the others (runs that differ in
    anything but the seed are never one arm: :mod:`coworld.report.arms`); raises CoworldError when there is none.
    Unreadable ``run.json`` files, and runs whose ``config.json`` cannot be read, are skipped with a line in
    ``problems`` (each run's other files: :attr:`RunResult.problems`)."""
    problems = problems if problems is not None else []
    dirs = find_run_dirs(root, problems)
    if not dirs:
        raise CoworldError(f"no run folders (with a run.json) under {root}; run `coworld sweep` or `coworld train`")
    qualities: dict[str, str | None] = {}
    loaded = []
    for run_dir in dirs:
        try:
            loaded.append(_load(run_dir, qualities))
        except UnreadableRun as err:
            problems.append(str(err))
    variants = arm_variants([(result.algo, result.variant, settings) for result, settings in loaded])
    return [replace(result, variant=variant) for (result, _), variant in zip(loaded, variants, strict=True)]


def shown_path(path: str | Path, folder: str | Path) -> str:
    """``path`` as a report written in ``folder`` names it: relative to that folder, so that a report committed with
    its runs names no folder of the machine that made it."""
    return os.path.relpath(path, folder)


def to_csv(results: Iterable[RunResult], folder: str | Path | None = None) -> str:
    """One row per run, columns :data:`CSV_COLUMNS`; empty cells where nothing was measured. ``folder``: where the
    CSV is written, which ``run_dir`` is relative to (:func:`shown_path`; as read without one)."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for result in results:
        row = asdict(result)
        row["pair"] = result.pair
        if folder is not None:
            row["run_dir"] = shown_path(result.run_dir, folder)
        number = result.paper
        if number is not None:
            row.update(paper_return=number.mean, paper_std=number.std, paper_table=number.where)
        else:
            row.update(paper_return=None, paper_std=None, paper_table=None)
        writer.writerow({key: "" if row[key] is None else row[key] for key in CSV_COLUMNS})
    return out.getvalue()
