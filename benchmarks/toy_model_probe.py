"""What a DreamerV2 run's world model believes about toy_reach: its reward map, its best move, its reconstructions.

Puts the dot at each point of an 8 x 8 grid over the square, lets the run's agent filter six frames of it standing
still (so the latent is a mid-episode one), and from each of those 64 latents prints:

- the reward head's prediction beside the true reward (the goal disc is worth 1.0);
- which of 9 constant actions (8 directions at full speed, and standing still) the model's imagination scores best
  over ``--horizon`` steps, against the best one in the true dynamics; near the goal the true best is to stand still;
- the decoder's squared reconstruction error of the frame (how well the model draws that state);
- the actor's mode action, and its mean before the ``tanh`` squash (beyond about +-3 the squash passes almost no
  gradient).

    python benchmarks/toy_model_probe.py RUN_FOLDER        # e.g. the .run folder `coworld collect` leaves
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from toy_transfer_probe import latents  # this folder is on the path of a script run from it

from coworld.agents.factory import make_agent
from coworld.config import from_dict
from coworld.envs import make
from coworld.envs.toy import GOAL, LIMIT, SPEED, reach_reward
from coworld.models.world_model import preprocess_image
from coworld.training.checkpoint import load_checkpoint

GRID = np.linspace(-0.8, 0.8, 8)
DIRECTIONS = np.concatenate(
    [np.stack([np.cos(a), np.sin(a)], 1) for a in [np.linspace(0, 2 * np.pi, 8, endpoint=False)]] + [np.zeros((1, 2))]
)
"""Rows 0-7: full speed at 0, 45, ..., 315 degrees (0 = +x, 90 = +y); row 8: stand still."""
NAMES = ("right", "up-right", "up", "up-left", "left", "down-left", "down", "down-right", "still")


def true_return(position: np.ndarray, direction: np.ndarray, horizon: int) -> float:
    total = 0.0
    for _ in range(horizon):
        position = np.clip(position + direction * SPEED, -LIMIT, LIMIT)
        total += reach_reward(position)
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", help="run folder (or checkpoint.pt) of a dreamerv2 run on toy_reach")
    parser.add_argument("--horizon", type=int, default=10, help="imagined steps per constant action")
    args = parser.parse_args()
    torch.set_num_threads(1)
    state = load_checkpoint(args.run)
    agent = make_agent("dreamerv2", config=from_dict(state["config"]), action_size=2, device="cpu")
    agent.load_state_dict(state["agent"])
    wm = agent.world_model

    env = make("toy_reach", seed=0)
    env.reset(seed=0)
    positions = np.array([(x, y) for x in GRID for y in GRID])
    start = latents(agent, env, positions, mode="random")
    frames = []
    for position in positions:
        env.unwrapped.position = position
        frames.append(env.unwrapped._draw())

    with torch.no_grad():
        feat = wm.features(start)
        reward = wm.reward_head(feat).mean.numpy()
        error = ((wm.decoder(feat) - preprocess_image(torch.as_tensor(np.stack(frames)))) ** 2).sum((1, 2, 3)).numpy()
        actor = agent.actor_critic.actor(feat).mode.numpy()
        squash_input = agent.actor_critic.actor.mlp(feat).chunk(2, dim=-1)[0].numpy()
        imagined = []
        for direction in DIRECTIONS:
            latent, total = start, 0.0
            action = torch.tensor(direction, dtype=torch.float32).expand(len(positions), 2)
            for _ in range(args.horizon):
                latent = wm.rssm.img_step(latent, action)
                total = total + wm.reward_head(wm.features(latent)).mean
            imagined.append(total.numpy())
    imagined = np.stack(imagined, 1)
    truth = np.array([[true_return(p, d, args.horizon) for d in DIRECTIONS] for p in positions])
    true_reward = np.array([reach_reward(p) for p in positions])

    def grid(values: np.ndarray, fmt: str) -> str:
        rows = []
        for j in range(len(GRID) - 1, -1, -1):  # top row first: y = +0.8
            rows.append(" ".join(fmt.format(*(v[i * len(GRID) + j] for v in values)) for i in range(len(GRID))))
        return "\n".join(rows)

    print(f"run {args.run}: {state['steps']:,} env steps, {state['updates']:,} updates")
    print("\nreward head / true reward (rows: y = +0.8 at the top; columns: x = -0.8 on the left)")
    print(grid([reward, true_reward], "{:5.2f}/{:4.2f}"))
    print("\nreconstruction error (sum of squares over pixels, images in [-0.5, 0.5])")
    print(grid([error], "{:6.1f}"))
    near = np.linalg.norm(positions - np.asarray(GOAL), axis=1) < 0.25
    best_model, best_true = imagined.argmax(1), truth.argmax(1)
    print(f"\nbest of 9 constant actions over {args.horizon} steps, model against truth:")
    print(f"  agree on {np.mean(best_model == best_true):.2f} of the 64 states")
    print(
        f"  true return of the model's choice {truth[np.arange(len(truth)), best_model].mean():.2f}, "
        f"of the true best {truth.max(1).mean():.2f}, of up-right {truth[:, 1].mean():.2f}"
    )
    print(f"  the {near.sum()} states within 0.25 of the goal centre:")
    for i in np.flatnonzero(near):
        print(
            f"    dot at ({positions[i][0]:+.2f}, {positions[i][1]:+.2f}): reward {reward[i]:.2f} (true "
            f"{true_reward[i]:.2f}), model's best {NAMES[best_model[i]]}, true best {NAMES[best_true[i]]}, "
            f"actor ({actor[i][0]:+.2f}, {actor[i][1]:+.2f}), reconstruction error {error[i]:.1f}"
        )
    print(f"  median reconstruction error elsewhere {np.median(error[~near]):.1f}")
    print(f"actor's mode action: std over the 64 states {actor.std(0).round(2).tolist()}")
    low, mid, high = np.percentile(squash_input, [0, 50, 100], axis=0).round(2)
    print(f"actor's mean before tanh, per dimension: min {low.tolist()}, median {mid.tolist()}, max {high.tolist()}")


if __name__ == "__main__":
    main()
