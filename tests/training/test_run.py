import json

import pytest

from coworld.config import make_config
from coworld.errors import CoworldError
from coworld.training import logger as logger_module
from coworld.training.logger import Logger, Rate, read_metrics
from coworld.training.run import load_run, prepare_run_dir


def test_prepare_then_resume_then_refuse(tmp_path):
    config = make_config("tiny")
    assert prepare_run_dir(tmp_path / "run", config, {"algo": "dreamerv2", "task": "toy_reach"}) is False
    assert prepare_run_dir(tmp_path / "run", config, {"algo": "dreamerv2", "task": "toy_reach"}) is True
    saved, info = load_run(tmp_path / "run")
    assert saved == config and info["task"] == "toy_reach"
    with pytest.raises(CoworldError, match="train.steps: saved 2000, now 5"):
        prepare_run_dir(tmp_path / "run", make_config("tiny", ["train.steps=5"]), {"algo": "dreamerv2"})
    with pytest.raises(CoworldError, match="task='toy_reach', not 'walker_walk'"):
        prepare_run_dir(tmp_path / "run", config, {"task": "walker_walk"})
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["steps"] == 2000


def test_logger_writes_jsonl_and_tensorboard(tmp_path):
    with Logger(tmp_path, outputs=("jsonl", "tensorboard")) as logger:
        logger.log({"wm/loss": 1.5, "eval/return": float("nan")}, step=10)
        logger.log({"wm/loss": 1.0}, step=20)
    records = read_metrics(tmp_path)
    assert [r["step"] for r in records] == [10, 20]
    assert records[0]["wm/loss"] == 1.5 and records[0]["eval/return"] is None
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"step": 30, "wm/lo')  # a kill in the middle of a write
    assert [r["step"] for r in read_metrics(tmp_path)] == [10, 20]


def test_rate_counts_per_second_over_each_window(monkeypatch):
    clock = iter([10.0, 12.0, 13.0])
    monkeypatch.setattr(logger_module.time, "perf_counter", lambda: next(clock))
    rate = Rate(100)  # starts at count 100, t = 10
    assert rate(110) == pytest.approx(5.0)  # 10 more in 2 s
    assert rate(113) == pytest.approx(3.0)  # the window restarted at 110, t = 12


def test_logger_labels_steps_with_what_they_count_and_keeps_the_console_short(tmp_path, capsys):
    with Logger(tmp_path, outputs=("console", "jsonl")) as logger:
        logger.log({"target/wm/loss": 2.0, "target/wm/kl": 0.5, "eval/return": 12.5}, step=2000, unit="target_update")
    record = read_metrics(tmp_path)[0]
    assert record["unit"] == "target_update" and record["target/wm/kl"] == 0.5  # the file keeps everything
    line = capsys.readouterr().err.strip()
    assert line.startswith("[target_update 2,000] ") and "eval/return 12.5" in line and "wm/loss 2" in line
    assert "wm/kl" not in line


def test_progress_off_a_terminal_writes_plain_lines_saying_what_they_count(capsys):
    from coworld.progress import progress_bar

    with progress_bar(total=40, desc="collect", unit="env steps") as bar:
        for _ in range(40):
            bar.update(1)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.strip().splitlines()
    assert lines and all(line.startswith("collect: ") and " env steps" in line for line in lines)
    assert lines[-1].startswith("collect: 40/40 env steps (100%)")
