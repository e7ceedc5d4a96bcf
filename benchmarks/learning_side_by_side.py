"""Learning side by side: our DreamerV2 (``--preset cpu``) and a reference Dreamer on the same toy task and budget.

Runs ``coworld collect --policy dreamerv2`` for each seed, and, with ``--reference PATH``, NM512/dreamerv3-torch
from a local checkout at the same sizes, batch, replay ratio, learning rates, horizon, prefill and evaluation. The
reference is imported from its checkout and given our environment through ``gymnasium.make("coworld/<task>-v0")``
at run time; none of its code is copied here. It needs ``gym==0.26.2`` and ``ruamel.yaml`` importable by
``--reference-python`` (default: this interpreter).

Writes ``<out>/<agent>-s<seed>/`` run folders and ``<out>/curves.json`` (return at each evaluation against env steps
and wall-clock seconds), prints a table (median and mean +- std over seeds per evaluation step) and, with
matplotlib, ``<out>/curves.png``.

    python benchmarks/learning_side_by_side.py --out out/side_by_side --seeds 0 1 2 \\
        --reference /path/to/dreamerv3-torch --reference-python /path/to/venv/bin/python
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

# Matched settings: the cpu preset's, written in the reference's config names.
REFERENCE_SETTINGS = {
    "dyn_deter": 64,
    "dyn_hidden": 64,
    "dyn_stoch": 8,
    "dyn_discrete": 8,
    "units": 64,
    "batch_size": 8,
    "batch_length": 16,
    "train_ratio": 64,  # replayed steps per env step: 8 x 16 every 2 env steps, as train.train_every=2
    "prefill": 500,
    "pretrain": 10,
    "model_lr": 6e-4,
    "imag_horizon": 10,
    "action_repeat": 1,
    "time_limit": 50,
    "envs": 1,
    "parallel": False,
    "compile": False,
    "precision": 32,
    "device": "cpu",
    "video_pred_log": False,
}
REFERENCE_NESTED = {
    "encoder": {"mlp_keys": "$^", "cnn_keys": "image", "cnn_depth": 8},
    "decoder": {"mlp_keys": "$^", "cnn_keys": "image", "cnn_depth": 8},
    "actor": {"lr": 2e-4},
    "critic": {"lr": 3e-4},
}

DRIVER = textwrap.dedent(
    """
    # Written by coworld's benchmarks/learning_side_by_side.py: runs the reference Dreamer on a coworld task.
    import json, pathlib, sys
    reference, task, settings = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    sys.path.insert(0, reference)
    import gym, gymnasium, numpy as np, ruamel.yaml
    import coworld.envs.gym_registration  # noqa: F401  (registers coworld/<task>-v0)
    import dreamer, tools
    import envs.wrappers as wrappers

    class CoworldTask:
        # gymnasium env -> the reference's env protocol (old gym API, dict observations)
        def __init__(self, seed):
            self._env = gymnasium.make(f"coworld/{task}-v0", disable_env_checker=True)
            self._seed = seed
            space = self._env.observation_space
            self.observation_space = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, space.shape, np.uint8)})
            act = self._env.action_space
            self.action_space = gym.spaces.Box(act.low, act.high, dtype=np.float32)
        def reset(self):
            image, _ = self._env.reset(seed=self._seed)
            self._seed = None
            return {"image": image, "is_first": True, "is_last": False, "is_terminal": False}
        def step(self, action):
            image, reward, terminated, truncated, info = self._env.step(action)
            obs = {"image": image, "is_first": False, "is_last": terminated or truncated, "is_terminal": terminated}
            return obs, reward, terminated or truncated, info

    def make_env(config, mode, id):
        env = wrappers.NormalizeActions(CoworldTask(config.seed + id + (10_000 if mode == "eval" else 0)))
        env = wrappers.TimeLimit(env, config.time_limit)
        return wrappers.UUID(wrappers.SelectAction(env, key="action"))

    dreamer.make_env = make_env
    configs = ruamel.yaml.YAML(typ="safe").load((pathlib.Path(reference) / "configs.yaml").read_text())
    config = configs["defaults"]
    for key, value in settings.items():
        if isinstance(value, dict):
            config[key].update(value)
        else:
            config[key] = value
    parser = dreamer.argparse.ArgumentParser()
    for key, value in sorted(config.items()):
        kind = tools.args_type(value)
        parser.add_argument(f"--{key}", type=kind, default=kind(value))
    dreamer.main(parser.parse_args([]))
    """
)


def run_ours(task: str, seed: int, steps: int, episodes: int, folder: Path, overrides: list[str]) -> None:
    command = [
        *(sys.executable, "-m", "coworld.cli"),
        *("collect", "--task", task, "--policy", "dreamerv2", "--preset", "cpu", "--device", "cpu"),
        *("--max-steps", str(steps), "--stop-return", "1e9", "--seed", str(seed), "--out", str(folder / "data.h5")),
        *("--set", "train.eval_every=500", "--set", f"train.eval_episodes={episodes}"),
        *[item for override in overrides for item in ("--set", override)],
    ]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"})


def run_reference(task: str, seed: int, steps: int, episodes: int, folder: Path, reference: Path, python: str) -> None:
    settings = {
        **REFERENCE_SETTINGS,
        **REFERENCE_NESTED,
        "seed": seed,
        "steps": steps,
        "eval_every": 500,
        "log_every": 500,
        "eval_episode_num": episodes,
        "logdir": str(folder),
    }
    driver = folder / "driver.py"
    folder.mkdir(parents=True, exist_ok=True)
    driver.write_text(DRIVER)
    command = [python, str(driver), str(reference), task, json.dumps(settings)]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"})


def read_curve(folder: Path, agent: str, started: float) -> list[tuple[int, float, float]]:
    """(env step, eval return, wall seconds since start) per evaluation, from the run's metrics.jsonl."""
    points = []
    if agent == "ours":
        path = folder / "data.run" / "metrics.jsonl"
        key, step_key = "eval/return", "step"
    else:
        path = folder / "metrics.jsonl"
        key, step_key = "eval_return", "step"
    # Wall-clock of each evaluation: ours logs seconds since its start ("time"); the reference logs none, so its
    # evaluation k ends when the last episode file of its k-th group of evaluation episodes was written.
    eval_files = sorted((folder / "eval_eps").glob("*.npz"), key=lambda file: file.stat().st_mtime)
    for line in path.read_text().splitlines():
        record = json.loads(line)
        if key in record:
            if agent == "ours":
                wall = float(record["time"])
            else:
                last = (len(points) + 1) * int(record.get("eval_episodes", 1)) - 1
                wall = eval_files[last].stat().st_mtime - started if last < len(eval_files) else float("nan")
            points.append((int(record[step_key]), float(record[key]), wall))
    return points


def started_at(folder: Path, agent: str) -> float:
    """When a finished run began: the modification time of the first file it wrote (our config.json, the
    reference's driver.py)."""
    first = folder / "data.run" / "config.json" if agent == "ours" else folder / "driver.py"
    return first.stat().st_mtime


def summarise(curves: dict[str, dict[int, list[tuple[int, float, float]]]]) -> str:
    rows = [
        "| agent | env steps | median return | mean ± std | per seed | median wall-clock (s) |",
        "|---|---|---|---|---|---|",
    ]
    for agent, by_seed in curves.items():
        steps = sorted({step for points in by_seed.values() for step, _, _ in points})
        for step in steps:
            values = [ret for points in by_seed.values() for s, ret, _ in points if s == step]
            walls = [wall for points in by_seed.values() for s, _, wall in points if s == step]
            each = " / ".join(f"{value:.1f}" for value in values)
            rows.append(
                f"| {agent} | {step:,} | {np.median(values):.1f} | {np.mean(values):.1f} ± {np.std(values):.1f} |"
                f" {each} | {np.median(walls):.0f} |"
            )
    return "\n".join(rows)


def plot(curves: dict[str, dict[int, list[tuple[int, float, float]]]], path: Path) -> None:
    """Return against env steps and against wall-clock seconds, mean +- std over seeds per agent."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for agent, by_seed in curves.items():
        steps = sorted({step for points in by_seed.values() for step, _, _ in points})
        mean, std, wall = [], [], []
        for step in steps:
            rows = [(ret, w) for points in by_seed.values() for s, ret, w in points if s == step]
            mean.append(np.mean([ret for ret, _ in rows]))
            std.append(np.std([ret for ret, _ in rows]))
            wall.append(np.nanmean([w for _, w in rows]))
        mean_a, std_a = np.array(mean), np.array(std)
        label = f"{agent} ({len(by_seed)} seeds)"
        for axis, x in ((axes[0], np.array(steps)), (axes[1], np.array(wall))):
            axis.plot(x, mean_a, marker="o", label=label)
            axis.fill_between(x, mean_a - std_a, mean_a + std_a, alpha=0.2)
    axes[0].set_xlabel("env steps")
    axes[1].set_xlabel("wall-clock seconds (mean over seeds)")
    axes[0].set_ylabel("evaluation return")
    axes[0].legend()
    for axis in axes:
        axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--task", default="toy_reach")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=3500)
    parser.add_argument("--episodes", type=int, default=20, help="Evaluation episodes (every 500 env steps).")
    parser.add_argument("--reference", type=Path, help="A dreamerv3-torch checkout; without it only ours runs.")
    parser.add_argument("--reference-python", default=sys.executable)
    parser.add_argument("--set", action="append", default=[], help="Override of our config (key=value).")
    parser.add_argument("--skip-ours", action="store_true")
    parser.add_argument(
        "--read-only",
        action="store_true",
        help="Run nothing: summarise the <agent>-s<seed> folders already under --out (wall-clock from file times).",
    )
    args = parser.parse_args()
    agents = ([] if args.skip_ours else ["ours"]) + (["reference"] if args.reference else [])
    if args.read_only:
        agents = [a for a in ("ours", "reference") if any((args.out / f"{a}-s{s}").is_dir() for s in args.seeds)]
    curves: dict[str, dict[int, list[tuple[int, float, float]]]] = {agent: {} for agent in agents}
    for seed in args.seeds:
        for agent in agents:
            folder = args.out / f"{agent}-s{seed}"
            if args.read_only:
                if folder.is_dir():
                    curves[agent][seed] = read_curve(folder, agent, started_at(folder, agent))
                continue
            started = time.time()
            if agent == "ours":
                run_ours(args.task, seed, args.steps, args.episodes, folder, args.set)
            else:
                run_reference(args.task, seed, args.steps, args.episodes, folder, args.reference, args.reference_python)
            curves[agent][seed] = read_curve(folder, agent, started)
            print(
                f"{agent} seed {seed}: {time.time() - started:.0f} s, returns {[r for _, r, _ in curves[agent][seed]]}"
            )
    (args.out / "curves.json").write_text(json.dumps(curves, indent=1))
    print(summarise(curves))
    try:
        plot(curves, args.out / "curves.png")
    except ImportError:
        print("matplotlib is not installed: no curves.png (pip install -e '.[report]')")


if __name__ == "__main__":
    main()
