"""A small random toy_reach_shifted dataset for the train / eval command tests."""

from __future__ import annotations

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
    from coworld.config import make_config, to_dict
    from coworld.training.checkpoint import save_checkpoint
    from coworld.training.run import prepare_run_dir
    from coworld.training.train import CHECKPOINT_KINDS, NEEDS_SOURCE

    TARGET = "toy_reach_shifted"

    def make_run(
        folder: Path, algo: str, dataset: Path, *, checkpoint_of: str | None = None, task: str = TARGET
    ) -> Path:
        """A run folder of ``algo`` as `coworld train` describes it, holding an untrained checkpoint of
        ``checkpoint_of`` (default: ``algo``) trained on ``task``."""
        config = make_config("tiny", ["device=cpu"])
        source = "toy_reach" if algo in NEEDS_SOURCE else None
        info = {"algo": algo, "source": source, "target": TARGET, "dataset": str(dataset), "preset": "tiny"}
        prepare_run_dir(folder, config, info)
        made = checkpoint_of or algo
        agent = make_agent(made, config=config, action_size=2, device="cpu")
        state = {"kind": CHECKPOINT_KINDS[made], "task": task, "config": to_dict(config), "agent": agent.state_dict()}
        save_checkpoint(folder / "checkpoint.pt", state)
        return folder

    return make_run
