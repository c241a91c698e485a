"""Meta-World as a registered suite: a task set is ``metaworld_mt10``, ``metaworld_mt50`` or one
task (``reach-v3``), its episodes the seeds from ``EVAL_SEED_START`` on, its protocol LeRobot's
(500 steps, 10 episodes per task, the ``corner2`` camera; :mod:`capvector.envs.metaworld.spec`)."""

from __future__ import annotations

from typing import Any

from capvector.envs.base import EVAL_SEED_START, EnvPool, Episode, Spec, Suite
from capvector.envs.metaworld.spec import (
    CAMERAS,
    EVAL_EPISODES,
    INSTRUCTIONS,
    SUITE_NAME,
    TASK_SETS,
    MetaWorldEpisodeSpec,
    metaworld_specs,
)
from capvector.envs.registry import SUITES


@SUITES.register(SUITE_NAME)
class MetaWorldSuite(Suite):
    name = SUITE_NAME
    task_sets = tuple(TASK_SETS)
    eval_episodes = EVAL_EPISODES
    cameras = CAMERAS
    example = {"task_set": "reach-v3", "episodes": 2}

    def specs(
        self,
        task_set: str,
        episodes: int,
        *,
        start_seed: int = EVAL_SEED_START,
        max_steps: int | None = None,
    ) -> list[Spec]:
        """``episodes`` seeds of each task of ``task_set``
        (:func:`~capvector.envs.metaworld.spec.metaworld_specs`)."""
        return list(metaworld_specs(task_set, episodes, start_seed=start_seed, max_steps=max_steps))

    def start(self, spec: Spec, envs: EnvPool, **settings: Any) -> Episode:
        from capvector.envs.metaworld.episode import MetaWorldEpisode  # Meta-World and MuJoCo

        assert isinstance(spec, MetaWorldEpisodeSpec), spec
        return MetaWorldEpisode(spec, envs, **settings)

    def instruction(self, spec: Spec) -> str | None:
        assert isinstance(spec, MetaWorldEpisodeSpec), spec
        return INSTRUCTIONS[spec.task]
