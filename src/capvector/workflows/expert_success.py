"""``python -m capvector.workflows.expert_success``: the scripted LIBERO expert's success on a
suite's official initial states (:mod:`capvector.envs.libero.experts`), as a Markdown table."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from capvector.envs.libero.experts import TrialResult, evaluate_expert, success_table
from capvector.tool_cli import run_tool


def expert_success(
    suite: str, tasks: Sequence[int] = (), trials: int = 50, progress: bool = True
) -> None:
    """Run the scripted expert on the official initial states of a LIBERO suite and print the
    per-task success (LIBERO's predicate) as a Markdown table.

    Args:
        suite: libero_spatial, libero_object, libero_goal, ...
        tasks: task ids (default: every task of the suite)
        trials: initial states per task, the first N of the official 50
        progress: show the progress bar
    """

    def report(task_id: int, results: list[TrialResult]) -> None:  # a long run shows as it goes
        wins = sum(r.success for r in results)
        print(f"{suite} task {task_id}: {wins}/{len(results)}", file=sys.stderr, flush=True)

    results = evaluate_expert(suite, list(tasks) or None, trials, progress=progress, on_task=report)
    print(success_table(suite, results))


def main(argv: Sequence[str] | None = None) -> int:
    return run_tool(expert_success, argv, "python -m capvector.workflows.expert_success")


if __name__ == "__main__":
    sys.exit(main())
