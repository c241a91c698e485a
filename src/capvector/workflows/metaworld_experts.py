"""``python -m capvector.workflows.metaworld_experts``: Meta-World's scripted policies under the
evaluation protocol (:mod:`capvector.envs.metaworld.spec`), as a Markdown table and a JSON file."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from capvector.envs.base import EVAL_SEED_START
from capvector.envs.metaworld.spec import EVAL_EPISODES, MAX_STEPS, task_set_tasks
from capvector.io.outputs import atomic_write_bytes, check_output
from capvector.tool_cli import run_tool


def metaworld_experts(
    task_set: str = "metaworld_mt50",
    episodes: int = EVAL_EPISODES,
    start_seed: int = EVAL_SEED_START,
    max_steps: int = MAX_STEPS,
    image_size: int = 0,
    json_out: Path | None = None,
) -> None:
    """Run each task's scripted policy (``metaworld.policies``) on the protocol's episodes and
    print the per-task success as a Markdown table.

    Args:
        task_set: metaworld_mt10, metaworld_mt50 or one task (reach-v3, ...)
        episodes: episodes per task (the protocol's 10)
        start_seed: first seed; the evaluation seeds by default, disjoint from demo seeds
        max_steps: step limit (the protocol's 500)
        image_size: > 0 renders the corner2 camera at every step at this size (the experts do
            not read it: this measures rendering's cost); 0: state only
        json_out: also write the per-episode results here (atomically)
    """
    tasks = list(task_set_tasks(task_set))
    if json_out is not None:
        check_output(json_out, overwrite=True, what="--json-out")
    from capvector.envs.metaworld.experts import evaluate_experts, success_table  # Meta-World

    def report(task: str, runs: list) -> None:  # a long run shows as it goes
        wins = sum(r.success for r in runs)
        print(f"{task}: {wins}/{len(runs)}", file=sys.stderr, flush=True)

    start = time.perf_counter()
    results = evaluate_experts(
        tasks, episodes, start_seed=start_seed, max_steps=max_steps, image_size=image_size,
        on_task=report,
    )  # fmt: skip
    seconds = time.perf_counter() - start
    print(success_table(results))
    steps = sum(r.steps for runs in results.values() for r in runs)
    print(f"\n{steps} steps in {seconds:.0f} s ({steps / seconds:.0f} steps/s)")
    if json_out is not None:
        record = {
            "task_set": task_set, "episodes": episodes, "start_seed": start_seed,
            "max_steps": max_steps, "image_size": image_size, "steps": steps,
            "seconds": round(seconds, 1),
            "tasks": {
                task: {
                    "success": sum(r.success for r in runs),
                    "episodes": len(runs),
                    "steps": [r.steps for r in runs],
                    "solved": [r.success for r in runs],
                }
                for task, runs in results.items()
            },
        }  # fmt: skip
        atomic_write_bytes(json_out, (json.dumps(record, indent=1) + "\n").encode())


def main(argv: Sequence[str] | None = None) -> int:
    return run_tool(metaworld_experts, argv, "python -m capvector.workflows.metaworld_experts")


if __name__ == "__main__":  # one error path: bad input is one line, as from a command
    from capvector.cli import run_module_tool

    sys.exit(run_module_tool("python -m capvector.workflows.metaworld_experts", main))
