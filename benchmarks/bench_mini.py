"""Training-step time of ``openvla-oft-mini`` against ``openvla-oft-tiny``, measured in one run.

The step the mini's recipe takes: batch 8, two 128 px cameras, LoRA (r 8) on the 6 Gemma layers,
projector and heads in full, AdamW; in float32 and under bf16 autocast with the frozen base stored
in bf16 (``model.frozen_dtype: bfloat16``). The tiny preset runs the same step at its own 64 px.
Time is the median over interleaved rounds (each round times every arm once, so machine load hits
all arms alike). Report the ratio: on a shared machine seconds mean little; on an idle 2-core CPU
the mini's bf16 step is the one the ``<= 1 s`` target is about. The load average (``uptime``'s
1/5/15-minute numbers) is printed before and after, so absolute seconds carry their context.

    nice python benchmarks/bench_mini.py [--rounds 8] [--batch 8] [--threads 1]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import time

import torch

from capvector.backbones import build_backbone
from capvector.training.lora import LoraSettings, cast_frozen_parameters, set_trainable


def make_arm(preset: str, bf16: bool, batch: int) -> tuple:
    torch.manual_seed(0)
    model = build_backbone(preset)
    set_trainable(model, LoraSettings(r=8, alpha=16))
    if bf16:
        cast_frozen_parameters(model, torch.bfloat16, keep=set())
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=1e-4)
    c = model.config
    g = torch.Generator().manual_seed(0)
    data = {
        "images": torch.rand(batch, c.num_images, 3, c.image_size, c.image_size, generator=g),
        "instruction": ["put the bowl on the plate"] * batch,
        "proprio": torch.rand(batch, c.proprio_dim, generator=g) * 2 - 1,
        "actions": torch.rand(batch, c.chunk_size, c.action_dim, generator=g) * 2 - 1,
    }
    trainable = sum(p.numel() for p in params)
    return model, optimizer, data, bf16, trainable


def step(arm: tuple) -> float:
    model, optimizer, data, bf16, _ = arm
    autocast = torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()
    start = time.perf_counter()
    with autocast:
        loss = model(data).loss
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return time.perf_counter() - start


def load_average() -> str:
    """The 1, 5 and 15-minute load averages, as ``uptime`` prints them."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"load average before: {load_average()}", flush=True)
    arms = {
        "tiny fp32": make_arm("openvla-oft-tiny", False, args.batch),
        "mini fp32": make_arm("openvla-oft-mini", False, args.batch),
        "mini bf16": make_arm("openvla-oft-mini", True, args.batch),
    }
    for arm in arms.values():  # warm-up: first-call allocations, autocast caches
        step(arm)
    times: dict[str, list[float]] = {name: [] for name in arms}
    for index in range(args.rounds):
        for name, arm in arms.items():
            times[name].append(step(arm))
        round_times = ", ".join(f"{name} {t[-1]:.3f} s" for name, t in times.items())
        print(f"round {index + 1}: {round_times}", flush=True)
    base = statistics.median(times["tiny fp32"])
    print(f"load average after: {load_average()} on {os.cpu_count()} cores")
    print(f"batch {args.batch}, {args.threads} threads, median of {args.rounds} interleaved rounds")
    print(f"{'arm':<10} {'trainable':>10} {'step s':>8} {'x tiny':>7}")
    for name, arm in arms.items():
        median = statistics.median(times[name])
        print(f"{name:<10} {arm[4]:>10,} {median:>8.3f} {median / base:>7.1f}")


if __name__ == "__main__":
    main()
