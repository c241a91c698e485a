"""The task table: which robosuite tasks the toolkit runs, their instructions, objects and step
limits. Imports nothing heavy, so episode specs and configs can name tasks without the simulator."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from capvector.errors import unknown_name


def _pick_place_can_target(env: Any) -> dict[str, np.ndarray]:
    # Centre of the can's compartment in the goal bin (robosuite PickPlace.target_bin_placements).
    return {"Can_target_pos": np.array(env.target_bin_placements[env.object_id], dtype=np.float64)}


@dataclass(frozen=True)
class TaskSpec:
    """A robosuite task as the toolkit uses it."""

    env_name: str
    instruction: str
    objects: Mapping[str, str]
    """Position key -> how the annotations name it, e.g. ``{"cube_pos": "red cube"}``."""
    orientations: tuple[str, ...]
    """robosuite observation keys of object quaternions (xyzw) kept in the observation."""
    max_steps: int
    """Rollout step limit: room above the expert's longest demo, as OFT sets LIBERO's limits."""
    camera_fovy: Mapping[str, float] = field(default_factory=dict)
    """Vertical field of view overrides (degrees), applied to the model before rendering."""
    extra_positions: Callable[[Any], dict[str, np.ndarray]] | None = None
    """Positions that are not robosuite observations (e.g. a goal), computed from the env."""


# Step limits: over 200 seeds (DART noise 0.1) the scripted expert's longest run to success is
# 57 steps for Lift, 133 for Stack and 209 for PickPlaceCan. OFT puts LIBERO's limits ~10% above
# the longest *human* demo; a scripted expert is faster and more direct than a learned policy,
# so these leave 2-2.6x room (Lift 150 and Stack 300 as in the feasibility study's evaluations).
# agentview fovy: at robosuite's 45 degrees Lift's cube covers ~35 px of a 64x64 image (its
# geom's pixels at reset); at 35 degrees ~63 px, and the gripper's whole path (start pose to lift
# height) stays in view. PickPlaceCan's two bins fill the default view already: it keeps 45.
TASKS: dict[str, TaskSpec] = {
    "Lift": TaskSpec(
        env_name="Lift",
        instruction="lift the red cube",
        objects={"cube_pos": "red cube"},
        orientations=("cube_quat",),
        max_steps=150,
        camera_fovy={"agentview": 35.0},
    ),
    "Stack": TaskSpec(
        env_name="Stack",
        instruction="stack the red cube on the green cube",
        objects={"cubeA_pos": "red cube", "cubeB_pos": "green cube"},
        orientations=("cubeA_quat", "cubeB_quat"),
        max_steps=300,
        camera_fovy={"agentview": 35.0},
    ),
    "PickPlaceCan": TaskSpec(
        env_name="PickPlaceCan",
        instruction="put the red can in its compartment of the dark bin",
        objects={"Can_pos": "red can", "Can_target_pos": "can's compartment"},
        orientations=("Can_quat",),
        max_steps=400,
        extra_positions=_pick_place_can_target,
    ),
}


def get_task(name: str) -> TaskSpec:
    """The :class:`TaskSpec` called ``name``, with the known names in the error."""
    try:
        return TASKS[name]
    except KeyError:
        raise unknown_name("task", name, TASKS) from None
