"""LIBERO trials as data: a task of a suite and the official initial state it starts from. No
simulator import: configs and the validation dataset build them freely, and a typo fails before
LIBERO is loaded."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, get_args

from capvector.envs.base import DEFAULT_ROBOT, EVAL_SEED_START
from capvector.envs.libero.env import LIBERO_MAX_STEPS, LIBERO_NUM_TASKS, LIBERO_TRIALS, Rendering
from capvector.errors import CapVectorError, unknown_name

LIBERO_RENDERINGS: tuple[str, ...] = get_args(Rendering)


@dataclass(frozen=True)
class LiberoEpisodeSpec:
    """One trial of a LIBERO task under the OpenVLA-OFT / openpi protocol: it starts from the
    task's official initial state number ``trial``."""

    SUITE: ClassVar[str] = "libero"

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
