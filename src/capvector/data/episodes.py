"""Evaluation episodes as a validation dataset: Lightning's validation loop runs MuJoCo rollouts.

Each rank gets its share of the episodes as one batch (a list of :class:`EpisodeItem`), which the
module evaluates batched. Every rank gets the same number of items; when the episodes do not
divide evenly the extra items are marked ``counted=False`` and are skipped, so the rate equals a
one-process run on the same episodes.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from torch.utils.data import Dataset, DistributedSampler

from capvector.envs.base import Spec, check_options
from capvector.envs.registry import SUITES, get_suite, suite_for_task_set
from capvector.errors import CapVectorError


@dataclass
class EvalTask:
    """Episodes of one task set of a registered suite for the rollout validation loop: its specs
    are ``Suite.specs(task, episodes, **options)``, the suite's own protocol (robosuite's seeds
    start far above demo seeds; LIBERO's trial i starts from the task's official state i)."""

    task: str
    """The task set: a robosuite task (``Lift``), a LIBERO suite (``libero_spatial``), ..."""
    episodes: int = 10
    """Episodes of each task of the set (LIBERO: trials per task, 1..50)."""
    suite: str | None = None
    """The registered suite (``capvector.envs.registry``) that runs ``task``; None: the one whose
    task sets hold it (``suite_for_task_set``), set on construction. Entries a config parses into
    this class directly (``{task: metaworld_mt10, episodes: 2}``) name no suite: a fixed default
    (robosuite) would send Meta-World's and LIBERO's task sets to robosuite."""
    options: dict[str, Any] = field(default_factory=dict)
    """The suite's own ``specs`` options: robosuite's ``robot``, ``start_seed``, ``gripper``,
    ``variant``, ``max_steps``; LIBERO's ``tasks``, ``max_steps``, ``rendering``, ``from_demos``."""

    def __post_init__(self) -> None:
        if self.suite is None:
            self.suite = suite_for_task_set(self.task).name

    def specs(self) -> list[Spec]:
        assert self.suite is not None  # set in __post_init__
        suite = get_suite(self.suite)
        check_options(suite.specs, self.options, f"eval task {self.task} of suite {self.suite}")
        return suite.specs(self.task, self.episodes, **self.options)


_FIELDS = {"task", "episodes", "suite", "options"}


def eval_task(entry: EvalTask | Mapping[str, Any] | Any) -> EvalTask:
    """An ``eval_tasks`` entry as an :class:`EvalTask`. Flat entries, as configs and checkpoints
    wrote them before the registry, still load: ``{task: Lift, robot: Sawyer, episodes: 10}``
    (keys other than ``task``/``episodes``/``suite`` are the suite's options) and LIBERO's
    ``{suite: libero_spatial, tasks: [0, 1], trials: 5}`` (``suite`` naming a task set, whose suite
    the registry finds; ``trials`` for ``episodes``)."""
    if isinstance(entry, EvalTask):
        return entry
    entry = dict(entry) if isinstance(entry, Mapping) else vars(entry)  # a config's Namespace
    flat = {k: v for k, v in entry.items() if v is not None or k not in _FIELDS}
    options = dict(flat.pop("options", None) or {})
    options.update({k: flat.pop(k) for k in list(flat) if k not in _FIELDS | {"trials"}})
    if "trials" in flat:
        if "episodes" in flat:
            raise CapVectorError("an eval_tasks entry gives episodes and trials: give one")
        flat["episodes"] = flat.pop("trials")
    suite = flat.pop("suite", None)
    task = flat.pop("task", None)
    if suite is not None and task is None and suite not in SUITES.names():
        task, suite = suite, suite_for_task_set(suite).name  # {suite: libero_spatial, ...}
    if task is None:
        raise CapVectorError(
            f"an eval_tasks entry names no task: {entry}; give task (e.g. Lift, "
            "libero_spatial) and, for a suite other than the task's, suite"
        )
    if suite is None:
        suite = suite_for_task_set(task).name
    return EvalTask(task, suite=suite, options=options, **flat)


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
    def __init__(self, tasks: list[EvalTask]) -> None:
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
