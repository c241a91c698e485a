"""The meta-device memory estimate (``capvector backbone-info --memory``) against a real step.

    python benchmarks/bench_memory.py [--batch 8] [--presets openvla-oft-tiny pi05-tiny ...]

For each tiny preset, fp32, one process per preset (so peak RSS is that preset's alone):

- estimate: activations (and gradients) from ``estimate_memory`` (weights on the meta device,
  nothing allocated);
- saved: the bytes autograd saves in a real forward on the CPU (what the activation estimate
  models);
- peak growth: the process's peak RSS during a real forward + backward, above its RSS before it
  (model and batch built, one warm-up step done and its memory returned to the OS with
  ``malloc_trim``), against the estimate's activations + gradients; it also holds the backward's
  temporaries, which the estimate leaves out.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import subprocess
import sys

MIB = 1024**2


def rss(field: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak since the last reset) of this process, in bytes."""
    with open("/proc/self/status") as f:
        line = next(line for line in f if line.startswith(field + ":"))
    return float(line.split()[1]) * 1024


def reset_peak_rss() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # Linux: VmHWM starts again from the current RSS


def measure(preset: str, batch_size: int) -> dict[str, float]:
    """Run in a fresh process: estimate, autograd-saved bytes and peak RSS growth of one step."""
    import torch

    from capvector.backbones import build_backbone
    from capvector.memory import estimate_memory, saved_activation_bytes, synthetic_batch

    torch.manual_seed(0)
    torch.set_num_threads(1)
    estimate = estimate_memory(preset, batch_size=batch_size, precision="32-true", strategy="ddp")
    model = build_backbone(preset)
    batch = synthetic_batch(model, batch_size, "cpu")
    model(batch).loss.backward()  # warm-up: lazy buffers, tokenizer caches, kernels' workspaces
    model.zero_grad(set_to_none=True)
    ctypes.CDLL("libc.so.6").malloc_trim(0)  # give the warm-up's freed memory back to the OS
    reset_peak_rss()  # the warm-up's own peak would hide this step's
    before = rss("VmRSS")
    store: list[float] = []
    with saved_activation_bytes(store):
        model(batch).loss.backward()
    return {
        "estimate": estimate.activations,
        "gradients": estimate.gradients,
        "saved": store[0],
        "peak_growth": rss("VmHWM") - before,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--presets", nargs="+", help="default: every registered tiny preset")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(args.one, args.batch)))
        return
    if not args.presets:
        from capvector.backbones import list_presets

        args.presets = [name for name in list_presets() if "tiny" in name]
    print(f"activations, fp32, batch {args.batch}, one forward + backward on the CPU\n")
    print("| preset | activations: estimate (MiB) | autograd saved (MiB) | ratio "
          "| activations + gradients: estimate (MiB) | peak RSS growth (MiB) | ratio |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for preset in args.presets:
        cmd = [sys.executable, __file__, "--one", preset, "--batch", str(args.batch)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        step = r["estimate"] + r["gradients"]
        print(
            f"| {preset} | {r['estimate'] / MIB:.1f} | {r['saved'] / MIB:.1f} | "
            f"{r['estimate'] / r['saved']:.2f} | {step / MIB:.1f} | "
            f"{r['peak_growth'] / MIB:.1f} | {step / r['peak_growth']:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
