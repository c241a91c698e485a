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

Episodes are described by :class:`~capvector.sim.episodes.EpisodeSpec` (seeds, arm, scene
variant; no simulator import). :class:`RolloutEvaluator` is the one loop every evaluation runs: the
validation loop of ``VLAModule``, ``capvector evaluate`` and ``capvector sweep-scale``.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capvector.sim.envs import SimEnv, SimulationFault
from capvector.sim.episodes import EVAL_SEED_START, EpisodeSpec, eval_specs
from capvector.sim.policy import EpisodeResult, Observation, Policy, as_chunk
from capvector.sim.variants import SceneRandomizer, get_variant

__all__ = [
    "EVAL_SEED_START",
    "EnvCache",
    "EpisodeResult",
    "EpisodeSpec",
    "Observation",
    "Policy",
    "RolloutEvaluator",
    "close_envs",
    "eval_specs",
    "run_episode",
    "to_env_action",
]

log = logging.getLogger(__name__)


def to_env_action(action: np.ndarray) -> np.ndarray:
    """(7,) policy action -> robosuite action: gripper binarised, > 0 closes (+1), else opens (-1).

    The arm dims are passed through; robosuite's OSC clips them to [-1, 1] itself.
    """
    out = np.array(action, dtype=np.float64, copy=True)
    out[-1] = 1.0 if out[-1] > 0 else -1.0
    return out


class EnvCache:
    """Keeps built :class:`SimEnv` s for reuse across episodes (``robosuite.make`` costs seconds).

    Keyed by everything that changes the env: task, arm, gripper, cameras, size, depth, fovy and
    scene variant (a variant's env carries its :class:`SceneRandomizer`, see :meth:`randomizer`).
    At most ``max_envs`` are kept; the least recently used one is closed beyond that.
    """

    def __init__(self, max_envs: int = 4) -> None:
        self.max_envs = max_envs
        self._envs: OrderedDict[tuple, SimEnv] = OrderedDict()
        self._randomizers: dict[int, SceneRandomizer] = {}

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
        variant: str | None = None,
    ) -> SimEnv:
        settings = {"gripper": gripper, "cameras": tuple(cameras), "image_size": image_size,
                    "depth": depth, "camera_fovy": dict(camera_fovy or {})}  # fmt: skip
        key = (task, robot, variant, repr(sorted(settings.items())))
        if key in self._envs:
            self._envs.move_to_end(key)
            return self._envs[key]
        sim = SimEnv(task, robot, **settings)
        self._envs[key] = sim
        if variant is not None:
            self._randomizers[id(sim)] = SceneRandomizer(sim, get_variant(variant))
        while len(self._envs) > self.max_envs:
            _, old = self._envs.popitem(last=False)
            self._close(old)
        return sim

    def randomizer(self, sim: SimEnv) -> SceneRandomizer | None:
        """The scene variant's randomizer of an env this cache built (None: no variant)."""
        return self._randomizers.get(id(sim))

    def _close(self, sim: SimEnv) -> None:
        self._randomizers.pop(id(sim), None)
        sim.close()

    def close(self) -> None:
        while self._envs:
            _, sim = self._envs.popitem()
            self._close(sim)

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
        variant=spec.variant,
    )
    limit = spec.step_limit
    sim.reset(spec.seed)
    if (randomizer := cache.randomizer(sim)) is not None:
        randomizer.apply(
            spec.seed
        )  # the variant's perturbation for this seed, as trained otherwise
    frames: list[np.ndarray] | None = [] if video else None

    def result(success: bool, reason: str | None) -> EpisodeResult:
        if reason is not None and not reason.startswith("step limit"):
            log.warning("%s seed %d (%s): %s", spec.task, spec.seed, spec.robot, reason)
        return EpisodeResult(
            success, sim.steps, reason, frames, spec.seed, spec.task, spec.robot, spec.variant
        )

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


@dataclass
class RolloutEvaluator:
    """The one rollout loop: a policy on a list of episodes, with the settings it was trained for.

    ``cameras``/``image_size``/``camera_fovy`` come from the data spec the policy was trained on;
    ``execute_steps`` executes only the first k actions of each chunk; the first ``videos``
    episodes (by their index in the full list) are written as mp4s to ``video_dir``.
    """

    cameras: Sequence[str]
    image_size: int
    camera_fovy: Mapping[str, float] | None = None
    execute_steps: int | None = None
    videos: int = 0
    video_dir: Path | None = None
    envs: EnvCache | None = None

    def run(
        self,
        policy: Policy,
        specs: Sequence[EpisodeSpec],
        indices: Sequence[int] | None = None,
        progress: bool = False,
    ) -> list[EpisodeResult]:
        """Results in the order of ``specs``; ``indices`` are their positions in the full episode
        list (for video selection) when ``specs`` is a part of it."""
        from tqdm import tqdm

        positions = range(len(specs)) if indices is None else indices
        bar = tqdm(
            list(zip(positions, specs, strict=True)),
            desc="evaluate",
            unit="episode",
            disable=not progress,
        )
        results = []
        for index, spec in bar:
            bar.set_postfix(task=spec.task, seed=spec.seed)
            video = self.video_dir is not None and index < self.videos
            result = run_episode(
                policy, spec, cameras=self.cameras, image_size=self.image_size, depth=False,
                video=video, execute_steps=self.execute_steps, camera_fovy=self.camera_fovy,
                envs=self.envs,
            )  # fmt: skip
            if result.frames:
                self._write_video(result)
            results.append(result)
        return results

    def _write_video(self, result: EpisodeResult) -> None:
        from capvector.sim.video import write_video

        assert self.video_dir is not None and result.frames
        variant = f"_{result.variant}" if result.variant else ""
        name = f"{result.task}_{result.robot}{variant}_seed{result.seed}.mp4"
        write_video(result.frames, Path(self.video_dir) / name)
