"""``coworld report`` turns no damaged number into a result: an eval.json whose fields are not what ``coworld eval``
writes is skipped with a line naming the file and the field, and a metrics record holding a value that is not a
finite number is not drawn."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from coworld.cli import main
from coworld.report.diagnostics import on_target
from coworld.report.results import learning_curve, load_result, read_run_metrics

TARGET = "toy_reach_shifted"


def run_folder(root: Path, name: str, evaluation: str | None = None, *, records: str | None = None) -> Path:
    """A dreamerv2 run folder; ``evaluation`` and ``records``: eval.json and metrics.jsonl as text, so a test can
    write what JSON allows and ``coworld eval`` never writes (NaN, Infinity)."""
    run = root / name
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"algo": "dreamerv2", "target": TARGET}))
    (run / "config.json").write_text(json.dumps({"seed": 0}))
    if evaluation is not None:
        (run / "eval.json").write_text(evaluation)
    if records is not None:
        (run / "metrics.jsonl").write_text(records)
    return run


GOOD = {
    "task": TARGET,
    "returns": [10.0, 20.0],
    "lengths": [50, 50],
    "successes": None,
    "value_estimate": [1.0, 2.0],
    "value_true": [1.5, 2.5],
    "value_source": None,
    "reward_estimate": [0.1, 0.2],
    "reward_true": [0.3, 0.4],
    "std": 5.0,
    "success_rate": None,
}

DAMAGE = {  # case: (field, its text in eval.json, what the line says of it)
    "returns a string": ("returns", '"55"', "returns must be a list of finite numbers, got a string"),
    "returns NaN": ("returns", "[10.0, NaN]", "returns must be a list of finite numbers, got NaN at index 1"),
    "returns a string in the list": ("returns", '[10.0, "20"]', "got a string at index 1"),
    "returns a bool": ("returns", "[true, 20.0]", "got a bool at index 0"),
    "returns empty": ("returns", "[]", "returns must be a list of finite numbers, got an empty list"),
    "returns missing": ("returns", None, "returns must be a list of finite numbers, got nothing"),
    "reward_estimate Infinity": (
        "reward_estimate",
        "[0.1, Infinity]",
        "reward_estimate must be a list of finite numbers or null, got Infinity at index 1",
    ),  # fmt: skip
    "reward_true -Infinity": ("reward_true", "[-Infinity, 0.1]", "got -Infinity at index 0"),
    "value_source strings": (
        "value_source",
        '["1.0", "2.0"]',
        "value_source must be a list of finite numbers or null, got a string at index 0",
    ),  # fmt: skip
    "value_source a number": (
        "value_source",
        "3.0",
        "value_source must be a list of finite numbers or null, got a number",
    ),  # fmt: skip
    "value_estimate NaN": ("value_estimate", "[NaN, 1.0]", "value_estimate must be a list"),
    "value_true an object": (
        "value_true",
        '{"a": 1}',
        "value_true must be a list of finite numbers or null, got an object",
    ),  # fmt: skip
    "lengths NaN": ("lengths", "[50, NaN]", "lengths must be a list of finite numbers or null, got NaN at index 1"),
    "successes NaN": (
        "successes",
        "[NaN, true]",
        "successes must be a list of true / false or null, got NaN at index 0",
    ),  # fmt: skip
    "std NaN": ("std", "NaN", "std must be a finite number, got NaN"),
    "success_rate a string": ("success_rate", '"most"', "success_rate must be a finite number or null, got a string"),
}


def evaluation_with(field: str, text: str | None) -> str:
    """eval.json's text: :data:`GOOD` with ``field`` written as ``text`` (left out where None)."""
    body = json.dumps({key: value for key, value in GOOD.items() if key != field})
    return body if text is None else f'{body[:-1]}, "{field}": {text}}}'


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_field_of_eval_json_skips_the_file_with_a_line_naming_it(tmp_path, case):
    field, text, says = DAMAGE[case]
    run = run_folder(tmp_path, "run", evaluation_with(field, text))
    result = load_result(run)
    assert (result.final_return, result.episodes, result.return_std) == (None, None, None)
    assert (result.value_estimate, result.value_true, result.value_source) == (None, None, None)
    assert (result.reward_estimate, result.reward_true, result.success_rate) == (None, None, None)
    (line,) = [p for p in result.problems if "eval.json" in p]
    assert line.startswith(f"{run / 'eval.json'}: ") and says in line, line


def test_a_whole_eval_json_is_read_as_before(tmp_path):
    run = run_folder(tmp_path, "run", json.dumps({**GOOD, "successes": [True, False], "success_rate": 0.5}))
    result = load_result(run)
    assert result.problems == ()
    assert (result.final_return, result.episodes, result.return_std, result.success_rate) == (15.0, 2, 5.0, 0.5)
    assert (result.value_estimate, result.value_true) == (1.5, 2.0)
    assert result.reward_estimate == pytest.approx(0.15) and result.reward_true == pytest.approx(0.35)


def test_the_report_prints_and_lists_a_damaged_eval_json_and_reports_the_rest(tmp_path):
    pytest.importorskip("matplotlib")
    pytest.importorskip("scipy")
    run_folder(tmp_path, "good", json.dumps(GOOD))
    bad = run_folder(tmp_path, "bad", json.dumps({**GOOD, "returns": "55"}))
    out = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert out.exit_code == 0, out.output
    line = f"{bad / 'eval.json'}: not an evaluation record (returns must be a list of finite numbers, got a string)"
    assert f"warning: skipped {line}" in out.stderr
    assert "1 finished" in out.stdout
    report = (tmp_path / "report.md").read_text()
    assert "- bad/eval.json: not an evaluation record (returns must be a list of finite numbers" in report
    rows = {row["run_dir"]: row for row in csv.DictReader(io.StringIO((tmp_path / "results.csv").read_text()))}
    assert rows["bad"]["final_return"] == rows["bad"]["episodes"] == ""  # "55" is not the returns 5 and 5
    assert rows["good"]["final_return"] == "15.0"


RECORDS = [
    {"step": 10, "unit": "update", "time": 1.0, "eval/return": 5.0, "wm/image": 2.0},
    {"step": 20, "unit": "update", "time": 2.0, "eval/return": 50.0, "wm/image": "NaN?"},  # a string
    {"step": 30, "unit": "update", "time": 3.0, "eval/return": 60.0, "eval/return_std": None},  # the logger's NaN
    {"step": 40, "unit": "update", "time": 4.0, "eval/return": 7.0, "wm/image": 3.0},
]


def test_a_metrics_record_with_a_value_that_is_not_a_finite_number_is_not_drawn_and_is_named(tmp_path):
    text = "".join(json.dumps(r) + "\n" for r in RECORDS)
    text += '{"step": 50, "unit": "update", "time": 5.0, "eval/return": 70.0, "wm/image": NaN}\n'
    text += '{"step": 60, "unit": "update", "time": Infinity, "eval/return": 80.0}\n'
    run = run_folder(tmp_path, "run", json.dumps(GOOD), records=text)
    assert learning_curve(run, "dreamerv2") == [(10, 5.0), (40, 7.0)]
    assert [r["step"] for r in read_run_metrics(run)] == [10, 40]
    summary = on_target(read_run_metrics(run), "wm/image")
    assert summary is not None and (summary.first, summary.last, summary.count) == (2.0, 3.0, 2)
    result = load_result(run)
    assert result.updates == 40 and result.wall_time_s == 4.0
    (line,) = [p for p in result.problems if "metrics.jsonl" in p]
    assert line == (
        f"{run / 'metrics.jsonl'}: 4 records holding a value that is not a finite number skipped (the first at step"
        " 20: wm/image is a string)"
    )
