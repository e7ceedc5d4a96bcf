"""The house has one way through: the import contracts in pyproject.toml hold (the layers, the layers inside
training/, and no import circle)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import grimp

ROOT = Path(__file__).parents[1]
ABOVE_AGENTS = ("coworld.training", "coworld.viz", "coworld.sweep", "coworld.report", "coworld.commands")


def test_the_import_contracts_hold() -> None:
    lint = Path(sys.executable).parent / "lint-imports"
    done = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "Contracts: 3 kept, 0 broken." in done.stdout


def test_no_agent_imports_the_loops_or_anything_above_them() -> None:
    """At module level or inside a function: what an agent needs from above is handed to it."""
    graph = grimp.build_graph("coworld", cache_dir=None)
    agents = graph.find_children("coworld.agents") | {"coworld.agents"}
    upward = {
        (agent, imported)
        for agent in agents
        for imported in graph.find_modules_directly_imported_by(agent)
        if imported.startswith(ABOVE_AGENTS)
    }
    assert not upward, sorted(upward)
