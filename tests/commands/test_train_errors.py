"""Bad input to `coworld train` / `coworld eval`: one line, exit code 2, no traceback, nothing written."""

from __future__ import annotations

import subprocess
import sys

import pytest
from click.testing import CliRunner

from coworld.cli import main


def run(args):
    result = CliRunner().invoke(main, args)
    return result.exit_code, result.output


def assert_one_line_error(code, output, *needles):
    assert code == 2, output
    lines = [line for line in output.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), output
    assert "Traceback" not in output
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_mismatched_action_spaces_for_fine_tuning(tmp_path, toy_dataset):
    """CoWorld takes a source of another action size (tests/agents/test_coworld_action_sizes.py); fine-tuning, which
    carries the source agent's networks over, does not."""
    code, out = run(
        [
            "train",
            "--algo",
            "dreamerv2-finetune",
            "--source",
            "walker_walk",
            "--target",
            "toy_reach_shifted",
            "--dataset",
            str(toy_dataset),
            "--logdir",
            str(tmp_path / "run"),
        ]
    )
    assert_one_line_error(code, out, "6 action dimensions", "has 2")
    assert not (tmp_path / "run").exists()


def test_dataset_of_another_task(tmp_path, toy_dataset):
    code, out = run(
        [
            "train",
            "--source",
            "toy_reach_shifted",
            "--target",
            "toy_reach",
            "--dataset",
            str(toy_dataset),
            "--logdir",
            str(tmp_path / "run"),
        ]
    )
    assert_one_line_error(code, out, "recorded in toy_reach_shifted", "not the target toy_reach")
    assert not (tmp_path / "run").exists()


def test_missing_dataset_points_at_collect(tmp_path):
    code, out = run(
        ["train", "--source", "toy_reach", "--target", "toy_reach_shifted", "--dataset", str(tmp_path / "nope.h5")]
    )
    assert_one_line_error(code, out, "no dataset at", "coworld collect --task toy_reach_shifted")


def test_unknown_task_lists_valid_ones(toy_dataset):
    code, out = run(["train", "--source", "toy_reach", "--target", "walker_sideways", "--dataset", str(toy_dataset)])
    assert_one_line_error(code, out, "walker_sideways", "walker_uphill")


def test_unknown_set_key(tmp_path, toy_dataset):
    code, out = run(
        [
            "train",
            "--source",
            "toy_reach",
            "--target",
            "toy_reach_shifted",
            "--dataset",
            str(toy_dataset),
            "--set",
            "coworld.allign=false",
            "--logdir",
            str(tmp_path / "run"),
        ]
    )
    assert_one_line_error(code, out, "unknown config key 'coworld.allign'")
    assert not (tmp_path / "run").exists()


def test_eval_missing_and_corrupt_checkpoint(tmp_path):
    code, out = run(["eval", "--ckpt", str(tmp_path / "nothing")])
    assert_one_line_error(code, out, "no run folder or checkpoint at")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoint.pt").write_bytes(b"\x80\x02garbage")
    before = (run_dir / "checkpoint.pt").read_bytes()
    code, out = run(["eval", "--ckpt", str(run_dir)])
    assert_one_line_error(code, out)
    assert (run_dir / "checkpoint.pt").read_bytes() == before


@pytest.mark.parametrize(
    "args", [["train", "--target", "nope", "--source", "toy_reach"], ["eval", "--ckpt", "/no/such"]]
)
def test_real_subprocess_exit_code(args):
    proc = subprocess.run(
        [sys.executable, "-c", "from coworld.cli import run; run()", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1
    assert "Traceback" not in proc.stderr
