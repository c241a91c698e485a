"""Policy rollouts in robosuite: episode specs in, success and (optionally) video frames out.

A policy is any callable ``policy(observation) -> (T, 7) array``. The observation carries what
the demos stored, in the same conventions:

- ``images``: ``{camera: (H, W, 3) uint8}``, upright, cameras as requested
- ``proprio``: ``(8,) float32``, raw (not normalised): eef pos, eef axis-angle, 2 finger joints
- ``instruction``: the task's language instruction
- ``depth``: ``{camera: (H, W) float32}`` in metres, only with ``depth=True``

The chunk is executed open loop (all T actions, or the first ``execute_steps``), as OpenVLA-OFT
does with its 8-action chunks; images are rendered only when a new chunk is requested. The gripper
dimension is binarised: > 0 closes (+1), otherwise opens (-1), the convention of our demos and of
robosuite. Success is ``env._check_success()`` after every step; the episode ends at the first
success or at the step limit (``EpisodeSpec.max_steps``, else the task's default limit).

Seeds: an episode's initial state is a function of its seed alone. Evaluation seeds must not be
seeds a training demo used; demos start at ``--seed`` (default 0), ``eval_specs`` starts at
``EVAL_SEED_START`` = 1,000,000.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from capvector.sim.envs import SimEnv, SimulationFault, get_task
from capvector.sim.policy import EpisodeResult, Observation, Policy, as_chunk

__all__ = [
    "EVAL_SEED_START",
    "EnvCache",
    "EpisodeResult",
    "EpisodeSpec",
    "Observation",
    "Policy",
    "close_envs",
    "eval_specs",
    "run_episode",
    "run_episodes",
    "to_env_action",
]

log = logging.getLogger(__name__)

EVAL_SEED_START = 1_000_000
"""First default evaluation seed; keep demo seeds below it."""


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode: the task, the seed of its initial state, the arm."""

    task: str
    seed: int
    robot: str = "Panda"
    max_steps: int | None = None
    """Step limit; None uses the task's default (``TaskSpec.max_steps``)."""
    gripper: str | None = None
    """Gripper override for arms whose default gripper lacks 2 finger joints, e.g. PandaGripper."""

    @property
    def step_limit(self) -> int:
        return self.max_steps if self.max_steps is not None else get_task(self.task).max_steps


def eval_specs(
    task: str,
    episodes: int,
    *,
    robot: str = "Panda",
    start_seed: int = EVAL_SEED_START,
    max_steps: int | None = None,
    gripper: str | None = None,
) -> list[EpisodeSpec]:
    """``episodes`` specs with consecutive seeds from ``start_seed`` (disjoint from demo seeds)."""
    return [
        EpisodeSpec(task, start_seed + i, robot=robot, max_steps=max_steps, gripper=gripper)
        for i in range(episodes)
    ]


def to_env_action(action: np.ndarray) -> np.ndarray:
    """(7,) policy action -> robosuite action: gripper binarised, > 0 closes (+1), else opens (-1).

    The arm dims are passed through; robosuite's OSC clips them to [-1, 1] itself.
    """
    out = np.array(action, dtype=np.float64, copy=True)
    out[-1] = 1.0 if out[-1] > 0 else -1.0
    return out


class EnvCache:
    """Keeps built :class:`SimEnv` s for reuse across episodes (``robosuite.make`` costs seconds).

    Keyed by everything that changes the env: task, arm, gripper, cameras, size, depth, fovy.
    At most ``max_envs`` are kept; the least recently used one is closed beyond that.
    """

    def __init__(self, max_envs: int = 4) -> None:
        self.max_envs = max_envs
        self._envs: OrderedDict[tuple, SimEnv] = OrderedDict()

    def get(
        self,
        task: str,
        robot: str = "Panda",
        *,
        gripper: str | None = None,
        cameras: Sequence[str],
        image_size: int,
        depth: bool = False,
        camera_fovy: Mapping[str, float] | None = None,
    ) -> SimEnv:
        key = (
            task,
            robot,
            gripper,
            tuple(cameras),
            image_size,
            depth,
            tuple(sorted((camera_fovy or {}).items())),
        )
        if key in self._envs:
            self._envs.move_to_end(key)
            return self._envs[key]
        sim = SimEnv(
            task,
            robot,
            gripper=gripper,
            cameras=cameras,
            image_size=image_size,
            depth=depth,
            camera_fovy=camera_fovy,
        )
        self._envs[key] = sim
        while len(self._envs) > self.max_envs:
            _, old = self._envs.popitem(last=False)
            old.close()
        return sim

    def close(self) -> None:
        while self._envs:
            _, sim = self._envs.popitem()
            sim.close()

    def __len__(self) -> int:
        return len(self._envs)


_default_envs = EnvCache()


def close_envs() -> None:
    """Close the envs :func:`run_episode` cached when called without ``envs``."""
    _default_envs.close()


def _observe(sim: SimEnv, images: dict[str, np.ndarray], depth: dict | None) -> Observation:
    obs: Observation = {"images": images, "proprio": sim.proprio(), "instruction": sim.instruction}
    if depth is not None:
        obs["depth"] = depth
    return obs


def run_episode(
    policy: Policy,
    spec: EpisodeSpec,
    *,
    cameras: Sequence[str],
    image_size: int,
    depth: bool = False,
    video: bool = False,
    execute_steps: int | None = None,
    camera_fovy: Mapping[str, float] | None = None,
    envs: EnvCache | None = None,
) -> EpisodeResult:
    """Run ``policy`` on one episode; simulator faults fail the episode, never the caller.

    ``cameras``/``image_size``/``camera_fovy`` must match what the policy was trained on (the
    dataset's ``cameras``, ``image_size`` and ``camera_fovy`` attrs; fovy defaults to the task's).
    ``execute_steps`` executes only the first k actions of each chunk before re-planning.
    ``envs`` defaults to a module-level cache (see :func:`close_envs`).
    """
    if execute_steps is not None and execute_steps < 1:
        raise ValueError(f"execute_steps must be at least 1, got {execute_steps}")
    cache = _default_envs if envs is None else envs
    sim = cache.get(
        spec.task,
        spec.robot,
        gripper=spec.gripper,
        cameras=cameras,
        image_size=image_size,
        depth=depth,
        camera_fovy=camera_fovy,
    )
    limit = spec.step_limit
    sim.reset(spec.seed)
    frames: list[np.ndarray] | None = [] if video else None

    def result(success: bool, reason: str | None) -> EpisodeResult:
        if reason is not None and not reason.startswith("step limit"):
            log.warning("%s seed %d (%s): %s", spec.task, spec.seed, spec.robot, reason)
        return EpisodeResult(success, sim.steps, reason, frames, spec.seed, spec.task, spec.robot)

    while sim.steps < limit:
        images, dep = sim.render()
        if frames is not None:
            frames.append(np.concatenate(list(images.values()), axis=1))
        chunk = as_chunk(policy(_observe(sim, images, dep)))
        if execute_steps is not None:
            chunk = chunk[:execute_steps]
        for i, action in enumerate(chunk):
            if not np.all(np.isfinite(action)):
                return result(False, f"non-finite action at step {sim.steps}: {action.tolist()}")
            try:
                sim.step(to_env_action(action))
            except SimulationFault as e:
                return result(False, f"simulation fault at step {sim.steps}: {e}")
            if sim.success():
                if frames is not None:
                    frames.append(np.concatenate(list(sim.render()[0].values()), axis=1))
                return result(True, None)
            if sim.steps >= limit:
                break
            if frames is not None and i + 1 < len(chunk):
                frames.append(np.concatenate(list(sim.render()[0].values()), axis=1))
    return result(False, f"step limit ({limit}) reached")


def run_episodes(
    policy: Policy,
    specs: Iterable[EpisodeSpec],
    *,
    cameras: Sequence[str],
    image_size: int,
    depth: bool = False,
    videos: int = 0,
    execute_steps: int | None = None,
    camera_fovy: Mapping[str, float] | None = None,
    envs: EnvCache | None = None,
) -> list[EpisodeResult]:
    """:func:`run_episode` over ``specs``, keeping video frames for the first ``videos`` ones."""
    return [
        run_episode(
            policy,
            spec,
            cameras=cameras,
            image_size=image_size,
            depth=depth,
            video=i < videos,
            execute_steps=execute_steps,
            camera_fovy=camera_fovy,
            envs=envs,
        )
        for i, spec in enumerate(specs)
    ]
