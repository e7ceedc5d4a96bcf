"""What the target agents of a toy transfer table see and do: does the latent hold the dot, does the actor use it?

For each run folder given (CoWorld or offline DreamerV2 trained on a toy target, ``toy_reach_shifted`` or
``toy_reach_centre_shifted``, read from its ``run.json``; a CoWorld run is probed through its target agent), puts
the dot at points of the square, lets the agent filter six frames of it, and from those latents reports:

- **position readout**: how well a ridge regression from the latent features recovers the dot's (x, y), fitted on
  a 12 x 12 grid and scored (R^2) on 64 other random positions. High R^2: the world model holds where the dot is
  (below 0: the readout fails on new positions);
- **the actor**: its mode action's spread over the 64 test states (0 when the same action is taken everywhere),
  its mean action, the share of states where it pushes up-right within 30 degrees (the corner pair's best constant
  direction), and the share where it pushes towards the goal within 30 degrees (what reading the dot allows);
- **the actor's mean before tanh** (beyond about +-3 the squash passes almost no gradient);
- **the critic**: its mean value, and for a CoWorld run the source critic's on the same latents (Eq. 6 caps the
  target critic only where the target's is higher).

    python benchmarks/toy_transfer_probe.py RUN [RUN ...]      # e.g. sweeps/toy-cpu/runs/*-s0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from coworld.agents.factory import make_agent
from coworld.config import from_dict
from coworld.envs import make
from coworld.training.checkpoint import load_checkpoint


def latents(agent, env, positions: np.ndarray, mode: str = "eval") -> dict[str, torch.Tensor]:
    """The agent's latent after six frames of the dot standing at each position (no action).

    ``mode``: the agent's policy mode while it filters (it draws random numbers in 'random', none in 'eval')."""
    out = []
    for position in positions:
        env.unwrapped.position = np.asarray(position, np.float64)
        frame = env.unwrapped._draw()
        state = None
        for _ in range(6):
            _, state = agent.policy(frame[None], state, mode=mode)
            state = (state[0], torch.zeros_like(state[1]))
        out.append(state[0])
    return {key: torch.cat([latent[key] for latent in out]) for key in out[0]}


def ridge_r2(train_x: np.ndarray, train_y: np.ndarray, test_x: np.ndarray, test_y: np.ndarray) -> float:
    """Held-out R^2 (both coordinates pooled) of a ridge regression with a bias, features standardised."""
    mean, std = train_x.mean(0), train_x.std(0) + 1e-6
    a = np.c_[(train_x - mean) / std, np.ones(len(train_x))]
    b = np.c_[(test_x - mean) / std, np.ones(len(test_x))]
    weights = np.linalg.solve(a.T @ a + 1.0 * np.eye(a.shape[1]), a.T @ train_y)
    residual = ((b @ weights - test_y) ** 2).sum()
    return float(1.0 - residual / ((test_y - test_y.mean(0)) ** 2).sum())


def probe(run: Path, train_positions: np.ndarray, test_positions: np.ndarray) -> dict[str, object]:
    torch.manual_seed(0)  # the latents are posterior samples: the same draws for every run and every call
    state = load_checkpoint(run)
    config = from_dict(state["config"])
    agent = make_agent("dreamerv2", config=config, action_size=2, device="cpu")
    agent.load_state_dict(state["agent"])
    env = make(json.loads((run / "run.json").read_text())["target"], seed=0)
    env.reset(seed=0)
    wm = agent.world_model
    with torch.no_grad():
        train_feat = wm.features(latents(agent, env, train_positions)).numpy()
        test_latent = latents(agent, env, test_positions)
        feat = wm.features(test_latent)
        actor = agent.actor_critic.actor(feat).mode.numpy()
        before_tanh = agent.actor_critic.actor.mlp(feat).chunk(2, dim=-1)[0].numpy()
        value = agent.actor_critic.critic(feat).mean.numpy()
        source_value = None
        if "source" in state:
            source = make_agent("dreamerv2", config=config, action_size=2, device="cpu")
            source.load_state_dict(state["source"])
            source_value = source.actor_critic.critic(feat).mean.numpy()
    angle = np.degrees(np.arctan2(actor[:, 1], actor[:, 0]))
    to_goal = env.unwrapped.goal - test_positions
    cosine = (actor * to_goal).sum(1) / (np.linalg.norm(actor, axis=1) * np.linalg.norm(to_goal, axis=1) + 1e-9)
    return {
        "run": run.name,
        "r2": ridge_r2(train_feat, train_positions, feat.numpy(), test_positions),
        "spread": np.linalg.norm(actor.std(0)),
        "mean_action": actor.mean(0),
        "up_right": float(np.mean(np.abs(angle - 45.0) < 30.0)),
        "to_goal": float(np.mean(cosine > np.cos(np.radians(30.0)))),
        "before_tanh": np.abs(before_tanh).mean(),
        "value": float(value.mean()),
        "source_value": None if source_value is None else float(source_value.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders trained on a toy target")
    args = parser.parse_args()
    torch.set_num_threads(1)
    grid = np.linspace(-0.85, 0.85, 12)
    train_positions = np.array([(x, y) for x in grid for y in grid])
    test_positions = np.random.default_rng(0).uniform(-0.85, 0.85, (64, 2))
    print(
        "run | position R^2 | actor spread | mean action | up-right share | to-goal share | |before tanh| | value"
        " | source value"
    )
    for run in args.runs:
        r = probe(run, train_positions, test_positions)
        source = "-" if r["source_value"] is None else f"{r['source_value']:.2f}"
        print(
            f"{r['run']} | {r['r2']:.3f} | {r['spread']:.3f} | ({r['mean_action'][0]:+.2f}, {r['mean_action'][1]:+.2f})"
            f" | {r['up_right']:.2f} | {r['to_goal']:.2f} | {r['before_tanh']:.2f} | {r['value']:.2f} | {source}"
        )


if __name__ == "__main__":
    main()
