"""Frames per second of the pixel envs against the bare simulators, and with 1 vs 2 processes.

One frame = one agent step (its action-repeated simulator steps) plus one 64 x 64 render. Rows per task:

* ``coworld.envs.make`` -- our env (default ``render_quality='standard'``);
* the bare simulator with its usual render call at default settings (dm_control ``physics.render``; Meta-World's
  gymnasium renderer, same camera view as ours), then with our settings (no MSAA, 512 shadow map), then the bare
  simulator drawn with ``mujoco.Renderer`` at our settings -- the drawing our env does, so the gap between that
  row and ours is the wrapper's own cost;
* ``make_vector`` with 1 env (in this process) and with 2 envs (2 worker processes), frames summed over envs.

RoboDesk has no bare-simulator rows (its package does not run on this stack: ``coworld/envs/robodesk.py``);
instead our env at ``render_quality`` 'full' (RoboDesk's own frames, pixel for pixel) and 'fast', and its
``simulate`` (the step without a frame), which shows what the drawing costs.

Two measures: wall-clock frames/s, and CPU milliseconds per frame of this process (all its threads, llvmpipe's
included) -- the second is what to compare on a machine shared with other work, where wall time swings with
their load. Worker processes' CPU is not visible from here, so vector rows give wall time only. Each number is
the best of ``--repeats`` rounds, rounds interleaved across rows.

Usage: ``python benchmarks/env_throughput.py [--steps 150] [--repeats 3] [--tasks walker_walk ...]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

SIZE = 64
TASKS = ("walker_walk", "cheetah_run", "mw_window_close", "robodesk_push_button", "toy_reach")
DMC = {"walker_walk": ("walker", "walk"), "cheetah_run": ("cheetah", "run")}


@dataclass
class Row:
    label: str
    step: Callable[[], np.ndarray]
    """One agent step; returns the frame(s) drawn."""
    close: Callable[[], None]
    frames_per_step: int = 1
    in_process: bool = True


def ours(name: str, quality: str = "standard") -> Row:
    from coworld.envs import make

    env = make(name, seed=0, render_quality=quality) if quality != "standard" else make(name, seed=0)
    env.reset()
    action = np.zeros(env.action_space.shape, np.float32)

    def step() -> np.ndarray:
        frame, _, _, truncated, _ = env.step(action)
        if truncated:
            env.reset()
        return frame

    label = "coworld.envs.make" if quality == "standard" else f"coworld.envs.make, render_quality={quality}"
    return Row(label, step, env.close)


def robodesk_simulate(name: str) -> Row:
    """The RoboDesk env's step without its frame (inverse kinematics and physics only)."""
    from coworld.envs import make

    env = make(name, seed=0)
    env.reset()
    sim = env.unwrapped
    action = np.zeros(env.action_space.shape, np.float32)
    frame = env.render()  # the reset's frame, returned so the blank-frame check passes; not redrawn

    def step() -> np.ndarray:
        if sim.simulate(action)[1]:
            sim.reset_state()
        return frame

    return Row("RoboDesk env.simulate, no frame", step, env.close)


def bare_dmc(domain: str, task: str, settings: str) -> Row:
    """dm_control suite env, action repeat 2, one render: 'default' / 'ours' (physics.render) or 'renderer'."""
    import mujoco
    from dm_control import suite

    env = suite.load(domain, task, task_kwargs={"random": 0})
    env.reset()
    physics = env.physics
    if settings != "default":
        physics.model.vis.quality.offsamples = 0
        physics.model.vis.quality.shadowsize = 512
    renderer = mujoco.Renderer(physics.model.ptr, SIZE, SIZE) if settings == "renderer" else None
    action = np.zeros(env.action_spec().shape)

    def step() -> np.ndarray:
        for _ in range(2):
            if env.step(action).last():
                env.reset()
        if renderer is None:
            return physics.render(SIZE, SIZE, camera_id=0)
        renderer.update_scene(physics.data.ptr, camera=0)
        return renderer.render()

    label = {
        "default": "bare dm_control + physics.render, default settings",
        "ours": "bare dm_control + physics.render, our settings",
        "renderer": "bare dm_control + mujoco.Renderer, our settings",
    }[settings]
    return Row(label, step, renderer.close if renderer else lambda: None)


def bare_metaworld(env_name: str, settings: str) -> Row:
    """Meta-World env stepped directly; its gymnasium renderer ('default' / 'ours') or 'renderer'."""
    import mujoco
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    from coworld.envs.meta_world import CAMERA, CAMERA_POS

    render_mode = None if settings == "renderer" else "rgb_array"
    env = ALL_V3_ENVIRONMENTS[env_name](render_mode=render_mode, camera_name=CAMERA, width=SIZE, height=SIZE)
    env._set_task_called = True
    env._freeze_rand_vec = False
    env.seed(0)
    env.reset()
    env.model.cam_pos[mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA)] = CAMERA_POS
    if settings != "default":
        env.model.vis.quality.offsamples = 0
        env.model.vis.quality.shadowsize = 512
    renderer = mujoco.Renderer(env.model, SIZE, SIZE) if settings == "renderer" else None
    action = np.zeros(4, np.float32)

    def step() -> np.ndarray:
        if env.step(action)[3]:
            env.reset()
        if renderer is not None:
            renderer.update_scene(env.data, camera=CAMERA)
            return renderer.render()
        viewer = env.mujoco_renderer.viewer
        if viewer is not None:  # gymnasium's viewer does not make its own context current (other rows' are)
            viewer.make_context_current()
        return env.render()

    label = {
        "default": "bare Meta-World + its renderer, default settings",
        "ours": "bare Meta-World + its renderer, our settings",
        "renderer": "bare Meta-World + mujoco.Renderer, our settings",
    }[settings]
    return Row(label, step, renderer.close if renderer else env.close)


def vector(name: str, num_envs: int) -> Row:
    from coworld.envs import make_vector

    envs = make_vector(name, num_envs, seed=0)
    envs.reset()
    actions = np.zeros(envs.action_space.shape, np.float32)
    label = "make_vector, 1 env (in process)" if num_envs == 1 else f"make_vector, {num_envs} envs (worker processes)"
    return Row(label, lambda: envs.step(actions)[0], envs.close, num_envs, in_process=num_envs == 1)


def rows_for(name: str) -> list[Row]:
    rows = [ours(name)]
    if name in DMC:
        rows += [bare_dmc(*DMC[name], settings) for settings in ("default", "ours", "renderer")]
    elif name.startswith("mw_"):
        rows += [bare_metaworld("window-close-v3", settings) for settings in ("default", "ours", "renderer")]
    elif name.startswith("robodesk_"):
        rows += [ours(name, "full"), ours(name, "fast"), robodesk_simulate(name)]
    return rows + [vector(name, 1), vector(name, 2)]


def measure(row: Row, steps: int) -> tuple[float, float]:
    """(frames per wall second, CPU ms of this process per frame) over ``steps`` agent steps."""
    for _ in range(5):  # warm-up: first renders allocate
        frame = row.step()
    if frame.std() < 5:
        raise RuntimeError(f"{row.label} draws blank frames")
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        row.step()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    frames = steps * row.frames_per_step
    return frames / wall, 1000 * cpu / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=150, help="timed agent steps per row and round (DMC)")
    parser.add_argument("--repeats", type=int, default=3, help="rounds; each row reports its best")
    parser.add_argument("--tasks", nargs="*", default=list(TASKS), choices=TASKS)
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    started = time.perf_counter()
    print(f"{platform.machine()}, {os.cpu_count()} CPUs, MUJOCO_GL={os.environ['MUJOCO_GL']}, ", end="")
    print(f"load average {os.getloadavg()[0]:.1f} at the start")
    print("\n| task | setup | frames/s (wall) | CPU ms / frame | CPU vs bare + mujoco.Renderer |")
    print("|---|---|---:|---:|---:|")
    for name in args.tasks:
        rows = rows_for(name)
        steps = {"toy": args.steps * 20, "mw": args.steps // 3, "robodesk": args.steps // 10}.get(  # ~equal time
            name.split("_")[0], args.steps
        )
        fps, cpu = [0.0] * len(rows), [float("inf")] * len(rows)
        for _ in range(args.repeats):
            for i, row in enumerate(rows):
                wall_fps, cpu_ms = measure(row, max(steps // row.frames_per_step, 1))
                fps[i], cpu[i] = max(fps[i], wall_fps), min(cpu[i], cpu_ms)
        reference = next((cpu[i] for i, row in enumerate(rows) if "mujoco.Renderer" in row.label), None)
        for row, wall_fps, cpu_ms in zip(rows, fps, cpu, strict=True):
            cpu_text = f"{cpu_ms:.2f}" if row.in_process else "-"
            ratio = f"{cpu_ms / reference:.2f}" if reference and row.in_process else "-"
            print(f"| {name} | {row.label} | {wall_fps:,.0f} | {cpu_text} | {ratio} |", flush=True)
        for row in rows:
            row.close()
    elapsed = time.perf_counter() - started
    print(f"\n({elapsed:.0f} s in all; load average {os.getloadavg()[0]:.1f} at the end)")


if __name__ == "__main__":
    main()
