"""Dataset throughput: writing, sampling B x L windows (RAM, streaming, a plain NumPy gather as the limit), the
memory of streaming at two dataset sizes, and the frame codecs.

    python benchmarks/data_throughput.py --dir /tmp/coworld-bench

Frames are real 64 x 64 walker_walk renders (a pool of --pool frames, random actions, tiled into episodes), so the
compression figures are those of DMC images. Everything is written under --dir (about 0.7 GB at the defaults) and
deleted at the end unless --keep. The OS page cache is warm (the files were just written): streaming figures are
decode-bound, not disk-bound.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import psutil

from coworld.data import CODECS, DatasetWriter, open_dataset

EPISODE_LENGTH = 500


def render_pool(path: Path, n: int) -> np.ndarray:
    """``n`` frames (n, 64, 64, 3) of walker_walk under random actions, cached in ``path``."""
    if path.exists():
        return np.load(path)
    from coworld.envs import make

    env = make("walker_walk", seed=0)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    frames = [obs]
    while len(frames) < n:
        obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        frames.append(obs)
        if terminated or truncated:
            obs, _ = env.reset()
            frames.append(obs)
    env.close()
    pool = np.stack(frames[:n])
    np.save(path, pool)
    return pool


def write_dataset(path: Path, pool: np.ndarray, rows: int, codec: str = "gzip") -> tuple[float, float]:
    """Write ``rows`` rows in episodes of 500 steps; returns frames (rows + final frames) written per second of
    wall time and per second of this process's CPU time."""
    rng = np.random.default_rng(0)
    episodes = rows // EPISODE_LENGTH
    start, cpu = time.perf_counter(), time.process_time()
    with DatasetWriter(
        path,
        task="walker_walk",
        env_config={},
        quality="random",
        collector={"algorithm": "benchmark"},
        action_size=6,
        force=True,
        compression=codec,
    ) as writer:
        for e in range(episodes):
            index = (e * 137 + np.arange(EPISODE_LENGTH + 1)) % len(pool)
            actions = rng.uniform(-1, 1, (EPISODE_LENGTH, 6)).astype(np.float32)
            writer.add_episode(pool[index], actions, rng.random(EPISODE_LENGTH, np.float32), False)
        writer.close(complete=True)
    frames = episodes * (EPISODE_LENGTH + 1)
    return frames / (time.perf_counter() - start), frames / (time.process_time() - cpu)


def sampling(path: Path, batch: int, length: int, batches: int, repeats: int = 3) -> dict[str, float]:
    """Frames/s of a NumPy gather from RAM, of the sampler in RAM mode and in streaming mode, on the same windows.

    Each is timed ``repeats`` times, interleaved, and the best run counts (other processes only ever slow a run).
    """
    frames = batch * length * batches
    with open_dataset(path) as data:
        stream = data.sampler(batch, length, seed=0, mode="stream")
        starts = [stream.sample_starts(np.random.default_rng(i)) for i in range(batches)]
        t = time.perf_counter()
        ram = data.sampler(batch, length, seed=0, mode="ram")  # loads every frame
        load_s = time.perf_counter() - t
        images, offsets = data.load_frames(), np.arange(length)
        runs = {
            "numpy": lambda s: images[s[:, None] + offsets],
            "ram": ram.gather,
            "stream": stream.gather,
        }
        best = dict.fromkeys(runs, 0.0)
        per_cpu_second = dict.fromkeys(runs, 0.0)  # frames per second of this process's own CPU time
        for _ in range(repeats):
            for name, gather in runs.items():
                t, cpu = time.perf_counter(), time.process_time()
                for s in starts:
                    gather(s)
                best[name] = max(best[name], frames / (time.perf_counter() - t))
                per_cpu_second[name] = max(per_cpu_second[name], frames / (time.process_time() - cpu))
    return {**best, "stream_per_cpu_s": per_cpu_second["stream"], "ram_load_s": load_s}


# Peak RSS from VmHWM: ru_maxrss would carry the parent's high-water mark across fork + exec.
MEMORY_PROBE = """
import json, re, sys, psutil
from coworld.data import open_dataset
def high_water_mark():
    with open("/proc/self/status") as status:
        return int(re.search(r"VmHWM:\\s+(\\d+) kB", status.read()).group(1)) * 1024
rss = psutil.Process().memory_info().rss
before = high_water_mark()
data = open_dataset(sys.argv[1], cache_mb=int(sys.argv[4]))
sampler = data.sampler(int(sys.argv[2]), int(sys.argv[2]), seed=0, mode="stream")
for _ in range(int(sys.argv[3])):
    next(sampler)
print(json.dumps({"before_open": rss, "peak_before": before, "peak": high_water_mark(), "frames": data.num_frames}))
"""


def stream_memory(path: Path, size: int, batches: int, cache_mb: int) -> dict[str, int]:
    """Peak RSS growth (bytes) of a fresh process streaming ``batches`` batches of size x size windows."""
    out = subprocess.run(
        [sys.executable, "-c", MEMORY_PROBE, str(path), str(size), str(batches), str(cache_mb)],
        check=True,
        capture_output=True,
        text=True,
    )
    probe = json.loads(out.stdout)
    assert probe["peak_before"] <= probe["before_open"] * 1.05, probe  # nothing bigger ran before the measurement
    return {"growth": probe["peak"] - probe["before_open"], "frames": probe["frames"]}


def loader_throughput(path: Path, batch: int, length: int, batches: int, workers: int) -> float:
    """Frames/s (best of 3 runs) of streaming batches through a torch DataLoader with ``workers`` processes."""
    from coworld.data.loader import make_loader

    with open_dataset(path) as data:
        loader = iter(make_loader(data, batch, length, seed=0, mode="stream", num_workers=workers))
        for _ in range(workers):  # workers started and warm
            next(loader)
        best = 0.0
        for _ in range(3):
            t = time.perf_counter()
            for _ in range(batches):
                next(loader)
            best = max(best, batch * length * batches / (time.perf_counter() - t))
        return best


def _load() -> str:
    """1, 5 and 15-minute load averages: other processes competing for the CPUs lower every figure."""
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


# (filter, level, frames per chunk) compared by --sweep-frames: the stock filters around the default gzip-4 x 16.
SWEEP = [("gzip", 4, 8), ("gzip", 4, 16), ("gzip", 4, 32), ("gzip", 4, 64), ("gzip", 1, 16), ("gzip", 6, 16),
         ("lzf", None, 16)]  # fmt: skip


def chunk_sweep(path: Path, pool: np.ndarray, frames: int, windows: int = 300, length: int = 50) -> None:
    """Ratio, writing and random ``length``-frame window reads (frames per CPU-s, no chunk cache), per filter and
    chunk shape, with plain h5py."""
    data = pool[np.arange(frames) % len(pool)]
    starts = np.random.default_rng(0).integers(0, frames - length, windows)
    out = np.empty((length, *pool.shape[1:]), np.uint8)
    for codec, level, chunk in SWEEP:
        cpu = time.process_time()
        with h5py.File(path, "w") as f:
            f.create_dataset("o", data=data, chunks=(chunk, *pool.shape[1:]), compression=codec, compression_opts=level)
        write_fps = frames / (time.process_time() - cpu)
        with h5py.File(path, "r", rdcc_nbytes=0) as f:
            node, cpu = f["o"], time.process_time()
            for s in starts:
                node.read_direct(out, np.s_[s : s + length])
            fps = windows * length / (time.process_time() - cpu)
        name = codec if level is None else f"{codec}-{level}"
        print(f"sweep {name:<6} x {chunk:>2} frames/chunk: ratio {data.nbytes / path.stat().st_size:.2f}  "
              f"write {write_fps:7,.0f}  window reads {fps:7,.0f} frames per CPU-s")  # fmt: skip
    path.unlink()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", type=Path, default=Path("/tmp/coworld-bench"))
    parser.add_argument("--rows", type=int, default=50_000, help="rows of the main dataset")
    parser.add_argument("--big-rows", type=int, default=200_000, help="rows of the second dataset (memory)")
    parser.add_argument("--pool", type=int, default=1000, help="distinct rendered frames")
    parser.add_argument("--batch", type=int, default=50)
    parser.add_argument("--length", type=int, default=50)
    parser.add_argument("--batches", type=int, default=20)
    parser.add_argument("--cache-mb", type=int, default=64)
    parser.add_argument("--codec-rows", type=int, default=10_000, help="rows per codec in the codec table (0: skip)")
    parser.add_argument("--sweep-frames", type=int, default=10_000, help="frames in the chunk sweep (0: skip)")
    parser.add_argument("--keep", action="store_true", help="keep the files under --dir")
    args = parser.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    memory = psutil.virtual_memory().total / 2**30
    print(f"machine: {os.cpu_count()} CPUs, {memory:.0f} GiB; {time.strftime('%Y-%m-%d')}; load {_load()}")
    pool = render_pool(args.dir / "walker_frames.npy", args.pool)
    try:
        small, big = args.dir / "small.h5", args.dir / "big.h5"
        fps, cpu_fps = write_dataset(small, pool, args.rows)
        mib = small.stat().st_size / 2**20
        print(f"write (gzip, {args.rows:,} rows): {fps:,.0f} frames/s ({cpu_fps:,.0f} per CPU-s); file {mib:,.0f} MiB")
        s = sampling(small, args.batch, args.length, args.batches)
        print(
            f"sampling B={args.batch} L={args.length}, {args.batches} batches, best of 3: "
            f"numpy gather {s['numpy']:,.0f} frames/s | ram {s['ram']:,.0f} ({s['ram'] / s['numpy']:.0%} of numpy) "
            f"| stream {s['stream']:,.0f} ({s['stream_per_cpu_s']:,.0f} per CPU-s) | ram load {s['ram_load_s']:.1f} s"
        )
        for workers in (1, 2):
            fps = loader_throughput(small, args.batch, args.length, args.batches, workers)
            print(f"stream through a DataLoader with {workers} workers: {fps:,.0f} frames/s")
        fps, cpu_fps = write_dataset(big, pool, args.big_rows)
        mib = big.stat().st_size / 2**20
        print(
            f"write (gzip, {args.big_rows:,} rows): {fps:,.0f} frames/s ({cpu_fps:,.0f} per CPU-s); file {mib:,.0f} MiB"
        )
        for path in (small, big):
            m = stream_memory(path, args.batch, args.batches, args.cache_mb)
            print(
                f"stream memory, {m['frames']:,} frames ({m['frames'] * 12288 / 2**30:.1f} GiB raw), cache "
                f"{args.cache_mb} MiB: peak RSS growth {m['growth'] / 2**20:,.0f} MiB"
            )
        for codec in CODECS if args.codec_rows else ():
            path = args.dir / f"codec_{codec}.h5"
            try:
                fps, cpu_fps = write_dataset(path, pool, args.codec_rows, codec)
            except Exception as err:  # a plugin codec without hdf5plugin
                print(f"codec {codec}: skipped ({err})")
                continue
            with open_dataset(path) as data:
                raw, stored = data.frame_storage()
            s = sampling(path, args.batch, args.length, 10, repeats=2)
            print(
                f"codec {codec:<5} ratio {raw / stored:4.1f}  write {fps:8,.0f} frames/s ({cpu_fps:8,.0f} per CPU-s)  "
                f"stream {s['stream']:8,.0f} frames/s ({s['stream_per_cpu_s']:8,.0f} per CPU-s)  "
                f"file/frames {path.stat().st_size / stored:.2f}"
            )
        if args.sweep_frames:
            chunk_sweep(args.dir / "sweep.h5", pool, args.sweep_frames)
    finally:
        if not args.keep:
            for name in os.listdir(args.dir):
                if name.endswith(".h5"):
                    os.remove(args.dir / name)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"benchmark process peak RSS {peak:.1f} GiB; load {_load()}")
    if not args.keep:
        shutil.rmtree(args.dir, ignore_errors=True)


if __name__ == "__main__":
    main()
