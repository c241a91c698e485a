"""The memory planner (``capvector backbone-info --memory``) against real CPU training steps, and
float32 against bfloat16 frozen weights.

    python benchmarks/bench_memory.py [--batch 8] [--lora-rank 8] [--presets pi05-tiny ...]

For each tiny preset and each frozen dtype, in a fresh process (so peak RSS is that run's alone):
LoRA of ``--lora-rank`` (the parameters ``VLAModule`` trains: adapters and heads), bf16-mixed (CPU
autocast, as Lightning's ``bf16-mixed`` on a CPU), AdamW (foreach, a GPU's default), training
steps (forward, backward, optimizer step) after one warm-up step.

The bf16 frozen weights are cast by hand here, ``p.data = p.data.to(torch.bfloat16)`` for every
parameter with ``requires_grad`` False after LoRA injection: what ``VLAModule(frozen_dtype=
"bfloat16")`` does, measured without it.

- allocated peak: parameters and AdamW state (their bytes) + the peak of what the CPU allocator
  holds during one step beyond what it held before (``torch.profiler``'s memory events): the
  CPU's counterpart of ``torch.cuda.max_memory_allocated``, and what the planner models;
- peak RSS: parameters and AdamW state + the process's peak RSS growth during one step (RSS
  before it taken after ``malloc_trim``); it adds the CPU runtime's own overhead (glibc arenas,
  oneDNN), which a GPU's allocated bytes do not have;
- estimate, CPU autocast: ``estimate_memory(..., TrainingSettings(strategy="ddp",
  attention="efficient"), device="cpu")`` total (weights on the meta device, nothing allocated), the trace following CPU
  autocast's casts to compare with this CPU run; CUDA autocast: the same as a GPU casts (what
  ``capvector backbone-info --memory`` reports). The CPU runs SDPA through its flash kernel (no
  attention matrix kept), as a GPU does;
- activations: the estimate's saved bytes against what autograd saves in the real step;
- step: the fastest of 7 steps' wall-clock seconds (one thread), the fp32 and bf16 models built in
  one process and their steps alternated, so load from other processes hits both alike.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from typing import Any

MIB = 1024**2
DTYPES = ("float32", "bfloat16")


def rss(field: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak since the last reset) of this process, in bytes."""
    with open("/proc/self/status") as f:
        line = next(line for line in f if line.startswith(field + ":"))
    return float(line.split()[1]) * 1024


def reset_peak_rss() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # Linux: VmHWM starts again from the current RSS


def profiled_peak(step: Callable[[], None]) -> float:
    """Peak bytes the CPU allocator holds during ``step`` beyond what it held before: the
    ``Total Allocated`` of ``torch.profiler``'s memory events, the CPU's counterpart of
    ``torch.cuda.max_memory_allocated``."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        step()
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "trace.json")
        prof.export_chrome_trace(path)
        with open(path) as f:
            events = json.load(f)["traceEvents"]
    return float(max(e["args"]["Total Allocated"] for e in events if e.get("name") == "[memory]"))


def training_step(
    preset: str, batch_size: int, lora_rank: int, frozen_dtype: str
) -> tuple[Any, Any, Callable[[], None]]:
    """(model, AdamW, one training step) for ``preset``: LoRA and the frozen set as ``VLAModule``,
    frozen weights cast by hand to ``frozen_dtype``, bf16-mixed (CPU autocast)."""
    import torch

    from capvector.backbones import build_backbone
    from capvector.profiling.memory import lora_settings, synthetic_batch
    from capvector.training.lora import FROZEN_DTYPES, cast_frozen_parameters, set_trainable

    torch.manual_seed(0)
    model = build_backbone(preset)
    set_trainable(model, lora_settings(lora_rank))  # what VLAModule trains
    cast_frozen_parameters(
        model, FROZEN_DTYPES[frozen_dtype], keep=set()
    )  # VLAModule(frozen_dtype)
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(trainable, lr=1e-4, foreach=True)  # a GPU's default
    batch = synthetic_batch(model, batch_size, "cpu")

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss = model(batch).loss
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    return model, optimizer, step


def step_seconds(preset: str, batch_size: int, lora_rank: int, rounds: int = 7) -> dict[str, float]:
    """Fastest step of each frozen dtype, both models in one process and their steps alternated,
    so that load from other processes hits both alike."""
    import torch

    torch.set_num_threads(1)
    steps = {dtype: training_step(preset, batch_size, lora_rank, dtype)[2] for dtype in DTYPES}
    best = {dtype: float("inf") for dtype in DTYPES}
    for round_ in range(rounds + 1):
        for dtype, step in steps.items():
            started = time.perf_counter()
            step()
            if round_:  # the first round warms up
                best[dtype] = min(best[dtype], time.perf_counter() - started)
    return best


def measure(preset: str, batch_size: int, lora_rank: int, frozen_dtype: str) -> dict[str, float]:
    """Run in a fresh process: the estimates, and one real step's peak memory."""
    import torch

    from capvector.profiling.memory import TrainingSettings, estimate_memory, saved_activation_bytes

    torch.manual_seed(0)
    torch.set_num_threads(1)
    settings = TrainingSettings(
        batch=batch_size, precision="bf16-mixed", strategy="ddp", lora_rank=lora_rank,
        frozen_dtype=frozen_dtype, attention="efficient",
    )  # fmt: skip
    estimate = estimate_memory(preset, settings, device="cpu")
    on_gpu = estimate_memory(preset, settings)
    model, optimizer, step = training_step(preset, batch_size, lora_rank, frozen_dtype)
    step()  # warm-up: AdamW state, lazy buffers, tokenizer caches, kernels' workspaces
    ctypes.CDLL("libc.so.6").malloc_trim(0)  # give the warm-up's freed memory back to the OS
    reset_peak_rss()  # the warm-up's own peak would hide this step's
    before = rss("VmRSS")
    step()
    growth = rss("VmHWM") - before
    allocated = profiled_peak(step)
    with saved_activation_bytes(store := [], model):
        step()
    static = sum(p.nbytes for p in model.parameters()) + sum(
        t.nbytes for state in optimizer.state.values() for t in state.values() if t.dim()
    )
    return {
        "estimate": estimate.total,
        "estimate_gpu": on_gpu.total,
        "estimate_activations": estimate.activations,
        "saved": store[0],
        "measured": static + growth,
        "allocated": static + allocated,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--lora-rank", type=int, default=8)
    parser.add_argument("--presets", nargs="+", help="default: every registered tiny preset")
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--time", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.time:
        print(json.dumps(step_seconds(args.time, args.batch, args.lora_rank)))
        return
    if args.one:
        print(json.dumps(measure(args.one[0], args.batch, args.lora_rank, args.one[1])))
        return
    if not args.presets:
        from capvector.backbones import list_presets

        args.presets = [name for name in list_presets() if "tiny" in name]
    print(
        f"LoRA r {args.lora_rank}, bf16-mixed (CPU autocast), batch {args.batch}, AdamW, one "
        "training step on the CPU, one thread; fp32 / bf16 = float32 / bfloat16 frozen weights\n"
    )
    print("| preset | frozen | allocated peak (MiB) | peak RSS (MiB) "
          "| estimate, CPU autocast (MiB) | / allocated | / RSS "
          "| estimate, CUDA autocast (MiB) | activations: estimate / autograd saved |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    ratios = []
    for preset in args.presets:
        r = {}
        for dtype in DTYPES:
            x = r[dtype] = run(preset, args, "--one", preset, dtype)
            print(
                f"| {preset} | {dtype} | {x['allocated'] / MIB:.1f} | {x['measured'] / MIB:.1f} | "
                f"{x['estimate'] / MIB:.1f} | {x['estimate'] / x['allocated']:.2f} | "
                f"{x['estimate'] / x['measured']:.2f} | {x['estimate_gpu'] / MIB:.1f} | "
                f"{x['estimate_activations'] / x['saved']:.2f} |",
                flush=True,
            )
        ratios.append((preset, r["float32"], r["bfloat16"], run(preset, args, "--time", preset)))
    print("\nbf16 frozen weights against fp32, same run (step: fastest of 7, the two alternated)\n")
    print("| preset | allocated peak bf16/fp32 | peak RSS bf16/fp32 | step fp32 (s) | step bf16 (s) "
          "| step time bf16/fp32 |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for preset, a, b, t in ratios:
        print(
            f"| {preset} | {b['allocated'] / a['allocated']:.2f} | "
            f"{b['measured'] / a['measured']:.2f} | {t['float32']:.3f} | {t['bfloat16']:.3f} | "
            f"{t['bfloat16'] / t['float32']:.2f} |"
        )


def run(preset: str, args: argparse.Namespace, *extra: str) -> dict[str, float]:
    """This script in a fresh process (so its peak RSS is that run's alone); its JSON line."""
    cmd = [sys.executable, __file__, *extra, "--batch", str(args.batch)]
    cmd += ["--lora-rank", str(args.lora_rank)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
