"""``capvector demos --suite``: scripted-expert demos of LIBERO tasks in LIBERO's released HDF5 layout.

One file per task, named as LIBERO names its released files (``<bddl name>_demo.hdf5``), with the
keys and attributes of LIBERO's ``scripts/create_dataset.py`` (the script that made the released
datasets), so a user's real LIBERO data and these demos load through the same reader::

    data                  attrs: env_name, problem_info (JSON: problem_name, domain_name,
                          language_instruction), macros_image_convention ("opengl"),
                          bddl_file_name, bddl_file_content, env_args (JSON: type=1, env_name,
                          problem_name, bddl_file, env_kwargs), num_demos, total;
                          ours: expert, suite, task_id, seeds (JSON); with --depth
                          <camera>_intrinsics (3x3 px, e.g. robot0_eye_in_hand_intrinsics) of
                          the frames as stored: rows bottom-up, so fy < 0 and cy = H - cy_upright
    data/demo_<i>         attrs: num_samples, model_file (MJCF), init_state; ours: seed
        actions           (T, 7) float64  gripper -1 open / +1 closed
        states            (T, D) float64  flattened sim state before step t
        robot_states      (T, 9)          gripper qpos (2), eef pos (3), eef quat (4, xyzw)
        rewards, dones    (T,) uint8      1 at the last step only (as create_dataset.py)
        obs/agentview_rgb, obs/eye_in_hand_rgb   (T, H, W, 3) uint8, as the env renders them
                          (OpenGL convention: rows bottom-up, like LIBERO's)
        ours: annotations (T,) str   what the expert does at step t, where every movable object
                          is and what it stands on (:class:`~capvector.envs.libero.annotations.LiberoAnnotator`)
        ours (--depth): obs/agentview_depth, obs/eye_in_hand_depth   (T, H, W) float32 metres
                          along the optical axis, in the orientation of the ``_rgb`` frames
        obs/ee_states (T, 6) eef pos + axis-angle, obs/ee_pos (T, 3), obs/ee_ori (T, 3),
        obs/gripper_states (T, 2), obs/joint_states (T, 7)

Start states: LIBERO's own placement initializer (an ``env.reset()`` after seeding numpy's global
RNG, which LIBERO's region samplers draw from) with seeds ``seed, seed+1, ...``; a placement
within :data:`MIN_DISTANCE` of one of the task's official evaluation initial states (in every
object coordinate) is skipped, so no demo starts where an evaluation trial does. The 10 wait
steps of the evaluation protocol run first (objects settle) and are not recorded; recording stops
at the first step LIBERO's success predicate holds, as a released demo ends when the task is done.

Depth is drawn by the fast renderer (:class:`~capvector.envs.libero.render.FastRenderEnv`) in
metres, or converted from robosuite's depth buffer with its ``get_real_depth_map`` when robosuite
renders. The reader (:class:`capvector.data.hdf5.HDF5RobotDataset`) rotates RGB, depth and
intrinsics alike, so back-projecting its depth with its intrinsics gives camera-frame points
(``tests/test_libero_depth.py``).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import queue
import signal
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from robosuite.utils import transform_utils as T
from tqdm import tqdm

from capvector.envs.base import DemoSummary, Observation
from capvector.envs.libero.annotations import LiberoAnnotator
from capvector.envs.libero.env import (
    LIBERO_NUM_TASKS,
    Rendering,
    drawn_by,
    initial_states,
    libero_observation,
    libero_task,
    make_libero_env,
    max_steps,
    seeded_reset,
)
from capvector.envs.libero.experts import LiberoPlaceExpert, place_goal, run_trial, task_env
from capvector.envs.recording import SKIP, Demo, record_file
from capvector.envs.robosuite.env import camera_intrinsics
from capvector.errors import CapVectorError, unknown_name
from capvector.io.outputs import check_output, remove_writer_leftovers

LIBERO_IMAGE_SIZE = 128
"""The released datasets' image size (``create_dataset.py``: ``camera_heights=128``)."""
MIN_DISTANCE = 1e-3
"""A demo placement differs from every official init state by more than this (m or rad) in at
least one object coordinate."""
CAMERA_KEYS = {"agentview": "agentview_rgb", "robot0_eye_in_hand": "eye_in_hand_rgb"}
"""Env camera -> the dataset key LIBERO stores its images under."""


def depth_key_for_rgb(rgb_key: str) -> str:
    """Our depth key beside LIBERO's image key: ``eye_in_hand_rgb`` -> ``eye_in_hand_depth``."""
    return rgb_key.removesuffix("_rgb") + "_depth"


def stored_intrinsics(fovy_degrees: float, image_size: int) -> np.ndarray:
    """(3, 3) pinhole intrinsics of frames stored as LIBERO stores them (OpenGL convention: the
    upright image's rows bottom-up, row v of the stored frame is row H - 1 - v upright): the
    upright intrinsics with the vertical axis reversed, ``fy -> -fy``, ``cy -> H - cy``."""
    k = camera_intrinsics(fovy_degrees, image_size)
    flip_rows = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, image_size], [0.0, 0.0, 1.0]])
    return flip_rows @ k


def _metric_depth(env: Any, obs: Any, camera: str) -> np.ndarray:
    """(H, W) float32 metres: the fast renderer's as is, robosuite's buffer through its own
    ``camera_utils.get_real_depth_map``."""
    from capvector.envs.libero.render import FastRenderEnv

    depth = np.asarray(obs[f"{camera}_depth"])
    if not isinstance(env, FastRenderEnv):
        from robosuite.utils.camera_utils import get_real_depth_map

        depth = get_real_depth_map(task_env(env).sim, depth)
    return depth.reshape(depth.shape[:2]).astype(np.float32)


@dataclass
class TaskDemos(DemoSummary):
    """A task's :class:`~capvector.envs.base.DemoSummary` (``task``: ``libero_spatial/3``)."""

    task_id: int = 0
    skipped_seeds: list[int] = field(default_factory=list)
    """Seeds whose placement was an official init state's (never recorded)."""


def demo_file_name(suite: str, task_id: int) -> str:
    """``<bddl name>_demo.hdf5``, the released dataset's file name for the task."""
    return libero_task(suite, task_id).bddl_file.stem + "_demo.hdf5"


def is_official_state(state: np.ndarray, official: np.ndarray, object_qpos: np.ndarray) -> bool:
    """True if ``state`` is within :data:`MIN_DISTANCE` of a row of ``official`` in every object
    coordinate (``object_qpos``: the qpos indices of the scene's free objects)."""
    cols = 1 + object_qpos  # flattened states start with the time
    return bool((np.abs(official[:, cols] - state[cols]).max(axis=1) <= MIN_DISTANCE).any())


def _object_qpos(env: Any) -> np.ndarray:
    """qpos indices of the movable objects' joints (the robot's excluded)."""
    inner = task_env(env)
    model = inner.sim.model._model
    out: list[int] = []
    for obj in inner.objects_dict.values():
        for joint in obj.joints:
            jid = inner.sim.model.joint_name2id(joint)
            start = int(model.jnt_qposadr[jid])
            width = {0: 7, 1: 4, 2: 1, 3: 1}[int(model.jnt_type[jid])]
            out.extend(range(start, start + width))
    return np.asarray(sorted(out), dtype=np.int64)


def demo_start(folder: str | Path, suite: str, task_id: int, index: int) -> tuple[int, np.ndarray]:
    """Where demo ``index`` of the task's file in ``folder`` started: the seed of its placement
    (:func:`seeded_reset`, which also placed the fixtures) and its first state (after the wait
    steps)."""
    path = Path(folder) / demo_file_name(suite, task_id)
    if not path.is_file():
        raise CapVectorError(
            f"from_demos: {folder} has no demos of {suite} task {task_id} ({path.name}); record "
            f"them with `capvector demos --suite {suite} --tasks {task_id} --out {folder}`"
        )
    try:
        file = h5py.File(path, "r")
    except OSError as exc:  # cut short while copying, or not HDF5 (as data/hdf5.py says it)
        raise CapVectorError(
            f"from_demos: {path} is not a readable HDF5 file (h5py: {exc}); re-record or "
            "re-download it"
        ) from exc
    with file as f:
        demos, key = f["data"], f"demo_{index}"
        if key not in demos:
            raise CapVectorError(
                f"from_demos: {path} has {len(demos)} demos and trial {index} starts where "
                f"{key} did: ask for at most {len(demos)} trials"
            )
        if "seed" not in demos[key].attrs:
            raise CapVectorError(
                f"from_demos: {path} {key} has no placement seed: only demos recorded by "
                "`capvector demos` have one (LIBERO's released files do not)"
            )
        return int(demos[key].attrs["seed"]), np.asarray(demos[key]["states"][0])


def record_episode(
    env: Any, limit: int, cameras: dict[str, str], seed: int, *, depth: bool = False
) -> Demo | None:
    """One demo from the env's current (just placed, from ``seed``) state, or None if the expert
    did not succeed in ``limit`` steps. ``depth``: the env renders depth (``camera_depths=True``).
    Its policy view is what a LIBERO trial shows the policy (:func:`libero_observation`)."""
    rows: dict[str, list[np.ndarray]] = {}
    seen: list[Observation] = []
    inner = task_env(env)
    goal = place_goal(env)
    annotator = LiberoAnnotator(inner, goal.obj, goal.relation, goal.target)

    def record(obs: Any, step: Any, t: int) -> None:
        if t == 0:  # after the wait steps: the objects have settled
            annotator.reset()
        # as create_dataset.py: eef position and robosuite's axis-angle of the eef quaternion
        ee_states = np.concatenate(
            [obs["robot0_eef_pos"], T.quat2axisangle(obs["robot0_eef_quat"])]
        )
        values = {
            "actions": step.action,
            "states": inner.sim.get_state().flatten(),
            "robot_states": inner.get_robot_state_vector(obs),
            "obs/ee_states": ee_states,
            "obs/ee_pos": ee_states[:3],
            "obs/ee_ori": ee_states[3:],
            "obs/gripper_states": np.asarray(obs["robot0_gripper_qpos"]),
            "obs/joint_states": np.asarray(obs["robot0_joint_pos"]),
            **{f"obs/{key}": np.asarray(obs[f"{cam}_image"]) for cam, key in cameras.items()},
        }
        if depth:
            for cam, key in cameras.items():
                values[f"obs/{depth_key_for_rgb(key)}"] = _metric_depth(env, obs, cam)
        for key, value in values.items():
            rows.setdefault(key, []).append(np.array(value))
        notes.append(annotator(step.phase, obs))
        seen.append(libero_observation(obs, "", list(cameras)))

    notes: list[str] = []
    result = run_trial(env, None, limit, on_step=record)
    if not result.success:
        return None
    steps: dict[str, np.ndarray | list[str]] = {k: np.stack(v) for k, v in rows.items()}
    steps["annotations"] = notes
    length = len(notes)
    last = np.zeros(length, np.uint8)
    last[-1] = 1
    steps["rewards"], steps["dones"] = last, last.copy()
    attrs = {"model_file": inner.sim.model.get_xml(), "init_state": rows["states"][0]}
    images = {cam: np.stack([o["images"][cam] for o in seen]) for cam in cameras}
    proprio = np.stack([o["proprio"] for o in seen])
    return Demo(seed, steps, attrs, length, images, proprio)


def _data_attrs(
    env: Any,
    suite: str,
    task_id: int,
    summary: DemoSummary,
    image_size: int,
    depth_cameras: Sequence[str] = (),
) -> dict[str, Any]:
    task = libero_task(suite, task_id)
    inner = task_env(env)
    model = inner.sim.model
    attrs: dict[str, Any] = {}
    for camera in depth_cameras:  # the attribute names capvector.envs.robosuite.demos writes
        fovy = float(model.cam_fovy[model.camera_name2id(camera)])
        attrs[f"{camera}_intrinsics"] = stored_intrinsics(fovy, image_size)
    problem = inner.parsed_problem
    problem_info = {
        "problem_name": problem["problem_name"],
        "domain_name": "robosuite",
        "language_instruction": task.instruction,
    }
    env_name = type(inner).__name__
    env_kwargs = {
        "bddl_file_name": str(task.bddl_file),
        "camera_names": ["robot0_eye_in_hand", "agentview"],
        "camera_heights": image_size,
        "camera_widths": image_size,
        "control_freq": inner.control_freq,
    }
    env_args = {
        "type": 1,
        "env_name": env_name,
        "problem_name": problem["problem_name"],
        "bddl_file": str(task.bddl_file),
        "env_kwargs": env_kwargs,
    }
    return attrs | {
        "env_name": env_name,
        "problem_info": json.dumps(problem_info),
        "macros_image_convention": "opengl",
        "bddl_file_name": str(task.bddl_file),
        "bddl_file_content": task.bddl_file.read_text(),
        "env_args": json.dumps(env_args),
        "num_demos": summary.demos,
        "total": sum(summary.lengths),
        "expert": LiberoPlaceExpert.__name__,
        "suite": suite,
        "task_id": task_id,
        "seeds": json.dumps(summary.seeds),
        "rendering": drawn_by(env),
    }


def record_task(
    suite: str,
    task_id: int,
    episodes: int,
    out_dir: Path,
    *,
    image_size: int = LIBERO_IMAGE_SIZE,
    cameras: Sequence[str] = tuple(CAMERA_KEYS),
    depth: bool = False,
    seed: int = 0,
    max_attempts: int | None = None,
    bar: Any = None,
    rendering: Rendering = "auto",
) -> TaskDemos:
    """``episodes`` successful demos of one task, written atomically to ``out_dir``; ``depth``
    adds each camera's depth in metres and its intrinsics; ``rendering`` draws the images
    (:data:`~capvector.envs.libero.env.Rendering`; the same states and actions whoever draws)."""
    unknown = [c for c in cameras if c not in CAMERA_KEYS]
    if unknown:
        raise CapVectorError(f"LIBERO demos record cameras {list(CAMERA_KEYS)}, not {unknown}")
    if depth and not cameras:
        raise CapVectorError("--depth needs cameras to render; drop the bare --cameras")
    max_attempts = max_attempts or max(2 * episodes, episodes + 20)
    path = out_dir / demo_file_name(suite, task_id)
    summary = TaskDemos(path, f"{suite}/{task_id}", task_id=task_id)
    env = make_libero_env(
        suite,
        task_id,
        cameras=list(cameras),
        image_size=image_size,
        render=bool(cameras),
        rendering=rendering,
        **({"camera_depths": True} if depth else {}),
    )
    keys = {c: CAMERA_KEYS[c] for c in cameras}
    try:
        official = initial_states(suite, task_id)
        object_qpos = _object_qpos(env)

        def attempt(attempt_seed: int) -> Demo | None | str:
            seeded_reset(env, attempt_seed)
            if is_official_state(task_env(env).sim.get_state().flatten(), official, object_qpos):
                summary.skipped_seeds.append(attempt_seed)
                return SKIP
            return record_episode(env, max_steps(suite), keys, attempt_seed, depth=depth)

        depth_cameras = list(cameras) if depth else []
        return record_file(
            path, summary, episodes, attempt, seed=seed, max_attempts=max_attempts,
            give_up="the LIBERO expert: raise --max-attempts", bar=bar,
            data_attrs=lambda s: _data_attrs(env, suite, task_id, s, image_size, depth_cameras),
        )  # fmt: skip
    finally:
        env.close()


def record_suite(
    suite: str,
    episodes_per_task: int,
    out: str | os.PathLike[str],
    *,
    tasks: Sequence[int] | None = None,
    image_size: int = LIBERO_IMAGE_SIZE,
    cameras: Sequence[str] = tuple(CAMERA_KEYS),
    depth: bool = False,
    seed: int = 0,
    max_attempts: int | None = None,
    progress: bool = True,
    workers: int = 0,
    rendering: Rendering = "auto",
) -> list[TaskDemos]:
    """Demos of every task in ``tasks`` (default: the whole suite), one file per task in ``out``;
    ``workers`` processes record tasks side by side (0: this process). A task's demos depend only
    on its id and ``seed``, so the files are the same either way."""
    if suite not in LIBERO_NUM_TASKS:
        raise unknown_name("LIBERO suite", suite, LIBERO_NUM_TASKS)
    if episodes_per_task < 1:
        raise CapVectorError(f"--episodes-per-task must be at least 1, got {episodes_per_task}")
    if workers < 0:
        raise CapVectorError(f"--workers must be 0 (this process) or more, got {workers}")
    task_ids = list(range(LIBERO_NUM_TASKS[suite])) if not tasks else list(tasks)
    for task_id in task_ids:
        libero_task(suite, task_id)  # a bad id fails before any simulation
    if rendering not in typing.get_args(Rendering):
        raise unknown_name("rendering", rendering, typing.get_args(Rendering))
    out_dir = check_output(out, overwrite=True, what="demo folder")
    if out_dir.exists() and not out_dir.is_dir():
        raise CapVectorError(
            f"--out {out_dir} is a file; with --suite give a folder (one file per task)"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    bar = tqdm(
        total=len(task_ids) * episodes_per_task,
        desc=f"{suite} demos",
        unit="demo",
        disable=not progress,
    )
    task_args = dict(
        suite=suite, episodes=episodes_per_task, out_dir=out_dir, image_size=image_size,
        cameras=cameras, depth=depth, seed=seed, max_attempts=max_attempts, rendering=rendering,
    )  # fmt: skip
    try:
        if workers > 0 and len(task_ids) > 1:
            return _record_in_workers(task_ids, min(workers, len(task_ids)), bar, task_args)
        return [record_task(task_id=task_id, bar=bar, **task_args) for task_id in task_ids]
    finally:
        bar.close()


class _QueueBar:
    """A worker's stand-in for the progress bar: each demo recorded is a message to the parent."""

    def __init__(self, messages: Any) -> None:
        self.messages = messages

    def update(self, n: int = 1) -> None:
        self.messages.put(n)

    def set_postfix(self, **_: Any) -> None:
        pass


_worker_bar: _QueueBar | None = None


def _start_worker(messages: Any, out_dir: Path) -> None:
    global _worker_bar
    _worker_bar = _QueueBar(messages)

    def stop(*_: Any) -> None:
        # The pool stops its workers with SIGTERM when a task fails, and waits for each. Raising
        # SystemExit here was not enough: a handler that runs inside a finalizer (__del__ of the
        # env's renderer, say) has its exception ignored, and the idle worker it missed kept the
        # pool, the command and a test waiting forever. So remove what this worker was writing
        # and end on the spot: no file is left half-written in the demo folder either way.
        remove_writer_leftovers(out_dir, os.getpid())
        os._exit(128 + signal.SIGTERM)

    signal.signal(signal.SIGTERM, stop)


def _record_task_in_worker(**task_args: Any) -> TaskDemos:
    return record_task(bar=_worker_bar, **task_args)


def _record_in_workers(
    task_ids: list[int], workers: int, bar: Any, task_args: dict[str, Any]
) -> list[TaskDemos]:
    """Each task in a spawned process (no GL context or threads of this one copied), ``workers``
    at a time; the bar advances as demos land. A failed task stops the others (the pool's exit
    terminates them; their files are written atomically, so none is left half-written)."""
    context = mp.get_context("spawn")
    messages = context.Queue()
    out_dir = task_args["out_dir"]
    with context.Pool(workers, initializer=_start_worker, initargs=(messages, out_dir)) as pool:
        pending = [
            pool.apply_async(_record_task_in_worker, kwds={"task_id": t, **task_args})
            for t in task_ids
        ]
        shown = 0
        while not all(result.ready() for result in pending):
            with contextlib.suppress(queue.Empty):
                bar.update(messages.get(timeout=0.5))
                shown += 1
            for result in pending:
                if result.ready() and not result.successful():
                    result.get()  # raises the task's error
        summaries = [result.get() for result in pending]
        for _ in range(sum(summary.demos for summary in summaries) - shown):
            bar.update(messages.get(timeout=60))  # the last demos' messages, still in flight
        # Every task is done: the workers exit on the pool's sentinels, not on the SIGTERM that
        # leaving the block sends (an idle worker once outlived that SIGTERM, blocked on the
        # pool's task lock, and the pool's join waited for it forever after the last file).
        pool.close()
        pool.join()
        return summaries
