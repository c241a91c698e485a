"""Resident memory of a LIBERO evaluation in this process: before it, at its peak (the envs of the
episodes in flight) and after it (what a fit keeps while it trains until its next validation).

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/bench_libero_eval_memory.py \
        [--tasks 5 6 --trials 4 --batch 4 --steps 40 --size 64]

The validation loop's setting in configs/recipes/libero_study_eval.yaml: 4 episodes in flight in
this process (``rollout.batch_size=4``, no worker processes, as a recipe stage with one core runs
it), LIBERO's two cameras. The policy holds the arm still: memory does not depend on what it does.
"""

from __future__ import annotations

import argparse
import resource

import numpy as np
import torch

from capvector.callbacks.step_cost import peak_memory_mib
from capvector.envs.libero.spec import libero_specs
from capvector.eval.rollout import RolloutEvaluator


def resident_gib() -> float:
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * resource.getpagesize() / 2**30


def hold(observation: dict) -> np.ndarray:
    return np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0], (8, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="libero_spatial")
    parser.add_argument("--tasks", type=int, nargs="+", default=[5, 6])
    parser.add_argument("--trials", type=int, default=4)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--size", type=int, default=64)
    args = parser.parse_args()

    before = resident_gib()
    specs = libero_specs(args.suite, args.tasks, trials=args.trials, max_steps=args.steps)
    evaluator = RolloutEvaluator(
        ("agentview", "robot0_eye_in_hand"), args.size, batch_size=args.batch, workers=0
    )
    evaluator.run(hold, specs)
    print(f"| {len(specs)} episodes, {args.batch} in flight, 2 cameras {args.size} px | GiB |")
    print("|---|---:|")
    print(f"| resident before | {before:.2f} |")
    print(f"| peak during | {peak_memory_mib(torch.device('cpu')) / 1024:.2f} |")
    print(f"| resident after | {resident_gib():.2f} |")


if __name__ == "__main__":
    main()
