"""``coworld report`` on hand-made run folders with known numbers."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from coworld import envs
from coworld.cli import main
from coworld.report import results as results_module
from coworld.report import write_report
from coworld.report.diagnostics import cap_curve, diagnostics_table, series, under_cap
from coworld.report.plots import curve_runs, mean_band
from coworld.report.results import (
    find_run_dirs,
    learning_curve,
    load_result,
    load_results,
    read_run_metrics,
    wall_clock_curve,
)
from coworld.report.tables import iqm_interval, label_order, results_table, seed_table, value_table
from coworld.training.description import collector_run_info


@pytest.fixture
def score_scale(monkeypatch):
    """Both toy tasks scored from 0 (random) to 100 (reference), so normalized scores are return / 100."""
    real = envs.task_spec

    def fake(name: str):
        return replace(real(name), random_return=0.0, reference_return=100.0)

    monkeypatch.setattr(results_module.envs, "task_spec", fake)


def make_run(
    root: Path,
    name: str,
    *,
    algo: str,
    target: str,
    seed: int,
    source: str | None = None,
    returns: list[float] | None = None,
    records: list[dict] | None = None,
    coworld: dict | None = None,
    variant: str | None = None,
    value: tuple[float, float] | None = None,
    reward: tuple[float, float] | None = None,
) -> Path:
    """A run folder as `coworld train` (+ `coworld eval`, + a sweep's record) leaves it."""
    run = root / name
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"algo": algo, "source": source, "target": target, "dataset": "d.h5"}))
    (run / "config.json").write_text(json.dumps({"seed": seed, "coworld": coworld or {}}))
    if returns is not None:
        result = {"task": target, "returns": returns, "std": float(np.std(returns)), "success_rate": None}
        if value is not None:
            result.update(value_estimate=[value[0]] * len(returns), value_true=[value[1]] * len(returns))
        if reward is not None:  # the reward check: predicted, received, a step
            result.update(reward_estimate=[reward[0]] * len(returns), reward_true=[reward[1]] * len(returns))
        (run / "eval.json").write_text(json.dumps(result))
    if records is not None:
        (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    if variant is not None:
        record = {"algo": algo, "variant": variant, "source": source or "toy_reach", "target": target, "seed": seed}
        (run / "sweep-run.json").write_text(json.dumps(record))
    return run


def make_grid(root: Path) -> None:
    """Final returns (mean of eval.json's returns):
    toy_reach_shifted (source toy_reach): coworld 25, 35, 45; dreamerv2 10, 10, 14
    toy_reach (source toy_reach_shifted): coworld 20, 30 (a third seed unfinished); dreamerv2 40, 40, 40
    """
    shifted, reach = "toy_reach_shifted", "toy_reach"
    for seed, r in enumerate([25.0, 35.0, 45.0]):
        make_run(root, f"cw-a{seed}", algo="coworld", source="toy_reach", target=shifted, seed=seed,
                 returns=[r - 5, r + 5], value=(3.0, 2.0))  # fmt: skip
    for seed, r in enumerate([10.0, 10.0, 14.0]):
        make_run(root, f"dv-a{seed}", algo="dreamerv2", target=shifted, seed=seed, returns=[r], value=(9.0, 1.0))
    for seed, r in enumerate([20.0, 30.0]):
        make_run(root, f"cw-b{seed}", algo="coworld", source=shifted, target=reach, seed=seed, returns=[r])
    partial = [{"step": 7, "target/wm/loss": 1.0}]
    make_run(root, "cw-b2", algo="coworld", source=shifted, target=reach, seed=2, records=partial)
    for seed in range(3):
        make_run(root, f"dv-b{seed}", algo="dreamerv2", target=reach, seed=seed, returns=[40.0])


def test_table_mean_std_bold_and_iqm_aggregate(tmp_path, score_scale):
    make_grid(tmp_path)
    table = results_table(load_results(tmp_path)).splitlines()
    assert table[0] == "| pair | dreamerv2 | coworld |"  # the paper's column order
    assert table[2] == "| toy_reach → toy_reach_shifted | 11.3 ± 1.9 | **35.0 ± 8.2** |"
    assert table[3] == "| toy_reach_shifted → toy_reach | **40.0 ± 0.0** | 25.0 ± 5.0 (n=2) |"
    # IQM of normalized scores (x 100, as eval prints them): dreamerv2 [10 10 14 40 40 40] -> middle four
    # 10 14 40 40 -> 26.0; coworld [25 35 45 20 30] -> middle three 25 30 35 -> 30.0
    aggregate = table[4].split(" | ")
    assert aggregate[0] == "| IQM normalized score [95% CI]"
    for cell, point in zip(aggregate[1:], ("26.0", "30.0"), strict=True):
        value, interval = cell.strip(" |").split(" [")
        low, high = (float(x) for x in interval.rstrip("]").split(", "))
        assert value == point and low <= float(value) <= high and low < high


def test_iqm_interval_known_answers():
    assert iqm_interval([[0, 1, 2, 3, 4, 5, 6, 7]]).point == pytest.approx(3.5)  # mean of 2..5
    # one task of two runs {0, 1}: resamples give IQMs 0, 0.5, 0.5, 1 (a quarter each): the 95% interval is [0, 1]
    ci = iqm_interval([[0.0, 1.0]])
    assert (ci.point, ci.low, ci.high, ci.runs, ci.tasks) == (0.5, 0.0, 1.0, 2, 1)
    # a one-run task is a constant in every resample: IQM of {5, a, b} = (5 + a + b) / 3, a, b from {0, 1}
    ci = iqm_interval([[5.0], [0.0, 1.0]])
    assert ci.point == pytest.approx(2.0)
    assert ci.low == pytest.approx(5 / 3) and ci.high == pytest.approx(7 / 3)
    assert iqm_interval([[0.4], [0.2]]).low == iqm_interval([[0.4], [0.2]]).high == pytest.approx(0.3)


def test_results_csv_one_row_per_run(tmp_path, score_scale):
    make_grid(tmp_path)
    made = write_report(tmp_path, tmp_path / "out")
    rows = list(csv.DictReader(io.StringIO((tmp_path / "out" / "results.csv").read_text())))
    assert len(rows) == len(made.results) == 12 and made.finished == 11
    row = next(r for r in rows if r["run_dir"].endswith("cw-a2"))
    assert row["pair"] == "toy_reach->toy_reach_shifted" and row["algo"] == "coworld" and row["seed"] == "2"
    assert float(row["final_return"]) == 45.0 and float(row["return_std"]) == 5.0 and row["episodes"] == "2"
    assert float(row["normalized_score"]) == pytest.approx(45.0)
    assert float(row["value_estimate"]) == 3.0 and float(row["value_true"]) == 2.0
    baseline = next(r for r in rows if r["run_dir"].endswith("dv-a0"))
    assert baseline["pair"] == "toy_reach_shifted" and baseline["source"] == ""  # plain train: no pair known
    unfinished = next(r for r in rows if r["run_dir"].endswith("cw-b2"))
    assert unfinished["final_return"] == "" and unfinished["updates"] == "7"


def test_the_report_names_run_folders_relative_to_its_own_folder(tmp_path, score_scale):
    """A committed report names no folder of the machine that made it: runs relative to where it is written."""
    sweep = tmp_path / "sweeps" / "toy"
    make_grid(sweep)
    (sweep / "dv-a1" / "eval.json").write_text("{")  # a skipped file is named the same way
    for out, prefix in ((sweep, ""), (tmp_path / "reports" / "toy", "../../sweeps/toy/")):
        write_report(sweep, out)
        rows = list(csv.DictReader(io.StringIO((out / "results.csv").read_text())))
        assert sorted(row["run_dir"] for row in rows)[:2] == [f"{prefix}cw-a0", f"{prefix}cw-a1"]
        text = (out / "report.md").read_text()
        assert text.startswith("# Results: toy\n") and str(tmp_path) not in text
        assert f"- `{prefix}cw-b2` (coworld, seed 2): 7 updates logged" in text
        assert f"- {prefix}dv-a1/eval.json: not JSON" in text


def test_an_evaluation_in_another_task_is_not_counted(tmp_path):
    run = make_run(tmp_path, "lompo", algo="lompo", target="toy_reach_shifted", seed=0)
    record = {"task": "robodesk_push_button", "returns": [158.0], "std": 0.0, "extra": {"algo": "lompo"}}
    (run / "eval.json").write_text(json.dumps(record))  # `coworld eval --task` writes into the run folder too
    result = load_result(run)
    assert result.final_return is None and result.normalized_score is None
    assert result.problems == (
        f"{run / 'eval.json'}: an evaluation in robodesk_push_button, not in the run's target toy_reach_shifted",
    )
    assert write_report(tmp_path).finished == 0


def test_the_curves_legend_counts_runs_in_the_singular_and_plural(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from coworld.report.plots import learning_curves

    records = [{"step": 10, "eval/return": 1.0, "eval/value_estimate": 0.5}]  # a CoWorld target's evaluation
    make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=0, records=records)
    for seed in range(2):
        make_run(tmp_path, f"dv{seed}", algo="dreamerv2", target="toy_reach_shifted", seed=seed, records=records)
    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: (drawn.append(fig), fig.draw_without_rendering()))
    assert learning_curves(load_results(tmp_path), "toy_reach_shifted", tmp_path / "c.png")
    (legend,) = drawn[0].legends  # the figure's, beside both plots, not on a curve
    assert [text.get_text() for text in legend.get_texts()] == ["dreamerv2 (2 runs)", "coworld (1 run)"]
    assert legend.get_window_extent().x0 >= max(ax.get_window_extent().x1 for ax in drawn[0].axes)


def test_the_curves_draw_no_two_labels_alike(tmp_path, monkeypatch):
    """Past matplotlib's ten cycle colours (the cap study has 11 labels), the next labels change line style."""
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from coworld.report.plots import learning_curves

    records = [{"step": 10, "time": 60.0, "eval/return": 1.0}, {"step": 20, "time": 120.0, "eval/return": 2.0}]
    for i in range(12):
        make_run(
            tmp_path, f"dv{i}", algo="dreamerv2", target="toy_reach_shifted", seed=0, records=records, variant=f"v{i}"
        )
    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: drawn.append(fig))
    assert learning_curves(load_results(tmp_path), "toy_reach_shifted", tmp_path / "c.png")
    by_updates, by_clock = drawn[0].axes
    styles = [(line.get_color(), line.get_linestyle()) for line in by_updates.lines]
    assert len(styles) == 12 and len(set(styles)) == 12
    assert len({(line.get_color(), line.get_marker()) for line in by_updates.lines}) == 12  # with a few evaluations
    assert [(line.get_color(), line.get_linestyle()) for line in by_clock.lines] == styles


def test_report_files_and_unfinished_runs(tmp_path, score_scale, drawn):
    make_grid(tmp_path)
    out = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert out.exit_code == 0, out.output
    assert "12 runs, 11 finished" in out.output
    text = (tmp_path / "report.md").read_text()
    assert "| toy_reach → toy_reach_shifted | 11.3 ± 1.9 | **35.0 ± 8.2** |" in text
    assert "## Not finished" in text and "cw-b2" in text and "7 updates logged" in text
    # value check: dreamerv2 9.00 vs 1.00 on the shifted task (the runs with eval.json's value check)
    assert "| toy_reach → toy_reach_shifted | dreamerv2 | 9.00 | 1.00 | – | – | 3 |" in text
    for name in ("value_check.png",):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
    (check,) = drawn["value_check.png"].axes
    (legend,) = drawn["value_check.png"].legends  # the figure's, above the bars, not on them
    assert check.get_legend() is None and legend.get_window_extent().y0 >= check.get_window_extent().y1
    assert not (tmp_path / "ablation.png").exists()  # no CoWorld variants here
    assert not (tmp_path / "cap.png").exists()  # no CoWorld run logged its critics


def test_curves_keep_the_target_evaluations_of_coworld(tmp_path):
    # CoWorld's run folder also logs its source agent's evaluations (no value check) under eval/return
    records = [
        {"step": 1000, "time": 5.0, "eval/return": 30.0},  # source, pretraining
        {"step": 100, "time": 9.0, "target/wm/loss": 1.0},
        {"step": 100, "time": 10.0, "eval/return": 4.0, "eval/value_estimate": 1.0, "eval/value_true": 2.0},
        {"step": 2000, "time": 3.0, "eval/return": 31.0},  # a resumed run: the logger's clock restarts
        {"step": 200, "time": 7.0, "eval/return": 6.0, "eval/value_estimate": 1.0, "eval/value_true": 2.0},
    ]
    run = make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=0,
                   records=records)  # fmt: skip
    assert learning_curve(run, "coworld") == [(100, 4.0), (200, 6.0)]
    assert learning_curve(run, "dreamerv2") == [(1000, 30.0), (100, 4.0), (2000, 31.0), (200, 6.0)]
    result = load_result(run)
    assert result.updates == 200  # target updates, not the source's environment steps
    assert result.wall_time_s == pytest.approx(10.0 + 7.0)
    # against the clock: the second segment's times follow the first's (10 s), in hours
    hours, values = zip(*wall_clock_curve(run, "coworld"), strict=True)
    assert hours == pytest.approx((10.0 / 3600, 17.0 / 3600)) and values == (4.0, 6.0)
    steps, mean, std = mean_band([[(100, 1.0), (200, 3.0)], [(100, 3.0), (200, 5.0)], [(100, 2.0)]])
    assert steps.tolist() == [100, 200] and mean.tolist() == [2.0, 4.0]
    assert std.tolist() == pytest.approx([np.std([1, 3, 2]), 1.0])


def test_a_resumed_runs_records_count_once(tmp_path):
    # killed after its update-200 log, resumed from the checkpoint at update 100: the resume logs 200 again
    train = {"unit": "target_update", "target/coworld/maxmin_active": 0.5}
    records = [
        {**train, "step": 100, "time": 9.0},
        {"unit": "target_update", "step": 100, "time": 10.0, "eval/return": 4.0, "eval/value_estimate": 1.0},
        {**train, "step": 200, "time": 12.0, "target/coworld/maxmin_active": 0.0},
        {**train, "step": 200, "time": 2.0},  # the rerun's clock starts again
        {"unit": "target_update", "step": 200, "time": 3.0, "eval/return": 6.0, "eval/value_estimate": 1.0},
    ]
    run = make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=0,
                   records=records)  # fmt: skip
    kept = read_run_metrics(run)
    assert [(r["step"], r["time"]) for r in kept] == [(100, 9.0), (100, 10.0), (200, 14.0), (200, 15.0)]
    assert [r["target/coworld/maxmin_active"] for r in kept[::2]] == [0.5, 0.5]  # the rerun's log, not the lost one
    assert learning_curve(run, "coworld") == [(100, 4.0), (200, 6.0)]
    assert load_result(run).wall_time_s == pytest.approx(12.0 + 3.0)  # the lost segment's time counts
    hours, _ = zip(*wall_clock_curve(run, "coworld"), strict=True)
    assert hours == pytest.approx((10.0 / 3600, 15.0 / 3600))


def test_ablation_from_plain_runs_and_from_sweep_records(tmp_path, score_scale):
    target = "toy_reach_shifted"
    for seed, r in enumerate([30.0, 34.0]):
        make_run(tmp_path, f"full{seed}", algo="coworld", source="toy_reach", target=target, seed=seed, returns=[r],
                 value=(5.0 + seed, 4.0), reward=(0.5 + seed, 0.25))  # fmt: skip
        make_run(tmp_path, f"noalign{seed}", algo="coworld", source="toy_reach", target=target, seed=seed,
                 returns=[r - 20], coworld={"align": False, "value_reg": True}, value=(9.0, 4.0))  # fmt: skip
        make_run(tmp_path, f"lr{seed}", algo="coworld", source="toy_reach", target=target, seed=seed,
                 returns=[r - 10], variant="slow-lr")  # fmt: skip
    results = load_results(tmp_path)
    assert sorted({r.variant for r in results}) == ["", "no-align", "slow-lr"]
    table = results_table(results, variants=True).splitlines()
    assert table[0] == "| pair | coworld | coworld (no-align) | coworld (slow-lr) |"
    assert table[2] == "| toy_reach → toy_reach_shifted | **32.0 ± 2.0** | 12.0 ± 2.0 | 22.0 ± 2.0 |"
    assert results_table(results).count("\n") == 3  # the main table: CoWorld as configured only
    values = value_table(results).splitlines()  # the value check tells the variants apart
    assert values[2:] == [
        "| toy_reach → toy_reach_shifted | coworld | 5.50 | 4.00 | – | 1.000 / 0.250 | 2 |",  # the seeds' mean
        "| toy_reach → toy_reach_shifted | coworld (no-align) | 9.00 | 4.00 | – | – | 2 |",
    ]
    write_report(tmp_path)
    assert (tmp_path / "ablation.png").read_bytes()[:4] == b"\x89PNG"
    assert "## Variants" in (tmp_path / "report.md").read_text()


def test_the_variants_table_holds_every_algorithms_variants(tmp_path):
    """A study's variants of another algorithm than CoWorld (offline DreamerV2 with 4x the updates) have their
    column beside it; the main table keeps the algorithms as configured."""
    target = "toy_reach_shifted"
    for seed in (0, 1):
        make_run(tmp_path, f"cw{seed}", algo="coworld", source="toy_reach", target=target, seed=seed, returns=[30.0])
        make_run(tmp_path, f"cw4x{seed}", algo="coworld", source="toy_reach", target=target, seed=seed,
                 returns=[40.0 + seed], variant="4x")  # fmt: skip
        make_run(tmp_path, f"dv{seed}", algo="dreamerv2", target=target, seed=seed, returns=[20.0])
        make_run(tmp_path, f"dv4x{seed}", algo="dreamerv2", target=target, seed=seed, returns=[10.0], variant="4x")
        make_run(tmp_path, f"pen{seed}", algo="dreamerv2-penalty", target=target, seed=seed, returns=[5.0])
    results = load_results(tmp_path)
    table = results_table(results, variants=True).splitlines()
    assert table[0] == "| pair | dreamerv2 | dreamerv2 (4x) | coworld | coworld (4x) |"  # the main table's order
    assert table[2] == "| toy_reach → toy_reach_shifted | 20.0 ± 0.0 | 10.0 ± 0.0 | 30.0 ± 0.0 | **40.5 ± 0.5** |"
    assert results_table(results).splitlines()[0] == "| pair | dreamerv2 | dreamerv2-penalty | coworld |"


def test_runs_are_shown_by_algorithm_each_followed_by_its_variants_in_natural_order(tmp_path):
    """The figures and every table put a study's arms beside their algorithm (offline DreamerV2 at 4x next to it,
    not after every CoWorld arm) and zeta 3 before zeta 10."""
    target = "toy_reach_shifted"
    for variant in ("zeta10", None, "4x", "zeta3"):
        make_run(tmp_path, f"cw-{variant}", algo="coworld", source="toy_reach", target=target, seed=0, returns=[1.0],
                 variant=variant, value=(1.0, 1.0), records=[{"step": 1}])  # fmt: skip
    for algo, variant in (("dreamerv2", "4x"), ("dreamerv2-penalty", None), ("dreamerv2", None)):
        make_run(tmp_path, f"{algo}-{variant}", algo=algo, target=target, seed=0, returns=[1.0], variant=variant,
                 value=(1.0, 1.0))  # fmt: skip
    results = load_results(tmp_path)
    order = [
        "dreamerv2",
        "dreamerv2 (4x)",
        "dreamerv2-penalty",
        "coworld",
        "coworld (4x)",
        "coworld (zeta3)",
        "coworld (zeta10)",
    ]
    assert label_order(results) == order
    assert [row.split(" | ")[1] for row in value_table(results).splitlines()[2:]] == order
    assert [row.split(" | ")[1] for row in diagnostics_table(results).splitlines()[2:]] == order[3:]


def test_a_report_whose_finished_runs_are_all_variants_says_so_above_their_table(tmp_path):
    """A study part-way through (one variant finished, the run as configured still training) says that no run as
    configured has finished, not that none has."""
    target = "toy_reach_shifted"
    make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target=target, seed=0, returns=None)
    make_run(tmp_path, "cw3", algo="coworld", source="toy_reach", target=target, seed=0, returns=[12.0],
             variant="zeta3")  # fmt: skip
    out = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(tmp_path / "out")])
    assert out.exit_code == 0, out.output
    text = (tmp_path / "out" / "report.md").read_text()
    results = text.split("## Results", 1)[1].split("##", 1)[0]
    assert "No run as configured has finished yet" in results and "No finished runs yet" not in text
    assert "## Variants" in text and "| toy_reach → toy_reach_shifted | 12.0 (n=1) |" in text


def test_run_folders_are_found_by_their_run_json(tmp_path):
    make_run(tmp_path / "a", "r1", algo="curl", target="toy_reach", seed=0, returns=[1.0])
    collector = tmp_path / "datasets" / "toy_reach-medium_replay.run"  # the online dreamerv2 run of a collection
    collector.mkdir(parents=True)
    described = {**collector_run_info("toy_reach", "tiny"), "quality": "medium-replay"}
    (collector / "run.json").write_text(json.dumps(described))
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "run.json").write_text(json.dumps({"something": "else"}))  # not a run description
    assert find_run_dirs(tmp_path) == [tmp_path / "a" / "r1", collector]
    assert load_result(collector).algo == "dreamerv2-online"
    # A collector nobody evaluated is listed as what made a dataset, not as a run still to finish.
    (collector / "metrics.jsonl").write_text(json.dumps({"step": 500, "unit": "env_step", "eval/return": 29.7}) + "\n")
    out = CliRunner().invoke(main, ["report", str(tmp_path), "--out", str(tmp_path / "out")])
    assert out.exit_code == 0 and "1 run, 1 finished" in out.output, out.output
    text = (tmp_path / "out" / "report.md").read_text()
    assert "1 run, 1 finished" in text and "## Not finished" not in text
    assert "## Dataset collectors" in text and "last evaluation while learning 29.7 at env step 500" in text
    # Their curves count env steps: a figure shows them only where no training run shares the target.
    results = load_results(tmp_path)
    assert [r.algo for r in results] == ["curl", "dreamerv2-online"]
    assert curve_runs(results, "toy_reach") == ([results[0]], "target updates")
    assert curve_runs(results[1:], "toy_reach") == ([results[1]], "env steps")
    empty = tmp_path / "empty"
    empty.mkdir()
    out = CliRunner().invoke(main, ["report", str(empty)])
    assert out.exit_code == 2 and "no run folders" in out.output
    out = CliRunner().invoke(main, ["report", str(tmp_path / "missing")])
    assert out.exit_code == 2 and "is not a folder" in out.output and not (tmp_path / "missing").exists()


@pytest.mark.parametrize("missing", ["scipy", "matplotlib"])
def test_missing_report_extra_gives_the_install_hint(tmp_path, monkeypatch, missing):
    make_run(tmp_path, "r", algo="curl", target="toy_reach", seed=0, returns=[1.0, 2.0],
             records=[{"step": 10, "eval/return": 1.0}])  # fmt: skip
    monkeypatch.setitem(sys.modules, missing, None)  # what importing it does without the extra
    monkeypatch.setitem(sys.modules, f"{missing}.stats" if missing == "scipy" else "matplotlib.figure", None)
    out = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert out.exit_code == 2 and "pip install 'coworld[report]'" in out.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]  # nothing written


def test_a_fine_tuned_run_reports_its_target_updates_and_evaluations_not_its_source_phase(tmp_path: Path) -> None:
    records = [
        {"step": 1000, "unit": "source_env_step", "source/eval/return": 30.0, "source/eval/return_std": 1.0},
        {"step": 2000, "unit": "source_env_step", "source/wm/loss": 5.0},
        {"step": 20, "unit": "update", "eval/return": 12.0, "eval/value_estimate": 1.0},
        {"step": 40, "unit": "update", "eval/return": 18.0, "eval/value_estimate": 1.0},
    ]
    run = make_run(tmp_path, "ft", algo="dreamerv2-finetune", source="toy_reach", target="toy_reach_shifted", seed=0,
                   returns=[18.0], records=records)  # fmt: skip
    result = load_result(run)
    assert result.updates == 40 and result.pair == "toy_reach->toy_reach_shifted"
    assert learning_curve(run, "dreamerv2-finetune") == [(20, 12.0), (40, 18.0)]
    make_run(tmp_path, "drq", algo="drq-bc", target="toy_reach_shifted", seed=0, returns=[9.0])
    make_run(tmp_path, "dv", algo="dreamerv2", target="toy_reach_shifted", seed=0, returns=[10.0])
    header = results_table(load_results(tmp_path)).splitlines()[0]
    assert header.index("drq-bc") < header.index("dreamerv2 ") < header.index("dreamerv2-finetune")  # the columns


def test_coworld_diagnostics_summarise_each_term_from_the_logs(tmp_path):
    records = [
        {"step": 100, "target/coworld/align_kl": 2.0, "target/coworld/maxmin_active": 0.5,
         "target/coworld/target_value": 4.0, "target/coworld/source_value": 3.0,
         "target/coworld/binds_zeta_2": 0.6, "target/coworld/binds_zeta_3": 0.7, "target/coworld/binds_zeta_5": 0.8,
         "target/coworld/binds_zeta_10": 0.9},
        {"step": 50, "unit": "source_env_step", "source/coworld/relabel_reward_loss": 0.8},
        {"step": 200, "target/coworld/align_kl": 0.5, "target/coworld/maxmin_active": 0.1,
         "target/coworld/target_value": 2.0, "target/coworld/source_value": 5.0,
         "target/coworld/binds_zeta_2": 0.2, "target/coworld/binds_zeta_3": 0.3, "target/coworld/binds_zeta_5": 0.4,
         "target/coworld/binds_zeta_10": 0.5},
        {"step": 90, "unit": "source_env_step", "source/coworld/relabel_reward_loss": 0.2},
        {"step": 300, "target/coworld/align_kl": float("nan")},  # a non-finite log is not a value
    ]  # fmt: skip
    on = make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=3,
                  returns=[1.0], records=records, coworld={"zeta": 2.0})  # fmt: skip
    off = [{"step": 100, "target/coworld/align_kl": 1.0}]  # value regulariser and relabelling switched off
    # cw-off has cw's settings (one arm of two seeds): runs that differ are two arms
    make_run(tmp_path, "cw-off", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=4,
             returns=[1.0], records=off, coworld={"zeta": 2.0})  # fmt: skip
    make_run(tmp_path, "dv", algo="dreamerv2", target="toy_reach_shifted", seed=0, returns=[1.0])
    kl = series(records, "target/coworld/align_kl")
    assert (kl.first, kl.last, kl.mean, kl.count) == (2.0, 0.5, 1.25, 2)
    assert series(records, "eval/return") is None
    table = diagnostics_table(load_results(tmp_path)).splitlines()
    assert len(table) == 2 + 2  # header, rule, the two CoWorld runs; not the DreamerV2 run
    pair = "| toy_reach → toy_reach_shifted | coworld"
    probes = "40.0% / 50.0% / 60.0% / 70.0%"  # where the term would bind at zeta 2, 3, 5, 10: the run's mean
    under = "0.80-2.67 (0.80)"  # the target critic over the cap (4 / 1.5, 2 / 2.5), logs from a quarter of the run on
    assert (
        table[2] == f"{pair} | 3 | 2 → 0.5 | 0.8 → 0.2 | 30.0% (10.0%) | {probes} | 3 (2) | 4 (5) | 2 (2.5) | {under} |"
    )
    assert table[3] == f"{pair} | 4 | 1 → 1 | – | – | – / – / – / – | – | – | – | – |"
    assert load_result(on).algo == "coworld"
    out = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert out.exit_code == 0, out.output
    assert "## CoWorld's terms" in (tmp_path / "report.md").read_text()
    assert load_result(on).zeta == 2.0
    assert cap_curve(records, 2.0) == [(100, 4.0, 1.5), (200, 2.0, 2.5)]  # the cap: the source critic / zeta
    later = [*records, {"step": 1000, "target/coworld/target_value": 3.0, "target/coworld/source_value": 8.0}]
    assert under_cap(later, 2.0) == (0.75, 0.75, 0.75)  # logs before a quarter of the run (250) are left out
    assert under_cap(records[1:2], 2.0) is None
    assert (tmp_path / "cap.png").read_bytes()[:4] == b"\x89PNG" and "(cap.png)" in (tmp_path / "report.md").read_text()


def test_the_by_seed_table_sets_each_arm_against_the_others_within_a_seed(tmp_path: Path) -> None:
    """One row per pair and label (variants too, in label order), one column per seed, each cell that run's final
    return; a seed a label lacks is a dash, an unfinished run is left out; no table while every label has one seed."""
    target = "toy_reach_shifted"
    make_run(tmp_path, "dv0", algo="dreamerv2", target=target, seed=0, returns=[10.0, 12.0])
    make_run(tmp_path, "cw10-1", algo="coworld", source="toy_reach", target=target, seed=1, returns=[3.0],
             variant="zeta10")  # fmt: skip
    assert seed_table(load_results(tmp_path)) == ""  # every label has one seed
    make_run(tmp_path, "dv1", algo="dreamerv2", target=target, seed=1, returns=[20.0])
    make_run(tmp_path, "cw10-0", algo="coworld", source="toy_reach", target=target, seed=0, returns=[5.0],
             variant="zeta10")  # fmt: skip
    make_run(tmp_path, "cw0", algo="coworld", source="toy_reach", target=target, seed=0, returns=[7.0], variant="")
    make_run(tmp_path, "cw1", algo="coworld", source="toy_reach", target=target, seed=1, variant="")  # unfinished
    pair = "| toy_reach → toy_reach_shifted"
    assert seed_table(load_results(tmp_path)).splitlines() == [
        "| pair | algorithm | seed 0 | seed 1 |",
        "|---|---|---:|---:|",
        f"{pair} | dreamerv2 | 11.0 | 20.0 |",
        f"{pair} | coworld | 7.0 | — |",
        f"{pair} | coworld (zeta10) | 5.0 | 3.0 |",
    ]
    write_report(tmp_path)
    assert "## By seed" in (tmp_path / "report.md").read_text()


def test_lompo_and_the_ewc_fine_tuned_runs_get_their_own_columns_and_curves(tmp_path: Path) -> None:
    records = [
        {"step": 0, "unit": "update", "ewc/fisher_world_model": 3.0},
        {"step": 20, "unit": "update", "eval/return": 14.0, "eval/value_estimate": 1.0},
        {"step": 40, "unit": "update", "eval/return": 21.0, "eval/value_estimate": 1.0},
    ]
    run = make_run(tmp_path, "ewc", algo="dreamerv2-finetune-ewc", source="toy_reach", target="toy_reach_shifted",
                   seed=0, returns=[21.0], records=records)  # fmt: skip
    assert load_result(run).pair == "toy_reach->toy_reach_shifted"
    assert learning_curve(run, "dreamerv2-finetune-ewc") == [(20, 14.0), (40, 21.0)]
    make_run(tmp_path, "lompo", algo="lompo", target="toy_reach_shifted", seed=0, returns=[7.0])
    make_run(tmp_path, "ft", algo="dreamerv2-finetune", source="toy_reach", target="toy_reach_shifted", seed=0,
             returns=[18.0])  # fmt: skip
    make_run(tmp_path, "pen", algo="dreamerv2-penalty", target="toy_reach_shifted", seed=0, returns=[9.0])
    table = results_table(load_results(tmp_path)).splitlines()
    header = table[0]
    order = ["dreamerv2-penalty", "lompo", "dreamerv2-finetune ", "dreamerv2-finetune-ewc"]
    assert [header.index(name) for name in order] == sorted(header.index(name) for name in order)  # columns
    cells = [cell.strip() for cell in table[2].split("|")[1:-1]]
    names = [cell.strip() for cell in header.split("|")[1:-1]]
    assert cells[names.index("lompo")] == "7.0 (n=1)"  # one seed: no spread to show
    assert cells[names.index("dreamerv2-finetune-ewc")] == "**21.0 (n=1)**"  # the best of the row


@pytest.fixture
def drawn(monkeypatch):
    """The figures the report saves, by file name, kept when they are written."""
    from matplotlib.figure import Figure

    figures = {}
    save = Figure.savefig

    def keep(figure, path, *args, **kwargs):
        figures[Path(path).name] = figure
        return save(figure, path, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def test_the_figures_draw_the_variants_against_the_baselines_and_each_critic_under_its_cap(tmp_path, drawn):
    """Figure 4(a) draws the other algorithms as configured as dashed lines at their mean; cap.png draws each CoWorld
    label's target critic (solid) and its cap, the capping critic's value over the run's zeta (dashed), and the
    uncapped critics, offline DreamerV2's (black) and a CoWorld run's without the cap (grey), each mean over seeds."""
    target = "toy_reach_shifted"
    logs = [{"step": s, "target/coworld/target_value": v, "target/coworld/source_value": 30.0} for s, v in
            ((100, 2.0), (200, 4.0))]  # fmt: skip
    for seed in (0, 1):
        make_run(tmp_path, f"cw{seed}", algo="coworld", source="toy_reach", target=target, seed=seed, returns=[20.0],
                 records=logs, coworld={"zeta": 1.0})  # fmt: skip
        make_run(tmp_path, f"cw10-{seed}", algo="coworld", source="toy_reach", target=target, seed=seed,
                 returns=[30.0], variant="zeta10", records=logs, coworld={"zeta": 10.0})  # fmt: skip
        critic = [{"step": s, "unit": "update", "critic/value": v + seed} for s, v in ((100, 5.0), (200, 9.0))]
        make_run(tmp_path, f"dv{seed}", algo="dreamerv2", target=target, seed=seed, returns=[10.0 + seed],
                 records=critic)  # fmt: skip
        make_run(tmp_path, f"pen{seed}", algo="dreamerv2-penalty", target=target, seed=seed, returns=[5.0])
    free = [{"step": s, "unit": "target_update", "target/critic/value": v} for s, v in ((100, 6.0), (200, 12.0))]
    make_run(tmp_path, "nocap", algo="coworld", source="toy_reach", target=target, seed=0, returns=[40.0],
             variant="no-cap", records=free, coworld={"zeta": 1.0, "value_reg": False})  # fmt: skip
    write_report(tmp_path)
    (ablation,) = drawn["ablation.png"].axes
    dashed = {line.get_label(): line.get_ydata()[0] for line in ablation.lines if line.get_linestyle() == "--"}
    assert dashed == {"dreamerv2": 10.5, "dreamerv2-penalty": 5.0}
    assert [round(bar.get_height(), 6) for bar in ablation.patches] == [20.0, 40.0, 30.0]
    (cap,) = drawn["cap.png"].axes
    lines = [(line.get_label(), line.get_linestyle(), list(line.get_ydata())) for line in cap.lines]
    assert lines[-1] == ("dashed: the cap (capping critic / zeta)", "--", [])  # the legend's key to the dashed lines
    assert [(style, values) for _, style, values in lines[:-1]] == [
        ("-", [2.0, 4.0]), ("--", [30.0, 30.0]), ("-", [2.0, 4.0]), ("--", [3.0, 3.0]), ("-", [5.5, 9.5]),
        ("-", [6.0, 12.0]),
    ]  # fmt: skip
    assert [label for label, _, _ in lines if not label.startswith("_")] == [
        "coworld: target critic",
        "coworld (zeta10): target critic",
        "dreamerv2: critic, no cap",
        "coworld (no-cap): critic, no cap",
        "dashed: the cap (capping critic / zeta)",
    ]
    assert cap.lines[-3].get_color() == "black" and cap.lines[-2].get_color() not in ("black", "white")
    assert cap.get_yscale() == "log"
    assert cap.get_legend().get_window_extent().x0 >= cap.get_window_extent().x1  # beside the lines, not on them


def test_the_cap_figure_draws_no_two_critics_alike_past_ten_labels(tmp_path, drawn):
    """Solid and dashed say target critic or cap in cap.png, so past ten colours the labels differ by marker."""
    logs = [{"step": s, "target/coworld/target_value": 2.0, "target/coworld/source_value": 30.0} for s in (100, 200)]
    for i in range(12):
        make_run(tmp_path, f"cw{i}", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=0,
                 returns=[20.0], variant=f"v{i}", records=logs, coworld={"zeta": 1.0})  # fmt: skip
    write_report(tmp_path)
    (cap,) = drawn["cap.png"].axes
    critics = [line for line in cap.lines if line.get_linestyle() == "-"]
    assert len(critics) == 12 and len({(line.get_color(), line.get_marker()) for line in critics}) == 12
    assert {line.get_marker() for line in critics[:10]} == {"None"}  # ten labels draw as before, without markers


def test_the_cap_figure_draws_a_linear_axis_where_a_log_one_would_label_under_two_ticks(tmp_path, drawn):
    from coworld.report.plots import _labelled_log_ticks

    assert [_labelled_log_ticks(*span) for span in ((1.1, 45.0), (33.0, 48.0), (12.0, 19.0))] == [6, 0, 0]
    assert _labelled_log_ticks(2.0, 3.0) == 2
    logs = [{"step": s, "target/coworld/target_value": v, "target/coworld/source_value": 48.0} for s, v in
            ((100, 33.0), (200, 40.0))]  # fmt: skip
    make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=0, returns=[20.0],
             records=logs, coworld={"zeta": 1.0})  # fmt: skip
    write_report(tmp_path)
    (cap,) = drawn["cap.png"].axes
    assert cap.get_yscale() == "linear" and len([t for t in cap.get_yticks() if 33.0 <= t <= 48.0]) >= 2


def test_a_log_axis_labels_its_minor_ticks_at_2_3_and_5_only():
    from coworld.report.plots import _two_three_five

    labels = [_two_three_five(v, 0) for v in (2.0, 3.0, 4.0, 5.0, 9.0, 20.0, 30.0, 70.0, 0.5)]
    assert labels == ["2", "3", "", "5", "", "20", "30", "", "0.5"]


def test_the_world_model_table_reads_each_runs_target_model_not_a_sources_pretraining(tmp_path):
    """Offline DreamerV2 logs its world model as ``wm/*`` by update; CoWorld its target's as ``target/wm/*`` by
    target update, beside its source's pretraining (``wm/*`` by env step), which the table leaves out."""
    target = "toy_reach_shifted"
    make_run(tmp_path, "dv", algo="dreamerv2", target=target, seed=0, returns=[1.0], records=[
        {"step": s, "unit": "update", "wm/image": image, "wm/reward": 1.0, "wm/kl": kl}
        for s, image, kl in ((100, 9.0, 2.0), (200, 6.0, 3.0), (300, 3.0, 4.0))])  # fmt: skip
    make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target=target, seed=1, returns=[1.0], records=[
        {"step": 500, "unit": "source_env_step", "wm/image": 99.0, "wm/reward": 99.0, "wm/kl": 99.0},
        {"step": 100, "unit": "target_update", "target/wm/image": 12.0, "target/wm/reward": 2.0},
        {"step": 200, "unit": "target_update", "target/wm/image": 8.0, "target/wm/reward": 1.0}])  # fmt: skip
    write_report(tmp_path)
    text = (tmp_path / "report.md").read_text().split("## Target world models", 1)[1]
    assert f"| {target} | dreamerv2 | 0 | 9 → 3 (6) | 1 → 1 (1) | 2 → 4 (3) |" in text
    assert f"| toy_reach → {target} | coworld | 1 | 12 → 8 (10) | 2 → 1 (1.5) | – |" in text


def test_the_actor_critic_table_reads_each_runs_target_agent_not_a_sources_pretraining(tmp_path):
    """The target agent's critic value, actor entropy and return scale: offline DreamerV2's by update, CoWorld's
    target agent's (``target/...``) by target update; the source's pretraining (by env step) is left out."""
    target = "toy_reach_shifted"
    make_run(tmp_path, "dv", algo="dreamerv2", target=target, seed=0, returns=[1.0], records=[
        {"step": s, "unit": "update", "critic/value": v, "actor/entropy": -18.0, "actor/return_scale": 5.0}
        for s, v in ((100, 10.0), (200, 30.0))])  # fmt: skip
    make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target=target, seed=1, returns=[1.0], records=[
        {"step": 500, "unit": "source_env_step", "critic/value": 99.0, "actor/entropy": 99.0},
        {"step": 100, "unit": "target_update", "target/critic/value": 4.0, "target/actor/entropy": -20.0},
        {"step": 200, "unit": "target_update", "target/critic/value": 2.0, "target/actor/entropy": -26.0}])  # fmt: skip
    write_report(tmp_path)
    text = (tmp_path / "report.md").read_text().split("## Target actor-critics", 1)[1]
    assert f"| {target} | dreamerv2 | 0 | 10 → 30 (20) | -18 → -18 (-18) | 5 → 5 (5) |" in text
    assert f"| toy_reach → {target} | coworld | 1 | 4 → 2 (3) | -20 → -26 (-23) | – |" in text


def test_an_unfinished_run_says_how_far_it_logged(tmp_path):
    """Target updates where it has made some; a CoWorld run still pretraining its source, its env steps there."""
    target = "toy_reach_shifted"
    source_steps = [{"step": s, "unit": "source_env_step", "source/wm/loss": 1.0} for s in (500, 1500)]
    make_run(tmp_path, "pretraining", algo="coworld", source="toy_reach", target=target, seed=0, records=source_steps)
    make_run(tmp_path, "target", algo="coworld", source="toy_reach", target=target, seed=1,
             records=[*source_steps, {"step": 250, "target/wm/loss": 1.0}])  # fmt: skip
    make_run(tmp_path, "fresh", algo="coworld", source="toy_reach", target=target, seed=2)
    write_report(tmp_path)
    unfinished = (tmp_path / "report.md").read_text().split("## Not finished", 1)[1]
    assert "`pretraining` (coworld, seed 0): pretraining its source, 1,500 env steps logged" in unfinished
    assert "`target` (coworld, seed 1): 250 updates logged" in unfinished
    assert "`fresh` (coworld, seed 2): nothing logged yet" in unfinished


def test_the_report_is_written_without_importing_torch(tmp_path):
    """`coworld report` reads JSON and draws figures: torch's import (seconds) is not on its path."""
    make_run(tmp_path, "cw", algo="coworld", source="toy_reach", target="toy_reach_shifted", seed=0, returns=[20.0],
             records=[{"step": 100, "eval/return": 20.0, "target/coworld/target_value": 2.0,
                       "target/coworld/source_value": 30.0}], coworld={"zeta": 1.0})  # fmt: skip
    code = (
        "import sys; from click.testing import CliRunner; from coworld.cli import main;"
        f"out = CliRunner().invoke(main, ['report', {str(tmp_path)!r}]); assert out.exit_code == 0, out.output;"
        "print('torch' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False"] and (tmp_path / "cap.png").exists()
