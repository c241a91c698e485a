"""``capvector evaluate``: roll a trained policy out in MuJoCo and print a success table."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

from tqdm import tqdm

from capvector.data.episodes import EvalTask
from capvector.errors import ToolParser
from capvector.fileio import atomic_write_bytes
from capvector.module import load_module
from capvector.policy import VLAPolicy


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate (robust at 0 and 1 with few episodes)."""
    if n == 0:
        return 0.0, 0.0
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def evaluate(
    checkpoint: str,
    tasks: list[EvalTask],
    video_dir: str | None = None,
    videos: int = 2,
    execute_steps: int | None = None,
) -> list[dict]:
    """One row per (task, robot): episodes, successes, rate with its 95% interval, mean steps."""
    from capvector.data.episodes import EpisodeDataset
    from capvector.sim.rollout import run_episode
    from capvector.sim.video import write_video

    module = load_module(checkpoint).eval()
    spec = module.data_spec
    policy = VLAPolicy(module.backbone, spec)
    episodes = EpisodeDataset(tasks).specs
    results = defaultdict(list)
    progress = tqdm(episodes, desc="evaluate", unit="episode")
    for i, episode in enumerate(progress):
        progress.set_postfix(task=episode.task, seed=episode.seed)
        result = run_episode(
            policy, episode, cameras=spec.cameras, image_size=spec.image_size,
            camera_fovy=spec.camera_fovy, video=video_dir is not None and i < videos,
            execute_steps=execute_steps,
        )  # fmt: skip
        if result.frames:
            write_video(
                result.frames,
                Path(video_dir) / f"{episode.task}_{episode.robot}_seed{episode.seed}.mp4",
            )
        results[(episode.task, episode.robot)].append(result)
    rows = []
    for (task, robot), runs in results.items():
        successes = sum(r.success for r in runs)
        low, high = wilson_interval(successes, len(runs))
        rows.append({
            "task": task, "robot": robot, "episodes": len(runs), "successes": successes,
            "success_rate": successes / len(runs), "ci95": [low, high],
            "mean_steps": sum(r.steps for r in runs) / len(runs),
            "failures": sorted({r.reason for r in runs if r.reason}),
        })  # fmt: skip
    return rows


def format_table(rows: list[dict]) -> str:
    lines = [
        "| task | robot | episodes | success | 95% CI | mean steps |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        low, high = r["ci95"]
        lines.append(
            f"| {r['task']} | {r['robot']} | {r['episodes']} | {r['success_rate']:.0%} "
            f"({r['successes']}) | {low:.0%}–{high:.0%} | {r['mean_steps']:.1f} |"
        )
    return "\n".join(lines)


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
        "--start-seed", type=int, default=EvalTask.start_seed, help="first evaluation seed"
    )
    parser.add_argument(
        "--video", default=None, help="folder for mp4s of the first --videos episodes"
    )
    parser.add_argument("--videos", type=int, default=2)
    parser.add_argument("--execute-steps", type=int, default=None)
    parser.add_argument("--json", default=None, help="also write the rows as JSON")
    args = parser.parse_args(argv)
    tasks = [
        EvalTask(t, args.episodes, args.robot, args.start_seed, gripper=args.gripper)
        for t in args.task
    ]
    rows = evaluate(args.ckpt, tasks, args.video, args.videos, args.execute_steps)
    print(format_table(rows))
    if args.json:
        atomic_write_bytes(args.json, json.dumps(rows, indent=2).encode())
    return 0
