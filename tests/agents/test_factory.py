"""The agent factory: one class per algorithm, named by its record and imported when asked for."""

from __future__ import annotations

import pytest

from coworld.agents.curl import Curl
from coworld.agents.dreamerv2 import DreamerV2
from coworld.agents.dreamerv2_ewc import EwcDreamerV2
from coworld.agents.dreamerv2_penalty import PenaltyDreamerV2
from coworld.agents.drq_bc import DrqBc
from coworld.agents.factory import agent_class
from coworld.agents.lompo import Lompo
from coworld.algorithms import ALGOS


def test_every_algorithm_has_its_agent_class() -> None:
    expected = {"coworld": DreamerV2, "dreamerv2": DreamerV2, "dreamerv2-finetune": DreamerV2, "curl": Curl,
                "curl-cql": Curl, "drq-bc": DrqBc, "dreamerv2-penalty": PenaltyDreamerV2, "lompo": Lompo,
                "dreamerv2-finetune-ewc": EwcDreamerV2}  # fmt: skip
    assert set(expected) <= set(ALGOS)  # and a new record names its own class (tests/test_registry.py)
    for algo, cls in expected.items():
        assert agent_class(algo) is cls, algo
    with pytest.raises(ValueError, match="unknown algorithm 'ppo'"):
        agent_class("ppo")


def test_only_the_agents_that_learn_an_ensemble_first_name_a_section() -> None:
    """``coworld.training.train.check_schedule`` reads ``<section>.model_updates`` of the classes that have one."""
    sections = {algo: getattr(agent_class(algo), "section", None) for algo in ALGOS}
    assert {algo: section for algo, section in sections.items() if section} == {
        "dreamerv2-penalty": "penalty",
        "lompo": "lompo",
    }
