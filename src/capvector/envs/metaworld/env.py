"""A Meta-World task's env as the rollout loop and the demo recorder use it: built once (as
LeRobot builds it, :mod:`capvector.envs.metaworld.spec`), reset from a seed, stepped with our 7-D
actions, rendered by our :class:`~capvector.envs.robosuite.env.CameraRenderer`.

Actions. Meta-World's Sawyer takes 4 numbers (``SawyerXYZEnv.step``): a position delta of the
hand's mocap target, each of x, y, z in [-1, 1] times ``action_scale`` (1 cm), and a gripper
effort in [-1, 1] (the two finger actuators get ``[a, -a]``; +1 closes, as in our convention).
The hand's orientation is not controlled: every step resets the mocap quaternion to
``[1, 0, 1, 0]``. So our 7-D action (dx, dy, dz, drx, dry, drz, gripper) maps as
``[dx, dy, dz, gripper]``: the rotation dims are ignored (demos label them 0, and a policy's
values there change nothing), xyz keep Meta-World's units (1 = 1 cm per step; Meta-World clips
to [-1, 1]) and the gripper is passed through continuously, clipped to [-1, 1], not binarised as
robosuite's is: Meta-World's experts use intermediate efforts (0, 0.6, ...), and a binarised
0 would close a gripper the expert keeps half open.

Proprio (8,), as our other suites': the hand body's position (Meta-World's ``get_endeff_pos``),
its orientation as an axis-angle (constant up to contact wobble, kept for the shared schema) and
the two finger joints (``r_close``, ``l_close``).

Rendering: Meta-World's visible geoms are groups 0-2 (MuJoCo's default); group 4 holds collision
proxies. 35-45 ms a frame on llvmpipe for 64-224 px (67k mesh faces), in the same process.
"""

from __future__ import annotations

import os

# MuJoCo binds its GL backend at first import: EGL on our headless machines (as envs/robosuite).
os.environ.setdefault("MUJOCO_GL", "egl")

from collections.abc import Sequence  # noqa: E402

import numpy as np  # noqa: E402

from capvector.envs.metaworld.spec import (  # noqa: E402
    CAMERAS,
    INSTRUCTIONS,
    MAX_STEPS,
    PROPRIO_KEYS,
)
from capvector.errors import CapVectorError, MissingExtraError, unknown_name  # noqa: E402


def missing_metaworld(err: ImportError) -> MissingExtraError:
    """One line: what to install, the extra and Meta-World without its MuJoCo pin."""
    reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
    return MissingExtraError(
        "Meta-World needs the metaworld extra, and Meta-World without its mujoco==3.3.0 pin: "
        f"pip install 'capvector[metaworld]' && pip install --no-deps metaworld==3.1.1 ({reason})"
    )


try:
    import metaworld
except ImportError as err:
    raise missing_metaworld(err) from err

from capvector.envs.robosuite.env import CameraRenderer  # noqa: E402

MT1_SEED = 42
"""LeRobot's ``metaworld.MT1(task, seed=42)``: fixes the task data set on the env."""
CORNER2_POS = (0.75, 0.075, 0.7)
"""LeRobot moves ``corner2`` here (``MetaworldEnv._ensure_env``) so the scene fills the frame."""
UPSIDE_DOWN = frozenset({"corner2"})
"""Cameras whose frames come out rotated 180 degrees (LeRobot flips ``corner2``'s both axes)."""
GEOM_GROUPS = (0, 1, 2)


def to_env_action(action: np.ndarray) -> np.ndarray:
    """(7,) policy action -> Meta-World's (4,): xyz delta and gripper; rotation dims dropped."""
    out = np.empty(4, dtype=np.float64)
    out[:3] = action[:3]
    out[3] = np.clip(action[6], -1.0, 1.0)
    return out


def from_env_action(action: np.ndarray) -> np.ndarray:
    """Meta-World's (4,) action -> our (7,): no rotation (Meta-World controls none)."""
    out = np.zeros(7, dtype=np.float32)
    out[:3] = np.clip(action[:3], -1.0, 1.0)
    out[6] = np.clip(action[3], -1.0, 1.0)
    return out


def quat_to_axis_angle(wxyz: np.ndarray) -> np.ndarray:
    """MuJoCo's (w, x, y, z) quaternion as an axis-angle 3-vector (angle in [0, pi])."""
    q = np.asarray(wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    sin = np.linalg.norm(q[1:])
    if sin < 1e-12:
        return np.zeros(3)
    return q[1:] / sin * (2.0 * np.arctan2(sin, q[0]))


class MetaWorldEnv:
    """One Meta-World task (``reach-v3``, ...), reset from seeds, with ``cameras`` rendered at
    ``image_size`` (none: state only, as the experts need)."""

    def __init__(
        self, task: str, *, cameras: Sequence[str] = CAMERAS, image_size: int = 64
    ) -> None:
        if task not in INSTRUCTIONS:
            raise unknown_name("Meta-World task", task, INSTRUCTIONS)
        self.task = task
        self.instruction = INSTRUCTIONS[task]
        self.cameras = tuple(cameras)
        self.image_size = image_size
        # LeRobot's MetaworldEnv._ensure_env: the MT1 task data, then placements drawn from the
        # env's own seeded generator at each reset (env.seed(seed) before it).
        mt1 = metaworld.MT1(task, seed=MT1_SEED)
        env = mt1.train_classes[task]()
        env.set_task(mt1.train_tasks[0])
        env.reset()
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        self.env = env
        model = env.model
        model.cam_pos[model.camera("corner2").id] = CORNER2_POS
        self._fingers = [model.joint(j).qposadr[0] for j in ("r_close", "l_close")]
        self._renderer = (
            CameraRenderer(model, self.cameras, image_size, geom_groups=GEOM_GROUPS)
            if self.cameras
            else None
        )
        self.state = np.zeros(0)
        """Meta-World's (39,) state observation: what its scripted policies read."""
        self.steps = 0

    def reset(self, seed: int, max_steps: int = MAX_STEPS) -> np.ndarray:
        """The initial state of ``seed`` (a function of it alone); Meta-World's state obs."""
        self.env.seed(seed)
        self.env.max_path_length = max_steps
        self.state, _ = self.env.reset()
        self.steps = 0
        return self.state

    def step(self, action: np.ndarray) -> bool:
        """One step of our (7,) action; whether the task is solved after it."""
        self.state, _, _, _, info = self.env.step(to_env_action(action))
        self.steps += 1
        return bool(info["success"])

    def step_env(self, action: np.ndarray) -> bool:
        """One step of Meta-World's own (4,) action (the experts'); whether it is solved."""
        self.state, _, _, _, info = self.env.step(np.asarray(action, dtype=np.float64))
        self.steps += 1
        return bool(info["success"])

    @property
    def faulted(self) -> bool:
        """Meta-World caught a MuJoCo instability (it then freezes the observation)."""
        return bool(self.env._did_see_sim_exception)

    def proprio(self) -> np.ndarray:
        """(8,) float32: hand position, hand axis-angle, the two finger joints."""
        data = self.env.data
        hand = data.body("hand")
        fingers = data.qpos[self._fingers]
        return np.concatenate([hand.xpos, quat_to_axis_angle(hand.xquat), fingers]).astype(
            np.float32
        )

    def proprio_parts(self) -> dict[str, np.ndarray]:
        """The proprio as the demo files store it, under :data:`PROPRIO_KEYS`."""
        p = self.proprio()
        return dict(zip(PROPRIO_KEYS, (p[:3], p[3:6], p[6:8]), strict=True))

    def render(self) -> dict[str, np.ndarray]:
        """``{camera: (H, W, 3) uint8}`` upright."""
        if self._renderer is None:
            raise CapVectorError(f"the {self.task} env was built without cameras")
        images, _ = self._renderer.render(self.env.data)
        for cam in UPSIDE_DOWN.intersection(images):
            images[cam] = np.ascontiguousarray(images[cam][::-1, ::-1])
        return images

    def flat_state(self) -> np.ndarray:
        """[time, qpos, qvel] of the MuJoCo state, as our other demo files store it."""
        data = self.env.data
        return np.concatenate([[data.time], data.qpos, data.qvel])

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self.env.close()
