"""``python -m capvector.workflows.expert_success``: the scripted LIBERO expert's success on a
suite's official initial states (:mod:`capvector.envs.libero.experts`), as a Markdown table."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Mapping, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from capvector.envs.libero.experts import TrialResult, evaluate_expert, success_table
from capvector.io.outputs import atomic_write_file, check_writable
from capvector.tool_cli import run_tool


def expert_success(
    suite: str,
    tasks: Sequence[int] = (),
    trials: int = 50,
    progress: bool = True,
    out: str | None = None,
) -> None:
    """Run the scripted expert on the official initial states of a LIBERO suite and print the
    per-task success (LIBERO's predicate) as a Markdown table.

    Args:
        suite: libero_spatial, libero_object, libero_goal, ...
        tasks: task ids (default: every task whose goal is one placement; the others are left
            out, and said)
        trials: initial states per task, the first N of the official 50
        progress: show the progress bar
        out: also write every trial (success, steps) as JSON here, atomically, with the commit
            and the simulator versions it was measured with; rewritten as each task finishes,
            so a run stopped early keeps the tasks it finished
    """
    commit = _commit()  # before the run, which takes hours: the code that ran, not a later one
    if out is not None:
        check_writable(out, "--out")

    finished: dict[int, list[TrialResult]] = {}

    def report(task_id: int, results: list[TrialResult]) -> None:  # a long run shows as it goes
        wins = sum(r.success for r in results)
        print(f"{suite} task {task_id}: {wins}/{len(results)}", file=sys.stderr, flush=True)
        finished[task_id] = results
        if out is not None:
            with atomic_write_file(out, "--out") as tmp:
                record = results_record(suite, finished, commit)
                Path(tmp).write_text(json.dumps(record, indent=1) + "\n")

    results = evaluate_expert(suite, list(tasks) or None, trials, progress=progress, on_task=report)
    print(success_table(suite, results))


def results_record(
    suite: str, results: Mapping[int, Sequence[TrialResult]], commit: str | None
) -> dict:
    """What ``--out`` writes: per task the trials in init-state order, and what measured them
    (``commit``, see :func:`_commit`, and the simulators' versions)."""
    return {
        "suite": suite,
        "commit": commit,
        "versions": {p: _version(p) for p in ("robosuite", "mujoco", "rpent-libero")},
        "tasks": {
            str(task): [{"success": r.success, "steps": r.steps} for r in trials]
            for task, trials in sorted(results.items())
        },
    }


def _commit() -> str | None:
    """The commit of the source tree this module runs from (an editable install's), ``-dirty``
    when its ``src`` had changes, or None outside a git checkout."""
    here = Path(__file__).parent

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(here), *args], capture_output=True, text=True, check=True
        ).stdout.strip()

    try:
        head = git("rev-parse", "HEAD")
        return head + ("-dirty" if git("status", "--porcelain", "--", ":/src") else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def _version(package: str) -> str | None:
    try:
        return version(package)
    except PackageNotFoundError:
        return None


def main(argv: Sequence[str] | None = None) -> int:
    return run_tool(expert_success, argv, "python -m capvector.workflows.expert_success")


if __name__ == "__main__":  # one error path: bad input is one line, as from a command
    from capvector.cli import run_module_tool

    sys.exit(run_module_tool("python -m capvector.workflows.expert_success", main))
