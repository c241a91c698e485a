"""Policy rollouts on any registered suite: episode specs in, success and (optionally) video
frames out.

A policy is any callable ``policy(observation) -> (T, 7) array`` (:mod:`capvector.envs.base`).
Each spec names its suite (``spec.SUITE``); the suite (:mod:`capvector.envs.registry`) starts the
episode, and this module only drives it: :class:`RolloutEvaluator` is the one loop every
evaluation runs: the validation loop of ``VLAModule``, ``capvector evaluate`` and ``capvector
sweep-scale``. It drives episodes one at a time (``batch_size=1``) or batched: ``batch_size``
episodes in flight in :class:`Slots` (here, or in :mod:`capvector.eval.workers` processes), one
policy call per round for all of their next chunks (:func:`act`). Each episode has its own env,
reset from its spec, so the outcome of an episode does not depend on how it was batched.
"""

from __future__ import annotations

import logging
import os
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from capvector.envs.base import Episode, EpisodeResult, Observation, Policy, Spec, as_chunk
from capvector.envs.registry import suite_of
from capvector.eval.workers import close_pools, worker_pool
from capvector.io.cpus import usable_cpus
from capvector.io.names import STAGE_CORES

__all__ = [
    "EnvCache",
    "EpisodeResult",
    "Observation",
    "Policy",
    "ProgressLines",
    "RolloutEvaluator",
    "close_envs",
    "run_episode",
    "start_episode",
]

log = logging.getLogger(__name__)


class EnvCache:
    """Keeps built envs for reuse across episodes (building one costs seconds): the
    :class:`~capvector.envs.base.EnvPool` suites take their envs from.

    Keyed by the suite's key (everything that changes the env). At most ``max_envs`` are kept; the
    least recently used one is closed beyond that, and a suite asks for an env ``alone`` when its
    envs hold gigabytes (LIBERO's ~1.2 GB each): its other envs are closed first.
    ``fast_step=False`` asks suites that have a fast step for their reference one (robosuite's
    full step: the same states, slower; see ``SimEnv``).
    """

    def __init__(self, max_envs: int = 4, *, fast_step: bool = True) -> None:
        self.max_envs = max_envs
        self.fast_step = fast_step
        self._envs: OrderedDict[tuple, Any] = OrderedDict()

    def get(self, key: tuple, build: Callable[[], Any], *, alone: bool = False) -> Any:
        """The env cached under ``key``, else ``build()``'s, kept (``key[0]`` names the suite)."""
        if key in self._envs:
            self._envs.move_to_end(key)
            return self._envs[key]
        if alone:
            for other in [k for k in self._envs if k[0] == key[0]]:
                self._envs.pop(other).close()
        return self._add(key, build())

    def _add(self, key: tuple, env: Any) -> Any:
        self._envs[key] = env
        while len(self._envs) > self.max_envs:
            _, old = self._envs.popitem(last=False)
            old.close()
        return env

    def close(self) -> None:
        while self._envs:
            _, env = self._envs.popitem()
            env.close()

    def __len__(self) -> int:
        return len(self._envs)


_default_envs = EnvCache()


def start_episode(spec: Spec, envs: EnvCache, **settings: Any) -> Episode:
    """The episode of ``spec``, reset to its initial state, started by its suite; ``settings`` as
    :meth:`capvector.envs.base.Suite.start`'s."""
    return suite_of(spec).start(spec, envs, **settings)


def run_episode(policy: Policy, episode: Episode) -> EpisodeResult:
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
        self._episodes: dict[int, Episode] = {}

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


class ProgressLines:
    """A long run of episodes reported as lines, where no bar shows it: a fit's rollout
    validation is one validation step (Lightning's bar sits at 0/1 for all of it, two hours on
    LIBERO here), and a recipe stage's output is a file (``capvector evaluate`` there). A line once
    ``every`` seconds have passed since the last one, and one at the end, each through ``write``;
    ``capvector recipe --status`` shows a running stage's last one."""

    def __init__(
        self, total: int, label: str, write: Callable[[str], None], every: float = 300.0
    ) -> None:
        self.total, self.label, self.write, self.every = total, label, write, every
        self.done = self.succeeded = 0
        self.began = self.last = time.monotonic()

    def update(self, success: bool) -> None:
        """One more episode ended, successful or not."""
        self.done += 1
        self.succeeded += int(success)
        now = time.monotonic()
        if self.done == self.total or now - self.last >= self.every:
            self.last = now
            self.write(self.line(now - self.began))

    def line(self, elapsed: float) -> str:
        left = ""
        if self.done < self.total:
            left = f", about {_minutes(elapsed / self.done * (self.total - self.done))} left"
        return (
            f"{self.label}: {self.done}/{self.total} episodes, {self.succeeded} succeeded, "
            f"{_minutes(elapsed)}{left}"
        )


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"


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
        specs: Sequence[Spec],
        indices: Sequence[int] | None = None,
        progress: bool = False,
        lines: ProgressLines | None = None,
    ) -> list[EpisodeResult]:
        """Results in the order of ``specs``; ``indices`` are their positions in the full episode
        list (for video selection) when ``specs`` is a part of it. ``progress``: a bar (for a
        terminal); ``lines``: progress as log lines (where no bar shows)."""
        from tqdm import tqdm

        positions = list(range(len(specs)) if indices is None else indices)
        bar = tqdm(total=len(specs), desc="evaluate", unit="episode", disable=not progress)

        def finished(result: EpisodeResult) -> None:
            bar.set_postfix(task=result.task, seed=result.seed)
            bar.update()
            if lines is not None:
                lines.update(result.success)

        try:
            if self.batch_size <= 1:
                return self._run_serial(policy, specs, positions, finished)
            return self._run_batched(policy, specs, positions, finished)
        finally:
            bar.close()
            if any(suite_of(spec).release_envs for spec in {type(s): s for s in specs}.values()):
                self._release_envs()

    def _release_envs(self) -> None:
        """Close the cached envs (and worker processes) after a run with a suite that asks for it
        (``Suite.release_envs``): a stepped LIBERO env holds ~1 GB, and a run builds each task's
        env anyway (building one closes the last task's), so keeping them would hold gigabytes
        through training until the next validation (4 episodes in flight: 6.2 GiB resident after
        the run, 2.2 with them closed; benchmarks/bench_libero_eval_memory.py)."""
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

    def _episode(self, spec: Spec, index: int) -> Episode:
        """Episode ``index`` of the one-at-a-time loop, in this process."""
        envs = _default_envs if self.envs is None else self.envs
        return start_episode(spec, envs, **self._episode_kwargs(index))

    def _finish(
        self, result: EpisodeResult, finished: Callable[[EpisodeResult], None]
    ) -> EpisodeResult:
        if result.frames:
            self._write_video(result)
        finished(result)
        return result

    def _run_serial(
        self, policy: Policy, specs: Sequence[Spec], positions: list[int],
        finished: Callable[[EpisodeResult], None],
    ) -> list[EpisodeResult]:  # fmt: skip
        return [
            self._finish(run_episode(policy, self._episode(spec, i)), finished)
            for i, spec in zip(positions, specs, strict=True)
        ]

    def _run_batched(
        self, policy: Policy, specs: Sequence[Spec], positions: list[int],
        finished: Callable[[EpisodeResult], None],
    ) -> list[EpisodeResult]:  # fmt: skip
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
                    results[running.pop(slot)] = self._finish(reply, finished)
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
