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

Episodes are described by :class:`~capvector.eval.episodes.EpisodeSpec` (seeds, arm, scene
variant; no simulator import), LIBERO trials by :class:`~capvector.eval.episodes.LiberoEpisodeSpec`
(run as :class:`~capvector.envs.libero.episode.LiberoEpisode`, LIBERO's protocol). :class:`RolloutEvaluator`
is the one loop every evaluation runs: the validation loop of ``VLAModule``, ``capvector evaluate``
and ``capvector sweep-scale``. It drives episodes one at a time (``batch_size=1``) or batched:
``batch_size`` episodes in flight in :class:`Slots` (here, or in :mod:`capvector.eval.workers`
processes), one policy call per round for all of their next chunks (:func:`act`). Each episode has
its own env, reset from its seed, so the outcome of an episode does not depend on how it was
batched.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capvector.envs.base import EpisodeResult, Observation, Policy, as_chunk
from capvector.envs.libero.episode import LiberoEpisode, build_libero_env
from capvector.envs.robosuite.env import SimEnv, SimulationFault
from capvector.envs.robosuite.variants import SceneRandomizer, get_variant
from capvector.eval.episodes import (
    EVAL_SEED_START,
    AnyEpisodeSpec,
    EpisodeSpec,
    LiberoEpisodeSpec,
    eval_specs,
)
from capvector.eval.workers import close_pools, worker_pool
from capvector.io.cpus import usable_cpus
from capvector.io.names import STAGE_CORES

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
    "start_episode",
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
    scene variant (a variant's env carries its :class:`SceneRandomizer`, see :meth:`randomizer`),
    and LIBERO's envs (:meth:`libero`). At most ``max_envs`` are kept, of them one LIBERO env (each
    holds ~1.2 GB); the least recently used one is closed beyond that. ``fast_step=False`` builds
    envs that run robosuite's full step (the same states, slower; see :class:`SimEnv`).
    """

    def __init__(self, max_envs: int = 4, *, fast_step: bool = True) -> None:
        self.max_envs = max_envs
        self.fast_step = fast_step
        self._envs: OrderedDict[tuple, Any] = OrderedDict()
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
        sim = SimEnv(task, robot, fast_step=self.fast_step, **settings)
        if variant is not None:
            self._randomizers[id(sim)] = SceneRandomizer(sim, get_variant(variant))
        return self._add(key, sim)

    def libero(
        self, suite: str, task_id: int, *, cameras: Sequence[str], image_size: int, rendering: str
    ) -> Any:
        """LIBERO's env of a task (:func:`~capvector.envs.libero.episode.build_libero_env`); building it
        closes the LIBERO env of another task first."""
        key = ("libero", suite, task_id, tuple(cameras), image_size, rendering)
        if key in self._envs:
            self._envs.move_to_end(key)
            return self._envs[key]
        for other in [k for k in self._envs if k[0] == "libero"]:
            self._close(self._envs.pop(other))
        return self._add(key, build_libero_env(suite, task_id, cameras, image_size, rendering))

    def _add(self, key: tuple, env: Any) -> Any:
        self._envs[key] = env
        while len(self._envs) > self.max_envs:
            _, old = self._envs.popitem(last=False)
            self._close(old)
        return env

    def randomizer(self, sim: SimEnv) -> SceneRandomizer | None:
        """The scene variant's randomizer of an env this cache built (None: no variant)."""
        return self._randomizers.get(id(sim))

    def _close(self, env: Any) -> None:
        self._randomizers.pop(id(env), None)
        env.close()

    def close(self) -> None:
        while self._envs:
            _, sim = self._envs.popitem()
            self._close(sim)

    def __len__(self) -> int:
        return len(self._envs)


_default_envs = EnvCache()


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
        envs: EnvCache,
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
        self.sim = envs.get(
            spec.task, spec.robot, gripper=spec.gripper, cameras=cameras, image_size=image_size,
            depth=depth, camera_fovy=camera_fovy, variant=spec.variant,
        )  # fmt: skip
        self.limit = spec.step_limit
        self.sim.reset(spec.seed)
        if (randomizer := envs.randomizer(self.sim)) is not None:
            randomizer.apply(spec.seed)  # the variant's perturbation for this seed
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
            self.frames.append(np.concatenate(list(images.values()), axis=1))

    def _result(self, success: bool, reason: str | None) -> EpisodeResult:
        spec = self.spec
        if reason is not None and not reason.startswith("step limit"):
            log.warning("%s seed %d (%s): %s", spec.task, spec.seed, spec.robot, reason)
        final = self.sim.proprio()  # after a simulation fault it may hold NaN: not a position
        return EpisodeResult(
            success, self.sim.steps, reason, self.frames, spec.seed, spec.task, spec.robot,
            spec.variant, tuple(final.tolist()) if np.isfinite(final).all() else None,
        )  # fmt: skip


def start_episode(spec: AnyEpisodeSpec, envs: EnvCache, **settings: Any) -> Episode | LiberoEpisode:
    """The episode of ``spec``, reset to its initial state; ``settings`` as :class:`Episode`'s."""
    if isinstance(spec, LiberoEpisodeSpec):
        return LiberoEpisode(spec, envs, **settings)
    return Episode(spec, envs, **settings)


def run_episode(policy: Policy, episode: Episode | LiberoEpisode) -> EpisodeResult:
    """Drive ``episode`` with ``policy``, one chunk at a time, until it ends."""
    while (result := episode.execute(policy(episode.observe()))) is None:
        pass
    return result


class Slots:
    """Episodes in flight in this process, one per slot, each slot with its own env cache (two
    episodes running at once never share an env). :mod:`capvector.eval.workers` runs the same
    in worker processes.

    ``handle`` takes ``(slot, "start", (spec, episode_kwargs))`` and ``(slot, "act", chunk)``
    commands and answers each with the slot's next observation, or its result when it ended.
    """

    def __init__(self) -> None:
        self._envs: dict[int, EnvCache] = {}
        self._episodes: dict[int, Episode | LiberoEpisode] = {}

    def handle(self, commands: Sequence[tuple[int, str, Any]]) -> list[tuple[int, Any]]:
        replies: list[tuple[int, Any]] = []
        for slot, command, payload in commands:
            if command == "start":
                spec, kwargs = payload
                envs = self._envs.setdefault(slot, EnvCache(max_envs=2))
                self._episodes[slot] = start_episode(spec, envs, **kwargs)
                replies.append((slot, self._episodes[slot].observe()))
            elif command == "act":
                episode = self._episodes[slot]
                result = episode.execute(payload)
                replies.append((slot, episode.observe() if result is None else result))
            else:
                raise ValueError(f"unknown slot command {command!r}")
        return replies

    def close(self) -> None:
        for envs in self._envs.values():
            envs.close()
        self._envs.clear()
        self._episodes.clear()


_local_slots = Slots()


def close_envs() -> None:
    """Close the envs and worker processes that evaluations cached for reuse."""
    _default_envs.close()
    _local_slots.close()
    close_pools()


def act(policy: Policy, observations: Sequence[Observation]) -> list[np.ndarray]:
    """One chunk per observation; one call of ``policy.act_batch`` when the policy has it
    (``capvector.policy.VLAPolicy``: one batched forward), else one call per observation."""
    batched = getattr(policy, "act_batch", None)
    chunks = batched(observations) if batched is not None else [policy(o) for o in observations]
    if len(chunks) != len(observations):
        raise ValueError(
            f"policy returned {len(chunks)} chunks for {len(observations)} observations"
        )
    return [as_chunk(c) for c in chunks]


def usable_cores() -> int:
    """The cores this process may use: ``CAPVECTOR_CORES`` (a ``capvector recipe`` stage's share
    of the machine), else ``OMP_NUM_THREADS``, else the CPUs this process may use (affinity and
    cgroup quota: :func:`capvector.io.cpus.usable_cpus`)."""
    return int(os.environ.get(STAGE_CORES) or os.environ.get("OMP_NUM_THREADS") or usable_cpus())


def default_workers(batch_size: int) -> int:
    """Worker processes for ``batch_size`` episodes in flight: one per usable core
    (:func:`usable_cores`), at most one per episode; fewer than 2 runs the simulators in this
    process. Outcomes do not depend on it."""
    workers = min(usable_cores(), batch_size)
    return workers if workers >= 2 else 0


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
    """Env cache of the one-at-a-time loop (``batch_size=1``); default: a module-level one."""
    batch_size: int = 8
    """Episodes in flight at once, one policy call for all of their chunks; 1: one at a time."""
    workers: int | None = None
    """Processes that step the simulators (0: this process); None: :func:`default_workers`."""

    def run(
        self,
        policy: Policy,
        specs: Sequence[AnyEpisodeSpec],
        indices: Sequence[int] | None = None,
        progress: bool = False,
    ) -> list[EpisodeResult]:
        """Results in the order of ``specs``; ``indices`` are their positions in the full episode
        list (for video selection) when ``specs`` is a part of it."""
        from tqdm import tqdm

        positions = list(range(len(specs)) if indices is None else indices)
        bar = tqdm(total=len(specs), desc="evaluate", unit="episode", disable=not progress)
        try:
            if self.batch_size <= 1:
                return self._run_serial(policy, specs, positions, bar)
            return self._run_batched(policy, specs, positions, bar)
        finally:
            bar.close()
            if any(isinstance(spec, LiberoEpisodeSpec) for spec in specs):
                self._release_envs()

    def _release_envs(self) -> None:
        """Close the cached envs (and worker processes) after a run with LIBERO's: a stepped
        LIBERO env holds ~1 GB, and a run builds each task's env anyway (building one closes the
        last task's), so keeping them would hold gigabytes through training until the next
        validation (4 episodes in flight: 6.2 GiB resident after the run, 2.2 with them closed;
        benchmarks/bench_libero_eval_memory.py)."""
        close_envs()
        if self.envs is not None:
            self.envs.close()

    def _episode_kwargs(self, index: int) -> dict[str, Any]:
        return {
            "cameras": tuple(self.cameras), "image_size": self.image_size,
            "camera_fovy": None if self.camera_fovy is None else dict(self.camera_fovy),
            "execute_steps": self.execute_steps,
            "video": self.video_dir is not None and index < self.videos,
        }  # fmt: skip

    def _episode(self, spec: AnyEpisodeSpec, index: int) -> Episode | LiberoEpisode:
        """Episode ``index`` of the one-at-a-time loop, in this process."""
        envs = _default_envs if self.envs is None else self.envs
        return start_episode(spec, envs, **self._episode_kwargs(index))

    def _finish(self, result: EpisodeResult, bar: Any) -> EpisodeResult:
        if result.frames:
            self._write_video(result)
        bar.set_postfix(task=result.task, seed=result.seed)
        bar.update()
        return result

    def _run_serial(
        self, policy: Policy, specs: Sequence[AnyEpisodeSpec], positions: list[int], bar: Any
    ) -> list[EpisodeResult]:
        return [
            self._finish(run_episode(policy, self._episode(spec, i)), bar)
            for i, spec in zip(positions, specs, strict=True)
        ]

    def _run_batched(
        self, policy: Policy, specs: Sequence[AnyEpisodeSpec], positions: list[int], bar: Any
    ) -> list[EpisodeResult]:
        """Up to ``batch_size`` episodes at once: the simulators step (in worker processes, or
        here) while the policy waits, then one policy call serves every episode's next chunk."""
        workers = default_workers(self.batch_size) if self.workers is None else self.workers
        slots = worker_pool(workers, Slots) if workers >= 2 else _local_slots
        pending = deque(zip(range(len(specs)), positions, specs, strict=True))
        results: list[EpisodeResult | None] = [None] * len(specs)
        running: dict[int, int] = {}  # slot -> index in specs

        def start(slot: int) -> tuple[int, str, Any]:
            order, position, spec = pending.popleft()
            running[slot] = order
            return slot, "start", (spec, self._episode_kwargs(position))

        commands = [start(slot) for slot in range(min(self.batch_size, len(specs)))]
        while commands:
            observations: dict[int, Observation] = {}
            next_commands = []
            for slot, reply in slots.handle(commands):
                if isinstance(reply, EpisodeResult):
                    results[running.pop(slot)] = self._finish(reply, bar)
                    if pending:  # the slot takes the next episode, observed next round
                        next_commands.append(start(slot))
                else:
                    observations[slot] = reply
            if observations:
                # In slot order, not in the order the workers replied: the batched forward sees
                # the same batch whatever the number of workers.
                order = sorted(observations)
                chunks = act(policy, [observations[slot] for slot in order])
                next_commands += [
                    (slot, "act", chunk) for slot, chunk in zip(order, chunks, strict=True)
                ]
            commands = next_commands
        return results  # type: ignore[return-value]

    def video_path(self, result: EpisodeResult) -> Path:
        """Where the mp4 of an episode recorded as video is written."""
        assert self.video_dir is not None
        variant = f"_{result.variant}" if result.variant else ""
        task = result.task.replace("/", "_")  # LIBERO's libero_spatial/3
        return Path(self.video_dir) / f"{task}_{result.robot}{variant}_seed{result.seed}.mp4"

    def _write_video(self, result: EpisodeResult) -> None:
        from capvector.eval.video import write_video

        assert result.frames
        write_video(result.frames, self.video_path(result))
