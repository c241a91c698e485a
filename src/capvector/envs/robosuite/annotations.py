"""Per-step text: what the scripted expert is doing and where the objects are.

These sentences are the targets of the multimodal-reasoning objective, so they only state what
the simulator knows for certain: the expert's phase, object positions in metres (robot base frame
= world frame for robosuite's fixed-base arms, table centre at x=y=0) and each object's offset from
the gripper in whole centimetres. Directions are the robot's own: "in front of" is +x (away from
the robot's base), "left of" is +y (the robot's left), "above" is +z.

Example (Lift)::

    The robot is moving above the red cube. The red cube is at x=0.02, y=-0.01 on the table,
    3 cm to the left of, 12 cm in front of and 18 cm below the gripper.

LIBERO scenes (:class:`capvector.envs.libero.annotations.LiberoAnnotator`) get the same sentences for every movable object of the
scene, positions in LIBERO's world frame (table centre at x=y=0, the robot's base at x=-0.66,
facing +x, so the directions are the robot's too), and what an object stands on by LIBERO's own
``On`` predicate (``ObjectState.check_ontop``, the one its goals are checked with)::

    The robot is carrying the akita black bowl 1 over the plate. The akita black bowl 1 is in the
    gripper at x=0.02, y=0.20, 9 cm above where it started. The plate is at x=0.05, y=0.21 on the
    table, 3 cm to the left of, 3 cm in front of and 20 cm below the gripper. ...
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from capvector.envs.robosuite.experts import ExpertAction
from capvector.envs.robosuite.tasks import TaskSpec

# Where a place task puts its object: (position key, "onto ..." phrase, "over ..." phrase).
_GOALS: dict[str, tuple[str, str, str]] = {
    "Stack": ("cubeB_pos", "onto the green cube", "over the green cube"),
    "PickPlaceCan": ("Can_target_pos", "into its compartment", "over its compartment"),
}
_SURFACES = {"PickPlaceCan": "in the bin"}  # what an object at rest stands on; default table
_HELD_PHASES = ("lift", "carry", "lower")
_STATIC_SUFFIX = "_target_pos"  # goal markers: positions that never move, no "on the table"


def _cm(metres: float) -> int:
    return round(abs(metres) * 100)


def _num(value: float) -> str:
    # round first so that -0.001 prints as 0.00, not -0.00
    return f"{round(float(value), 2) + 0.0:.2f}"


def _offset_phrase(obj: np.ndarray, eef: np.ndarray) -> str:
    dx, dy, dz = (obj - eef).tolist()
    parts = []
    if _cm(dy):
        parts.append(f"{_cm(dy)} cm to the {'left' if dy > 0 else 'right'} of")
    if _cm(dx):
        parts.append(f"{_cm(dx)} cm {'in front of' if dx > 0 else 'behind'}")
    if _cm(dz):
        parts.append(f"{_cm(dz)} cm {'above' if dz > 0 else 'below'}")
    if not parts:
        return "right at the gripper"
    if len(parts) == 1:
        return f"{parts[0]} the gripper"
    return f"{', '.join(parts[:-1])} and {parts[-1]} the gripper"


def _doing(phase: str, obj: str, onto: str, over: str) -> str:
    """The sentence for the expert's ``phase`` (:mod:`capvector.envs.robosuite.experts`' phase machine)."""
    text = {
        "approach": f"moving above the {obj}",
        "descend": f"lowering the open gripper around the {obj}",
        "grasp": f"closing the gripper on the {obj}",
        "lift": f"lifting the {obj}",
        "carry": f"carrying the {obj} {over}",
        "lower": f"lowering the {obj} {onto}",
        "release": f"opening the gripper to release the {obj}",
        "retreat": "moving the open gripper up and away",
    }[phase]
    return f"The robot is {text}."


class Annotator:
    """Turns (expert step, observation) into a sentence; call :meth:`reset` at each episode start."""

    def __init__(self, task: str, spec: TaskSpec) -> None:
        self.task = task
        self.spec = spec
        self._rest_z: dict[str, float] = {}

    def reset(self, obs: Mapping[str, np.ndarray]) -> None:
        # Objects start at rest on the table/bin floor; "on the table" means near that height.
        self._rest_z = {key: float(obs[key][2]) for key in self.spec.objects}

    def __call__(self, step: ExpertAction, obs: Mapping[str, np.ndarray]) -> str:
        return f"{self._doing(step)} {self._scene(step, obs)}"

    def _doing(self, step: ExpertAction) -> str:
        _, onto, over = _GOALS.get(self.task, ("", "", ""))
        return _doing(step.phase, self.spec.objects[step.target], onto, over)

    def _scene(self, step: ExpertAction, obs: Mapping[str, np.ndarray]) -> str:
        eef = obs["robot0_eef_pos"]
        sentences = []
        for key, name in self.spec.objects.items():
            pos = obs[key]
            where = f"x={_num(pos[0])}, y={_num(pos[1])}"
            if key.endswith(_STATIC_SUFFIX):
                sentences.append(f"The {name} is at {where}.")
                continue
            height = _cm(pos[2] - self._rest_z[key])
            if key == step.target and step.phase in _HELD_PHASES:
                text = f"is in the gripper at {where}, {height} cm above where it started"
            elif pos[2] - self._rest_z[key] < 0.01:
                surface = _SURFACES.get(self.task, "on the table")
                text = f"is at {where} {surface}, {_offset_phrase(pos, eef)}"
            else:
                text = f"is at {where}, {height} cm up, {_offset_phrase(pos, eef)}"
            sentences.append(f"The {name} {text}.")
        return " ".join(sentences)
