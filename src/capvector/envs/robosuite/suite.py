"""robosuite as a registered suite: a task set is a task of :mod:`capvector.envs.robosuite.tasks`
(Lift, Stack, PickPlaceCan, ...), its episodes the seeds from ``EVAL_SEED_START`` on, its step limit
the task's own."""

from __future__ import annotations

from typing import Any

from capvector.envs.base import EVAL_SEED_START, EnvPool, Episode, Spec, Suite
from capvector.envs.registry import SUITES
from capvector.envs.robosuite.spec import EpisodeSpec, eval_specs


@SUITES.register("robosuite")
class RobosuiteSuite(Suite):
    name = "robosuite"
    cameras = ("agentview", "robot0_eye_in_hand")
    example = {"task_set": "Lift", "episodes": 2}

    def specs(
        self, task_set: str, episodes: int, *, start_seed: int = EVAL_SEED_START, **options: Any
    ) -> list[Spec]:
        """``episodes`` seeds of the task ``task_set``; ``options``: ``robot``, ``max_steps``,
        ``gripper``, ``variant`` (:func:`~capvector.envs.robosuite.spec.eval_specs`)."""
        return list(eval_specs(task_set, episodes, start_seed=start_seed, **options))

    def start(self, spec: Spec, envs: EnvPool, **settings: Any) -> Episode:
        from capvector.envs.robosuite.episode import Episode as RobosuiteEpisode  # the simulator

        assert isinstance(spec, EpisodeSpec), spec
        return RobosuiteEpisode(spec, envs, **settings)
