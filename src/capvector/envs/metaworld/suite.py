"""Meta-World as a registered suite: a task set is ``metaworld_mt10``, ``metaworld_mt50`` or one
task (``reach-v3``), its episodes the seeds from ``EVAL_SEED_START`` on, its protocol LeRobot's
(500 steps, 10 episodes per task, the ``corner2`` camera; :mod:`capvector.envs.metaworld.spec`)."""

from __future__ import annotations

import os
from typing import Any

from capvector.envs.base import (
    DEMO_SETTINGS,
    EVAL_SEED_START,
    DemoSettings,
    DemoSummary,
    EnvPool,
    Episode,
    Spec,
    Suite,
)
from capvector.envs.metaworld.spec import (
    CAMERAS,
    EVAL_EPISODES,
    INSTRUCTIONS,
    PROPRIO_KEYS,
    SUITE_NAME,
    TASK_SETS,
    MetaWorldEpisodeSpec,
    metaworld_specs,
)
from capvector.envs.registry import SUITES
from capvector.errors import CapVectorError


@SUITES.register(SUITE_NAME)
class MetaWorldSuite(Suite):
    name = SUITE_NAME
    task_sets = tuple(TASK_SETS)
    eval_episodes = EVAL_EPISODES
    cameras = CAMERAS
    example = {"task_set": "reach-v3", "episodes": 2}
    demo_example = {"task_set": "reach-v3", "noise": 0.0, "extra_steps": 1}
    demo_proprio_keys = PROPRIO_KEYS
    stack_packages = (("Meta-World", "metaworld"), ("MuJoCo", "mujoco"))

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

    def record_demos(
        self,
        task_set: str,
        episodes: int,
        out: str | os.PathLike[str],
        settings: DemoSettings = DEMO_SETTINGS,
        /,
        *,
        noise: float | None = None,
        extra_steps: int | None = None,
    ) -> list[DemoSummary]:
        """A folder ``out`` of one file per task of ``task_set`` (``<task>.hdf5``), ``episodes``
        successful expert demos each (:func:`~capvector.envs.metaworld.demos.record_task_set`);
        cameras default to the protocol's ``corner2`` (the default settings' cameras are
        robosuite's, which Meta-World has none of), the image size to 64."""
        from capvector.envs.metaworld import demos  # Meta-World and MuJoCo

        if settings.depth:
            raise CapVectorError("Meta-World demos record no depth; drop --depth")
        cameras = CAMERAS if settings.cameras == DEMO_SETTINGS.cameras else settings.cameras
        own = {"noise": noise, "extra_steps": extra_steps, "max_attempts": settings.max_attempts}
        return demos.record_task_set(
            task_set,
            episodes,
            out,
            cameras=tuple(cameras),
            image_size=settings.image_size or demos.DEFAULT_IMAGE_SIZE,
            seed=settings.seed,
            progress=settings.progress,
            **{k: v for k, v in own.items() if v is not None},
        )
