"""What a critic estimates, measured on recorded rewards: the discounted return from each step of an episode.

The value check (``coworld eval``, Figure 4(b)) compares a critic's estimate with it on evaluation episodes, and
``coworld dataset info`` reports it over a dataset's steps: the value of the behaviour that collected the data.
"""

from __future__ import annotations

import numpy as np


def discounted_returns(rewards: np.ndarray, discount: float) -> np.ndarray:
    """G_t = sum_k discount^k r_{t+k} for every step of one episode; rewards (T,) -> (T,)."""
    out = np.zeros(len(rewards), dtype=np.float64)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + discount * running
        out[t] = running
    return out


def arrival_rewards(rewards: np.ndarray) -> np.ndarray:
    """The reward of arriving at each observation of one episode: ``rewards (T,)``, ``rewards[t]`` earned by the
    action taken at ``o_t``, -> ``(T+1,)`` ``[0, rewards[0], ..., rewards[T-1]]`` for ``o_0 .. o_T`` (the replay
    convention: step ``t`` holds the reward of the action that led to it, zero at the first step)."""
    return np.concatenate([[0.0], np.asarray(rewards, np.float64)])


def true_values(rewards: np.ndarray, discount: float) -> np.ndarray:
    """What the critic's ``v(z_t)`` estimates, measured: the discounted return from step ``t`` of an episode.

    ``rewards (T,)``: ``rewards[t]`` is earned by the action taken at observation ``o_t``. A DreamerV2 critic
    at the state ``z_t`` that filtered ``o_t`` regresses lambda-returns ``R_t = r_t + gamma * ...`` whose first
    reward is the one received on *arriving* at ``o_t``. So the true value of step ``t`` is ``sum_k gamma^k r'_{t+k}``
    over the arrival rewards ``r'`` (:func:`arrival_rewards`); returns ``(T,)`` for the steps ``0 .. T-1`` where the
    policy acted. The sum stops at the episode's end, a time limit included, where the critic would go on.
    """
    return discounted_returns(arrival_rewards(rewards), discount)[:-1]
