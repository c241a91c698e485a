"""Meta-World expert demonstrations in the robomimic-layout HDF5 that ``capvector demos`` writes
for robosuite (:mod:`capvector.envs.robosuite.demos`): one file per task, ``<out>/<task>.hdf5``,
read by :mod:`capvector.data.hdf5` with the default ``proprio_keys``.

Per file: ``data`` attrs ``env_args`` (JSON: suite, task, protocol), ``language_instruction``
(LeRobot's description of the task), ``cameras``, ``image_size``, ``proprio_keys``, ``noise_std``,
``expert``; per ``data/demo_<i>``: attrs ``num_samples``, ``seed``, ``language_instruction``,
``first_success``, and

    actions            (T, 7) float32  the expert's clean action in our convention
                                       (dx, dy, dz, 0, 0, 0, gripper); see ``env.py``
    executed_actions   (T, 7) float32  what the env executed: the action + DART noise on xyz
    states             (T, D) float64  [time, qpos, qvel] before step t
    rewards, dones     (T,)            1 after a step that solved the task / from the first success
    obs/corner2_image  (T, H, W, 3) uint8 upright
    obs/robot0_eef_pos (T, 3), robot0_eef_axis_angle (T, 3), robot0_gripper_qpos (T, 2)
    obs/metaworld_state (T, 39)        Meta-World's state observation (what the expert read)

DART noise (Laskey et al. 2017, as our robosuite demos): the env executes the expert's xyz plus
N(0, ``noise``) (0.2 = 2 mm a step in Meta-World's 1 cm units) so the demos show recoveries;
the label is the clean action. Attempts use seeds ``seed, seed + 1, ...``; failed ones are skipped.
Evaluation seeds start at ``EVAL_SEED_START`` (1,000,000), far above.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm import tqdm

from capvector.envs.base import DemoSummary
from capvector.envs.metaworld.env import PROPRIO_KEYS, MetaWorldEnv
from capvector.envs.metaworld.experts import MetaWorldExpert
from capvector.envs.metaworld.spec import CAMERAS, MAX_STEPS, SUITE_NAME, task_set_tasks
from capvector.errors import CapVectorError
from capvector.io.frames import write_frames
from capvector.io.outputs import atomic_write_file, check_output

DEFAULT_NOISE = 0.2
"""Std of the DART noise on the xyz action dims (Meta-World units: 0.2 = 2 mm a step)."""
DEFAULT_EXTRA_STEPS = 6
"""Steps recorded after the first success, so a policy also learns to hold the result."""
DEFAULT_IMAGE_SIZE = 64


def record_episode(
    env: MetaWorldEnv, seed: int, *, noise: float, extra_steps: int
) -> dict[str, np.ndarray] | None:
    """The expert from ``seed``'s initial state, recorded; None if it did not solve the task in
    the protocol's 500 steps, or was no longer solved at the last recorded step."""
    expert = MetaWorldExpert(env.task)
    rng = np.random.default_rng([seed, 0xDA27])  # noise tied to the seed, not to past attempts
    env.reset(seed, MAX_STEPS + extra_steps)
    rows: dict[str, list[np.ndarray]] = {}
    first_success = -1
    for t in range(MAX_STEPS + extra_steps):
        for cam, image in env.render().items():
            rows.setdefault(f"obs/{cam}_image", []).append(image)
        for key, value in env.proprio_parts().items():
            rows.setdefault(f"obs/{key}", []).append(value)
        rows.setdefault("obs/metaworld_state", []).append(env.state.copy())
        rows.setdefault("states", []).append(env.flat_state())
        label = expert.label(env.state)
        executed = label.copy()
        if noise > 0:
            executed[:3] = np.clip(executed[:3] + rng.normal(0.0, noise, 3), -1.0, 1.0)
        solved = env.step(executed)
        if env.faulted:
            return None
        rows.setdefault("actions", []).append(label)
        rows.setdefault("executed_actions", []).append(executed)
        rows.setdefault("rewards", []).append(np.float64(solved))
        if solved and first_success < 0:
            first_success = t
        rows.setdefault("dones", []).append(np.int64(first_success >= 0))
        if first_success < 0 and t + 1 >= MAX_STEPS:
            return None
        if first_success >= 0 and t >= first_success + extra_steps:
            if not solved:
                return None
            break
    out = {key: np.stack(values) for key, values in rows.items()}
    out["first_success"] = np.int64(first_success)
    return out


def _write_demo(
    group: h5py.Group, demo: dict[str, np.ndarray], seed: int, env: MetaWorldEnv
) -> None:
    group.attrs["num_samples"] = demo["actions"].shape[0]
    group.attrs["seed"] = seed
    group.attrs["language_instruction"] = env.instruction
    group.attrs["first_success"] = int(demo["first_success"])
    for key, value in demo.items():
        if key == "first_success":
            continue
        if key.endswith("_image"):
            write_frames(group.require_group("obs"), key.removeprefix("obs/"), value)
        elif key in ("actions", "executed_actions"):
            group.create_dataset(key, data=value.astype(np.float32))
        else:
            group.create_dataset(key, data=value)


def record_task(
    task: str,
    episodes: int,
    out: str | os.PathLike[str],
    *,
    cameras: Sequence[str] = CAMERAS,
    image_size: int = DEFAULT_IMAGE_SIZE,
    seed: int = 0,
    noise: float = DEFAULT_NOISE,
    extra_steps: int = DEFAULT_EXTRA_STEPS,
    max_attempts: int | None = None,
) -> DemoSummary:
    """``episodes`` successful expert demos of ``task`` in the file ``out`` (written atomically;
    more than ``max_attempts``, default ``max(2 * episodes, episodes + 20)``, attempts is an error
    that leaves no file)."""
    if episodes < 1:
        raise CapVectorError(f"episodes must be at least 1, got {episodes}")
    if not cameras:
        raise CapVectorError("Meta-World demos need a camera, e.g. --cameras corner2")
    max_attempts = max_attempts or max(2 * episodes, episodes + 20)
    out = check_output(out, overwrite=True, what="demo file")
    summary = DemoSummary(path=out, task=task)
    start = time.perf_counter()
    env = MetaWorldEnv(task, cameras=cameras, image_size=image_size)
    try:
        with atomic_write_file(out, what="demo file") as tmp, h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            while summary.demos < episodes:
                if summary.attempts >= max_attempts:
                    raise CapVectorError(
                        f"the {task} expert succeeded in only {summary.demos} of {summary.attempts}"
                        f" attempts (seeds {seed}..{seed + summary.attempts - 1}), short of the "
                        f"{episodes} demos asked for: raise --max-attempts or lower --noise"
                    )
                attempt = seed + summary.attempts
                summary.attempts += 1
                demo = record_episode(env, attempt, noise=noise, extra_steps=extra_steps)
                if demo is None:
                    continue
                _write_demo(data.create_group(f"demo_{summary.demos}"), demo, attempt, env)
                summary.demos += 1
                summary.samples += int(demo["actions"].shape[0])
                summary.seeds.append(attempt)
                summary.lengths.append(int(demo["first_success"]) + 1)
            data.attrs["env_args"] = json.dumps(
                {"env_name": task, "type": SUITE_NAME, "env_kwargs": {"max_steps": MAX_STEPS}}
            )
            data.attrs["total"] = summary.samples
            data.attrs["language_instruction"] = env.instruction
            data.attrs["cameras"] = json.dumps(list(cameras))
            data.attrs["image_size"] = image_size
            data.attrs["proprio_keys"] = json.dumps(list(PROPRIO_KEYS))
            data.attrs["noise_std"] = noise
            data.attrs["expert"] = type(MetaWorldExpert(task).policy).__name__
    finally:
        env.close()
    summary.seconds = time.perf_counter() - start
    return summary


def record_task_set(
    task_set: str,
    episodes: int,
    out: str | os.PathLike[str],
    *,
    progress: bool = True,
    **options: Any,
) -> list[DemoSummary]:
    """A folder ``out`` with one file per task of ``task_set`` (``<task>.hdf5``), each written
    atomically as it finishes; ``options`` as :func:`record_task`'s; ``progress``: a bar over
    the tasks."""
    tasks = task_set_tasks(task_set)
    folder = Path(out)
    if folder.exists() and not folder.is_dir():
        raise CapVectorError(f"--out {folder} is a file; give a folder for one file per task")
    folder.mkdir(parents=True, exist_ok=True)
    summaries = []
    for task in tqdm(tasks, desc=f"{task_set} demos", unit="task", disable=not progress):
        summaries.append(record_task(task, episodes, folder / f"{task}.hdf5", **options))
    return summaries
