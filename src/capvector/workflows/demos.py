"""``capvector demos``: record scripted-expert demonstrations of robosuite tasks
(:mod:`capvector.envs.robosuite.demos`) or of a LIBERO suite (:mod:`capvector.envs.libero.demos`)."""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np

from capvector.envs.robosuite.demos import (
    DEFAULT_CAMERAS,
    DEFAULT_EXTRA_STEPS,
    DEFAULT_IMAGE_SIZE,
    DEFAULT_NOISE,
    record_demos,
)
from capvector.errors import CapVectorError
from capvector.tool_cli import run_tool


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``capvector demos``; returns the process exit code."""
    return run_tool(demos_cli, argv, "demos")


def demos_cli(
    out: str,
    task: str | None = None,
    episodes: int | None = None,
    suite: str | None = None,
    tasks: Sequence[int] = (),
    episodes_per_task: int | None = None,
    robot: str = "Panda",
    gripper: str | None = None,
    image_size: int | None = None,
    cameras: Sequence[str] = DEFAULT_CAMERAS,
    depth: bool = False,
    seed: int = 0,
    noise: float = DEFAULT_NOISE,
    extra_steps: int = DEFAULT_EXTRA_STEPS,
    max_attempts: int | None = None,
    fovy: Sequence[str] = (),
    progress: bool = True,
    workers: int = 0,
) -> None:
    """Record scripted-expert demonstrations: robosuite tasks (--task) to robomimic-layout HDF5,
    or a LIBERO suite (--suite) to LIBERO's released layout, one file per task.

    Args:
        out: HDF5 file to write (atomically); with --suite a folder for one file per task
        task: Lift, Stack, PickPlaceCan, ... (capvector.envs.robosuite.tasks)
        episodes: successful demos to save (--task)
        suite: a LIBERO suite (libero_spatial, libero_object, libero_goal, ...) instead of --task
        tasks: with --suite, the task ids to record (default: every task of the suite)
        episodes_per_task: with --suite, successful demos per task
        robot: robosuite arm: Panda, IIWA, UR5e, Kinova3, ...
        gripper: gripper override, e.g. PandaGripper (arms whose default gripper has 6 joints
            need one)
        cameras: cameras to render; none (a bare --cameras) records low-dim demos only, fast
        depth: also store <camera>_depth in metres and the cameras' intrinsics
        image_size: image height and width (default 64; LIBERO: 128, its released size)
        seed: first seed; attempts use seed, seed+1, ... (LIBERO: seeds of its placement
            initializer, skipping any that lands on an official evaluation initial state)
        noise: DART noise std on xyz
        max_attempts: attempts before giving up (default: max(2 x episodes, episodes + 20))
        fovy: CAMERA=DEG: override a camera's vertical field of view (task defaults: Lift/Stack
            agentview=35)
        progress: show the progress bar
        workers: with --suite, processes recording tasks side by side, a task each (0: this
            one); the files are the same either way
    """
    if suite is not None:
        _libero_demos(suite, tasks, episodes_per_task, out, task, episodes, image_size, cameras,
                      depth, seed, max_attempts, progress, workers)  # fmt: skip
        return
    if task is None or episodes is None:
        raise CapVectorError(
            "give --task and --episodes (robosuite), or --suite and --episodes-per-task (LIBERO) "
            "(see capvector demos --help)"
        )
    if tasks or episodes_per_task is not None or workers:
        raise CapVectorError(
            "--tasks, --episodes-per-task and --workers go with --suite; with --task give --episodes"
        )
    image_size = DEFAULT_IMAGE_SIZE if image_size is None else image_size
    summary = record_demos(
        task, episodes, out, robot=robot, gripper=gripper, cameras=cameras, image_size=image_size,
        depth=depth, seed=seed, noise=noise, extra_steps=extra_steps, max_attempts=max_attempts,
        camera_fovy=_parse_fovy(fovy), progress=progress,
    )  # fmt: skip
    lengths = np.asarray(summary.lengths)
    print(
        f"wrote {summary.demos} {task} demos ({robot}, {summary.samples} samples) to "
        f"{summary.path}: expert success {summary.demos}/{summary.attempts} attempts "
        f"({summary.success_rate:.1%}), steps to success mean {lengths.mean():.1f} "
        f"max {lengths.max()}, {summary.seconds / summary.demos:.2f} s/demo"
    )


def _libero_demos(
    suite: str,
    tasks: Sequence[int],
    episodes_per_task: int | None,
    out: str,
    task: str | None,
    episodes: int | None,
    image_size: int | None,
    cameras: Sequence[str],
    depth: bool,
    seed: int,
    max_attempts: int | None,
    progress: bool,
    workers: int,
) -> None:
    if task is not None or episodes is not None:
        raise CapVectorError(
            "--suite records LIBERO tasks: give --tasks ID ... and --episodes-per-task, not --task/--episodes"
        )
    if episodes_per_task is None:
        raise CapVectorError("--suite needs --episodes-per-task N")
    from capvector.envs.libero.demos import LIBERO_IMAGE_SIZE, record_suite

    summaries = record_suite(
        suite, episodes_per_task, out, tasks=tasks, cameras=cameras, depth=depth, seed=seed,
        image_size=LIBERO_IMAGE_SIZE if image_size is None else image_size,
        max_attempts=max_attempts, progress=progress, workers=workers,
    )  # fmt: skip
    for s in summaries:
        print(
            f"{suite} task {s.task_id}: {s.demos} demos in {s.attempts} attempts "
            f"(mean {np.mean(s.lengths):.0f} steps) -> {s.path}"
        )


def _parse_fovy(items: Sequence[str]) -> dict[str, float]:
    fovy = {}
    for item in items:
        cam, sep, deg = item.partition("=")
        try:
            fovy[cam] = float(deg)
        except ValueError:
            sep = ""
        if not sep or not cam:
            raise CapVectorError(f"--fovy takes CAMERA=DEGREES, got {item!r}")
    return fovy


if __name__ == "__main__":  # one error path: bad input is one line, as from `capvector demos`
    from capvector.cli import main as capvector

    sys.exit(capvector(["demos", *sys.argv[1:]]))
