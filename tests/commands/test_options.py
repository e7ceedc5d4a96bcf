"""Options shared by the torch commands."""

from __future__ import annotations

import pytest
import torch
from click.testing import CliRunner

from coworld.cli import main


@pytest.fixture
def restore_threads():
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize(
    "args",
    [
        ["train", "--target", "no_such_task"],
        ["collect", "--task", "no_such_task"],
        ["eval", "--ckpt", "no/such/run"],
    ],
)
def test_threads_sets_torch_threads(args, restore_threads):
    torch.set_num_threads(2)
    # The option acts while the options are parsed, before the command refuses the bad input.
    result = CliRunner().invoke(main, [*args, "--threads", "1"])
    assert result.exit_code == 2 and result.output.startswith("error: "), result.output
    assert torch.get_num_threads() == 1


def test_threads_must_be_positive(restore_threads):
    result = CliRunner().invoke(main, ["eval", "--threads", "0", "--ckpt", "x"])
    assert result.exit_code == 2 and "--threads" in result.output


def test_without_threads_the_cli_uses_one_thread_unless_omp_num_threads_says_otherwise(restore_threads, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    torch.set_num_threads(2)
    CliRunner().invoke(main, ["eval", "--ckpt", "no/such/run"])
    assert torch.get_num_threads() == 1  # the measured default (benchmarks/RESULTS.md, "Threads")
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    torch.set_num_threads(2)
    CliRunner().invoke(main, ["eval", "--ckpt", "no/such/run"])
    assert torch.get_num_threads() == 2  # the user's setting stands


def test_python_dash_m_runs_the_cli() -> None:
    """`python -m coworld.cli` is the CLI (benchmarks/learning_side_by_side.py runs a checkout that way)."""
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "coworld.cli", "tasks"], capture_output=True, text=True, check=True, timeout=120
    )
    assert "walker_walk" in result.stdout
