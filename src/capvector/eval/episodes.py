"""Evaluation episodes as data: which task, arm, seed and scene variant. No simulator imports.

Seeds: an episode's initial state is a function of its seed alone. Evaluation seeds must not be
seeds a training demo used; demos start at ``--seed`` (default 0), evaluation at
``EVAL_SEED_START`` = 1,000,000, and the λ sweep's validation episodes at
``VALIDATION_SEED_START`` = 2,000,000, so choosing λ never looks at the reported episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

from capvector.sim.tasks import get_task
from capvector.sim.variants import get_variant

EVAL_SEED_START = 1_000_000
"""First default evaluation seed; keep demo seeds below it."""
VALIDATION_SEED_START = 2_000_000
"""First λ-sweep seed: disjoint from demo seeds and from evaluation seeds."""
DEFAULT_ROBOT = "Panda"


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode: the task, the seed of its initial state, the arm, the variant."""

    task: str
    seed: int
    robot: str = DEFAULT_ROBOT
    max_steps: int | None = None
    """Step limit; None uses the task's default (``TaskSpec.max_steps``)."""
    gripper: str | None = None
    """Gripper override for arms whose default gripper lacks 2 finger joints, e.g. PandaGripper."""
    variant: str | None = None
    """A visual scene variant (``capvector.sim.variants``) drawn from the seed; None: as trained."""

    @property
    def step_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else get_task(self.task).max_steps


def eval_specs(
    task: str,
    episodes: int,
    *,
    robot: str = DEFAULT_ROBOT,
    start_seed: int = EVAL_SEED_START,
    max_steps: int | None = None,
    gripper: str | None = None,
    variant: str | None = None,
) -> list[EpisodeSpec]:
    """``episodes`` specs with consecutive seeds from ``start_seed`` (disjoint from demo seeds).

    A variant that swaps the arm (``sawyer``, ``ur5e``) sets ``robot``/``gripper``; a visual one
    is kept on the spec and applied after each reset.
    """
    get_task(task)
    visual = None
    if variant is not None:
        v = get_variant(variant)
        robot, gripper = v.robot or robot, v.gripper if v.robot else gripper
        visual = variant if v.visual else None
    return [
        EpisodeSpec(task, start_seed + i, robot, max_steps, gripper, visual)
        for i in range(episodes)
    ]
