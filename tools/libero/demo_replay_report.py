"""Print, as a Markdown table, how this project's LIBERO agrees with upstream LIBERO on robosuite
1.4 / MuJoCo 2.3.7 when the port's scripted-expert demos are replayed open loop in both
(tests/fixtures/libero_demo_replay), per task::

    PYTHONPATH=src python tools/libero/demo_replay_report.py [SUITE ...] [--tasks ID ...]

Success is LIBERO's predicate at any step of the replay (an episode of the protocol ends there).
The comparisons are the test's (tests/test_sim_libero.py: demo_replay): per task the demos'
outcomes in both stacks, how many steps apart the predicate first holds where both succeed, and
the farthest object from robosuite 1.4's after the protocol's 10 wait steps and at the replay's
end; then the agreement per suite.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from capvector.envs.libero import env as libero

TEST = Path(__file__).resolve().parents[2] / "tests" / "test_sim_libero.py"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("suites", nargs="*", default=None, help="default: every suite")
    parser.add_argument("--tasks", type=int, nargs="+", help="these task ids only")
    args = parser.parse_args()
    spec = importlib.util.spec_from_file_location("test_sim_libero", TEST)
    assert spec is not None and spec.loader is not None
    test = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(test)
    tasks = sorted({(e["suite"], e["task_id"]) for e in test.DEMO_EPISODES})
    print(
        "| suite | task | demos | success in 1.4 / port | outcome agrees | first success, "
        "steps apart (max) | objects after the wait steps, max (mm) | objects at the end, max "
        "(mm) | disagreeing |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    agreed: dict[str, list[int]] = {}  # suite: [agreeing, demos]
    for suite, task_id in tasks:
        if (args.suites and suite not in args.suites) or (args.tasks and task_id not in args.tasks):
            continue
        episodes = [e for e in test.DEMO_EPISODES if (e["suite"], e["task_id"]) == (suite, task_id)]
        env = libero.make_libero_env(suite, task_id, render=False)
        try:
            outs = [test.demo_replay(env, e) for e in episodes]
        finally:
            env.close()
        agree = [o["success"] == o["ref_success"] for o in outs]
        gaps = [abs(o["first"] - o["ref_first"]) for o in outs if o["success"] and o["ref_success"]]
        count = agreed.setdefault(suite, [0, 0])
        count[0], count[1] = count[0] + sum(agree), count[1] + len(outs)
        print(
            f"| {suite} | {task_id} | {len(outs)} | {sum(o['ref_success'] for o in outs)} / "
            f"{sum(o['success'] for o in outs)} | {sum(agree)}/{len(outs)} | "
            f"{max(gaps) if gaps else '-'} | {max(o['settled_mm'] for o in outs):.2f} | "
            f"{max(o['final_mm'] for o in outs):.2f} | "
            f"{', '.join(e['key'] for e, a in zip(episodes, agree, strict=True) if not a) or '-'} |",
            flush=True,
        )
    print()
    for suite, (n, total) in agreed.items():
        print(f"{suite}: outcomes agree on {n}/{total} ({100 * n / total:.1f} %)")
    n, total = (sum(c[i] for c in agreed.values()) for i in (0, 1))
    print(f"all: outcomes agree on {n}/{total} ({100 * n / max(total, 1):.1f} %)")


if __name__ == "__main__":
    main()
