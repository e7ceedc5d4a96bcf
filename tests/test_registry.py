"""The algorithm registry (:mod:`coworld.algorithms`): every record trains, evaluates and is reported at the tiny
preset, and ``coworld viz`` looks inside a run exactly where its record says there is a world model; and the lists
that used to name algorithms one by one are the records' traits."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from coworld import algorithms
from coworld.algorithms import ALGOS, REGISTRY, algorithm
from coworld.cli import main

FAST = ["--set", "train.prefill=100", "--set", "train.eval_episodes=1", "--device", "cpu", "--no-progress"]
SHORT = {
    "coworld": ["coworld.pretrain_steps=150", "coworld.iterations=1", "coworld.target_updates=12",
                "coworld.source_updates=3"],
    "curl": ["curl.updates=6", "curl.eval_every=6", "curl.checkpoint_every=6", "curl.batch_size=8"],
    "offline": ["offline.updates=12", "offline.eval_every=12", "offline.checkpoint_every=12"],
    "drqbc": ["drqbc.updates=6", "drqbc.eval_every=6", "drqbc.checkpoint_every=6", "drqbc.batch_size=8"],
}  # fmt: skip
"""Each schedule section cut to a few updates (12 target updates: past the ensembles' 10 model updates at the tiny
preset): the test asks that every record's path runs, not that it learns."""


def cli(*args: str) -> str:
    result = CliRunner().invoke(main, list(args))
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """One tiny run of each algorithm on one random dataset, each evaluated on one episode."""
    root = tmp_path_factory.mktemp("registry")
    data = root / "toy_reach_shifted-random.h5"
    cli("collect", "--task", "toy_reach_shifted", "--policy", "random", "--episodes", "3", "--out", str(data),
        "--quiet")  # fmt: skip
    made = {}
    for record in REGISTRY:
        run = root / "runs" / record.name
        source = ["--source", "toy_reach"] if record.needs_source else []
        schedule = [*SHORT["coworld"], *SHORT.get(record.schedule, [])]
        sets = [arg for key in schedule for arg in ("--set", key)]
        cli("train", "--algo", record.name, *source, "--target", "toy_reach_shifted", "--dataset", str(data),
            "--preset", "tiny", "--logdir", str(run), *FAST, *sets)  # fmt: skip
        cli("eval", "--ckpt", str(run), "--episodes", "1", "--device", "cpu")
        made[record.name] = run
    return made


@pytest.mark.long
def test_every_record_trains_evaluates_and_is_reported(runs, tmp_path) -> None:
    for name, run in runs.items():
        record = algorithm(name)
        state = torch.load(run / "checkpoint.pt", weights_only=True, map_location="cpu")
        assert state["kind"] == record.checkpoint, name
        assert (run / "source_replay.h5").exists() == record.needs_source, name  # learned online in a source or not
        assert ("source" in state) == record.collaborative, name  # CoWorld's checkpoint holds both agents
        assert len(json.loads((run / "eval.json").read_text())["returns"]) == 1, name
    out = tmp_path / "report"
    cli("report", str(next(iter(runs.values())).parent), "--out", str(out))
    header = next(line for line in (out / "report.md").read_text().splitlines() if line.startswith("| pair |"))
    columns = [cell.strip() for cell in header.strip("|").split("|")][1:]
    assert columns == algorithms.by_column(ALGOS)  # each algorithm once, in its record's column


@pytest.mark.long
def test_viz_looks_inside_a_run_exactly_where_its_record_has_a_world_model(runs, tmp_path) -> None:
    for name, run in runs.items():
        out = tmp_path / f"{name}.png"
        args = ["viz", "predictions", "--ckpt", str(run), "--out", str(out), "--episodes", "1", "--length", "6",
                "--device", "cpu"]  # fmt: skip
        result = CliRunner().invoke(main, args)
        if algorithm(name).world_model:
            assert result.exit_code == 0 and out.stat().st_size > 0, (name, result.output)
        else:
            assert result.exit_code == 2 and "has no world model to look inside" in result.output, name
            assert not out.exists()


def test_the_records_traits_are_the_lists_that_named_algorithms() -> None:
    """What the tables that once listed algorithms by name held, now read from the records."""
    assert set(algorithms.names(world_model=False)) == {"curl", "curl-cql", "drq-bc"}
    assert set(algorithms.names(needs_source=True)) == {"coworld", "dreamerv2-finetune", "dreamerv2-finetune-ewc"}
    assert algorithms.names(collaborative=True) == ("coworld",)
    assert len({r.checkpoint for r in REGISTRY}) == len(REGISTRY)  # a checkpoint says which algorithm made it
    assert len({r.column for r in REGISTRY}) == len(REGISTRY)  # one place each in the report
    assert algorithms.by_column(ALGOS)[-1] == "coworld" and algorithms.by_column(["x", "curl"]) == ["curl", "x"]
    with pytest.raises(ValueError, match="unknown algorithm 'ppo'"):
        algorithm("ppo")


def test_every_record_names_what_exists(tmp_path) -> None:
    """Each record's agent, sampler, config section and keys are real, so a typo fails here, not in a run."""
    from coworld.agents.factory import agent_class, import_named
    from coworld.config import make_config

    config = make_config("tiny")
    for record in REGISTRY:
        assert isinstance(agent_class(record.name), type)
        if record.sampler is not None:
            assert callable(import_named(record.sampler))
        for key in (record.discount, *(k for keys in record.knobs.values() for k in keys)):
            section, field = key.split(".")
            assert hasattr(getattr(config, section), field), (record.name, key)
        if record.section is not None:
            assert hasattr(config, record.section), record.name
        if record.schedule != "coworld":
            own = getattr(config, record.schedule)
            assert all(hasattr(own, k) for k in ("updates", "log_every", "eval_every", "checkpoint_every")), record.name
        assert str(record.length(config))
