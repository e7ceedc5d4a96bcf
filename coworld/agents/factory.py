"""Build an agent by algorithm name (what ``coworld train`` and ``coworld eval`` share)."""

from __future__ import annotations

from typing import Any

import torch

from coworld.config import Config


def make_agent(algo: str, *, config: Config, action_size: int, device: torch.device | str) -> Any:
    """The agent whose ``policy`` is evaluated for ``algo`` (for CoWorld: the target agent, a DreamerV2)."""
    if algo in ("coworld", "dreamerv2", "dreamerv2-finetune"):
        from coworld.agents.dreamerv2 import DreamerV2

        return DreamerV2(config=config, action_size=action_size, device=device)
    if algo in ("curl", "curl-cql"):
        from coworld.agents.curl import Curl

        return Curl(config=config, action_size=action_size, device=device, cql=algo == "curl-cql")
    if algo == "dreamerv2-penalty":
        from coworld.agents.dreamerv2_penalty import PenaltyDreamerV2

        return PenaltyDreamerV2(config=config, action_size=action_size, device=device)
    if algo == "lompo":
        from coworld.agents.lompo import Lompo

        return Lompo(config=config, action_size=action_size, device=device)
    if algo == "dreamerv2-finetune-ewc":
        from coworld.agents.dreamerv2_ewc import EwcDreamerV2

        return EwcDreamerV2(config=config, action_size=action_size, device=device)
    if algo == "drq-bc":
        from coworld.agents.drq_bc import DrqBc

        return DrqBc(config=config, action_size=action_size, device=device)
    raise ValueError(f"unknown algorithm {algo!r}")
