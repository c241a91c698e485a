"""``capvector evaluate``: roll a trained policy out in MuJoCo and print a success table."""

from __future__ import annotations

import json
from pathlib import Path

from capvector.data.episodes import EvalTask
from capvector.errors import ToolParser
from capvector.eval.policy import VLAPolicy
from capvector.eval.results import SuccessRow, format_success_table, success_rows
from capvector.io.outputs import atomic_write_bytes, check_output
from capvector.module import load_module


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
    parser = ToolParser(prog="capvector evaluate", description="MuJoCo rollouts of a checkpoint.")
    parser.add_argument("--ckpt", required=True, help="Lightning checkpoint or export folder")
    parser.add_argument("--task", nargs="+", default=["Lift"], help="robosuite task(s)")
    parser.add_argument("--robot", default="Panda")
    parser.add_argument(
        "--gripper", default=None, help="e.g. PandaGripper for IIWA/UR5e/Kinova3/Jaco"
    )
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument(
        "--variant", nargs="+", default=[None], metavar="NAME",
        help="zero-shot scene variants (camera, camera-strong, lighting, color, all, sawyer, ur5e);"
        " each task is evaluated in each",
    )  # fmt: skip
    parser.add_argument(
        "--start-seed", type=int, default=EvalTask.start_seed, help="first evaluation seed"
    )
    parser.add_argument(
        "--video", default=None, help="folder for mp4s of the first --videos episodes"
    )
    parser.add_argument("--videos", type=int, default=2)
    parser.add_argument("--execute-steps", type=int, default=None)
    parser.add_argument(
        "--batch-size", type=int, default=8,
        help="episodes in flight at once, one batched policy forward for all (1: one at a time)",
    )  # fmt: skip
    parser.add_argument(
        "--workers", type=int, default=None,
        help="processes stepping the simulators (0: this one; default: one per core)",
    )  # fmt: skip
    parser.add_argument("--json", default=None, help="also write the rows as JSON")
    args = parser.parse_args(argv)
    for what, out in (("--json", args.json), ("--video", args.video)):
        if out is not None:  # before minutes of rollouts
            check_output(out, overwrite=True, inputs=[args.ckpt], what=what)
    tasks = [
        EvalTask(t, args.episodes, args.robot, args.start_seed, gripper=args.gripper, variant=v)
        for t in args.task
        for v in args.variant
    ]
    rows = evaluate(
        args.ckpt, tasks, args.video, args.videos, args.execute_steps, args.batch_size,
        args.workers,
    )  # fmt: skip
    print(format_success_table(rows))
    if args.json:
        payload = [r.to_dict() for r in rows]
        atomic_write_bytes(args.json, json.dumps(payload, indent=2).encode())
    return 0
