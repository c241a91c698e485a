"""Package scripted-expert demos recorded by ``capvector demos --suite`` for a replay in upstream
LIBERO on robosuite 1.4 (``tools/libero/make_demo_fixture.py``, run in that stack)::

    PYTHONPATH=src python tools/libero/demo_replay_inputs.py DEMO_DIR OUT_DIR

Per demo: the placement it started from (the state LIBERO's placement initializer gave under the
demo's seed, *before* the protocol's 10 wait steps, so the replay includes the settling), the
fixtures' poses there (no state holds them), and the actions: 10 wait steps, the demo's, then
:data:`HOLD_STEPS` wait steps (a demo ends at the step the port's predicate first holds; a bowl
released a little higher in another simulator needs a step or two more to land, as an episode of
the protocol would give it), stored as float32 (the exact values both stacks replay). Writes ``OUT_DIR/inputs.npz``
(``<suite>/<task>/<demo>/{start, actions, fixtures}``) and ``OUT_DIR/episodes.json`` (key, seed,
object and fixture names, the demo's length; for each task's first demo, how far the port's own
wait steps from the placement land from the demo's first state), atomically.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np

from capvector.envs.libero import env as libero
from capvector.envs.libero.experts import task_env
from capvector.io.outputs import atomic_write_file

HOLD_STEPS = 10
"""Wait steps after a demo's last action (gripper open, no motion)."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("demos", type=Path, help="a folder `capvector demos --suite` wrote")
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    arrays: dict[str, np.ndarray] = {}
    episodes = []
    for path in sorted(args.demos.glob("*.hdf5")):
        with h5py.File(path, "r") as f:
            suite, task_id = str(f["data"].attrs["suite"]), int(f["data"].attrs["task_id"])
            demos = [
                (int(g.attrs["seed"]), np.asarray(g["actions"]), np.asarray(g["states"][0]))
                for g in (f["data"][f"demo_{i}"] for i in range(len(f["data"])))
            ]
        env = libero.make_libero_env(suite, task_id, render=False)
        try:
            for i, (seed, actions, first) in enumerate(demos):
                libero.seeded_reset(env, seed)
                start = task_env(env).sim.get_state().flatten()
                fixtures = libero.fixture_poses(env)
                objects = sorted(task_env(env).objects_dict)
                wait = np.tile(libero.WAIT_ACTION, (libero.NUM_WAIT_STEPS, 1))
                gap = None
                if i == 0:  # the placement is the demo's: its wait steps reach the demo's start
                    libero.replay_actions(env, start, wait, objects=objects, fixtures=fixtures)
                    settled = task_env(env).sim.get_state().flatten()
                    gap = float(np.abs(settled[1:] - first[1:]).max())
                key = f"{suite}/{task_id}/{i}"
                arrays[f"{key}/start"] = start
                hold = np.tile(libero.WAIT_ACTION, (HOLD_STEPS, 1))
                arrays[f"{key}/actions"] = np.concatenate([wait, actions, hold]).astype(np.float32)
                # LIBERO-Object's floor scenes have no fixtures: (0, 7)
                poses = [fixtures[n] for n in sorted(fixtures)]
                arrays[f"{key}/fixtures"] = np.stack(poses) if poses else np.zeros((0, 7))
                episodes.append(
                    {
                        "key": key,
                        "suite": suite,
                        "task_id": task_id,
                        "seed": seed,
                        "demo_steps": len(actions),
                        "hold_steps": HOLD_STEPS,
                        "objects": objects,
                        "fixtures": sorted(fixtures),
                        "settled_vs_demo_max_abs": gap,
                    }
                )
                print(key, seed, len(actions), f"settled vs demo {gap}", flush=True)
        finally:
            env.close()
    args.out.mkdir(parents=True, exist_ok=True)
    with (
        atomic_write_file(args.out / "inputs.npz", what="replay inputs") as tmp,
        open(tmp, "wb") as fh,
    ):
        np.savez_compressed(fh, **arrays)
    with atomic_write_file(args.out / "episodes.json", what="replay episodes") as tmp:
        Path(tmp).write_text(json.dumps(episodes, indent=1) + "\n")


if __name__ == "__main__":
    main()
