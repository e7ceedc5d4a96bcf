"""Does acting beside learning change what the ``cpu`` preset learns? The perception test's run on one seed.

    .venv/bin/python benchmarks/acting_beside_learning.py SEED VARIANT [--steps 3000]

Trains the ``cpu`` preset's DreamerV2 online on toy_reach for ``--steps`` env steps in this process (the helper of
``tests/training/test_learning.py``'s perception test, one torch thread) and prints the mean return of 20 evaluation
episodes. VARIANT:

* ``default``: each update made before the next step, acting drawing from torch's default generator;
* ``background``: ``train.background_updates=true`` (updates on a thread, the agent acting one update behind with
  a generator of its own);
* ``own-generator``: the default schedule with acting's generator of its own, as ``background`` draws: the two
  differences of ``background`` taken one at a time.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seed", type=int)
    parser.add_argument("variant", choices=["default", "background", "own-generator"])
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    sys.path.insert(0, str(ROOT / "tests" / "training"))
    from test_learning import _learn_online

    from coworld.config import make_config
    from coworld.training import online
    from coworld.training.evaluate import evaluate

    sets = ["device=cpu", f"seed={args.seed}", "train.eval_every=100000", "train.log_every=500"]
    if args.variant == "background":
        sets.append("train.background_updates=true")
    if args.variant == "own-generator":
        policy = online.OnlineTrainer.run

        def run(self: online.OnlineTrainer, **kwargs):  # acting's generator without the thread or the lag
            agent, generator = self.agent, self.act_rng
            acting = agent.policy
            agent.policy = lambda *a, **k: acting(*a, **{**k, "generator": generator})
            try:
                return policy(self, **kwargs)
            finally:
                agent.policy = acting

        online.OnlineTrainer.run = run  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as folder:
        agent, updates = _learn_online(Path(folder), make_config("cpu", sets), max_steps=args.steps)
    learned, _ = evaluate(agent, "toy_reach", episodes=20, seed=123)
    print(f"seed {args.seed} {args.variant}: {updates} updates, return {learned.mean:.1f}")


if __name__ == "__main__":
    main()
