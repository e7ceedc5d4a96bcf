"""Build an agent by algorithm name (what ``coworld train`` and ``coworld eval`` share)."""

from __future__ import annotations

from typing import Any

import torch

from coworld.config import Config


def agent_class(algo: str) -> type:
    """The class of the agent whose ``policy`` is evaluated for ``algo`` (for CoWorld: the target agent, a
    DreamerV2), imported only when asked for."""
    if algo in ("coworld", "dreamerv2", "dreamerv2-finetune"):
        from coworld.agents.dreamerv2 import DreamerV2

        return DreamerV2
    if algo in ("curl", "curl-cql"):
        from coworld.agents.curl import Curl

        return Curl
    if algo == "dreamerv2-penalty":
        from coworld.agents.dreamerv2_penalty import PenaltyDreamerV2

        return PenaltyDreamerV2
    if algo == "lompo":
        from coworld.agents.lompo import Lompo

        return Lompo
    if algo == "dreamerv2-finetune-ewc":
        from coworld.agents.dreamerv2_ewc import EwcDreamerV2

        return EwcDreamerV2
    if algo == "drq-bc":
        from coworld.agents.drq_bc import DrqBc

        return DrqBc
    raise ValueError(f"unknown algorithm {algo!r}")


def make_agent(algo: str, *, config: Config, action_size: int, device: torch.device | str) -> Any:
    """The agent whose ``policy`` is evaluated for ``algo``, built for ``config``."""
    extra = {"cql": algo == "curl-cql"} if algo in ("curl", "curl-cql") else {}
    return agent_class(algo)(config=config, action_size=action_size, device=device, **extra)
