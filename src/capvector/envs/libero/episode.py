"""LIBERO trials under the OpenVLA-OFT / openpi protocol, run by the one rollout loop.

:class:`LiberoEpisode` is to LIBERO what :class:`~capvector.envs.robosuite.episode.Episode` is to robosuite:
:class:`~capvector.eval.rollout.RolloutEvaluator` drives it one chunk at a time, batched with other
episodes and in worker processes alike. The protocol, from OpenVLA-OFT
``experiments/robot/libero/run_libero_eval.py`` and openpi ``examples/libero/main.py``:

- ``env.reset()``, then the task's official initial state number ``trial`` (``set_init_state``),
  then 10 steps of ``[0, 0, 0, 0, 0, 0, -1]`` while objects settle (not counted, not filmed);
- chunks executed open loop up to the suite's step limit; success is the env's ``done`` after a
  step (every BDDL goal predicate holds); an exception of the simulator fails the trial;
- images rotated 180°, the 8-d proprio, the gripper binarised to -1 open / +1 close.

Where it differs from OFT's serial loop, outcomes do not: each env is reset softly
(``hard_reset=False``: the same states as a hard reset, to the bit, in a tenth of the time; tested
against OFT's loop), and the fixtures' placement of trial i is drawn from its own seed
(:attr:`~capvector.envs.libero.spec.LiberoEpisodeSpec.fixture_seed`) rather than from wherever
numpy's global random stream stands after the trials before it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from capvector.envs.base import EnvPool, EpisodeResult, Observation, Spec, as_chunk, end_episode
from capvector.envs.libero.env import (
    NUM_WAIT_STEPS,
    WAIT_ACTION,
    GripperConvention,
    flip_image,
    initial_states,
    libero_observation,
    libero_proprio,
    libero_task,
    make_libero_env,
    seeded_reset,
    to_libero_action,
)
from capvector.envs.libero.spec import LiberoEpisodeSpec
from capvector.errors import CapVectorError

POLICY_GRIPPER: GripperConvention = "close_positive"
"""How a policy's gripper value reads: our policies train on robosuite's -1 open / +1 close, the
convention of LIBERO's HDF5 and of the demos `capvector demos` records."""


def build_libero_env(
    suite: str, task_id: int, cameras: Sequence[str], image_size: int, rendering: str = "auto"
) -> Any:
    """The env of a task as evaluation uses it: ``cameras`` at ``image_size`` drawn by
    ``rendering`` (no camera: no renderer, for state-based policies), soft resets (module
    docstring)."""
    return make_libero_env(
        suite, task_id, cameras=tuple(cameras), image_size=image_size, render=bool(cameras),
        rendering=rendering, hard_reset=False,
    )  # fmt: skip


def start_trial(env: Any, spec: LiberoEpisodeSpec) -> dict[str, Any]:
    """Reset ``env`` and load the trial's initial state: the task's official state ``trial`` with
    the fixtures placed from the trial's seed or, with ``from_demos``, where demo ``trial`` started,
    its fixtures placed from its own seed. The observation; the wait steps are the caller's."""
    if spec.from_demos is None:
        seed, state = spec.fixture_seed, initial_states(spec.suite, spec.task_id)[spec.trial]
    else:
        from capvector.envs.libero.demos import demo_start

        seed, state = demo_start(spec.from_demos, spec.suite, spec.task_id, spec.trial)
    seeded_reset(env, seed)
    return env.set_init_state(state)


def check_trial_starts(specs: Sequence[Spec]) -> None:
    """Every trial that starts from a demo (``from_demos``) finds it; a clear error if not."""
    from capvector.envs.libero.demos import demo_start

    for spec in specs:
        if isinstance(spec, LiberoEpisodeSpec) and spec.from_demos is not None:
            demo_start(spec.from_demos, spec.suite, spec.task_id, spec.trial)


class LiberoEpisode:
    """One LIBERO trial in progress: :meth:`observe`, then :meth:`execute` a chunk, until it
    returns the result (:class:`capvector.envs.base.Episode`).

    ``cameras``/``image_size`` are the policy's (its data spec); ``camera_fovy``, when the policy
    records one, must be the scene's own (LIBERO's cameras are fixed). ``execute_steps`` executes
    only the first k actions of each chunk before re-planning (openpi: 5; OFT: all 8).
    """

    def __init__(
        self,
        spec: LiberoEpisodeSpec,
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
        self.spec = spec
        self.cameras = tuple(cameras)
        self.execute_steps = execute_steps
        key = ("libero", spec.suite, spec.task_id, self.cameras, image_size, spec.rendering)
        self.env = envs.get(
            key,
            lambda: build_libero_env(
                spec.suite, spec.task_id, self.cameras, image_size, spec.rendering
            ),
            alone=True,
        )
        # alone: a LIBERO env holds ~1.2 GB; building one closes the env of the last task
        if camera_fovy:
            _check_fovy(self.env, camera_fovy)
        self.instruction = libero_task(spec.suite, spec.task_id).instruction
        self.limit = spec.step_limit
        self.steps = 0
        self.frames: list[np.ndarray] | None = [] if video and self.cameras else None
        self.fault: str | None = None
        """Why the wait steps failed: the trial fails at its first :meth:`execute`."""
        self.obs = start_trial(self.env, spec)
        try:
            for _ in range(NUM_WAIT_STEPS):
                self.obs, _, _, _ = self.env.step(WAIT_ACTION.tolist())
        except Exception as e:
            self.fault = f"{type(e).__name__} during the wait steps: {e}"
        self._record()

    def observe(self) -> Observation:
        return libero_observation(self.obs, self.instruction, self.cameras)

    def execute(self, actions: Any) -> EpisodeResult | None:
        """Run the chunk open loop (its first ``execute_steps`` actions); the trial's result when
        it ended (success, step limit, simulator exception), else None: observe again."""
        chunk = as_chunk(actions)[: self.execute_steps]
        if self.fault is not None:
            return self._result(False, self.fault)
        for action in chunk:
            if not np.all(np.isfinite(action)):
                return self._result(
                    False, f"non-finite action at step {self.steps}: {action.tolist()}"
                )
            command = to_libero_action(action, POLICY_GRIPPER).tolist()
            try:
                self.obs, _, done, _ = self.env.step(command)
            except Exception as e:  # as OFT and openpi: the trial fails, the evaluation goes on
                return self._result(False, f"{type(e).__name__} at step {self.steps}: {e}")
            self.steps += 1
            self._record()
            if done:
                return self._result(True, None)
            if self.steps >= self.limit:
                return self._result(False, f"step limit ({self.limit}) reached")
        return None

    def _record(self) -> None:
        if self.frames is not None:
            images = [flip_image(self.obs[f"{camera}_image"]) for camera in self.cameras]
            self.frames.append(np.concatenate(images, axis=1))

    def _result(self, success: bool, reason: str | None) -> EpisodeResult:
        final = libero_proprio(self.obs)
        return end_episode(self.spec, success, self.steps, reason, self.frames, final)


def _check_fovy(env: Any, camera_fovy: Mapping[str, float]) -> None:
    model = env.sim.model
    for camera, fovy in camera_fovy.items():
        scene = float(model.cam_fovy[model.camera_name2id(camera)])
        if abs(scene - fovy) > 1e-3:
            raise CapVectorError(
                f"the policy was trained with camera {camera} at a vertical field of view of "
                f"{fovy}°, LIBERO's scene has {scene}°: LIBERO's cameras are fixed, so evaluate "
                "a policy trained on LIBERO's views"
            )
