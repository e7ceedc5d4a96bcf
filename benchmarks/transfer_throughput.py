"""Dataset import and export throughput: V-D4RL folders in (both layouts), Minari and npz episodes out.

    python benchmarks/transfer_throughput.py --dir /tmp/coworld-transfer --episodes 20

Builds V-D4RL-format folders from real walker_walk renders (two 500-step episodes under random actions at 64 and
at 84 pixels, repeated --episodes times, each written the way V-D4RL's scripts write them), then times
``import_vd4rl`` on the 64px npz folder and on the 84px shards (``resize=64``), ``export_minari`` and
``export_npz_episodes`` of the result, and reports the sizes on disk. Times are wall-clock and CPU time of this
process; on a shared machine the frames per CPU-second are what one free core gives.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from coworld.data import export_minari, export_npz_episodes, import_vd4rl


def rendered_episode(size: int, seed: int) -> dict[str, np.ndarray]:
    """One 500-step walker_walk episode under random actions in V-D4RL's step layout (501 entries)."""
    from coworld.envs import make

    env = make("walker_walk", seed=seed, image_size=size)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset()
    frames, actions, rewards = [obs], [np.zeros(6, np.float32)], [0.0]
    for _ in range(env.unwrapped.settings.episode_length):
        action = rng.uniform(-1, 1, 6).astype(np.float32)
        obs, reward, *_ = env.step(action)
        frames.append(obs)
        actions.append(action)
        rewards.append(reward)
    env.close()
    j = np.arange(len(frames))
    return {
        "image": np.stack(frames),
        "action": np.stack(actions),
        "reward": np.asarray(rewards, np.float32),
        "discount": np.ones(len(frames), np.float32),
        "is_first": j == 0,
        "is_last": j == j[-1],
        "is_terminal": np.zeros(len(frames), bool),
    }


def write_vd4rl(root: Path, episodes: int) -> tuple[Path, Path, int]:
    """The 64px npz folder and the 84px shard folder of ``episodes`` episodes; returns them and the frame count."""
    npz = root / "walker_walk/medium_replay/64px"
    shards = root / "walker_walk/medium_replay/84px"
    npz.mkdir(parents=True)
    shards.mkdir(parents=True)
    small = [rendered_episode(64, seed) for seed in range(2)]
    large = [rendered_episode(84, seed) for seed in range(2)]
    for i in range(episodes):
        with io.BytesIO() as buffer:
            np.savez_compressed(buffer, **small[i % 2])
            (npz / f"20220101T{i:06d}-{uuid.uuid4().hex}-501.npz").write_bytes(buffer.getvalue())
    chosen = [large[i % 2] for i in range(episodes)]
    step_type = [np.where(ep["is_first"], 0, np.where(ep["is_last"], 2, 1)) for ep in chosen]
    table = {
        "observation": np.concatenate([ep["image"].transpose(0, 3, 1, 2) for ep in chosen]),
        "action": np.concatenate([ep["action"] for ep in chosen]),
        "reward": np.concatenate([ep["reward"] for ep in chosen]).astype(np.float64),
        "discount": np.concatenate([ep["discount"] for ep in chosen]).astype(np.float64),
        "step_type": np.concatenate(step_type).astype(np.int64),
    }
    with h5py.File(shards / "shard_1_reward_0.hdf5", "w") as f:
        for key, value in table.items():
            f.create_dataset(key, data=value, compression="gzip")
    return npz, shards, sum(len(ep["image"]) for ep in chosen)


def timed(label: str, frames: int, fn: Callable[[], Any]) -> dict[str, Any]:
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    row = {"step": label, "frames": frames, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2)}
    row["frames_per_cpu_s"] = round(frames / cpu)
    print(json.dumps(row))
    return row


def mib(path: Path) -> float:
    files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
    return round(sum(f.stat().st_size for f in files) / 2**20, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path("/tmp/coworld-transfer"), help="scratch folder (emptied)")
    parser.add_argument("--episodes", type=int, default=20, help="episodes of 500 steps per folder")
    parser.add_argument("--keep", action="store_true", help="keep the files")
    args = parser.parse_args()
    root = args.dir
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    os.environ["MINARI_DATASETS_PATH"] = str(root / "minari")  # this script's own Minari folder
    npz, shards, frames = write_vd4rl(root, args.episodes)
    ours = root / "walker_walk-medium_replay.h5"
    timed("import vd4rl 64px npz", frames, lambda: import_vd4rl(npz, ours, task="walker_walk"))
    resized = root / "resized.h5"
    timed(
        "import vd4rl 84px shards --resize 64",
        frames,
        lambda: import_vd4rl(shards, resized, task="walker_walk", resize=64),
    )
    name = "coworld/walker_walk/medium-replay-v0"
    timed("export minari", frames, lambda: export_minari(ours, name))
    timed("export npz-episodes", frames, lambda: export_npz_episodes(ours, root / "npz"))
    sizes = {
        "vd4rl 64px npz": mib(npz),
        "vd4rl 84px shards": mib(shards),
        "imported (gzip)": mib(ours),
        "imported from 84px": mib(resized),
        "minari": mib(root / "minari" / name),
        "npz export": mib(root / "npz"),
    }
    print(json.dumps({"sizes_mib": sizes}))
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
