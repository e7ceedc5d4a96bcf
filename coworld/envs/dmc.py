"""DeepMind Control walker and cheetah tasks, plain and modified (slopes, disabled actuators), as pixel envs.

Each task is built from ``dm_control.suite.<domain>.get_model_and_assets()`` with the XML edited in memory
(nothing is written into site-packages) and reuses dm_control's own task classes (``walker.PlanarWalker`` with
move speed 1, ``cheetah.Cheetah``) and ``control.Environment`` on a ``Physics`` built from the edited XML.

Modifications:

* **slope** (``*_uphill`` / ``*_downhill``, 15 degrees): the floor stays flat and gravity is rotated by the
  slope angle about the y axis, which gives exactly the dynamics of a tilted floor (``9.81 sin 15 = 2.54`` m/s^2
  along the floor, ``9.47`` into it). The tracking camera and the light are rotated by the same angle, so the
  frames show a tilted floor with gravity pointing down the image. The floor is drawn 1 km each way
  (:data:`FLOOR_HALF_LENGTH`), so a body sliding down the slope stays on visible ground. Rewards are
  dm_control's, measured in the floor frame: speed along the slope, torso height above the slope, uprightness
  relative to the slope normal.
* **disabled actuators** (``walker_nofoot``: right ankle; ``cheetah_nopaw``: front thigh, shin and foot):
  ``gear="0"`` on their motors. The action size is unchanged; those action entries have no effect.

Episodes: 1000 control steps (walker: 25 s at 40 Hz; cheetah: 10 s at 100 Hz), i.e. 500 agent steps at the
default action repeat of 2. The reward of an agent step is the sum of the rewards of its repeated control
steps, so an episode's return is at most 1000 whatever the action repeat. The tasks never terminate; they
truncate at the episode length.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from coworld.envs.base import PixelEnv
from coworld.envs.render import FrameRenderer, ensure_gl_backend

if TYPE_CHECKING:
    from dm_control.mujoco import Physics

    from coworld.envs.spec import EnvSettings, TaskSpec

SLOPE_DEGREES = 15.0
"""Incline of the paper's uphill / downhill tasks."""

GRAVITY = 9.81
"""MuJoCo's default gravity magnitude, m/s^2."""

FLOOR_HALF_LENGTH = 1000.0
"""Half-length (m) of the drawn floor on the slope tasks, centred on the start. dm_control draws the walker's floor
over x in [-2, 498] and the cheetah's over [-2, 198]; on an uphill the body slides back past x = -2 (a random
walker reaches x = -17.8 in one episode), and the frames would show it in an empty sky. Collisions are unchanged:
a MuJoCo plane is infinite for contacts, its size only sets what is drawn."""

_SUB_STEPS = {"walker": 10, "cheetah": 1}
"""Physics steps per control step, as in ``dm_control.suite`` (walker 0.025 s control step, cheetah 0.01 s)."""


@dataclass(frozen=True)
class DMCVariant:
    """How one DMC task is built."""

    domain: Literal["walker", "cheetah"]
    slope_degrees: float = 0.0
    """Incline the body moves along: positive is uphill (moving forward, +x, climbs), negative downhill."""
    disabled_actuators: tuple[str, ...] = ()
    """Motors whose gear is set to 0 (their actions do nothing)."""


VARIANTS: dict[str, DMCVariant] = {
    "walker_walk": DMCVariant("walker"),
    "walker_downhill": DMCVariant("walker", slope_degrees=-SLOPE_DEGREES),
    "walker_uphill": DMCVariant("walker", slope_degrees=SLOPE_DEGREES),
    "walker_nofoot": DMCVariant("walker", disabled_actuators=("right_ankle",)),
    "cheetah_run": DMCVariant("cheetah"),
    "cheetah_downhill": DMCVariant("cheetah", slope_degrees=-SLOPE_DEGREES),
    "cheetah_uphill": DMCVariant("cheetah", slope_degrees=SLOPE_DEGREES),
    "cheetah_nopaw": DMCVariant("cheetah", disabled_actuators=("fthigh", "fshin", "ffoot")),
}


def model_xml(variant: DMCVariant) -> tuple[str, dict[str, bytes]]:
    """The domain's XML with the variant's edits applied, and its assets (for ``Physics.from_xml_string``)."""
    from dm_control.suite import cheetah, walker

    xml, assets = (walker if variant.domain == "walker" else cheetah).get_model_and_assets()
    text = xml.decode() if isinstance(xml, bytes) else xml
    if not variant.slope_degrees and not variant.disabled_actuators:
        return text, assets
    root = ET.fromstring(text)
    for name in variant.disabled_actuators:
        motor = root.find(f"./actuator/motor[@name='{name}']")
        if motor is None:
            raise ValueError(f"{variant.domain} has no motor named {name!r}")
        motor.set("gear", "0")
    if variant.slope_degrees:
        _tilt(root, text, assets, math.radians(variant.slope_degrees))
        _extend_floor(root)
    return ET.tostring(root, encoding="unicode"), assets


def _extend_floor(root: ET.Element) -> None:
    """Draw the floor plane over ``[-FLOOR_HALF_LENGTH, FLOOR_HALF_LENGTH]`` along x (see the constant)."""
    floor = root.find(".//worldbody/geom[@type='plane']")
    assert floor is not None, "the domain has no floor plane"
    _, half_width, grid = floor.get("size", "1 1 1").split()
    floor.set("pos", "0 0 0")
    floor.set("size", f"{FLOOR_HALF_LENGTH:g} {half_width} {grid}")


def _tilt(root: ET.Element, text: str, assets: dict[str, bytes], angle: float) -> None:
    """Rotate gravity by ``angle`` about +y (positive: uphill), and the tracking camera and lights with it.

    The camera and lights are turned by the rotation that maps the real "up" (against the rotated gravity)
    onto +z, seen from the simulator's frame; their placement is read from the compiled unedited model.
    """
    import mujoco

    option = root.find("option")
    if option is None:
        option = ET.SubElement(root, "option")
    option.set("gravity", _fmt((-GRAVITY * math.sin(angle), 0.0, -GRAVITY * math.cos(angle))))

    model = mujoco.MjModel.from_xml_string(text, assets)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    turn = np.array([math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0])  # rotation by `angle` about +y

    camera = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, 0)  # the tracking camera the tasks render
    element = root.find(f".//camera[@name='{camera}']")
    assert element is not None, camera
    body_quat = data.xquat[model.cam_bodyid[0]]
    for attribute in ("quat", "euler", "axisangle", "xyaxes", "zaxis"):
        element.attrib.pop(attribute, None)
    element.set("pos", _fmt(_rotate_in_body(turn, body_quat, model.cam_pos[0])))
    element.set("quat", _fmt(_turn_in_body(turn, body_quat, model.cam_quat[0])))

    for light_id in range(model.nlight):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_LIGHT, light_id)
        element = root.find(f".//light[@name='{name}']")
        assert element is not None, name
        body_quat = data.xquat[model.light_bodyid[light_id]]
        element.set("pos", _fmt(_rotate_in_body(turn, body_quat, model.light_pos[light_id])))
        element.set("dir", _fmt(_rotate_in_body(turn, body_quat, model.light_dir[light_id])))


def _rotate_in_body(turn: np.ndarray, body_quat: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """Apply the world rotation ``turn`` to a vector given in a body frame (orientation ``body_quat``)."""
    import mujoco

    local_turn = _turn_in_body(turn, body_quat, np.array([1.0, 0.0, 0.0, 0.0]))
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.asarray(vector, float), local_turn)
    return out


def _turn_in_body(turn: np.ndarray, body_quat: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Local orientation after turning by the world rotation ``turn``: ``body^-1 * turn * body * quat``."""
    import mujoco

    inverse, tmp, local, out = np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4)
    mujoco.mju_negQuat(inverse, body_quat)
    mujoco.mju_mulQuat(tmp, inverse, turn)
    mujoco.mju_mulQuat(local, tmp, body_quat)
    mujoco.mju_mulQuat(out, local, np.asarray(quat, float))
    return out


def _fmt(values: Any) -> str:
    return " ".join(f"{float(v):.9g}" for v in values)


class DMCEnv(PixelEnv):
    """A DMC walker or cheetah task seen through its tracking camera (camera 0).

    Observation: ``(S, S, 3)`` uint8 RGB frame after the step (``S`` = ``image_size``). Action: ``(6,)`` float32
    in [-1, 1], held for ``action_repeat`` control steps. Reward: sum over those control steps. Never terminates;
    truncates after ``episode_length`` agent steps.

    Attributes:
        physics: the dm_control ``Physics`` (read states such as ``physics.named.data.qpos['rootx']``).
        task: the :class:`~coworld.envs.registry.TaskSpec`; ``settings``: the resolved overrides.
    """

    def __init__(self, task: TaskSpec, settings: EnvSettings, *, seed: int, variant: DMCVariant) -> None:
        ensure_gl_backend()
        from dm_control.rl import control
        from dm_control.suite import cheetah, walker

        super().__init__(task, settings, task.action_size, seed)
        xml, assets = model_xml(variant)
        if variant.domain == "walker":
            physics: Physics = walker.Physics.from_xml_string(xml, assets)
            dm_task: Any = walker.PlanarWalker(move_speed=1.0, random=seed)  # walker-walk's speed
        else:
            physics = cheetah.Physics.from_xml_string(xml, assets)
            dm_task = cheetah.Cheetah(random=seed)
        self._dm_task = dm_task
        self._env = control.Environment(physics, dm_task, n_sub_steps=_SUB_STEPS[variant.domain])
        # Frames per second of simulated time, one frame per agent step (walker 20, cheetah 50).
        self.metadata = {**self.metadata, "render_fps": 1.0 / (self._env.control_timestep() * settings.action_repeat)}
        size = settings.image_size
        self._renderer = FrameRenderer(physics.model.ptr, camera=0, size=size, quality=settings.render_quality)

    @property
    def physics(self) -> Physics:
        return self._env.physics

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode, its initial state drawn from the episode's seed (:class:`~coworld.envs.base.PixelEnv`)."""
        seed = self._episode_seed(seed)
        super().reset(seed=seed)
        self._dm_task.random.seed(seed)
        self._env.reset()
        self._start_episode()
        self._frame = self._renderer.render(self.physics.data.ptr)
        return self._frame, {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        action = self._checked(action)
        reward = 0.0
        for _ in range(self.settings.action_repeat):
            reward += self._env.step(action).reward
        truncated = self._count_step()
        self._frame = self._renderer.render(self.physics.data.ptr)
        return self._frame, reward, False, truncated, {}

    def close(self) -> None:
        self._renderer.close()


def make_dmc(task: TaskSpec, settings: EnvSettings, seed: int) -> DMCEnv:
    """Build the DMC task ``task.name``."""
    return DMCEnv(task, settings, seed=seed, variant=VARIANTS[task.name])


__all__ = ["DMCEnv", "DMCVariant", "SLOPE_DEGREES", "VARIANTS", "make_dmc", "model_xml"]
