"""``capvector demos``: record scripted-expert demonstrations to a robomimic/LIBERO-layout HDF5.

Layout (robomimic ``docs/datasets/overview.md``, plus LIBERO's per-demo language)::

    data                      attrs: env_args (JSON: env_name, type=1, env_version, env_kwargs),
                              total, language_instruction, cameras (JSON list),
                              <camera>_intrinsics (3x3 px), camera_fovy (JSON), image_size,
                              proprio_keys (JSON), model_fixes (JSON), noise_std, expert
    data/demo_<i>             attrs: num_samples, model_file (MJCF), seed,
                              language_instruction, first_success (step index)
        actions               (T, 7) float32  clean expert action; gripper -1 open / +1 closed
        executed_actions      (T, 7) float32  what the env executed: action + DART noise on xyz
        states                (T, D) float64  flattened sim state [time, qpos, qvel] before step t
        rewards, dones        (T,)            sparse reward after step t; 1 from the first success
        annotations           (T,) str        what the expert does at step t, where things are
        obs/<camera>_image    (T, H, W, 3) uint8 upright (row 0 = top of the picture)
        obs/<camera>_depth    (T, H, W) float32 metres along the optical axis (--depth)
        obs/robot0_eef_pos (T,3), robot0_eef_quat (T,4) xyzw, robot0_eef_axis_angle (T,3),
        obs/robot0_gripper_qpos (T,2), object positions/quaternions, e.g. cube_pos, cube_quat

Row t of every per-step dataset describes the same moment: the observation before action t.

DART-style noise (Laskey et al. 2017, as in the feasibility study): the env executes the expert's
action plus N(0, noise) on the xyz dims while the *clean* action is the label, so the demos visit
the states a slightly-off policy reaches and show how to recover. A replay of ``executed_actions``
from the demo's seed reproduces the episode exactly (see ``tests/test_sim_rollout.py``).

Seeds: episode attempts use consecutive seeds from ``--seed``; failed attempts are skipped, so the
saved demos record their seed. Evaluation must use seeds no demo used: ``capvector.eval.rollout``
starts its default evaluation seeds at ``EVAL_SEED_START`` (1,000,000).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from capvector.envs.base import DemoSummary
from capvector.envs.recording import Demo, record_file
from capvector.envs.robosuite.annotations import Annotator
from capvector.envs.robosuite.env import (
    DEFAULT_CAMERAS,
    DEFAULT_IMAGE_SIZE,
    PROPRIO_KEYS,
    SimEnv,
    SimulationFault,
    proprio_from,
)
from capvector.envs.robosuite.experts import ScriptedExpert, make_expert
from capvector.errors import CapVectorError
from capvector.io.outputs import check_output

log = logging.getLogger(__name__)

DEFAULT_NOISE = 0.1
"""Std of the DART noise on the xyz action dims (0.1 ≈ 5 mm per step)."""
DEFAULT_EXTRA_STEPS = 6
"""Steps recorded after the first success, so a policy also learns to hold the result."""


@dataclass
class Episode:
    """One recorded episode, arrays stacked over its T steps."""

    seed: int
    first_success: int
    actions: np.ndarray
    executed_actions: np.ndarray
    states: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    annotations: list[str]
    obs: dict[str, np.ndarray]

    @property
    def num_samples(self) -> int:
        return int(self.actions.shape[0])


def record_episode(
    sim: SimEnv,
    expert: ScriptedExpert,
    annotator: Annotator,
    seed: int,
    *,
    noise: float = DEFAULT_NOISE,
    extra_steps: int = DEFAULT_EXTRA_STEPS,
    render: bool = True,
) -> Episode | None:
    """Run the expert from ``seed``'s initial state; the episode, or None if it failed.

    An episode fails when the task is not solved within the task's step limit, when it is not
    solved anymore at the last recorded step, or on a :class:`SimulationFault`.
    """
    obs = sim.reset(seed)
    expert.reset()
    annotator.reset(obs)
    # Noise stream tied to the seed, independent of how many attempts came before.
    rng = np.random.default_rng([seed, 0xDA27])
    rows: dict[str, list[np.ndarray]] = {}
    actions, executed, states, rewards, dones, notes = [], [], [], [], [], []
    first_success = -1
    for t in range(sim.max_steps + extra_steps):
        obs = sim.observation
        if render:
            images, depth = sim.render()
            for cam, img in images.items():
                rows.setdefault(f"{cam}_image", []).append(img)
            for cam, dep in (depth or {}).items():
                rows.setdefault(f"{cam}_depth", []).append(dep)
        for key, value in obs.items():
            rows.setdefault(key, []).append(value)
        step = expert.act(obs)
        action = step.action
        noisy = action.copy()
        if noise > 0:
            noisy[:3] = np.clip(noisy[:3] + rng.normal(0.0, noise, 3), -1.0, 1.0)
        notes.append(annotator(step, obs))
        states.append(sim.flat_state())
        try:
            reward = sim.step(noisy)
        except SimulationFault as e:
            log.warning("seed %d: %s; episode dropped", seed, e)
            return None
        actions.append(action)
        executed.append(noisy)
        rewards.append(reward)
        success = sim.success()
        if success and first_success < 0:
            first_success = t
        dones.append(int(first_success >= 0))
        if first_success < 0 and t + 1 >= sim.max_steps:
            return None
        if first_success >= 0 and t >= first_success + extra_steps:
            if not success:
                return None
            break
    return Episode(
        seed=seed,
        first_success=first_success,
        actions=np.asarray(actions, dtype=np.float32),
        executed_actions=np.asarray(executed, dtype=np.float32),
        states=np.asarray(states, dtype=np.float64),
        rewards=np.asarray(rewards, dtype=np.float64),
        dones=np.asarray(dones, dtype=np.int64),
        annotations=notes,
        obs={key: np.stack(values) for key, values in rows.items()},
    )


def to_demo(ep: Episode, sim: SimEnv, model_xml: str) -> Demo:
    """``ep`` in the layout of the module docstring (images upright as stored: the policy's)."""
    steps: dict[str, np.ndarray | list[str]] = {
        "actions": ep.actions,
        "executed_actions": ep.executed_actions,
        "states": ep.states,
        "rewards": ep.rewards,
        "dones": ep.dones,
        "annotations": ep.annotations,
        **{f"obs/{key}": value for key, value in ep.obs.items()},
    }
    attrs = {
        "model_file": model_xml,
        "language_instruction": sim.instruction,
        "first_success": ep.first_success,
    }
    images = {cam: ep.obs[f"{cam}_image"] for cam in sim.cameras if f"{cam}_image" in ep.obs}
    # the policy's view of each step, by the function a rollout's observation uses
    proprio = np.stack(
        [proprio_from({k: ep.obs[k][t] for k in ep.obs}) for t in range(len(ep.actions))]
    )
    return Demo(ep.seed, steps, attrs, ep.first_success + 1, images, proprio)


def _data_attrs(sim: SimEnv, total: int, noise: float, expert: str) -> dict[str, object]:
    attrs: dict[str, object] = {
        "env_args": json.dumps(sim.env_args()),
        "total": total,
        "language_instruction": sim.instruction,
        "cameras": json.dumps(list(sim.cameras)),
        "camera_fovy": json.dumps(sim.camera_fovy),
        "image_size": sim.image_size,
        "proprio_keys": json.dumps(list(PROPRIO_KEYS)),
        "model_fixes": json.dumps(sim.model_fixes),
        "noise_std": noise,
        "expert": expert,
    }
    attrs.update({f"{cam}_intrinsics": k for cam, k in sim.intrinsics().items()})
    return attrs


def record_demos(
    task: str,
    episodes: int,
    out: str | os.PathLike[str],
    *,
    robot: str = "Panda",
    gripper: str | None = None,
    cameras: Sequence[str] = DEFAULT_CAMERAS,
    image_size: int = DEFAULT_IMAGE_SIZE,
    depth: bool = False,
    seed: int = 0,
    noise: float = DEFAULT_NOISE,
    extra_steps: int = DEFAULT_EXTRA_STEPS,
    max_attempts: int | None = None,
    camera_fovy: Mapping[str, float] | None = None,
    progress: bool = True,
    sim: SimEnv | None = None,
) -> DemoSummary:
    """Record ``episodes`` successful expert demos of ``task`` into ``out`` (written atomically,
    by :func:`capvector.envs.recording.record_file`).

    Attempts use seeds ``seed, seed+1, ...`` until ``episodes`` succeed; more than
    ``max_attempts`` (default ``max(2 * episodes, episodes + 20)``) attempts is an error and
    leaves no file behind. ``sim`` reuses an existing env (its task/robot/cameras win).
    """
    if episodes < 1:
        raise CapVectorError(f"episodes must be at least 1, got {episodes}")
    if max_attempts is None:
        max_attempts = max(2 * episodes, episodes + 20)
    # Checked before any simulation: a bad path must not cost minutes of recording first.
    out = check_output(out, overwrite=True, what="demo file")
    if out.is_dir():
        raise CapVectorError(f"--out {out} is a folder; give a file, e.g. {out / 'demos.hdf5'}")
    own_sim = sim is None
    if sim is None:
        sim = SimEnv(
            task,
            robot,
            gripper=gripper,
            cameras=cameras,
            image_size=image_size,
            depth=depth,
            camera_fovy=camera_fovy,
        )
    expert = make_expert(sim)
    annotator = Annotator(sim.task, sim.spec)
    model_xml = sim.model_xml()
    render = bool(sim.cameras)

    def attempt(attempt_seed: int) -> Demo | None:
        ep = record_episode(
            sim, expert, annotator, attempt_seed, noise=noise, extra_steps=extra_steps,
            render=render,
        )  # fmt: skip
        return None if ep is None else to_demo(ep, sim, model_xml)

    bar = tqdm(total=episodes, desc=f"{sim.task} demos", unit="demo", disable=not progress)
    try:
        return record_file(
            out, DemoSummary(out, sim.task), episodes, attempt, seed=seed,
            max_attempts=max_attempts,
            give_up=f"the {sim.task} expert on {sim.robot}: raise --max-attempts or lower "
            f"--noise (now {noise})",
            data_attrs=lambda s: _data_attrs(sim, s.samples, noise, type(expert).__name__),
            bar=bar,
        )  # fmt: skip
    finally:
        bar.close()
        if own_sim:
            sim.close()
