"""Episodes per minute of a MuJoCo evaluation, policy included: one at a time against batched.

    python benchmarks/bench_evaluation.py [--episodes 16] [--batch-sizes 4 8]

The policy is the tiny OpenVLA-OFT preset (untrained: every episode runs to Lift's 150-step
limit, the worst case and the same work in every row) on 2 cameras at 64 px, 8-action chunks.
Rows, all on the same episode seeds, in this one run:

- one at a time, robosuite's full step: ``RolloutEvaluator(batch_size=1)`` with envs that run
  robosuite's whole step (``fast_step=False``): the loop every evaluation ran before (baseline)
- one at a time: the same loop with ``SimEnv``'s fast step (the same states and observations)
- batched here: B episodes in flight in this process, one policy forward for all each round
- batched, workers: the same with the simulators in one worker process per core (the default)

Every row must give the same episodes (success and length) as the baseline: it is checked.

"cold" includes building the envs (and starting the workers): one ``capvector evaluate``;
"warm" repeats the run with them kept, as the validation loop does from its second evaluation.
The machine is shared: the 1-minute load average is printed with the table.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from capvector.backbones.base import build_backbone
from capvector.data.spec import DataSpec
from capvector.data.statistics import compute_statistics
from capvector.envs.robosuite.spec import eval_specs
from capvector.eval.rollout import EnvCache, RolloutEvaluator, close_envs, default_workers
from capvector.policy import VLAPolicy


def tiny_policy() -> VLAPolicy:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    statistics = compute_statistics(rng.normal(size=(100, 7)), rng.normal(size=(100, 8)), 4)
    spec = DataSpec(statistics={"capvector": statistics})
    backbone = build_backbone("openvla-oft-tiny", **spec.backbone_overrides()).eval()
    return VLAPolicy(backbone, spec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[4, 8])
    args = parser.parse_args()
    policy = tiny_policy()
    specs = eval_specs("Lift", args.episodes)
    # (name, batch size, workers, env cache of the one-at-a-time loop)
    rows = [
        ("one at a time, robosuite's full step (before)", 1, 0, EnvCache(fast_step=False)),
        ("one at a time", 1, 0, None),
    ]
    for size in args.batch_sizes:
        rows.append((f"batched here, B={size}", size, 0, None))
        if (workers := default_workers(size)) >= 2:
            rows.append((f"batched, {workers} workers, B={size}", size, workers, None))
    print(f"{args.episodes} Lift episodes x 150 steps, tiny OFT policy, {os.cpu_count()} cores")
    print("| loop | cold: episodes/min | × before | warm: episodes/min | × before |")
    print("|---|---|---|---|---|")
    baseline: dict[str, float] = {}
    reference = None
    for name, batch_size, n, envs in rows:
        evaluator = RolloutEvaluator(
            ("agentview", "robot0_eye_in_hand"), 64, batch_size=batch_size, workers=n, envs=envs
        )
        rates = {}
        outcomes = []
        for phase in ("cold", "warm"):
            start = time.perf_counter()
            results = evaluator.run(policy, specs)
            rates[phase] = len(specs) / (time.perf_counter() - start) * 60
            outcomes.append([(r.success, r.steps) for r in results])
        close_envs()
        if envs is not None:
            envs.close()
        reference = reference or outcomes[0]
        assert outcomes[0] == outcomes[1] == reference, "the same seeds must give the same episodes"
        baseline = baseline or rates
        print(
            f"| {name} | {rates['cold']:.1f} | {rates['cold'] / baseline['cold']:.2f} "
            f"| {rates['warm']:.1f} | {rates['warm'] / baseline['warm']:.2f} |"
        )
    print(f"load average (1 min) after the run: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
