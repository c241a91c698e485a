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
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from capvector.envs.base import DemoSummary
from capvector.envs.metaworld.env import MetaWorldEnv
from capvector.envs.metaworld.experts import MetaWorldExpert
from capvector.envs.metaworld.spec import (
    CAMERAS,
    MAX_STEPS,
    PROPRIO_KEYS,
    SUITE_NAME,
    task_set_tasks,
)
from capvector.envs.recording import Demo, record_file
from capvector.errors import CapVectorError
from capvector.io.outputs import check_output

DEFAULT_NOISE = 0.2
"""Std of the DART noise on the xyz action dims (Meta-World units: 0.2 = 2 mm a step)."""
DEFAULT_EXTRA_STEPS = 6
"""Steps recorded after the first success, so a policy also learns to hold the result."""
DEFAULT_IMAGE_SIZE = 64


def record_episode(env: MetaWorldEnv, seed: int, *, noise: float, extra_steps: int) -> Demo | None:
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
    steps = {key: np.stack(values) for key, values in rows.items()}
    for key in ("actions", "executed_actions"):
        steps[key] = steps[key].astype(np.float32)
    return Demo(
        seed=seed,
        steps=dict(steps),
        attrs={"language_instruction": env.instruction, "first_success": first_success},
        length=first_success + 1,
        # frames are stored upright, as the episode shows them
        images={cam: steps[f"obs/{cam}_image"] for cam in env.cameras},
        proprio=np.concatenate([steps[f"obs/{k}"] for k in PROPRIO_KEYS], 1).astype(np.float32),
    )


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
    env = MetaWorldEnv(task, cameras=cameras, image_size=image_size)

    def data_attrs(summary: DemoSummary) -> dict[str, Any]:
        return {
            "env_args": json.dumps(
                {"env_name": task, "type": SUITE_NAME, "env_kwargs": {"max_steps": MAX_STEPS}}
            ),
            "total": summary.samples,
            "language_instruction": env.instruction,
            "cameras": json.dumps(list(cameras)),
            "image_size": image_size,
            "proprio_keys": json.dumps(list(PROPRIO_KEYS)),
            "noise_std": noise,
            "expert": type(MetaWorldExpert(task).policy).__name__,
        }

    try:
        return record_file(
            out,
            DemoSummary(path=out, task=task),
            episodes,
            lambda seed: record_episode(env, seed, noise=noise, extra_steps=extra_steps),
            seed=seed,
            max_attempts=max_attempts,
            give_up="raise --max-attempts or lower --noise",
            data_attrs=data_attrs,
        )
    finally:
        env.close()


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
