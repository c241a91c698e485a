"""``capvector demos``: record scripted-expert demonstrations of a task set of any registered suite
(``Suite.record_demos``: robosuite tasks to one robomimic-layout file, a LIBERO suite to a folder of
files in LIBERO's released layout, ...)."""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np

from capvector.envs.base import DemoSettings, check_options
from capvector.envs.registry import suite_for_task_set
from capvector.errors import CapVectorError
from capvector.tool_cli import run_tool

DEFAULT_CAMERAS = ("agentview", "robot0_eye_in_hand")
"""robosuite's and LIBERO's ``Suite.cameras``; a suite with other cameras records its own when
``--cameras`` is left at this default."""


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
    robot: str | None = None,
    gripper: str | None = None,
    image_size: int | None = None,
    cameras: Sequence[str] = DEFAULT_CAMERAS,
    depth: bool = False,
    seed: int = 0,
    noise: float | None = None,
    extra_steps: int | None = None,
    max_attempts: int | None = None,
    fovy: Sequence[str] = (),
    progress: bool = True,
    workers: int | None = None,
    rendering: str | None = None,
) -> None:
    """Record scripted-expert demonstrations of a task (--task, e.g. a robosuite task, to one
    robomimic-layout HDF5 file) or a task set (--suite, e.g. a LIBERO suite, to a folder of one
    file per task in LIBERO's released layout): any registered suite's, found by the name.

    Args:
        out: HDF5 file to write (atomically); with --suite a folder for one file per task
        task: Lift, Stack, PickPlaceCan, ... (capvector.envs.robosuite.tasks)
        episodes: successful demos to save (of each task)
        suite: a task set instead of --task: a LIBERO suite (libero_spatial, libero_object,
            libero_goal, ...)
        tasks: with --suite, the task ids to record (default: every task of the set)
        episodes_per_task: --episodes, as LIBERO's demos were asked for
        robot: robosuite arm: Panda, IIWA, UR5e, Kinova3, ...
        gripper: gripper override, e.g. PandaGripper (arms whose default gripper has 6 joints
            need one)
        cameras: cameras to render (default: the suite's, Suite.cameras: agentview and
            robot0_eye_in_hand; Meta-World: corner2); none (a bare --cameras) records low-dim
            demos only, fast
        depth: also store <camera>_depth in metres and the cameras' intrinsics
        image_size: image height and width (default 64; LIBERO: 128, its released size)
        seed: first seed; attempts use seed, seed+1, ... (LIBERO: seeds of its placement
            initializer, skipping any that lands on an official evaluation initial state)
        noise: DART noise std on xyz (robosuite; default 0.1)
        extra_steps: steps recorded after the first success (robosuite; default 6)
        max_attempts: attempts before giving up (default: max(2 x episodes, episodes + 20))
        fovy: CAMERA=DEG: override a camera's vertical field of view (task defaults: Lift/Stack
            agentview=35)
        progress: show the progress bar
        workers: with --suite, processes recording tasks side by side, a task each (0: this
            one); the files are the same either way
        rendering: LIBERO: who draws the images (auto, fast, fast-close, official; see
            capvector evaluate --rendering); the states and actions are the same whoever draws
    """
    if (task is None) == (suite is None):
        raise CapVectorError(
            "give --task (e.g. Lift) or --suite (e.g. libero_spatial), and --episodes "
            "(see capvector demos --help)"
        )
    if episodes is not None and episodes_per_task is not None:
        raise CapVectorError("--episodes and --episodes-per-task are the same: give one")
    episodes = episodes if episodes is not None else episodes_per_task
    if episodes is None:
        raise CapVectorError(
            f"give --episodes N: successful demos of {task or suite} to record "
            "(see capvector demos --help)"
        )
    task_set = task if task is not None else suite
    assert task_set is not None
    found = suite_for_task_set(task_set)
    settings = DemoSettings(
        _cameras(cameras, found.cameras), image_size, depth, seed, max_attempts, progress
    )
    # the suite's own options when given (robot, noise, tasks, workers, ...)
    given = dict(robot=robot, gripper=gripper, noise=noise, extra_steps=extra_steps,
                 fovy=_parse_fovy(fovy) or None, tasks=tuple(tasks) or None, workers=workers,
                 rendering=rendering)  # fmt: skip
    options = {k: v for k, v in given.items() if v is not None}
    check_options(found.record_demos, options, f"{found.name} demos", _flag)
    for summary in found.record_demos(task_set, episodes, out, settings, **options):
        lengths = np.asarray(summary.lengths)
        print(
            f"wrote {summary.demos} {summary.task} demos ({summary.samples} samples) to "
            f"{summary.path}: expert success {summary.demos}/{summary.attempts} attempts "
            f"({summary.success_rate:.1%}), steps to success mean {lengths.mean():.1f} "
            f"max {lengths.max()}, {summary.seconds / max(summary.demos, 1):.2f} s/demo"
        )


def _cameras(given: Sequence[str], own: Sequence[str]) -> tuple[str, ...]:
    """``--cameras`` as given, the suite's own when left at the default: the option's default
    must be a list for a bare ``--cameras`` (no cameras) to parse, so "not given" is the default
    value; robosuite and LIBERO have exactly these cameras, Meta-World has none of them."""
    return tuple(own) if tuple(given) == DEFAULT_CAMERAS else tuple(given)


def _flag(option: str) -> str:
    return "--" + option.replace("_", "-")


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
