"""Print, as a Markdown table, how LIBERO's evaluation through `capvector serve` on upstream LIBERO
(robosuite 1.4) compares with `capvector evaluate --suite` on our port, per trial of the committed
runs (tests/fixtures/libero_served), with each trial's first requests replayed live here::

    PYTHONPATH=src MUJOCO_GL=egl python tools/libero/served_report.py

The measures are the test's (tests/test_libero_served.py: run_differences, replay).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

TEST = Path(__file__).resolve().parents[2] / "tests" / "test_libero_served.py"
REQUESTS = 3  # the first chunks of each trial replayed: the closed loop before it diverges


def main() -> None:
    spec = importlib.util.spec_from_file_location("test_libero_served", TEST)
    assert spec is not None and spec.loader is not None
    test = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(test)
    print(
        "| trial | success (1.4 / ours) | steps (1.4 / ours) | first images, agentview / wrist "
        "(grey levels) | first state (max) | first chunk (max) | eef at requests 2-3 (mm) | "
        "final eef (mm) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for d in test.run_differences():
        r = test.replay(d["trial"], REQUESTS)
        images = " / ".join(f"{r['image'][camera]:.2f}" for camera in test.CAMERAS)
        later = ", ".join(f"{mm:.2f}" for mm in r["eef_mm"][1:])
        print(
            f"| {d['trial']} | {d['success'][0]} / {d['success'][1]} | {d['steps'][0]} / "
            f"{d['steps'][1]} | {images} | {r['state'][0]:.1e} | {r['chunk']:.3f} | {later} | "
            f"{d['final_eef_mm']:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
