"""The docs' claims about the `paper` preset hold: docs/algorithms.md's Table 3 table matches the paper and preset."""

from __future__ import annotations

import json
import re
from pathlib import Path

from click.testing import CliRunner

from coworld.cli import main
from coworld.config import make_config, to_dict
from coworld.training.run import prepare_run_dir

README = Path(__file__).parents[1] / "docs" / "algorithms.md"  # the Table 3 table

# Table 3 of the paper, with the K rows by their names (the README explains the reading).
PAPER_TABLE_3 = {
    "Domain KL loss scale": 1.5,
    "Source reward balancing": 0.2,
    "Target critic value loss scale": 0.2,
    "Target domain update steps": 5e4,
    "Source domain update steps": 2e4,
    "Batch size": 50,
    "Sequence length": 50,
    "KL loss scale": 1,
    "Discrete latent dimensions": 32,
    "Discrete latent classes": 32,
    "RSSM number of units": 600,
    "World model learning rate": 2e-4,
    "Imagination horizon": 15,
    "Discount": 0.995,
    "lambda-target": 0.95,
    "Actor learning rate": 4e-5,
    "Critic learning rate": 1e-4,
}


def readme_table_3() -> dict[str, tuple[float, str]]:
    text = README.read_text()
    section = text[text.index("### The `paper` preset is Table 3") :]
    section = section[: section.index("\n\n", section.index("| Table 3 |"))]
    rows = {}
    for line in section.splitlines():
        match = re.match(r"\| ([^|]+?)(?: \(Alg\. 1's K\d\))? \|[^|]*\| ([^|]+) \| `([^`]+)` \|$", line)
        if match:
            rows[match.group(1)] = (float(match.group(2)), match.group(3))
    return rows


def test_the_readme_table_is_table_3_and_the_paper_preset_holds_it():
    rows = readme_table_3()
    assert set(rows) == set(PAPER_TABLE_3)
    paper = to_dict(make_config("paper"))
    for name, (value, key) in rows.items():
        assert value == PAPER_TABLE_3[name], name
        section, field = key.split(".")
        assert paper[section][field] == value, key


def test_coworld_config_prints_what_a_run_saves(tmp_path):
    result = CliRunner().invoke(main, ["config", "--preset", "tiny", "--set", "coworld.k=0.5"])
    assert result.exit_code == 0, result.output
    config = make_config("tiny", ["coworld.k=0.5"])
    prepare_run_dir(tmp_path / "run", config, {"algo": "coworld"})
    assert json.loads(result.output) == json.loads((tmp_path / "run" / "config.json").read_text())
    assert json.loads(result.output)["coworld"]["k"] == 0.5
