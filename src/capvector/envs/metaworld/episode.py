"""A Meta-World episode in progress, as the rollout loop drives it: the task's env (built once per
task, camera set and image size, kept in the pool) reset from the spec's seed, each chunk executed
open loop, success read from Meta-World's ``info["success"]`` after every step; the episode ends at
the first success or at the step limit (LeRobot's protocol, :mod:`capvector.envs.metaworld.spec`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from capvector.envs.base import (
    EnvPool,
    EpisodeResult,
    Observation,
    as_chunk,
    end_episode,
    side_by_side,
)
from capvector.envs.metaworld.env import MetaWorldEnv
from capvector.envs.metaworld.spec import MetaWorldEpisodeSpec
from capvector.errors import CapVectorError


def metaworld_env(
    envs: EnvPool, task: str, *, cameras: Sequence[str], image_size: int
) -> MetaWorldEnv:
    """The env of ``task`` with these cameras from ``envs``, built once (~3 s: MT1's task data)."""
    key = ("metaworld", task, tuple(cameras), image_size)
    return envs.get(key, lambda: MetaWorldEnv(task, cameras=cameras, image_size=image_size))


class MetaWorldEpisode:
    """:class:`~capvector.envs.base.Episode` of a :class:`MetaWorldEpisodeSpec`. ``camera_fovy``
    is refused (Meta-World's cameras are the model's); ``execute_steps`` executes only the first
    k actions of each chunk."""

    def __init__(
        self,
        spec: MetaWorldEpisodeSpec,
        envs: EnvPool,
        *,
        cameras: Sequence[str],
        image_size: int,
        video: bool = False,
        execute_steps: int | None = None,
        camera_fovy: Mapping[str, float] | None = None,
    ) -> None:
        if execute_steps is not None and execute_steps < 1:
            raise ValueError(f"execute_steps must be at least 1, got {execute_steps}")
        if camera_fovy:
            raise CapVectorError(
                f"camera_fovy {dict(camera_fovy)}: Meta-World's cameras keep the model's field of "
                "view; train on Meta-World demos (they record none) or drop it"
            )
        self.spec = spec
        self.execute_steps = execute_steps
        self.sim = metaworld_env(envs, spec.task, cameras=cameras, image_size=image_size)
        self.limit = spec.step_limit
        self.sim.reset(spec.seed, self.limit)
        self.frames: list[np.ndarray] | None = [] if video else None

    def observe(self) -> Observation:
        images = self.sim.render()
        self._record(images)
        return {
            "images": images,
            "proprio": self.sim.proprio(),
            "instruction": self.sim.instruction,
        }

    def execute(self, actions: Any) -> EpisodeResult | None:
        """Run the chunk open loop (its first ``execute_steps`` actions); the result when the
        episode ended (success, step limit, fault), else None: observe again."""
        chunk = as_chunk(actions)
        if self.execute_steps is not None:
            chunk = chunk[: self.execute_steps]
        sim = self.sim
        for i, action in enumerate(chunk):
            if not np.all(np.isfinite(action)):
                return self._result(
                    False, f"non-finite action at step {sim.steps}: {action.tolist()}"
                )
            solved = sim.step(action)
            if sim.faulted:
                return self._result(False, f"simulation fault at step {sim.steps}")
            if solved:
                if self.frames is not None:
                    self._record(sim.render())
                return self._result(True, None)
            if sim.steps >= self.limit:
                return self._result(False, f"step limit ({self.limit}) reached")
            if self.frames is not None and i + 1 < len(chunk):
                self._record(sim.render())
        return None

    def _record(self, images: Mapping[str, np.ndarray]) -> None:
        if self.frames is not None:
            self.frames.append(side_by_side(images))

    def _result(self, success: bool, reason: str | None) -> EpisodeResult:
        # after a simulation fault the proprio may hold NaN: end_episode reports no position
        final = self.sim.proprio()
        return end_episode(self.spec, success, self.sim.steps, reason, self.frames, final)
