"""A robosuite episode in progress, as the rollout loop drives it: the env reset from the spec's
seed (and its scene variant applied), the chunk executed open loop, success checked every step.

The chunk is executed open loop (all T actions, or the first ``execute_steps``), as OpenVLA-OFT
does with its 8-action chunks; images are rendered only when a new chunk is requested. The gripper
dimension is binarised: > 0 closes (+1), otherwise opens (-1), the convention of our demos and of
robosuite. Success is ``env._check_success()`` after every step; the episode ends at the first
success or at the step limit (``EpisodeSpec.max_steps``, else the task's default limit).
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
from capvector.envs.robosuite.env import SimEnv, SimulationFault
from capvector.envs.robosuite.spec import EpisodeSpec
from capvector.envs.robosuite.variants import SceneRandomizer, get_variant


def to_env_action(action: np.ndarray) -> np.ndarray:
    """(7,) policy action -> robosuite action: gripper binarised, > 0 closes (+1), else opens (-1).

    The arm dims are passed through; robosuite's OSC clips them to [-1, 1] itself.
    """
    out = np.array(action, dtype=np.float64, copy=True)
    out[-1] = 1.0 if out[-1] > 0 else -1.0
    return out


def robosuite_env(
    envs: EnvPool,
    task: str,
    robot: str = "Panda",
    *,
    gripper: str | None = None,
    cameras: Sequence[str],
    image_size: int,
    depth: bool = False,
    camera_fovy: Mapping[str, float] | None = None,
    variant: str | None = None,
) -> SimEnv:
    """The :class:`SimEnv` of these settings from ``envs``, built once. Keyed by everything that
    changes the env; a variant's env carries its :class:`SceneRandomizer` (``sim.randomizer``)."""
    settings = {"gripper": gripper, "cameras": tuple(cameras), "image_size": image_size,
                "depth": depth, "camera_fovy": dict(camera_fovy or {})}  # fmt: skip

    def build() -> SimEnv:
        sim = SimEnv(task, robot, fast_step=envs.fast_step, **settings)
        if variant is not None:
            sim.randomizer = SceneRandomizer(sim, get_variant(variant))
        return sim

    return envs.get(("robosuite", task, robot, variant, repr(sorted(settings.items()))), build)


def _observe(sim: SimEnv, images: dict[str, np.ndarray], depth: dict | None) -> Observation:
    obs: Observation = {"images": images, "proprio": sim.proprio(), "instruction": sim.instruction}
    if depth is not None:
        obs["depth"] = depth
    return obs


class Episode:
    """One episode in progress, as both loops drive it: :meth:`observe` (render the cameras) for
    the policy's next chunk, then :meth:`execute` that chunk, until it returns the result.

    Simulator faults and non-finite actions fail the episode, never the caller.
    ``cameras``/``image_size``/``camera_fovy`` must match what the policy was trained on (the
    dataset's ``cameras``, ``image_size`` and ``camera_fovy`` attrs; fovy defaults to the task's).
    ``execute_steps`` executes only the first k actions of each chunk before re-planning.
    """

    def __init__(
        self,
        spec: EpisodeSpec,
        envs: EnvPool,
        *,
        cameras: Sequence[str],
        image_size: int,
        depth: bool = False,
        video: bool = False,
        execute_steps: int | None = None,
        camera_fovy: Mapping[str, float] | None = None,
    ) -> None:
        if execute_steps is not None and execute_steps < 1:
            raise ValueError(f"execute_steps must be at least 1, got {execute_steps}")
        self.spec = spec
        self.execute_steps = execute_steps
        self.sim = robosuite_env(
            envs, spec.task, spec.robot, gripper=spec.gripper, cameras=cameras,
            image_size=image_size, depth=depth, camera_fovy=camera_fovy, variant=spec.variant,
        )  # fmt: skip
        self.limit = spec.step_limit
        self.sim.reset(spec.seed)
        if self.sim.randomizer is not None:
            self.sim.randomizer.apply(spec.seed)  # the variant's perturbation for this seed
        self.frames: list[np.ndarray] | None = [] if video else None

    def observe(self) -> Observation:
        images, depth = self.sim.render()
        self._record(images)
        return _observe(self.sim, images, depth)

    def execute(self, actions: Any) -> EpisodeResult | None:
        """Run the chunk open loop (its first ``execute_steps`` actions); the episode's result
        when it ended (success, step limit, fault), else None: observe again."""
        chunk = as_chunk(actions)
        if self.execute_steps is not None:
            chunk = chunk[: self.execute_steps]
        sim = self.sim
        for i, action in enumerate(chunk):
            if not np.all(np.isfinite(action)):
                return self._result(
                    False, f"non-finite action at step {sim.steps}: {action.tolist()}"
                )
            try:
                sim.step(to_env_action(action))
            except SimulationFault as e:
                return self._result(False, f"simulation fault at step {sim.steps}: {e}")
            if sim.success():
                if self.frames is not None:  # the last state, without rendering for nothing
                    self._record(sim.render()[0])
                return self._result(True, None)
            if sim.steps >= self.limit:
                break
            if self.frames is not None and i + 1 < len(chunk):
                self._record(sim.render()[0])
        if sim.steps >= self.limit:
            return self._result(False, f"step limit ({self.limit}) reached")
        return None

    def _record(self, images: Mapping[str, np.ndarray]) -> None:
        if self.frames is not None:
            self.frames.append(side_by_side(images))

    def _result(self, success: bool, reason: str | None) -> EpisodeResult:
        # after a simulation fault the proprio may hold NaN: end_episode reports no position
        final = self.sim.proprio()
        return end_episode(self.spec, success, self.sim.steps, reason, self.frames, final)
