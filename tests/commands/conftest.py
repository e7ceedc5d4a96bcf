"""Fixtures of the command tests: a small random toy_reach_shifted dataset, run folders as `coworld train` makes
them, and `cli` / `one_line` (a command run in this process, and the check of its one-line refusal)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def toy_dataset(tmp_path_factory, toy_dataset_writer) -> Path:
    path = tmp_path_factory.mktemp("data") / "toy_reach_shifted-medium_replay.h5"
    return toy_dataset_writer(path, "toy_reach_shifted")


@pytest.fixture(scope="session")
def make_run():
    """``make_run(folder, algo, dataset, checkpoint_of=None, task=...)``: a run folder as `coworld train` makes it
    (tiny preset, CPU), with an untrained checkpoint."""
    from coworld.agents.factory import make_agent
    from coworld.algorithms import algorithm
    from coworld.config import make_config, to_dict
    from coworld.training.checkpoint import save_checkpoint
    from coworld.training.run import prepare_run_dir

    TARGET = "toy_reach_shifted"

    def make_run(
        folder: Path, algo: str, dataset: Path, *, checkpoint_of: str | None = None, task: str = TARGET
    ) -> Path:
        """A run folder of ``algo`` as `coworld train` describes it, holding an untrained checkpoint of
        ``checkpoint_of`` (default: ``algo``) trained on ``task``."""
        config = make_config("tiny", ["device=cpu"])
        source = "toy_reach" if algorithm(algo).needs_source else None
        info = {"algo": algo, "source": source, "target": TARGET, "dataset": str(dataset), "preset": "tiny"}
        prepare_run_dir(folder, config, info)
        made = checkpoint_of or algo
        agent = make_agent(made, config=config, action_size=2, device="cpu")
        kind = algorithm(made).checkpoint
        state = {"kind": kind, "task": task, "config": to_dict(config), "agent": agent.state_dict()}
        save_checkpoint(folder / "checkpoint.pt", state)
        return folder

    return make_run


@pytest.fixture(scope="session")
def cli() -> Callable[..., tuple[int, str]]:
    """``cli(*args) -> (exit code, output)``: ``coworld ARGS`` in this process."""
    from click.testing import CliRunner

    from coworld.cli import main

    def invoke(*args: str) -> tuple[int, str]:
        result = CliRunner().invoke(main, list(args))
        return result.exit_code, result.output

    return invoke


@pytest.fixture(scope="session")
def one_line() -> Callable[..., str]:
    """``one_line(code, output, *needles) -> the line``: asserts a refusal: exit code 2 and one ``error:`` line
    (besides warnings and notes), no traceback, holding every needle."""

    def check(code: int, output: str, *needles: str) -> str:
        assert code == 2, output
        lines = [line for line in output.splitlines() if line.strip() and not line.startswith(("warning: ", "note: "))]
        assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in output, output
        for needle in needles:
            assert needle in lines[0], lines[0]
        return lines[0]

    return check
