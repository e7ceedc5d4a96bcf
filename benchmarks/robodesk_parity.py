"""Our RoboDesk env against the ``robodesk`` package itself: same state and actions -> same states, rewards, frames.

The package (1.0.0) does not import on this project's stack (see coworld/envs/robodesk.py's module and
docs/usage.md, "Tasks"), so this script installs nothing: point it at a folder where the package was unpacked
without its dependencies, and it stands in for the two things the package needs and the stack lacks (a ``gym``
module with ``Env`` and ``spaces``, Pillow's removed ``Image.ANTIALIAS``, which is ``Image.LANCZOS``)::

    python -m pip install --no-deps --target .deps robodesk==1.0.0
    MUJOCO_GL=egl .venv/bin/python benchmarks/robodesk_parity.py --package-dir .deps --steps 200

For each task: the package resets with NumPy's global seed, our env takes over its exact state, then both take the
same uniform random actions (the package drawing no frames on the way); printed are the largest differences of the
joint positions and of the step rewards, and the mean absolute pixel difference of the 64 x 64 frames at the end
(ours at ``render_quality='full'``, the package's own settings).
"""

from __future__ import annotations

import argparse
import os
import sys
import types

import numpy as np

from coworld.envs.robodesk import TASK_NAMES


def import_robodesk(package_dir: str) -> types.ModuleType:
    """``import robodesk`` from ``package_dir`` with stand-ins for ``gym`` and ``Image.ANTIALIAS``."""
    import gymnasium
    from PIL import Image

    gym = types.ModuleType("gym")
    gym.Env = object  # type: ignore[attr-defined]
    gym.spaces = gymnasium.spaces  # type: ignore[attr-defined]
    sys.modules.setdefault("gym", gym)
    if not hasattr(Image, "ANTIALIAS"):
        Image.ANTIALIAS = Image.LANCZOS  # type: ignore[attr-defined]
    sys.path.insert(0, package_dir)
    import robodesk

    return robodesk


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--package-dir", required=True, help="folder holding the unpacked robodesk package")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    from coworld.envs import make  # before the package: our builder picks the GL backend

    probe = make("robodesk_push_button", seed=0, image_size=8)
    probe.close()
    robodesk = import_robodesk(args.package_dir)
    print("| task | RoboDesk task | max joint-position difference | max reward difference | frame difference |")
    print("|---|---|---:|---:|---:|")
    for ours, theirs in TASK_NAMES.items():
        package = robodesk.RoboDesk(task=theirs, reward="dense")
        package._get_obs = lambda: None  # its steps draw no frame here (each would take a new full-quality camera)
        np.random.seed(args.seed)
        package.reset()
        env = make(ours, seed=0, render_quality="full")
        sim = env.unwrapped
        sim.reset_state(0)
        sim.physics.data.qpos[:] = package.physics.data.qpos
        sim.physics.data.qvel[:] = package.physics.data.qvel
        sim.physics.forward()
        sim._ik_physics.data.qpos[:] = sim.physics.data.qpos
        rng = np.random.default_rng(args.seed)
        qpos_gap = reward_gap = 0.0
        for _ in range(args.steps):
            action = rng.uniform(-1, 1, 5).astype(np.float32)
            _, theirs_reward, _, _ = package.step(action.astype(np.float64))
            ours_reward, _, _ = sim.simulate(action)
            qpos_gap = max(qpos_gap, float(np.abs(package.physics.data.qpos - sim.physics.data.qpos).max()))
            reward_gap = max(reward_gap, abs(theirs_reward - ours_reward))
        frame_gap = np.abs(sim._render().astype(int) - package.render()).mean()  # the package's frame of the state
        print(f"| {ours} | {theirs} | {qpos_gap:.1e} | {reward_gap:.1e} | {frame_gap:.2f} |", flush=True)
        env.close()


if __name__ == "__main__":
    main()
