"""Scripted experts: small phase machines over the low-dim state of a :class:`SimEnv`.

Every expert outputs the same 7-d OSC_POSE delta action on any arm: the translation is
``clip(10 * (target - eef), -1, 1)`` (one unit = 5 cm per step, so a 1 cm error gives 5 mm), the
rotation holds the gripper at its orientation at reset (robosuite's delta OSC otherwise lets it
drift), and the gripper is -1 (open) or +1 (close). Recipe from the feasibility study
(``research/toy_benchmark_feasibility.md`` §1), plus three things that took Stack and
PickPlaceCan from ~93% to 100%: the grasp yaw is chosen per task (Stack closes on two faces of
the red cube with no finger towards the green one; the can is gripped with the fingers along x,
away from the bin's side walls); a descent that drifts off the object or stalls goes back up and
lines up again; and an object that slips out of the gripper sends the expert back to approach.

The phase names are a shared vocabulary that :mod:`capvector.envs.robosuite.annotations` turns into text.

Measured success (DART noise 0.1, seeds 0..N-1, success = the env's own ``_check_success``,
still true 6 steps later; robosuite 1.5.2, mujoco 3.9.0)::

    task          arm (gripper)           success   steps to success: mean / max
    Lift          Panda                   200/200   46 / 57
    Stack         Panda                   200/200   109 / 133
    PickPlaceCan  Panda                   200/200   163 / 209
    Lift          IIWA (PandaGripper)     200/200   45 / 57
    Lift          Sawyer (RethinkGripper) 200/200   51 / 124   (needs envs.MODEL_FIXES)
    Lift          UR5e (PandaGripper)     100/100   55 / 66
    Lift          Kinova3 (PandaGripper)  100/100   51 / 60
    Lift          Jaco (PandaGripper)     100/100   52 / 59
    Stack         IIWA (PandaGripper)      50/50    104 / 124
    PickPlaceCan  IIWA (PandaGripper)      50/50    186 / 271

Reproduce with ``python -m capvector.envs.robosuite.demos --task Lift --episodes 200 --out lift.hdf5
--cameras`` (low-dim only; images do not change the physics) and read the printed success.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from capvector.envs.robosuite.env import SimEnv
from capvector.errors import missing_extra

try:
    from robosuite.utils import transform_utils as T
except ImportError as err:
    raise missing_extra("the simulator", "sim", err) from err

GRIPPER_OPEN = -1.0
GRIPPER_CLOSED = 1.0

PHASES = ("approach", "descend", "grasp", "lift", "carry", "lower", "release", "retreat")
"""What an expert may be doing; :attr:`ExpertAction.phase` is one of these."""


@dataclass(frozen=True)
class ExpertAction:
    action: np.ndarray
    """(7,) float64: clean action (no exploration noise), gripper -1 open / +1 closed."""
    phase: str
    target: str
    """Key of the object the phase is about, e.g. ``"cube_pos"`` (a key of ``TaskSpec.objects``)."""


def _translate(eef: np.ndarray, target: np.ndarray, gain: float = 10.0) -> np.ndarray:
    return np.clip(gain * (target - eef), -1.0, 1.0)


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _yaw(quat_xyzw: np.ndarray) -> float:
    """Heading of the body's x axis in the world xy plane."""
    rot = T.quat2mat(quat_xyzw)
    return math.atan2(rot[1, 0], rot[0, 0])


class ScriptedExpert(ABC):
    """Base class: orientation hold, gripper bookkeeping and the grasp-an-object phases.

    Subclasses implement :meth:`_after_grasp` (what to do once the object is in the hand) and set
    ``obj`` (the key of the object to grasp).
    """

    obj: str = ""
    approach_height = 0.08
    grasp_offset = -0.005
    grasp_steps = 8
    descend_steps = 30
    release_steps = 6

    def __init__(self, sim: SimEnv) -> None:
        self.sim = sim
        self.reset()

    def reset(self) -> None:
        """Start a new episode from the env's current (just reset) state."""
        obs = self.sim.observation
        self._hold: np.ndarray | None = None
        self._rot0 = T.quat2mat(obs["robot0_eef_quat"])
        axis = self.sim.finger_axis()
        self._axis0 = math.atan2(axis[1], axis[0])
        self._restart(obs)

    def _restart(self, obs: Mapping[str, np.ndarray]) -> None:
        """(Re)start from the approach phase, with a grasp yaw chosen for the current scene."""
        self._enter("approach")
        want = self._finger_direction(obs)
        if want is None:
            self._ref_rot = self._rot0
            return
        # Two fingers: a yaw and the same yaw + 180 degrees grasp alike; turn by at most 90.
        delta = (want - self._axis0 + math.pi / 2) % math.pi - math.pi / 2
        self._ref_rot = _rot_z(delta) @ self._rot0

    def _finger_direction(self, obs: Mapping[str, np.ndarray]) -> float | None:
        """World xy heading the fingers should close along, or None to keep the reset yaw."""
        return None

    def _rotation_error(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        rot = T.quat2mat(obs["robot0_eef_quat"])
        # World-frame rotation taking the current orientation to the reference one; robosuite's
        # OSC applies a delta d as R_goal = R(d) @ R_now (controllers/parts/arm/osc.py).
        return np.asarray(T.quat2axisangle(T.mat2quat(self._ref_rot @ rot.T)))

    def act(self, obs: Mapping[str, np.ndarray]) -> ExpertAction:
        eef = obs["robot0_eef_pos"]
        obj = obs[self.obj]
        if self.phase == "approach":
            target = obj + np.array([0.0, 0.0, self.approach_height])
            err = target - eef
            aligned = np.linalg.norm(self._rotation_error(obs)) < 0.1
            if np.linalg.norm(err[:2]) < 0.01 and abs(err[2]) < 0.02 and aligned:
                self._enter("descend")
            return self._act(obs, target, GRIPPER_OPEN, self.obj)
        if self.phase == "descend":
            target = obj + np.array([0.0, 0.0, self.grasp_offset])
            self._count += 1
            # Drifted off the object (noise, or a finger caught on an edge) or stuck on something:
            # go back up and line up again rather than press down off-centre.
            if np.linalg.norm((target - eef)[:2]) > 0.015 or self._count > self.descend_steps:
                self._restart(obs)
                return self.act(obs)
            if np.linalg.norm(target - eef) < 0.01:
                self._enter("grasp")
                self._hold = target
            return self._act(obs, target, GRIPPER_OPEN, self.obj)
        if self.phase == "grasp":
            self._count += 1
            if self._count >= self.grasp_steps:
                self._enter("lift")
                self._hold = eef.copy()
            assert self._hold is not None
            return self._act(obs, self._hold, GRIPPER_CLOSED, self.obj)
        return self._after_grasp(obs)

    @abstractmethod
    def _after_grasp(self, obs: Mapping[str, np.ndarray]) -> ExpertAction:
        """The action once the object is in the hand."""

    def _holding(self, obs: Mapping[str, np.ndarray], max_gap: float = 0.04) -> bool:
        # The object travels with the gripper: slip shows up as a growing eef-object distance.
        return bool(np.linalg.norm(obs[self.obj] - obs["robot0_eef_pos"]) < max_gap)

    def _enter(self, phase: str) -> None:
        self.phase = phase
        self._count = 0

    def _act(
        self, obs: Mapping[str, np.ndarray], target: np.ndarray, gripper: float, about: str
    ) -> ExpertAction:
        # One rotation unit is 0.5 rad per step: this closes the error in about two steps.
        drot = np.clip(self._rotation_error(obs) / 0.5, -1.0, 1.0)
        action = np.concatenate([_translate(obs["robot0_eef_pos"], target), drot, [gripper]])
        return ExpertAction(action=action, phase=self.phase, target=about)


class LiftExpert(ScriptedExpert):
    """Grasp the cube, then raise the gripper to z = 1.05 m (success: cube 4 cm above the table)."""

    obj = "cube_pos"
    lift_z = 1.05

    def _after_grasp(self, obs: Mapping[str, np.ndarray]) -> ExpertAction:
        assert self._hold is not None
        if not self._holding(obs):
            self._restart(obs)
            return self.act(obs)
        target = np.array([self._hold[0], self._hold[1], self.lift_z])
        return self._act(obs, target, GRIPPER_CLOSED, self.obj)


class _PlaceExpert(ScriptedExpert):
    """Grasp ``obj``, lift, carry it over ``goal``, lower it to ``place_height`` above, release."""

    carry_clearance = 0.12
    place_tolerance = 0.008
    place_with_reset_yaw = False
    """Turn the gripper back to its reset yaw once the object is lifted (before carrying)."""

    @abstractmethod
    def _goal(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Where the held object's position should be when it is released."""

    def _carry_z(self, obs: Mapping[str, np.ndarray]) -> float:
        return float(self._goal(obs)[2] + self.carry_clearance)

    def _after_grasp(self, obs: Mapping[str, np.ndarray]) -> ExpertAction:
        eef, obj = obs["robot0_eef_pos"], obs[self.obj]
        goal = self._goal(obs)
        if self.phase in ("lift", "carry", "lower") and not self._holding(obs):
            self._restart(obs)
            return self.act(obs)
        # While held, move the gripper so that the *object* reaches its target: this absorbs
        # wherever in the fingers the object ended up.
        grip_offset = eef - obj
        if self.phase == "lift":
            target = np.array([eef[0], eef[1], self._carry_z(obs) + grip_offset[2]])
            if obj[2] > self._carry_z(obs) - 0.03:
                self._enter("carry")
                if self.place_with_reset_yaw:
                    self._ref_rot = self._rot0
            return self._act(obs, target, GRIPPER_CLOSED, self.obj)
        if self.phase == "carry":
            target = np.array([goal[0], goal[1], self._carry_z(obs)]) + grip_offset
            if np.linalg.norm(goal[:2] - obj[:2]) < self.place_tolerance:
                self._enter("lower")
            return self._act(obs, target, GRIPPER_CLOSED, self.obj)
        if self.phase == "lower":
            target = goal + grip_offset
            err = goal - obj
            if abs(err[2]) < self.place_tolerance and np.linalg.norm(err[:2]) < 0.015:
                self._enter("release")
                self._hold = eef.copy()
            return self._act(obs, target, GRIPPER_CLOSED, self.obj)
        if self.phase == "release":
            self._count += 1
            if self._count >= self.release_steps:
                self._enter("retreat")
            assert self._hold is not None
            return self._act(obs, self._hold, GRIPPER_OPEN, self.obj)
        # retreat: straight up, gripper open
        assert self._hold is not None
        target = np.array([self._hold[0], self._hold[1], self._carry_z(obs) + 0.03])
        return self._act(obs, target, GRIPPER_OPEN, self.obj)


class StackExpert(_PlaceExpert):
    """Put cubeA (red, 4 cm) on cubeB (green, 5 cm): centres 4.5 cm apart when stacked."""

    obj = "cubeA_pos"

    def _finger_direction(self, obs: Mapping[str, np.ndarray]) -> float | None:
        # Close on two faces of cubeA (not its corners), choosing the pair of faces whose normal
        # is most perpendicular to the direction of cubeB, so no finger lands on cubeB.
        faces = _yaw(obs["cubeA_quat"])
        to_b = obs["cubeB_pos"] - obs["cubeA_pos"]
        towards = math.atan2(to_b[1], to_b[0])
        return max((faces, faces + math.pi / 2), key=lambda a: abs(math.sin(a - towards)))

    def _goal(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        return obs["cubeB_pos"] + np.array([0.0, 0.0, 0.047])


class PickPlaceCanExpert(_PlaceExpert):
    """Carry the can into its compartment of the goal bin and let go a few cm above the floor.

    The compartment centre is at the edge of the Panda's reach (~0.79 m from the base in xy with
    the hand pointing down), so the expert aims 5-6 cm from the centre towards the robot (the
    success test only needs the can inside the compartment).
    """

    obj = "Can_pos"
    approach_height = 0.10
    # The can is 10 cm tall with its origin 4 cm below the top; the Panda's palm meets the top
    # when the fingertips are ~3 cm below it, so grasp 2.5 cm below the top.
    grasp_offset = 0.015
    carry_clearance = 0.15
    # Fingers along y again for the place: the goal compartment's dividers are 2 cm from the
    # fingers that way, and the arm's reach there is tight with the wrist turned.
    place_with_reset_yaw = True

    def _finger_direction(self, obs: Mapping[str, np.ndarray]) -> float | None:
        # The can may stand 2.5 cm from the bin's side walls (y) but 7.5 cm from its front and
        # back walls (x): fingers closing along x never hit a wall.
        return 0.0

    def _goal(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        centre = obs["Can_target_pos"]
        # Compartment = centre ± (0.0975, 0.1225); the can's body origin rests 6 cm above the floor.
        return np.array([centre[0] - 0.05, centre[1] - 0.06, centre[2] + 0.08])


EXPERTS: dict[str, type[ScriptedExpert]] = {
    "Lift": LiftExpert,
    "Stack": StackExpert,
    "PickPlaceCan": PickPlaceCanExpert,
}


def make_expert(sim: SimEnv) -> ScriptedExpert:
    """The scripted expert for ``sim``'s task."""
    try:
        cls = EXPERTS[sim.task]
    except KeyError:
        raise KeyError(
            f"no scripted expert for {sim.task!r}; experts exist for {', '.join(EXPERTS)}"
        ) from None
    return cls(sim)
