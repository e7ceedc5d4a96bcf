"""The progress view: latest evaluation of a running run, the counts, plain lines off a terminal."""

from __future__ import annotations

import io
import json

from coworld.sweep.progress import ProgressView, latest_eval, summary_line


def test_latest_eval_reads_the_last_evaluation_from_the_tail(tmp_path):
    assert latest_eval(tmp_path) is None and latest_eval(None) is None
    lines = [json.dumps({"step": i, "wm/loss": 1.0, "pad": "x" * 500}) for i in range(200)]  # > the 64 KiB tail
    lines.insert(3, json.dumps({"step": 3, "eval/return": 1.5}))
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    assert latest_eval(tmp_path) is None  # the only evaluation is before the tail
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 300, "eval/return": 12.25}) + "\n")
        f.write(json.dumps({"step": 301, "wm/loss": 0.5}) + "\n")
        f.write('{"step": 302, "eval/return": 9')  # a line being written
    assert latest_eval(tmp_path) == 12.25
    with open(tmp_path / "metrics.jsonl", "a") as f:  # CoWorld's source agent evaluated (no value check)
        f.write("\n" + json.dumps({"step": 4000, "eval/return": 40.0}) + "\n")
    assert latest_eval(tmp_path, "coworld") is None and latest_eval(tmp_path, "curl") == 40.0
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 400, "eval/return": 7.5, "eval/value_estimate": 1.0, "eval/value_true": 2.0}))
    assert latest_eval(tmp_path, "coworld") == 7.5


def test_summary_line_counts_and_running_returns():
    counts = {"done": 3, "running": 2, "failed": 1, "pending": 6}
    line = summary_line(counts, {"coworld-a-s0": 30.44, "curl-a-s1": None})
    assert line == ("sweep: 3/12 done, 2 running, 1 failed, 6 pending | coworld-a-s0 eval 30.4, curl-a-s1 eval -")


def test_plain_lines_when_not_a_terminal_at_most_one_per_interval():
    stream = io.StringIO()
    view = ProgressView(3, interval=3600, stream=stream)
    states = {"a": "done", "b": "running", "c": "pending"}
    view.update(states, {"b": 1.0})
    view.update(states, {"b": 2.0})  # within the interval: no second line
    view.event("done a: return 5.0")
    view.close()
    assert stream.getvalue().splitlines() == [
        "sweep: 1/3 done, 1 running, 0 failed, 1 pending | b eval 1.0",
        "done a: return 5.0",
    ]
    quiet = io.StringIO()
    view = ProgressView(3, enabled=False, stream=quiet)
    view.update(states, {})
    view.event("FAILED b")
    assert quiet.getvalue() == "FAILED b\n"  # events are shown even without the periodic view
