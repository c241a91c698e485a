"""What rendering costs a Meta-World episode, as a ratio to state-only stepping in the same run.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/bench_metaworld_render.py \
        [--task pick-place-v3 --episodes 3 --sizes 64 224 480]

Every row runs the task's scripted policy from the same evaluation seeds (1,000,000, ...) for the
same steps (the episodes' own, to success), so rows differ only in drawing ``corner2`` at every
step, at each size (LeRobot's protocol draws 480 px); the states are checked equal across rows.
Wall and CPU time (this process) are both given, with the 1-minute load average: the machine is
shared, so read the ratios, not the seconds.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from capvector.envs.base import EVAL_SEED_START  # noqa: E402
from capvector.envs.metaworld.env import MetaWorldEnv  # noqa: E402
from capvector.envs.metaworld.experts import MetaWorldExpert  # noqa: E402
from capvector.envs.metaworld.spec import MAX_STEPS  # noqa: E402


def run(env: MetaWorldEnv, seeds: list[int], render: bool) -> tuple[int, float, float, list]:
    """(steps, wall s, cpu s, final states) of the expert's episodes from ``seeds``."""
    expert = MetaWorldExpert(env.task)
    steps, finals = 0, []
    wall, cpu = time.perf_counter(), time.process_time()
    for seed in seeds:
        env.reset(seed)
        for _ in range(MAX_STEPS):
            if render:
                env.render()
            steps += 1
            if env.step_env(expert.act(env.state)):
                break
        finals.append(env.flat_state())
    return steps, time.perf_counter() - wall, time.process_time() - cpu, finals


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="pick-place-v3")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 224, 480])
    args = parser.parse_args()
    seeds = [EVAL_SEED_START + i for i in range(args.episodes)]
    rows = []
    base = MetaWorldEnv(args.task, cameras=())
    steps, wall0, cpu0, reference = run(base, seeds, render=False)
    base.close()
    rows.append(("state only", steps, wall0, cpu0))
    for size in args.sizes:
        env = MetaWorldEnv(args.task, image_size=size)
        n, wall, cpu, finals = run(env, seeds, render=True)
        env.close()
        for a, b in zip(reference, finals, strict=True):
            np.testing.assert_array_equal(a, b)  # drawing changes no state
        rows.append((f"corner2 {size} px", n, wall, cpu))
    print(
        f"{args.task}, {args.episodes} expert episodes, {steps} steps; load {os.getloadavg()[0]:.1f}"
    )
    print("| row | steps/s (wall) | CPU ms/step | × state-only CPU |")
    print("|---|---|---|---|")
    for name, n, wall, cpu in rows:
        print(f"| {name} | {n / wall:.0f} | {1000 * cpu / n:.1f} | {cpu / cpu0:.1f} |")


if __name__ == "__main__":
    main()
