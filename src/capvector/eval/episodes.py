"""Evaluation episodes as data: which task, arm, seed and scene variant, or which LIBERO trial.
No simulator imports.

Seeds: an episode's initial state is a function of its seed alone. Evaluation seeds must not be
seeds a training demo used; demos start at ``--seed`` (default 0), evaluation at
``EVAL_SEED_START`` = 1,000,000, and the λ sweep's validation episodes at
``VALIDATION_SEED_START`` = 2,000,000, so choosing λ never looks at the reported episodes.

LIBERO trials start from the task's fixed official initial states (trial i from state i), which
no demo of ours starts from (demos sample placements). What those states leave open, the fixtures'
placement (cabinets, stoves: LIBERO draws it at every reset), is drawn from seed
``EVAL_SEED_START + i``, so a trial's scene does not depend on which trials ran before it.
``from_demos`` starts trial i where demo i started instead: not the protocol, a diagnostic.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, get_args

from capvector.envs.libero.env import LIBERO_MAX_STEPS, LIBERO_NUM_TASKS, LIBERO_TRIALS, Rendering
from capvector.envs.robosuite.tasks import get_task
from capvector.envs.robosuite.variants import get_variant
from capvector.errors import CapVectorError, unknown_name

LIBERO_RENDERINGS: tuple[str, ...] = get_args(Rendering)

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
    """A visual scene variant (``capvector.envs.robosuite.variants``) drawn from the seed; None: as trained."""

    @property
    def step_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else get_task(self.task).max_steps

    def describe(self) -> dict[str, Any]:
        """Which episode it is, as JSON fields (``capvector evaluate --json``)."""
        return {"task": self.task, "robot": self.robot, "variant": self.variant, "seed": self.seed}


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


@dataclass(frozen=True)
class LiberoEpisodeSpec:
    """One trial of a LIBERO task under the OpenVLA-OFT / openpi protocol: it starts from the
    task's official initial state number ``trial``."""

    suite: str
    task_id: int
    trial: int
    max_steps: int | None = None
    """Step limit after the wait steps; None: the suite's (220 spatial, 280 object, ...)."""
    rendering: Rendering = "auto"
    """Who draws the images (``capvector.envs.libero.env.Rendering``): auto, fast or official."""
    from_demos: str | None = None
    """A folder of demos (``capvector demos``): the trial starts where demo ``trial`` of the
    task's file started instead (a diagnostic: success from the placements a policy trained on)."""

    robot: ClassVar[str] = DEFAULT_ROBOT  # every LIBERO scene has one Panda
    variant: ClassVar[str | None] = None

    @property
    def task(self) -> str:
        """How results, metrics and ``episodes.csv`` name the task: ``libero_spatial/3``."""
        return f"{self.suite}/{self.task_id}"

    @property
    def seed(self) -> int:
        """The trial, i.e. the index of the initial state (what results call an episode's seed)."""
        return self.trial

    @property
    def fixture_seed(self) -> int:
        """Seeds the reset that places the fixtures (module docstring)."""
        return EVAL_SEED_START + self.trial

    @property
    def step_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else LIBERO_MAX_STEPS[self.suite]

    def describe(self) -> dict[str, Any]:
        """Which trial it is, as JSON fields (``capvector evaluate --json``)."""
        where = {} if self.from_demos is None else {"from_demos": self.from_demos}
        return {"suite": self.suite, "task": self.task_id, "trial": self.trial, **where}


AnyEpisodeSpec = EpisodeSpec | LiberoEpisodeSpec


def libero_specs(
    suite: str,
    tasks: Sequence[int] | None = None,
    trials: int = LIBERO_TRIALS,
    max_steps: int | None = None,
    rendering: Rendering = "auto",
    from_demos: str | None = None,
) -> list[LiberoEpisodeSpec]:
    """Trials ``0..trials-1`` of each of ``tasks`` (default: the whole suite), task by task;
    ``from_demos``: from the start states of that folder's demos (:class:`LiberoEpisodeSpec`).

    Checked without importing LIBERO, so a typo fails before anything is loaded.
    """
    if suite not in LIBERO_NUM_TASKS:
        raise unknown_name("LIBERO suite", suite, LIBERO_NUM_TASKS)
    count = LIBERO_NUM_TASKS[suite]
    tasks = list(range(count)) if tasks is None else list(tasks)
    for task_id in tasks:
        if not 0 <= task_id < count:
            raise CapVectorError(f"{suite} has tasks 0..{count - 1}, not {task_id}")
        if tasks.count(task_id) > 1:
            raise CapVectorError(f"{suite} task {task_id} is given twice")
    if not 1 <= trials <= LIBERO_TRIALS:
        raise CapVectorError(
            f"LIBERO tasks have {LIBERO_TRIALS} official initial states, one per trial: trials "
            f"must be 1..{LIBERO_TRIALS}, not {trials}"
        )
    if max_steps is not None and max_steps < 1:
        raise CapVectorError(f"max_steps must be at least 1, not {max_steps}")
    if rendering not in LIBERO_RENDERINGS:
        raise unknown_name("LIBERO rendering", rendering, LIBERO_RENDERINGS)
    if from_demos is not None and not Path(from_demos).is_dir():
        raise CapVectorError(f"from_demos: {from_demos} is not a folder of demos")
    return [
        LiberoEpisodeSpec(suite, task_id, trial, max_steps, rendering, from_demos)
        for task_id in tasks
        for trial in range(trials)
    ]
