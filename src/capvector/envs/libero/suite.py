"""LIBERO as a registered suite: a task set is a LIBERO suite (libero_spatial, libero_object,
libero_goal, libero_10, libero_90), its episodes the trials of each task (trial i starts from the
task's official initial state i), its step limits the OpenVLA-OFT / openpi protocol's."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from capvector.envs.base import EnvPool, Episode, Spec, Suite
from capvector.envs.libero.spec import LiberoEpisodeSpec, libero_specs
from capvector.envs.registry import SUITES


@SUITES.register("libero")
class LiberoSuite(Suite):
    name = "libero"
    release_envs = True  # a stepped LIBERO env holds ~1 GB
    cameras = ("agentview", "robot0_eye_in_hand")  # LIBERO_CAMERAS
    example = {"task_set": "libero_spatial", "episodes": 2, "tasks": [0]}

    def specs(self, task_set: str, episodes: int, **options: Any) -> list[Spec]:
        """``episodes`` trials of each task of the LIBERO suite ``task_set``; ``options``:
        ``tasks``, ``max_steps``, ``rendering``, ``from_demos``
        (:func:`~capvector.envs.libero.spec.libero_specs`)."""
        return list(libero_specs(task_set, trials=episodes, **options))

    def start(self, spec: Spec, envs: EnvPool, **settings: Any) -> Episode:
        from capvector.envs.libero.episode import LiberoEpisode  # LIBERO and the simulator

        assert isinstance(spec, LiberoEpisodeSpec), spec
        return LiberoEpisode(spec, envs, **settings)

    def instruction(self, spec: Spec) -> str | None:
        from capvector.envs.libero.env import libero_task

        assert isinstance(spec, LiberoEpisodeSpec), spec
        return libero_task(spec.suite, spec.task_id).instruction

    def check(self, specs: Sequence[Spec]) -> None:
        """Every trial that starts from a demo (``from_demos``) finds it."""
        if any(getattr(s, "from_demos", None) is not None for s in specs):
            from capvector.envs.libero.episode import check_trial_starts

            check_trial_starts(specs)
