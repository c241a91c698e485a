"""Evaluation episodes as a validation dataset: Lightning's validation loop runs MuJoCo rollouts.

Each rank gets its share of the episodes as one batch (a list of :class:`EpisodeItem`), which the
module evaluates batched. Every rank gets the same number of items; when the episodes do not
divide evenly the extra items are marked ``counted=False`` and are skipped, so the rate equals a
one-process run on the same episodes.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from torch.utils.data import Dataset, DistributedSampler

from capvector.envs.base import DEFAULT_ROBOT, EVAL_SEED_START, Spec
from capvector.envs.libero.spec import libero_specs
from capvector.envs.robosuite.spec import eval_specs


@dataclass
class EvalTask:
    """Episodes of one task for the rollout validation loop. Seeds start far above demo seeds."""

    task: str
    episodes: int = 10
    robot: str = DEFAULT_ROBOT
    start_seed: int = EVAL_SEED_START
    max_steps: int | None = None
    gripper: str | None = None
    """Gripper override for arms whose own gripper lacks 2 finger joints (IIWA, UR5e, Kinova3,
    Jaco take PandaGripper), as the demos were recorded."""
    variant: str | None = None
    """A zero-shot scene variant (``capvector.envs.robosuite.variants``: camera, lighting, color, all,
    sawyer, ur5e, ...); None evaluates the scene as trained."""

    def specs(self) -> list[Spec]:
        return list(
            eval_specs(
                self.task,
                self.episodes,
                robot=self.robot,
                start_seed=self.start_seed,
                max_steps=self.max_steps,
                gripper=self.gripper,
                variant=self.variant,
            )  # fmt: skip
        )


@dataclass
class LiberoEvalTask:
    """Trials of LIBERO tasks under the official protocol (``capvector.envs.libero.episode``): trial i
    starts from the task's official initial state i, which no demo of ours starts from."""

    suite: str
    """libero_spatial, libero_object, libero_goal, libero_10 or libero_90."""
    tasks: list[int] | None = None
    """Task ids in the suite's canonical order; None: all of them."""
    trials: int = 10
    """Trials per task, 1..50 (the official protocol runs 50)."""
    max_steps: int | None = None
    """Step limit after the wait steps; None: the suite's (220 spatial, 280 object, ...)."""
    rendering: str = "auto"
    """Who draws the images: auto (the fast renderer on a CPU's OpenGL, robosuite's on a GPU),
    fast, or official (LIBERO's own; ``capvector.envs.libero.env.make_libero_env``)."""
    from_demos: str | None = None
    """A folder of demos (``capvector demos``): trial i starts where the task's demo i started,
    not from official state i (success from the placements trained on: a diagnostic)."""

    def specs(self) -> list[Spec]:
        return list(
            libero_specs(
                self.suite,
                self.tasks,
                self.trials,
                self.max_steps,
                self.rendering,  # type: ignore[arg-type]
                self.from_demos,
            )
        )


def eval_task(entry: EvalTask | LiberoEvalTask | Mapping[str, Any]) -> EvalTask | LiberoEvalTask:
    """An ``eval_tasks`` entry as its dataclass: a mapping with ``suite`` is a LIBERO one."""
    if not isinstance(entry, Mapping):
        return entry
    return LiberoEvalTask(**entry) if "suite" in entry else EvalTask(**entry)


@dataclass(frozen=True)
class EpisodeItem:
    spec: Spec
    index: int
    """Position in the full episode list (video naming, ordering)."""
    counted: bool = True
    """False for the padding items that even out ranks."""


def is_episode_batch(batch: object) -> bool:
    """Whether a validation batch is rollout episodes (a list of :class:`EpisodeItem`)."""
    return isinstance(batch, list) and bool(batch) and isinstance(batch[0], EpisodeItem)


class EpisodeDataset(Dataset):
    def __init__(self, tasks: list[EvalTask | LiberoEvalTask]) -> None:
        self.specs: list[Spec] = [spec for t in tasks for spec in t.specs()]

    def __len__(self) -> int:
        return len(self.specs)

    def __getitem__(self, i: int) -> EpisodeItem:
        n = len(self.specs)
        return EpisodeItem(self.specs[i % n], i % n, counted=i < n)


class EpisodeSampler(DistributedSampler):
    """Rank r takes episodes r, r + world, ...; ranks are padded to equal length with uncounted
    repeats (indices past the end, which ``EpisodeDataset`` maps to counted=False items)."""

    def __init__(self, dataset: EpisodeDataset, num_replicas: int, rank: int) -> None:
        super().__init__(dataset, num_replicas=num_replicas, rank=rank, shuffle=False)
        self.per_rank = math.ceil(len(dataset) / num_replicas)

    def __iter__(self) -> Iterator[int]:
        return iter(range(self.rank, self.per_rank * self.num_replicas, self.num_replicas))

    def __len__(self) -> int:
        return self.per_rank
