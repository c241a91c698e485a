"""robosuite as a registered suite: a task set is a task of :mod:`capvector.envs.robosuite.tasks`
(Lift, Stack, PickPlaceCan, ...), its episodes the seeds from ``EVAL_SEED_START`` on, its step limit
the task's own."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from capvector.envs.base import (
    DEFAULT_ROBOT,
    DEMO_SETTINGS,
    DemoSettings,
    DemoSummary,
    EnvPool,
    Episode,
    Spec,
    Suite,
)
from capvector.envs.registry import SUITES
from capvector.envs.robosuite.spec import EpisodeSpec, eval_specs
from capvector.envs.robosuite.tasks import TASKS


@SUITES.register("robosuite")
class RobosuiteSuite(Suite):
    name = "robosuite"
    task_sets = tuple(TASKS)  # a task set is one task
    cameras = ("agentview", "robot0_eye_in_hand")
    example = {"task_set": "Lift", "episodes": 2}
    # capvector.envs.robosuite.env.PROPRIO_KEYS (that module imports the simulator)
    demo_proprio_keys = ("robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos")
    demo_example = {"task_set": "Lift", "noise": 0.0, "extra_steps": 1}
    stack_packages = (("robosuite", "robosuite"), ("MuJoCo", "mujoco"))

    # ``episodes`` seeds of the task ``task_set`` from ``start_seed``; options ``robot``,
    # ``start_seed``, ``max_steps``, ``gripper``, ``variant``: the spec module's function itself
    specs = staticmethod(eval_specs)  # type: ignore[assignment]

    def start(self, spec: Spec, envs: EnvPool, **settings: Any) -> Episode:
        from capvector.envs.robosuite.episode import Episode as RobosuiteEpisode  # the simulator

        assert isinstance(spec, EpisodeSpec), spec
        return RobosuiteEpisode(spec, envs, **settings)

    def record_demos(
        self,
        task_set: str,
        episodes: int,
        out: str | os.PathLike[str],
        settings: DemoSettings = DEMO_SETTINGS,
        /,
        *,
        robot: str = DEFAULT_ROBOT,
        gripper: str | None = None,
        noise: float | None = None,
        extra_steps: int | None = None,
        fovy: Mapping[str, float] | None = None,
    ) -> list[DemoSummary]:
        """One robomimic-layout file ``out`` of the task ``task_set``
        (:func:`~capvector.envs.robosuite.demos.record_demos`; defaults: 64 px images, DART noise
        0.1, 6 steps after success)."""
        from capvector.envs.robosuite import demos  # the simulator

        given = {"noise": noise, "extra_steps": extra_steps, "image_size": settings.image_size}
        summary = demos.record_demos(
            task_set, episodes, out, robot=robot, gripper=gripper, cameras=settings.cameras,
            depth=settings.depth, seed=settings.seed, max_attempts=settings.max_attempts,
            camera_fovy=fovy, progress=settings.progress,
            **{k: v for k, v in given.items() if v is not None},
        )  # fmt: skip
        return [summary]
