"""Print, as a Markdown table, how far this project's LIBERO scenes are after the protocol's 10
wait steps from where upstream LIBERO on robosuite 1.4 / MuJoCo 2.3.7 puts them
(tests/fixtures/libero_settle), per task::

    PYTHONPATH=src python tools/libero/settle_report.py [--raw] [SUITE ...]

``--raw`` builds the port without the MuJoCo 2.3.7 corrections (capvector.envs.libero.physics),
to show what they change. The distances are the test's (tests/test_sim_libero.py: settle_errors).
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from capvector.envs.libero import env as libero
from capvector.envs.libero import physics as libero_physics

TEST = Path(__file__).resolve().parents[2] / "tests" / "test_sim_libero.py"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("suites", nargs="*", default=None)
    parser.add_argument("--raw", action="store_true", help="without the MuJoCo 2.3.7 corrections")
    args = parser.parse_args()
    spec = importlib.util.spec_from_file_location("test_sim_libero", TEST)
    assert spec is not None and spec.loader is not None
    test = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(test)
    if args.raw:
        libero_physics.match_mujoco_237 = lambda env: None  # type: ignore[assignment]
    print(
        "| suite | task | init states | worst object after the wait steps (mm) | objects > 2 mm |"
    )
    print("|---|---|---|---|---|")
    for suite, task_id in test.SETTLE_TASKS:
        if args.suites and suite not in args.suites:
            continue
        env = libero.make_libero_env(suite, task_id, render=False)
        errors = test.settle_errors(env, suite, task_id)
        env.close()
        worst = max(float(e.max()) for e in errors.values()) * 1000
        far = sorted(
            {
                f"{k.split('/')[-1]}:{name}"
                for k, e in errors.items()
                for name in test.far_objects(e, k)
            }
        )
        print(
            f"| {suite} | {task_id} | {len(errors)} | {worst:.2f} | {', '.join(far) or '-'} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
