"""Print, as a Markdown table, how this project's LIBERO agrees with upstream LIBERO on robosuite
1.4 / MuJoCo 2.3.7 when the port's scripted-expert demos are replayed open loop in both
(tests/fixtures/libero_demo_replay), per task::

    PYTHONPATH=src python tools/libero/demo_replay_report.py [SUITE ...]

Success is LIBERO's predicate at any step of the replay (an episode of the protocol ends there).
The comparisons are the test's (tests/test_sim_libero.py: demo_replay).
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from capvector.envs.libero import env as libero

TEST = Path(__file__).resolve().parents[2] / "tests" / "test_sim_libero.py"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("suites", nargs="*", default=None)
    args = parser.parse_args()
    spec = importlib.util.spec_from_file_location("test_sim_libero", TEST)
    assert spec is not None and spec.loader is not None
    test = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(test)
    tasks = sorted({(e["suite"], e["task_id"]) for e in test.DEMO_EPISODES})
    print(
        "| suite | task | demos | success in 1.4 / port | outcome agrees | first success, "
        "steps apart (max) | objects after the wait steps, max (mm) | disagreeing |"
    )
    print("|---|---|---|---|---|---|---|---|")
    total = agreed = 0
    for suite, task_id in tasks:
        if args.suites and suite not in args.suites:
            continue
        episodes = [e for e in test.DEMO_EPISODES if (e["suite"], e["task_id"]) == (suite, task_id)]
        env = libero.make_libero_env(suite, task_id, render=False)
        outs = [test.demo_replay(env, e) for e in episodes]
        env.close()
        agree = [o["success"] == o["ref_success"] for o in outs]
        gaps = [abs(o["first"] - o["ref_first"]) for o in outs if o["success"] and o["ref_success"]]
        total, agreed = total + len(outs), agreed + sum(agree)
        print(
            f"| {suite} | {task_id} | {len(outs)} | {sum(o['ref_success'] for o in outs)} / "
            f"{sum(o['success'] for o in outs)} | {sum(agree)}/{len(outs)} | "
            f"{max(gaps) if gaps else '-'} | {max(o['settled_mm'] for o in outs):.2f} | "
            f"{', '.join(e['key'] for e, a in zip(episodes, agree, strict=True) if not a) or '-'} |",
            flush=True,
        )
    print(f"\nagreement: {agreed}/{total} ({100 * agreed / max(total, 1):.1f} %)")


if __name__ == "__main__":
    main()
