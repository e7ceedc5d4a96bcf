"""The later CoWorld paper's tables end to end at the smallest size: ``coworld sweep --table`` on the ``tiny``
preset, one pair, one seed, then ``coworld report``, whose report shows our number beside the paper's.

The target dataset is the table's own quality, made by the dreamerv2 collector with a budget of one episode that
its random prefill fills (so no DreamerV2 update is spent on it); every run trains a few updates and is evaluated
once, on one episode, by the sweep. DMC renders at 50-330 frames/s here, so each episode costs seconds: the whole
tables are ``slow``, and one algorithm of one table is the fast representative.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from coworld.report import paper

CLI = [sys.executable, "-c", "from coworld.cli import run; run()"]
TINY = [
    "train.eval_episodes=1",
    "train.eval_every=100000",
    "train.prefill=50",
    "coworld.pretrain_steps=50",
    "coworld.iterations=1",
    "coworld.eval_every=100",
    "coworld.target_updates=2",
    "coworld.source_updates=2",
    "offline.updates=2",
    "offline.eval_episodes=1",
    "offline.eval_every=100",
    "penalty.model_updates=1",
    "lompo.model_updates=1",
    "curl.updates=2",
    "curl.eval_every=2",
    "curl.checkpoint_every=2",
    "curl.eval_episodes=1",
    "drqbc.updates=2",
    "drqbc.std_updates=1",
    "drqbc.eval_every=2",
    "drqbc.checkpoint_every=2",
    "drqbc.eval_episodes=1",
]
"""Every run of the table, a few updates each (the table's own ``--set`` come first; these win)."""
DATA = {"max_steps": 500, "set": ["train.prefill=1000", "train.pretrain_updates=0", "train.eval_every=100000"]}
"""One walker episode, all of it the collector's random prefill: no update, no evaluation."""


def grid_file(tmp_path: Path, table: str, pair: tuple[str, str], algos: list[str] | None) -> Path:
    lines = [
        f'table = "{table}"',
        f'pairs = ["{pair[0]}:{pair[1]}"]',
        "seeds = 1",
        'preset = "tiny"',
        "eval_episodes = 1",
        f"set = {json.dumps(TINY)}",
    ]
    if algos is not None:
        lines.append(f"algos = {json.dumps(algos)}")
    lines += ["[data]", f"max_steps = {DATA['max_steps']}", f"set = {json.dumps(DATA['set'])}"]
    path = tmp_path / "grid.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def sweep_then_report(tmp_path: Path, table: str, pair: tuple[str, str], algos: list[str] | None) -> str:
    root = tmp_path / "sweep"
    args = [*CLI, "sweep", "--grid", str(grid_file(tmp_path, table, pair, algos)), "--dir", str(root)]
    done = subprocess.run([*args, "--device", "cpu", "--no-progress"], capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    report = subprocess.run([*CLI, "report", str(root)], capture_output=True, text=True, timeout=600)
    assert report.returncode == 0, report.stderr[-3000:]
    return (root / "report.md").read_text()


def assert_side_by_side(text: str, table: paper.PaperTable, pair: tuple[str, str], algos: list[str]) -> None:
    """A row per algorithm with a column: the pair, the algorithm, the quality, ours (one seed), the paper's."""
    section = text.split("## Beside the published numbers")[1].split("\n## ")[0]
    rows = {line.split(" | ")[1]: line for line in section.splitlines() if line.startswith(f"| {pair[0]} → ")
            or line.startswith(f"| {pair[1]} |")}  # fmt: skip
    expected = [algo for algo in algos if table.number(algo, pair[0], pair[1]) is not None]
    assert expected and sorted(rows) == sorted(expected), section
    for algo in expected:
        number = table.number(algo, pair[0], pair[1])
        cells = [cell.strip() for cell in rows[algo].strip("|").split("|")]
        assert cells[1:3] == [algo, table.quality]
        ours, theirs = cells[3], cells[4]
        assert ours.endswith(" (n=1)") and float(ours.removesuffix(" (n=1)")) >= 0.0  # walker returns are >= 0
        assert theirs == f"{number.mean:.0f} ± {number.std:.0f}" and cells[5] == number.where


@pytest.mark.slow  # the medium-replay tables' tests run in CI
def test_dmc_medium_expert_table_fast_representative(tmp_path):
    """One algorithm of Table 9 on one pair: its medium-expert dataset, its run, the report's row."""
    table, pair, algos = paper.DMC_MEDIUM_EXPERT, ("walker_walk", "walker_downhill"), ["dreamerv2-penalty"]
    text = sweep_then_report(tmp_path, table.name, pair, algos)
    assert_side_by_side(text, table, pair, algos)
    data = tmp_path / "sweep" / "datasets" / "walker_downhill-medium_expert.h5"
    from coworld.data import open_dataset

    with open_dataset(data) as dataset:
        assert dataset.quality == "medium-expert" and dataset.complete and dataset.num_steps == 500


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, pair",
    [("dmc-mr", ("cheetah_run", "cheetah_uphill")), ("dmc-me", ("walker_walk", "walker_downhill"))],
)
def test_a_later_table_runs_every_algorithm_through_sweep_and_report(tmp_path, name, pair):
    from coworld.sweep.grid import named_table

    table, algos = paper.TABLES[name], list(named_table(name).algos)
    text = sweep_then_report(tmp_path, name, pair, None)
    assert_side_by_side(text, table, pair, algos)
    header = next(line for line in text.splitlines() if line.startswith("| pair |"))
    assert sorted(header.strip("| ").split(" | ")[1:]) == sorted(algos)  # every algorithm of the table finished
    assert "## Not finished" not in text


@pytest.mark.slow
def test_the_robodesk_table_trains_a_meta_world_source_with_a_robodesk_target(tmp_path):
    """Figure 4's first pair across environments (4-d Meta-World source, 5-d RoboDesk target): CoWorld and the
    penalised DreamerV2, the two columns with printed numbers, beside the paper's."""
    table, pair = paper.META_WORLD_TO_ROBODESK, ("mw_button_press", "robodesk_push_button")
    algos = ["dreamerv2-penalty", "coworld"]
    text = sweep_then_report(tmp_path, table.name, pair, algos)
    assert_side_by_side(text, table, pair, algos)
    assert "## Not finished" not in text
