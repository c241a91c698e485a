"""Meta-World episodes as data: a task, the seed of its initial state, the step limit. No
simulator import: configs and the validation dataset build them freely, and a typo fails before
Meta-World (or MuJoCo) is loaded.

The protocol is LeRobot's (huggingface/lerobot ``src/lerobot/envs/metaworld.py`` and
``docs/source/metaworld.mdx``, read at commit 7427f31):

- a task's env is built as ``MetaworldEnv._ensure_env`` builds it: ``metaworld.MT1(task,
  seed=42)``, its first train task set, then the object and goal placement drawn afresh from the
  env's seeded generator at every reset (``_freeze_rand_vec = False``, ``seeded_rand_vec = True``),
  so an episode's initial state is a function of its seed;
- at most 500 steps (``_max_episode_steps = 500``: Meta-World's ``max_path_length``); the episode
  ends at the first step whose ``info["success"]`` is set (``terminated = done or is_success``);
- 10 episodes per task ("Recommended evaluation episodes": 500 for MT50);
- one camera, ``corner2``, moved to ``cam_pos = [0.75, 0.075, 0.7]`` and turned upright (its
  frames come out rotated 180 degrees), 480x480 there; here the policy's data spec picks the size;
- the instruction is LeRobot's description of the task (``metaworld_config.json``
  ``TASK_DESCRIPTIONS``, the strings of its ``lerobot/metaworld_mt50`` dataset), kept below.

Task sets: ``metaworld_mt10`` (Meta-World's ``MT10_V3``), ``metaworld_mt50`` (all 50, in
Meta-World's ``ALL_V3_ENVIRONMENTS`` order) or one task (``reach-v3``). Evaluation seeds start at
``EVAL_SEED_START``; demos at ``capvector demos --seed`` (default 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from capvector.envs.base import EVAL_SEED_START
from capvector.errors import CapVectorError, unknown_name

SUITE_NAME = "metaworld"
ROBOT = "Sawyer"
MAX_STEPS = 500
"""LeRobot's ``MetaworldEnv._max_episode_steps`` (Meta-World's ``max_path_length``)."""
EVAL_EPISODES = 10
"""LeRobot's recommended episodes per task (``docs/source/metaworld.mdx``)."""
PROPRIO_KEYS = ("robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos")
"""The demo files' proprio keys: the names of robosuite's, so configs need no change."""
CAMERAS = ("corner2",)
"""LeRobot's one camera; the others of the model (topview, corner, ...) are not set up upright."""

# LeRobot's src/lerobot/envs/metaworld_config.json TASK_DESCRIPTIONS (Apache-2.0), in Meta-World's
# ALL_V3_ENVIRONMENTS order: the instruction of each task, as LeRobot's Meta-World env and its
# lerobot/metaworld_mt50 dataset give it.
INSTRUCTIONS: dict[str, str] = {
    "assembly-v3": "Pick up a nut and place it onto a peg",
    "basketball-v3": "Dunk the basketball into the basket",
    "bin-picking-v3": "Grasp the puck from one bin and place it into another bin",
    "box-close-v3": "Grasp the cover and close the box with it",
    "button-press-topdown-v3": "Press a button from the top",
    "button-press-topdown-wall-v3": "Bypass a wall and press a button from the top",
    "button-press-v3": "Press a button",
    "button-press-wall-v3": "Bypass a wall and press a button",
    "coffee-button-v3": "Push a button on the coffee machine",
    "coffee-pull-v3": "Pull a mug from a coffee machine",
    "coffee-push-v3": "Push a mug under a coffee machine",
    "dial-turn-v3": "Rotate a dial 180 degrees",
    "disassemble-v3": "Pick a nut out of a peg",
    "door-close-v3": "Close a door with a revolving joint",
    "door-lock-v3": "Lock the door by rotating the lock clockwise",
    "door-open-v3": "Open a door with a revolving joint",
    "door-unlock-v3": "Unlock the door by rotating the lock counter-clockwise",
    "hand-insert-v3": "Insert the gripper into a hole",
    "drawer-close-v3": "Push and close a drawer",
    "drawer-open-v3": "Open a drawer",
    "faucet-open-v3": "Rotate the faucet counter-clockwise",
    "faucet-close-v3": "Rotate the faucet clockwise",
    "hammer-v3": "Hammer a screw on the wall",
    "handle-press-side-v3": "Press a handle down sideways",
    "handle-press-v3": "Press a handle down",
    "handle-pull-side-v3": "Pull a handle up sideways",
    "handle-pull-v3": "Pull a handle up",
    "lever-pull-v3": "Pull a lever down 90 degrees",
    "pick-place-wall-v3": "Pick a puck, bypass a wall and place the puck",
    "pick-out-of-hole-v3": "Pick up a puck from a hole",
    "pick-place-v3": "Pick and place a puck to a goal",
    "plate-slide-v3": "Slide a plate into a cabinet",
    "plate-slide-side-v3": "Slide a plate into a cabinet sideways",
    "plate-slide-back-v3": "Get a plate from the cabinet",
    "plate-slide-back-side-v3": "Get a plate from the cabinet sideways",
    "peg-insert-side-v3": "Insert a peg sideways",
    "peg-unplug-side-v3": "Unplug a peg sideways",
    "soccer-v3": "Kick a soccer into the goal",
    "stick-push-v3": "Grasp a stick and push a box using the stick",
    "stick-pull-v3": "Grasp a stick and pull a box with the stick",
    "push-v3": "Push the puck to a goal",
    "push-wall-v3": "Bypass a wall and push a puck to a goal",
    "push-back-v3": "Push the puck to a goal",
    "reach-v3": "Reach a goal position",
    "reach-wall-v3": "Bypass a wall and reach a goal",
    "shelf-place-v3": "Pick and place a puck onto a shelf",
    "sweep-into-v3": "Sweep a puck into a hole",
    "sweep-v3": "Sweep a puck off the table",
    "window-open-v3": "Push and open a window",
    "window-close-v3": "Push and close a window",
}

MT10: tuple[str, ...] = (
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "peg-insert-side-v3",
    "window-open-v3",
    "window-close-v3",
)
"""Meta-World's ``env_dict.MT10_V3``, in its order."""

TASK_SETS: dict[str, tuple[str, ...]] = {
    "metaworld_mt10": MT10,
    "metaworld_mt50": tuple(INSTRUCTIONS),
    **{task: (task,) for task in INSTRUCTIONS},
}


@dataclass(frozen=True)
class MetaWorldEpisodeSpec:
    """One Meta-World episode: the task and the seed its object and goal placement is drawn from."""

    SUITE: ClassVar[str] = SUITE_NAME

    task: str
    seed: int
    max_steps: int | None = None
    """Step limit; None: the protocol's 500."""

    robot: ClassVar[str] = ROBOT  # every Meta-World scene has one Sawyer
    variant: ClassVar[str | None] = None

    @property
    def step_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else MAX_STEPS

    @property
    def instruction(self) -> str:
        return INSTRUCTIONS[self.task]

    def describe(self) -> dict[str, Any]:
        """Which episode it is, as JSON fields (``capvector evaluate --json``)."""
        return {"task": self.task, "seed": self.seed}


def task_set_tasks(task_set: str) -> tuple[str, ...]:
    """The tasks of ``task_set`` (``metaworld_mt10``, ``metaworld_mt50`` or one task)."""
    if task_set not in TASK_SETS:
        raise unknown_name("Meta-World task set", task_set, TASK_SETS)
    return TASK_SETS[task_set]


def metaworld_specs(
    task_set: str,
    episodes: int = EVAL_EPISODES,
    *,
    start_seed: int = EVAL_SEED_START,
    max_steps: int | None = None,
) -> list[MetaWorldEpisodeSpec]:
    """``episodes`` episodes of each task of ``task_set``, task by task, with the seeds
    ``start_seed .. start_seed + episodes - 1`` (the same placements seeds for every task)."""
    tasks = task_set_tasks(task_set)
    if episodes < 1:
        raise CapVectorError(f"episodes must be at least 1, not {episodes}")
    if max_steps is not None and not 1 <= max_steps <= MAX_STEPS:
        # Meta-World's env refuses to step past its max_path_length (500).
        raise CapVectorError(
            f"max_steps must be 1..{MAX_STEPS} (Meta-World's limit), not {max_steps}"
        )
    return [
        MetaWorldEpisodeSpec(task, start_seed + i, max_steps)
        for task in tasks
        for i in range(episodes)
    ]
