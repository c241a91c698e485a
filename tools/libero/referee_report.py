"""Print, as a Markdown table, how far this project's LIBERO (rpent-libero on robosuite 1.5)
is from the robosuite 1.4 referee (tests/fixtures/libero_referee), per suite::

    PYTHONPATH=src python tools/libero/referee_report.py

The replay and the error measures are the test's (tests/test_sim_libero.py: referee_errors).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from capvector.envs.libero import env as libero

TEST = Path(__file__).resolve().parents[2] / "tests" / "test_sim_libero.py"


def main() -> None:
    spec = importlib.util.spec_from_file_location("test_sim_libero", TEST)
    assert spec is not None and spec.loader is not None
    test = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(test)
    rows: dict[str, list[dict[str, np.ndarray]]] = {}
    for suite, task_id in test.REFEREE_TASKS:
        env = libero.make_libero_env(suite, task_id, render=False)
        for episode in test.REFEREE_EPISODES:
            if (episode["suite"], episode["task_id"]) == (suite, task_id):
                rows.setdefault(suite, []).append(test.referee_errors(env, episode))
        env.close()
    print(
        "| suite | episodes | eef after the wait steps (mm, °) | eef before contact, max (mm) "
        "| eef max / mean (mm) | objects max / mean (mm) | success (1.4 / ours) |"
    )
    print("|---|---|---|---|---|---|---|")
    for suite in sorted(rows, key=libero.LIBERO_SUITES.index):
        errors = rows[suite]
        eef = np.concatenate([e["eef"] for e in errors])
        objects = np.concatenate([e["objects"].ravel() for e in errors])
        wait_mm = max(e["eef"][10] for e in errors) * 1000
        wait_deg = max(e["eef_deg"][10] for e in errors)
        before = max(e["eef"][: test.CONTACT_FREE_STEPS + 1].max() for e in errors) * 1000
        ref = sum(bool(e["ref_success"].any()) for e in errors)
        ours = sum(bool(e["success"].any()) for e in errors)
        print(
            f"| {suite} | {len(errors)} | {wait_mm:.2f}, {wait_deg:.2f} | {before:.2f} "
            f"| {eef.max() * 1000:.1f} / {eef.mean() * 1000:.1f} "
            f"| {objects.max() * 1000:.1f} / {objects.mean() * 1000:.1f} | {ref} / {ours} |"
        )


if __name__ == "__main__":
    main()
