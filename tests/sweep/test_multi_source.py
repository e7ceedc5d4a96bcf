"""Sweep grids with CoWorld choosing among several sources (``SOURCE+SOURCE:TARGET``) and with pairs of different
action sizes: parsing, the one-line refusals, the runs' command lines, and a whole sweep killed and resumed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from coworld.errors import CoworldError
from coworld.sweep.grid import SweepSpec, parse_pairs, read_grid_file
from coworld.sweep.runner import Execution, run_steps

CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]


def test_pairs_with_several_sources_parse_and_keep_source_target_working(tmp_path: Path) -> None:
    pairs = parse_pairs("walker_walk+cheetah_run:walker_uphill, walker_walk:walker_downhill")
    assert pairs == (("walker_walk+cheetah_run", "walker_uphill"), ("walker_walk", "walker_downhill"))
    grid = tmp_path / "grid.toml"
    grid.write_text('pairs = ["toy_reach+toy_reach_centre:toy_reach_shifted"]\nalgos = ["coworld", "dreamerv2"]\n')
    assert read_grid_file(grid)["pairs"] == (("toy_reach+toy_reach_centre", "toy_reach_shifted"),)
    spec = SweepSpec(pairs=read_grid_file(grid)["pairs"], algos=("coworld", "dreamerv2"), seeds=(0,), preset="tiny")
    runs = spec.check().runs()
    assert [r.name for r in runs] == [
        "coworld-toy_reach+toy_reach_centre-toy_reach_shifted-s0",
        "dreamerv2-toy_reach_shifted-s0",
    ]
    train, _ = run_steps(spec, runs[0], tmp_path / "r", tmp_path / "d.h5", Execution(device="cpu"))
    assert train[train.index("--source") + 1] == "toy_reach+toy_reach_centre"


@pytest.mark.parametrize(
    ("pairs", "algos", "message"),
    [
        ("toy_reach+nope:toy_reach_shifted", ("coworld",), "unknown task 'nope'"),
        ("toy_reach+toy_reach:toy_reach_shifted", ("coworld",), "names toy_reach twice"),
        ("toy_reach+toy_reach_centre:toy_reach_shifted", ("coworld", "dreamerv2-finetune"), "takes one source"),
        ("toy_reach:toy_reach_shifted_act3", ("dreamerv2-finetune",), "carries the source agent's networks"),
    ],
)
def test_grids_the_method_cannot_serve_are_one_line(pairs: str, algos: tuple[str, ...], message: str) -> None:
    with pytest.raises(CoworldError, match=message) as err:
        SweepSpec(pairs=parse_pairs(pairs), algos=algos, seeds=(0,), preset="tiny").check()
    assert "\n" not in str(err.value)


def test_coworld_takes_a_pair_of_different_action_sizes() -> None:
    spec = SweepSpec(pairs=parse_pairs("toy_reach:toy_reach_shifted_act3"), algos=("coworld",), preset="tiny")
    assert [r.source for r in spec.check().runs()] == ["toy_reach"] * 3


GRID = """
pairs = ["toy_reach+toy_reach_shifted_act3:toy_reach_shifted"]
algos = ["coworld"]
seeds = 1
preset = "tiny"
eval_episodes = 1
set = ["train.eval_episodes=1", "train.prefill=100", "coworld.pretrain_steps=200", "coworld.iterations=1",
       "coworld.target_updates=4", "coworld.source_updates=4", "coworld.select_batches=2"]
[data]
policy = "random"
episodes = 3
"""


@pytest.mark.slow
def test_a_multi_source_sweep_killed_after_its_choice_resumes_without_choosing_again(tmp_path: Path) -> None:
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID)
    root = tmp_path / "sweep"
    args = [*CLI, "sweep", "--grid", str(grid), "--dir", str(root), "--device", "cpu", "--no-progress", "--jobs", "1"]
    run = root / "runs" / "coworld-toy_reach+toy_reach_shifted_act3-toy_reach_shifted-s0"
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 600
        while not (run / "source_choice.json").exists():
            assert proc.poll() is None and time.time() < deadline
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)  # the sweep and its train child, right after the choice
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    choice = (run / "source_choice.json").read_bytes()
    stamp = (run / "source_choice.json").stat().st_mtime_ns
    out = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads((run / "eval.json").read_text())["returns"]
    assert (run / "source_choice.json").read_bytes() == choice and (
        run / "source_choice.json"
    ).stat().st_mtime_ns == stamp
    chosen = json.loads(choice)["chosen"]
    assert (run / "source" / "checkpoint.pt").exists() and not (run / "sources" / chosen / "source").exists()
    report = subprocess.run([*CLI, "report", str(root)], capture_output=True, text=True, timeout=600)
    assert report.returncode == 0, report.stderr[-3000:]
    assert f"**{chosen}**" in (root / "report.md").read_text()
