"""LIBERO as a registered suite: a task set is a LIBERO suite (libero_spatial, libero_object,
libero_goal, libero_10, libero_90), its episodes the trials of each task (trial i starts from the
task's official initial state i), its step limits the OpenVLA-OFT / openpi protocol's."""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from typing import Any

from capvector.envs.base import (
    DEMO_SETTINGS,
    DemoSettings,
    DemoSummary,
    EnvPool,
    Episode,
    Provenance,
    Spec,
    Suite,
    stack_label,
)
from capvector.envs.libero.env import LIBERO_NUM_TASKS, LIBERO_TRIALS, Rendering
from capvector.envs.libero.spec import LiberoEpisodeSpec, libero_specs
from capvector.envs.registry import SUITES


@functools.cache
def resolved_rendering(rendering: Rendering) -> str:
    """``fast`` or ``official``: who draws the images under ``rendering`` on this machine (asked
    of OpenGL once a process)."""
    if rendering != "auto":
        return rendering
    from capvector.envs.libero.render import fast_rendering_default  # queries OpenGL

    return "fast" if fast_rendering_default() else "official"


@SUITES.register("libero")
class LiberoSuite(Suite):
    name = "libero"
    task_sets = tuple(LIBERO_NUM_TASKS)  # LIBERO's suites: libero_spatial, ...
    seeded = False  # trial i starts from the task's official initial state i
    eval_episodes = LIBERO_TRIALS  # the official protocol: 50 trials per task
    release_envs = True  # a stepped LIBERO env holds ~1 GB
    cameras = ("agentview", "robot0_eye_in_hand")  # LIBERO_CAMERAS
    example = {"task_set": "libero_spatial", "episodes": 2, "tasks": [0]}
    demo_proprio_keys = ("ee_states", "gripper_states")  # LIBERO's released layout
    demo_example = {"task_set": "libero_spatial", "tasks": [0]}
    stack_packages = (("robosuite", "robosuite"), ("MuJoCo", "mujoco"))  # rpent-libero's

    def specs(
        self,
        task_set: str,
        episodes: int,
        *,
        tasks: Sequence[int] | None = None,
        max_steps: int | None = None,
        rendering: Rendering = "auto",
        from_demos: str | None = None,
    ) -> list[Spec]:
        """``episodes`` trials of each of ``tasks`` (default: all) of the LIBERO suite
        ``task_set`` (:func:`~capvector.envs.libero.spec.libero_specs`)."""
        return list(libero_specs(task_set, tasks, episodes, max_steps, rendering, from_demos))

    def start(self, spec: Spec, envs: EnvPool, **settings: Any) -> Episode:
        from capvector.envs.libero.episode import LiberoEpisode  # LIBERO and the simulator

        assert isinstance(spec, LiberoEpisodeSpec), spec
        return LiberoEpisode(spec, envs, **settings)

    def instruction(self, spec: Spec) -> str | None:
        from capvector.envs.libero.env import libero_task

        assert isinstance(spec, LiberoEpisodeSpec), spec
        return libero_task(spec.suite, spec.task_id).instruction

    def provenance(self, spec: Spec) -> Provenance:
        """The port (LIBERO on robosuite 1.5 and MuJoCo 3, ``rpent-libero``), never to be read as
        upstream LIBERO's stack (robosuite 1.4, MuJoCo 2.3.7: ``evaluate --backend upstream``),
        and the renderer ``rendering`` resolves to here (``auto``: fast where OpenGL is
        software)."""
        assert isinstance(spec, LiberoEpisodeSpec), spec
        stack = f"port ({stack_label(self.stack_packages)})"
        return Provenance(stack, resolved_rendering(spec.rendering))

    def check(self, specs: Sequence[Spec]) -> None:
        """Every trial that starts from a demo (``from_demos``) finds it."""
        if any(getattr(s, "from_demos", None) is not None for s in specs):
            from capvector.envs.libero.episode import check_trial_starts

            check_trial_starts(specs)

    def record_demos(
        self,
        task_set: str,
        episodes: int,
        out: str | os.PathLike[str],
        settings: DemoSettings = DEMO_SETTINGS,
        /,
        *,
        tasks: Sequence[int] = (),
        workers: int = 0,
        rendering: Rendering = "auto",
    ) -> list[DemoSummary]:
        """A folder ``out`` of one file per task of the LIBERO suite ``task_set`` (default: every
        task), in LIBERO's released layout, 128 px as released
        (:func:`~capvector.envs.libero.demos.record_suite`); ``workers`` processes record tasks
        side by side; ``rendering`` draws the images (the states do not depend on it)."""
        from capvector.envs.libero.demos import LIBERO_IMAGE_SIZE, record_suite  # LIBERO

        size = settings.image_size
        return record_suite(
            task_set, episodes, out, tasks=tasks, cameras=settings.cameras, depth=settings.depth,
            seed=settings.seed, image_size=LIBERO_IMAGE_SIZE if size is None else size,
            max_attempts=settings.max_attempts, progress=settings.progress, workers=workers,
            rendering=rendering,
        )  # fmt: skip
