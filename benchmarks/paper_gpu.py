"""The paper preset on a GPU (issue 19, item 6): update times in fp32 and bf16, eager and compiled, peak GPU
memory, acting, and the ETA of the paper's CoWorld schedule.

Each part runs in a fresh process (so compilation caches and peak-memory counters stay apart) under a time limit,
and prints one JSON line per measurement as soon as it has it, so a part cut off by its limit still reports what
it finished:

* ``update MODE`` (``fp32-eager``, ``bf16-eager``, ``fp32-compile``, ``bf16-compile``; ``tf32-eager`` and
  ``tf32-compile``: fp32 with TensorFloat-32 matmuls and convolutions; ``fp32-phases``: eager with
  the CPU path's decoder-phase forms forced onto the GPU, against the reference that ``fp32-eager`` runs):
  DreamerV2's update, then CoWorld's target update and source update (with the relabelled-reward pass over a
  target batch), each on a random batch of the preset's size. Per update: the warm-up's seconds (with compile,
  the compilation), the median and min seconds of the timed updates (CUDA synchronised before each clock read),
  and the peak GPU memory allocated and reserved by torch, counted from the agent's construction.
* ``act``: one agent step of ``walker_walk`` (its simulator steps and a 64 x 64 render, on this machine), and
  the paper-size agent's policy for one environment on the device, over whole episodes.

Then the ETA of the preset's schedule (``coworld.pretrain_steps`` online source steps, then
``coworld.iterations`` x {``target_updates`` offline target updates; ``source_updates`` source updates with
``train.train_every`` environment steps each}, plus the evaluations), from the fastest mode that measured all
three updates, with acting and updates in turn (``train.background_updates=false``, the default) and
overlapped (``true``). The paper reports "600K steps" in under 4 days on one RTX 3090; the preset reads that as
8 x (5e4 + 2e4) = 560K updates of the two agents (``coworld.iterations``' docstring).

Usage::

    python benchmarks/paper_gpu.py --json OUT/paper_gpu.json          # on a CUDA machine
    python benchmarks/paper_gpu.py --device cpu --preset tiny --modes fp32-eager --updates 2   # a dry run
    # the report again from saved records, the act part's from another machine's (where it could not run)
    python benchmarks/paper_gpu.py --device cpu --records A.json --act-from B.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_throughput import random_batch  # noqa: E402

from coworld.config import PRESETS, Config, make_config  # noqa: E402
from coworld.devices import resolve_device  # noqa: E402
from coworld.storage import write_text_atomically  # noqa: E402

MODES = ("bf16-eager", "fp32-eager", "tf32-eager", "fp32-phases", "bf16-compile", "fp32-compile", "tf32-compile")
UPDATES = ("dreamerv2", "coworld target", "coworld source")


def emit(record: Mapping[str, Any]) -> None:
    print(json.dumps(record), flush=True)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_memory(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def _peak_memory(device: torch.device) -> dict[str, float | None]:
    if device.type != "cuda":
        return {"peak_allocated_gib": None, "peak_reserved_gib": None}
    return {
        "peak_allocated_gib": torch.cuda.max_memory_allocated(device) / 2**30,
        "peak_reserved_gib": torch.cuda.max_memory_reserved(device) / 2**30,
    }


def time_update(
    name: str,
    mode: str,
    update: Callable[[], Mapping[str, float]],
    device: torch.device,
    warmup: int,
    updates: int,
) -> None:
    """Warm ``update`` up, time it, and print its record with the peak memory counted since the last reset."""
    _sync(device)
    start = time.perf_counter()
    first = None
    for _ in range(warmup):
        update()
        _sync(device)
        first = first if first is not None else time.perf_counter() - start
    warmup_s = time.perf_counter() - start
    times, losses = [], []
    for _ in range(updates):
        start = time.perf_counter()
        metrics = update()
        _sync(device)
        times.append(time.perf_counter() - start)
        losses.append(next(float(v) for k, v in metrics.items() if k.endswith("wm/loss")))
    emit(
        {
            "part": "update",
            "mode": mode,
            "update": name,
            "first_s": first,
            "warmup_s": warmup_s,
            "median_s": statistics.median(times),
            "min_s": min(times),
            "times": times,
            "wm_loss": [losses[0], losses[-1]],  # the same batch again and again: finite, and falling
            **_peak_memory(device),
        }
    )


def mode_config(args: argparse.Namespace, mode: str) -> Config:
    """The preset in ``mode``'s precision and compilation; ``tf32`` is fp32 with TensorFloat-32 matmuls and
    convolutions, which :func:`part_update` switches on."""
    precision, how = mode.split("-")
    precision = "fp32" if precision == "tf32" else precision
    return make_config(args.preset, {"device": args.device, "precision": precision, "compile": how == "compile"})


def with_phases(agent: Any) -> Any:
    """``agent`` with the CPU path's decoder-phase forms (coworld.backends.cpu) forced onto its device, which
    ``train.backend`` never does off a CPU: to see whether they would win there."""
    from coworld.backends import cpu

    agent.model_path = cpu.CpuPath(agent.world_model, *cpu.pixel_affine())
    return agent


def part_update(args: argparse.Namespace, mode: str) -> None:
    from coworld.agents.coworld import CoWorld
    from coworld.agents.dreamerv2 import DreamerV2

    config = mode_config(args, mode)
    device = resolve_device(args.device)
    if mode.startswith("tf32"):
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    torch.manual_seed(0)
    batch = random_batch(config.train.batch_size, config.train.seq_len, args.action_size)
    _reset_memory(device)
    dreamer = DreamerV2(config=config, action_size=args.action_size, device=device)
    if mode.endswith("phases"):
        with_phases(dreamer)
    time_update("dreamerv2", mode, partial(dreamer.train, batch), device, args.warmup, args.updates)
    del dreamer  # its memory back before CoWorld's two agents
    _reset_memory(device)
    pair = CoWorld(config=config, action_size=args.action_size, device=device)
    if mode.endswith("phases"):
        with_phases(pair.source), with_phases(pair.target)
    time_update("coworld target", mode, lambda: pair.train_target(batch), device, args.warmup, args.updates)
    _reset_memory(device)
    # the same batch as the relabelled-reward pass's target batch
    time_update("coworld source", mode, lambda: pair.train_source(batch, batch), device, args.warmup, args.updates)


def part_act(args: argparse.Namespace) -> None:
    """Seconds per agent step of ``walker_walk`` and of the paper-size policy, each over whole episodes."""
    from coworld.agents.dreamerv2 import DreamerV2
    from coworld.envs import make

    env = make(args.task, seed=0)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    steps, episodes, start = 0, 0, time.perf_counter()
    while episodes < args.episodes:
        obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        steps += 1
        if terminated or truncated:
            episodes += 1
            obs, _ = env.reset()
    env_s = (time.perf_counter() - start) / steps
    emit(
        {"part": "act", "what": "env", "task": args.task, "step_s": env_s, "steps": steps, "episode": steps // episodes}
    )
    env.close()

    config = make_config(args.preset, {"device": args.device})
    device = resolve_device(args.device)
    agent = DreamerV2(config=config, action_size=env.action_space.shape[0], device=device)
    frame = obs[None]
    for mode in ("train", "eval"):
        state = None
        for _ in range(20):  # warm-up
            _, state = agent.policy(frame, state, mode)
        start = time.perf_counter()
        for _ in range(steps):
            _, state = agent.policy(frame, state, mode)
        emit({"part": "act", "what": f"policy {mode}", "step_s": (time.perf_counter() - start) / steps})


def eta(config: Config, t: Mapping[str, float], env_s: float, act_s: float, episode: int) -> dict[str, float]:
    """Hours of the preset's whole CoWorld run, from seconds per update (``t``) and per agent step."""
    tr, cw = config.train, config.coworld
    step = env_s + act_s
    pre_updates = tr.pretrain_updates + (cw.pretrain_steps - tr.prefill) // tr.train_every + 1
    source_steps = cw.iterations * cw.source_updates * tr.train_every
    evals = (cw.pretrain_steps + source_steps) // tr.eval_every + cw.iterations // cw.eval_every
    eval_s = evals * tr.eval_episodes * episode * step
    regular = pre_updates - tr.pretrain_updates  # the pretraining's updates every train_every steps
    source = cw.iterations * cw.source_updates
    offline_s = tr.pretrain_updates * t["dreamerv2"] + cw.iterations * cw.target_updates * t["coworld target"]
    updates_s = offline_s + regular * t["dreamerv2"] + source * t["coworld source"]
    steps_s = (cw.pretrain_steps + source_steps) * step
    overlapped = (  # an update and the train_every steps beside it take the longer of the two; the prefill alone
        offline_s
        + tr.prefill * step
        + regular * max(t["dreamerv2"], tr.train_every * step)
        + source * max(t["coworld source"], tr.train_every * step)
    )
    return {
        "in_turn_h": (updates_s + steps_s + eval_s) / 3600,
        "overlapped_h": (overlapped + eval_s) / 3600,
        "updates_h": updates_s / 3600,
        "env_steps_h": (steps_s + eval_s) / 3600,
        "env_steps": cw.pretrain_steps + source_steps + evals * tr.eval_episodes * episode,
        "updates": pre_updates + cw.iterations * (cw.target_updates + cw.source_updates),
    }


def run_part(args: argparse.Namespace, part: list[str], limit: float) -> list[dict[str, Any]]:
    """Run one part in a fresh process for at most ``limit`` seconds; its JSON lines, echoed as they come."""
    cmd = [sys.executable, __file__, "--worker", *part, *forwarded(args)]
    print(f"== {' '.join(part)} (limit {limit:.0f} s)", flush=True)
    records: list[dict[str, Any]] = []
    start = time.perf_counter()
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}) as p:
        timer = threading.Timer(limit, p.kill)
        timer.start()
        for line in iter(p.stdout.readline, ""):  # type: ignore[union-attr]
            print(line, end="", flush=True)
            if line.startswith("{"):
                records.append(json.loads(line))
        p.wait()
        timer.cancel()
    if p.returncode == -9:
        print(f"== {' '.join(part)}: cut off at its limit after {time.perf_counter() - start:.0f} s", flush=True)
    elif p.returncode:
        print(f"== {' '.join(part)}: exit code {p.returncode}", flush=True)
    return records


def _saved(path: str) -> list[dict[str, Any]]:
    return json.loads(Path(path).read_text())["records"]


def forwarded(args: argparse.Namespace) -> list[str]:
    return [
        f"--preset={args.preset}",
        f"--device={args.device}",
        f"--updates={args.updates}",
        f"--warmup={args.warmup}",
        f"--action-size={args.action_size}",
        f"--task={args.task}",
        f"--episodes={args.episodes}",
    ]


def report(args: argparse.Namespace, records: list[dict[str, Any]]) -> dict[str, Any]:
    config = make_config(args.preset, {"device": args.device})
    print(f"\npreset={args.preset} device={args.device} batch={config.train.batch_size}x{config.train.seq_len}")
    if torch.cuda.is_available() and args.device != "cpu":
        print(f"gpu={torch.cuda.get_device_name()} torch={torch.__version__}")
    print(
        f"{'mode':<14}{'update':<16}{'median s':>10}{'min s':>9}{'warm-up s':>11}{'peak alloc GiB':>16}"
        f"{'wm loss first->last':>22}"
    )
    timed: dict[str, dict[str, float]] = {}
    for r in (r for r in records if r["part"] == "update"):
        timed.setdefault(r["mode"], {})[r["update"]] = r["median_s"]
        peak = r["peak_allocated_gib"]
        print(
            f"{r['mode']:<14}{r['update']:<16}{r['median_s']:>10.4f}{r['min_s']:>9.4f}{r['warmup_s']:>11.1f}"
            f"{'-' if peak is None else f'{peak:.2f}':>16}{r['wm_loss'][0]:>12.1f} ->{r['wm_loss'][1]:>8.1f}"
        )
    acts = {r["what"]: r for r in records if r["part"] == "act"}
    for what, r in acts.items():
        print(f"act: {what:<14}{r['step_s'] * 1000:>8.2f} ms per agent step")
    out: dict[str, Any] = {"records": records, "eta": {}}
    if "env" not in acts or "policy train" not in acts:
        print("no ETA: the act part did not finish (--records FILE --act-from OTHER reports with another run's)")
        return out
    for mode, t in timed.items():
        if set(UPDATES) <= set(t):
            e = eta(config, t, acts["env"]["step_s"], acts["policy train"]["step_s"], acts["env"]["episode"])
            out["eta"][mode] = e
            print(
                f"ETA {mode}: {e['in_turn_h']:.1f} h in turn, {e['overlapped_h']:.1f} h with acting beside learning "
                f"({e['updates']:,} updates: {e['updates_h']:.1f} h; {e['env_steps']:,} agent steps: "
                f"{e['env_steps_h']:.1f} h)"
            )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--device", default="cuda", help="cuda or cpu (a dry run)")
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, of {', '.join(MODES)}")
    parser.add_argument("--updates", type=int, default=20, help="timed updates per update kind")
    parser.add_argument("--warmup", type=int, default=3, help="untimed updates first (compilation happens here)")
    parser.add_argument("--action-size", type=int, default=6, help="actions of the timed updates (walker: 6)")
    parser.add_argument("--task", default="walker_walk", help="the env the act part steps")
    parser.add_argument("--episodes", type=int, default=2, help="whole episodes the act part times")
    parser.add_argument("--limit", type=float, default=240.0, help="seconds each part may run")
    parser.add_argument("--compile-limit", type=float, default=300.0, help="seconds each compiled mode may run")
    parser.add_argument("--budget", type=float, default=3600.0, help="seconds the whole run may take (the report kept)")
    parser.add_argument("--json", help="also write every record and the ETAs to this file")
    parser.add_argument("--records", help="measure nothing: the report from this earlier --json file's records")
    parser.add_argument("--act-from", help="the act part's records from this earlier --json file, not measured")
    parser.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        part, *rest = args.worker
        return part_act(args) if part == "act" else part_update(args, rest[0])
    modes = [m for m in args.modes.split(",") if m]
    if unknown := [m for m in modes if m not in MODES]:
        parser.error(f"unknown mode(s) {', '.join(unknown)}; choose from {', '.join(MODES)}")
    deadline = time.perf_counter() + args.budget - 10.0  # the report's time kept back

    def limit(most: float) -> float:
        return max(0.0, min(most, deadline - time.perf_counter()))

    borrowed = [r for r in _saved(args.act_from) if r["part"] == "act"] if args.act_from else None
    if args.records:
        records = [r for r in _saved(args.records) if borrowed is None or r["part"] != "act"] + (borrowed or [])
        report(args, records)
        return
    records = []
    eager = [m for m in modes if m.endswith(("eager", "phases"))]
    for mode in eager:
        records += run_part(args, ["update", mode], limit(args.limit))
        if not any(r.get("mode") == mode for r in records):
            sys.exit(f"{mode} measured nothing: stopping before the longer parts")
    records += borrowed if borrowed is not None else run_part(args, ["act"], limit(args.limit))
    for mode in (m for m in modes if m not in eager):
        if limit(args.compile_limit) < 30:
            print(f"== update {mode}: skipped, the budget is spent", flush=True)
            continue
        records += run_part(args, ["update", mode], limit(args.compile_limit))
    out = report(args, records)
    if args.json:
        write_text_atomically(args.json, json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
