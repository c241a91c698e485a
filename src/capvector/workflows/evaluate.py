"""``capvector evaluate``: roll a trained policy out in MuJoCo and print a success table."""

from __future__ import annotations

from collections.abc import Sequence
from json import dumps
from pathlib import Path

from capvector.data.episodes import EvalTask
from capvector.eval.policy import VLAPolicy
from capvector.eval.results import SuccessRow, format_success_table, success_rows
from capvector.io.outputs import atomic_write_bytes, check_output
from capvector.module import load_module
from capvector.tool_cli import run_tool


def evaluate(
    checkpoint: str,
    tasks: list[EvalTask],
    video_dir: str | None = None,
    videos: int = 2,
    execute_steps: int | None = None,
    batch_size: int = 8,
    workers: int | None = None,
) -> list[SuccessRow]:
    """One row per (task, robot, variant): episodes, successes and each episode's outcome.
    ``batch_size`` episodes run at once, their simulators in ``workers`` processes (see
    ``RolloutEvaluator``)."""
    from capvector.data.episodes import EpisodeDataset
    from capvector.eval.rollout import RolloutEvaluator

    specs = EpisodeDataset(tasks).specs  # an unknown task or variant fails before the load
    module = load_module(checkpoint).eval()
    spec = module.data_spec
    evaluator = RolloutEvaluator(
        cameras=spec.cameras, image_size=spec.image_size, camera_fovy=spec.camera_fovy,
        execute_steps=execute_steps, videos=videos,
        video_dir=None if video_dir is None else Path(video_dir), batch_size=batch_size,
        workers=workers,
    )  # fmt: skip
    policy = VLAPolicy(module.backbone, spec)
    return success_rows(evaluator.run(policy, specs, progress=True))


def main(argv: list[str] | None = None) -> int:
    return run_tool(evaluate_cli, argv, "evaluate")


def evaluate_cli(
    ckpt: str,
    task: Sequence[str] = ("Lift",),
    robot: str = "Panda",
    gripper: str | None = None,
    episodes: int = 20,
    variant: Sequence[str | None] = (None,),
    start_seed: int = EvalTask.start_seed,
    video: str | None = None,
    videos: int = 2,
    execute_steps: int | None = None,
    batch_size: int = 8,
    workers: int | None = None,
    json: str | None = None,
) -> None:
    """MuJoCo rollouts of a checkpoint.

    Args:
        ckpt: Lightning checkpoint or export folder
        task: robosuite task(s)
        gripper: e.g. PandaGripper for IIWA/UR5e/Kinova3/Jaco
        variant: zero-shot scene variants (camera, camera-strong, lighting, color, all, sawyer,
            ur5e); each task is evaluated in each
        start_seed: first evaluation seed
        video: folder for mp4s of the first --videos episodes
        batch_size: episodes in flight at once, one batched policy forward for all (1: one at a
            time)
        workers: processes stepping the simulators (0: this one; default: one per core)
        json: also write the rows as JSON
    """
    for what, path in (("--json", json), ("--video", video)):
        if path is not None:  # before minutes of rollouts
            check_output(path, overwrite=True, inputs=[ckpt], what=what)
    tasks = [
        EvalTask(t, episodes, robot, start_seed, gripper=gripper, variant=v)
        for t in task
        for v in variant
    ]
    rows = evaluate(ckpt, tasks, video, videos, execute_steps, batch_size, workers)
    print(format_success_table(rows))
    if json:
        payload = [r.to_dict() for r in rows]
        atomic_write_bytes(json, dumps(payload, indent=2).encode())
