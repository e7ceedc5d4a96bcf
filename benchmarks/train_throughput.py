"""Training throughput: DreamerV2 updates per second, split into world model, imagination and actor-critic;
CoWorld's target and source updates; CURL and CURL+CQL updates.

Examples::

    python benchmarks/train_throughput.py --algo all                   # every algorithm, tiny preset, CPU
    python benchmarks/train_throughput.py                              # tiny preset on CPU (2 threads)
    python benchmarks/train_throughput.py --preset paper --device cpu --updates 1 --warmup 0
    python benchmarks/train_throughput.py --preset paper --device cuda --compare   # fp32 / bf16, eager / compiled

Batches are random uint8 frames (throughput does not depend on content). Timings are medians over
``--updates`` measured steps after ``--warmup`` steps; CUDA work is synchronised before each clock read.

* ``wm``: one world-model update (encode, RSSM over B x T, decode, heads, backward, AdamW);
* ``imagine``: the imagination rollout alone (H steps from B * T start states, forward only with graph);
* ``actor_critic``: one full actor-critic update (imagination, losses, backward, two AdamW steps);
* ``train``: one complete :meth:`DreamerV2.train` call (both updates plus the batch transfer).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import torch

from coworld.agents.dreamerv2 import DreamerV2
from coworld.config import make_config
from coworld.models.actor_critic import flatten_states
from coworld.models.networks import frozen_parameters
from coworld.training.run import resolve_device


@dataclass(frozen=True)
class Timing:
    """Median seconds per call of each part, and the resulting full updates per second."""

    label: str
    wm_s: float
    imagine_s: float
    actor_critic_s: float
    train_s: float

    @property
    def updates_per_s(self) -> float:
        return 1.0 / self.train_s


def random_batch(batch: int, length: int, action_size: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A replay-convention batch of random frames and actions."""
    rng = np.random.default_rng(seed)
    is_first = np.zeros((batch, length), bool)
    is_first[:, 0] = True
    flags = np.zeros((batch, length), bool)
    return {
        "image": rng.integers(0, 256, (batch, length, 64, 64, 3), dtype=np.uint8),
        "action": rng.uniform(-1, 1, (batch, length, action_size)).astype(np.float32),
        "reward": rng.normal(size=(batch, length)).astype(np.float32),
        "is_first": is_first,
        "is_last": flags,
        "is_terminal": flags,
    }


def _median_time(fn: Callable[[], object], device: torch.device, warmup: int, repeats: int) -> float:
    """Median wall-clock seconds of ``fn`` over ``repeats`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(
    preset: str, device: str, overrides: dict[str, object], label: str, warmup: int, repeats: int, action_size: int
) -> Timing:
    """Time each part of a DreamerV2 update for one configuration."""
    config = make_config(preset, {"device": device, **overrides})
    agent = DreamerV2(config=config, action_size=action_size)
    batch_np = random_batch(config.train.batch_size, config.train.seq_len, action_size)
    batch = agent.to_batch(batch_np)
    _, post = agent.train_world_model(batch)
    start = flatten_states(post)

    def imagine() -> None:
        with frozen_parameters(agent.world_model), agent._autocast():
            agent.actor_critic.imagine(agent.world_model, start)

    return Timing(
        label=label,
        wm_s=_median_time(lambda: agent.train_world_model(batch), agent.device, warmup, repeats),
        imagine_s=_median_time(imagine, agent.device, warmup, repeats),
        actor_critic_s=_median_time(lambda: agent.train_actor_critic(post), agent.device, warmup, repeats),
        train_s=_median_time(lambda: agent.train(batch_np), agent.device, warmup, repeats),
    )


def measure_others(preset: str, device: str, warmup: int, repeats: int, action_size: int) -> list[tuple[str, float]]:
    """Median seconds of one update of CoWorld's target and source agents, CURL and CURL+CQL."""
    from coworld.agents.coworld import CoWorld
    from coworld.agents.curl import Curl

    config = make_config(preset, {"device": device})
    dev = resolve_device(device)
    coworld = CoWorld(config=config, action_size=action_size, device=dev)
    batch = random_batch(config.train.batch_size, config.train.seq_len, action_size)
    coworld.target_batches = iter(lambda: batch, None)
    out = [
        ("coworld target update", _median_time(lambda: coworld.train_target(batch), dev, warmup, repeats)),
        ("coworld source update", _median_time(lambda: coworld.train_source(batch), dev, warmup, repeats)),
    ]
    c = config.curl
    rng = np.random.default_rng(0)
    frames = (c.batch_size, 3 * c.frame_stack, 64, 64)
    curl_batch = {
        "obs": rng.integers(0, 256, frames, dtype=np.uint8),
        "next_obs": rng.integers(0, 256, frames, dtype=np.uint8),
        "action": rng.uniform(-1, 1, (c.batch_size, action_size)).astype(np.float32),
        "reward": rng.normal(size=c.batch_size).astype(np.float32),
        "not_done": np.ones(c.batch_size, np.float32),
    }
    for cql in (False, True):
        agent = Curl(config=config, action_size=action_size, device=dev, cql=cql)
        seconds = _median_time(lambda agent=agent: agent.train(curl_batch), dev, warmup, repeats)
        out.append(("curl-cql update" if cql else "curl update", seconds))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=["tiny", "paper"])
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--updates", type=int, default=20, help="measured calls per part")
    parser.add_argument("--warmup", type=int, default=3, help="unmeasured calls per part first")
    parser.add_argument("--action-size", type=int, default=6)
    parser.add_argument(
        "--compare", action="store_true", help="fp32 / bf16 autocast, each eager and torch.compiled (meant for CUDA)"
    )
    parser.add_argument(
        "--algo",
        default="dreamerv2",
        choices=["dreamerv2", "others", "all"],
        help="dreamerv2 (with its breakdown), others (CoWorld, CURL, CURL+CQL) or all",
    )
    parser.add_argument("--json", default=None, help="also write the timings to this JSON file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.algo in ("others", "all"):
        print(f"preset={args.preset} device={args.device} threads={args.threads}")
        print(f"{'update':<24}{'s':>10}{'updates/s':>11}")
        for label, seconds in measure_others(args.preset, args.device, args.warmup, args.updates, args.action_size):
            print(f"{label:<24}{seconds:>10.4f}{1.0 / seconds:>11.2f}")
        if args.algo == "others":
            return

    runs = [("default", {})]
    if args.compare:
        runs = [
            (f"{precision}-{mode}", {"precision": precision, "compile": mode == "compile"})
            for mode in ("eager", "compile")
            for precision in ("fp32", "bf16")
        ]
    results = [
        measure(args.preset, args.device, overrides, label, args.warmup, args.updates, args.action_size)
        for label, overrides in runs
    ]
    config = make_config(args.preset)
    print(
        f"preset={args.preset} device={args.device} threads={args.threads} "
        f"batch={config.train.batch_size}x{config.train.seq_len} horizon={config.actor_critic.horizon}"
    )
    print(f"{'run':<14}{'wm s':>10}{'imagine s':>12}{'ac s':>10}{'train s':>10}{'updates/s':>11}")
    for r in results:
        print(
            f"{r.label:<14}{r.wm_s:>10.4f}{r.imagine_s:>12.4f}{r.actor_critic_s:>10.4f}"
            f"{r.train_s:>10.4f}{r.updates_per_s:>11.2f}"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {
                    "preset": args.preset,
                    "device": args.device,
                    "threads": args.threads,
                    "runs": [asdict(r) for r in results],
                },
                f,
                indent=2,
            )


if __name__ == "__main__":
    main()
