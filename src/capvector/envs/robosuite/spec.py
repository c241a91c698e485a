"""robosuite evaluation episodes as data: the task, the seed of its initial state, the arm and the
scene variant. No simulator import: configs and the validation dataset build them freely.

An episode's initial state is a function of its seed alone; evaluation seeds start at
``EVAL_SEED_START`` (1,000,000), far above the demos' (``capvector demos --seed``, default 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from capvector.envs.base import DEFAULT_ROBOT, EVAL_SEED_START
from capvector.envs.robosuite.tasks import get_task
from capvector.envs.robosuite.variants import get_variant


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode: the task, the seed of its initial state, the arm, the variant."""

    SUITE: ClassVar[str] = "robosuite"

    task: str
    seed: int
    robot: str = DEFAULT_ROBOT
    max_steps: int | None = None
    """Step limit; None uses the task's default (``TaskSpec.max_steps``)."""
    gripper: str | None = None
    """Gripper override for arms whose default gripper lacks 2 finger joints, e.g. PandaGripper."""
    variant: str | None = None
    """A visual scene variant (``capvector.envs.robosuite.variants``) drawn from the seed; None: as trained."""

    @property
    def step_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else get_task(self.task).max_steps

    def describe(self) -> dict[str, Any]:
        """Which episode it is, as JSON fields (``capvector evaluate --json``)."""
        return {"task": self.task, "robot": self.robot, "variant": self.variant, "seed": self.seed}


def eval_specs(
    task_set: str,
    episodes: int,
    *,
    robot: str = DEFAULT_ROBOT,
    start_seed: int = EVAL_SEED_START,
    max_steps: int | None = None,
    gripper: str | None = None,
    variant: str | None = None,
) -> list[EpisodeSpec]:
    """``episodes`` specs of the task ``task_set`` with consecutive seeds from ``start_seed``
    (disjoint from demo seeds): the robosuite suite's ``specs``.

    A variant that swaps the arm (``sawyer``, ``ur5e``) sets ``robot``/``gripper``; a visual one
    is kept on the spec and applied after each reset.
    """
    get_task(task_set)
    visual = None
    if variant is not None:
        v = get_variant(variant)
        robot, gripper = v.robot or robot, v.gripper if v.robot else gripper
        visual = variant if v.visual else None
    return [
        EpisodeSpec(task_set, start_seed + i, robot, max_steps, gripper, visual)
        for i in range(episodes)
    ]
