"""What each part of the CPU fast path (``train.backend=cpu``) gains on a whole DreamerV2 update.

One process, one agent per variant (the same weights and batch), their updates alternating round by round, so
the machine's drift falls on every variant alike. Variants: the reference path; the CPU path whole; and the CPU
path with one of its parts replaced by the reference's (``no-<part>``). A part is worth keeping where
removing it costs at least 5% of the update (the issue-50 rule).

    python benchmarks/backend_parts.py --preset tiny --set train.batch_size=16 --set train.seq_len=32
    python benchmarks/backend_parts.py --preset cpu --rounds 30

Updates are timed in CPU seconds of this process (one torch thread), which another process's load on the machine
disturbs less than wall-clock. Prints per variant the median seconds per update and its ratio to the whole CPU path's.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time
from collections.abc import Callable, Iterator

import numpy as np
import torch

from coworld.agents.dreamerv2 import DreamerV2
from coworld.backends import ReferencePath
from coworld.config import PRESETS, make_config


def random_batch(batch: int, length: int, action_size: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, action_size)).astype(np.float32),
        "reward": rng.normal(size=(batch, length)).astype(np.float32),
        "is_first": np.zeros((batch, length), bool),
        "is_last": np.zeros((batch, length), bool),
        "is_terminal": np.zeros((batch, length), bool),
    }
    out["is_first"][:, 0] = True
    return out


@contextlib.contextmanager
def patched(module: object, name: str, value: object) -> Iterator[None]:
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, old)


def variants(agent: DreamerV2) -> dict[str, Callable[[], contextlib.AbstractContextManager]]:
    """Each variant's patch of the CPU path (entered around its update)."""
    path = agent.model_path
    reference = ReferencePath(agent.world_model)

    def loss_without_decoder_phases(batch: dict, generator: torch.Generator | None = None) -> tuple:
        """The CPU path's loss with the reference decoder and image term (its encoder kept)."""
        return agent.world_model.loss(path.prepare(batch), generator)

    return {
        "cpu": contextlib.nullcontext,
        "no-decoder-phases": lambda: patched(path, "loss", loss_without_decoder_phases),
        "reference": lambda: patched(agent, "model_path", reference),
    }


@contextlib.contextmanager
def _stack(*managers: contextlib.AbstractContextManager) -> Iterator[None]:
    with contextlib.ExitStack() as stack:
        for manager in managers:
            stack.enter_context(manager)
        yield


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=sorted(PRESETS))
    parser.add_argument("--set", action="append", default=[], help="config override KEY=VALUE (repeatable)")
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--only", default="", help="comma-separated variants (default: all)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = make_config(args.preset, [*args.set, "train.backend=cpu"])
    torch.manual_seed(0)
    agent = DreamerV2(config=config, action_size=6, device="cpu")
    batch = random_batch(config.train.batch_size, config.train.seq_len, 6)
    chosen = variants(agent)
    if args.only:
        chosen = {name: chosen[name] for name in args.only.split(",")}
    state = {key: value.clone() for key, value in agent.world_model.state_dict().items()}
    times: dict[str, list[float]] = {name: [] for name in chosen}
    for round_ in range(args.rounds + 2):
        for name, patch in chosen.items():
            agent.world_model.load_state_dict(state)  # every variant updates the same weights
            with patch():
                start = time.process_time()  # CPU time: another process's load does not count
                agent.train(batch)
                elapsed = time.process_time() - start
            if round_ >= 2:  # the first rounds warm up
                times[name].append(elapsed)
    base = statistics.median(times["cpu"]) if "cpu" in times else None
    print(f"preset {args.preset} batch {config.train.batch_size} x {config.train.seq_len}, {args.rounds} rounds")
    for name, values in times.items():
        median = statistics.median(values)
        ratio = f"  {median / base:.3f}x the CPU path's" if base else ""
        print(f"{name:22s} {median * 1000:8.1f} ms{ratio}")


if __name__ == "__main__":
    main()
