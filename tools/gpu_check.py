"""Check CapVector on one CUDA GPU of your own node: one command, no interaction, one table out.

For one full-size preset per family at its recipe's settings (frozen weights built in bf16, LoRA
r 32 alpha 16, ``bf16-mixed`` autocast, AdamW, batch 8), a warm-up and a timed training step:
``torch.cuda.max_memory_allocated`` against the planner's GPU estimate
(``capvector backbone-info PRESET --memory``), samples/s and the model FLOPs utilisation (the
planner's FLOPs per sample, ``--flops``, over the step time and ``--gpu-tflops``); then the GL
renderer MuJoCo's EGL gets (LIBERO renders through it: an NVIDIA renderer, not llvmpipe).

    python tools/gpu_check.py [--presets pi05-3b ...] [--batch 8] [--gpu-tflops 989]

Without CUDA it says so in one line and exits 0. Not here yet: ``capvector evaluate --device cuda
--precision bf16`` on one LIBERO episode (issue 58, item 7) needs a full-size export to evaluate.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass

FAMILIES = ("openvla-oft-7b", "pi05-3b", "starvla-qwen2.5-vl-3b-oft")
GIB = 1024**3


@dataclass
class Row:
    preset: str
    loss: float
    step_seconds: float
    peak_gib: float
    planned_gib: float
    samples_per_second: float
    mfu: float

    def line(self) -> str:
        ratio = self.peak_gib / self.planned_gib if self.planned_gib else math.nan
        return (
            f"{self.preset:<28} {self.loss:8.4f} {self.step_seconds:8.2f} {self.peak_gib:9.2f} "
            f"{self.planned_gib:9.2f} {ratio:6.2f} {self.samples_per_second:9.2f} {self.mfu:6.1%}"
        )


HEADER = (
    f"{'preset':<28} {'loss':>8} {'step s':>8} {'peak GiB':>9} {'plan GiB':>9} {'ratio':>6} "
    f"{'samples/s':>9} {'MFU':>6}"
)


def check_preset(preset: str, batch: int, gpu_tflops: float) -> Row:
    import torch

    from capvector.backbones.base import preset_config
    from capvector.module import VLAModule
    from capvector.profiling.flops import estimate_flops
    from capvector.profiling.memory import estimate_memory, synthetic_batch
    from capvector.profiling.settings import TrainingSettings
    from capvector.training.lora import LoraSettings

    settings = TrainingSettings(batch=batch, strategy="ddp", lora_rank=32, frozen_dtype="bfloat16")
    planned = estimate_memory(preset, settings).total
    flops_per_sample = estimate_flops(preset, batch_size=batch, lora_rank=32).training()
    tokenizer = {} if getattr(preset_config(preset), "tokenizer", "x") else {"tokenizer": "byte"}
    module = VLAModule(
        backbone=preset, backbone_overrides=tokenizer, lora=LoraSettings(r=32, alpha=16),
        frozen_dtype="bfloat16",
    )  # fmt: skip
    backbone = module.backbone.to("cuda")
    optimizer = torch.optim.AdamW([p for p in backbone.parameters() if p.requires_grad])
    data = synthetic_batch(backbone, batch, "cuda")
    torch.cuda.reset_peak_memory_stats()
    seconds, loss = 0.0, math.nan
    for _ in range(2):  # the first step warms up kernels and the allocator
        torch.cuda.synchronize()
        start = time.perf_counter()
        with torch.autocast("cuda", dtype=torch.bfloat16):
            out = backbone(data).loss
        out.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        torch.cuda.synchronize()
        seconds, loss = time.perf_counter() - start, float(out)
    peak = torch.cuda.max_memory_allocated()
    del module, backbone, optimizer
    torch.cuda.empty_cache()
    return Row(
        preset, loss, seconds, peak / GIB, planned / GIB, batch / seconds,
        flops_per_sample * batch / seconds / (gpu_tflops * 1e12),
    )  # fmt: skip


def egl_renderer() -> str:
    os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        from capvector.envs.libero.render import gl_renderer

        return gl_renderer() or "none (no GL context)"
    except ImportError as err:
        return f"not checked ({err}; pip install capvector[sim])"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(FAMILIES))
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--gpu-tflops", type=float, default=989.0, help="H100 bf16 dense: 989")
    args = parser.parse_args(argv)
    import torch

    if not torch.cuda.is_available():
        print(f"gpu_check: no CUDA device (torch {torch.__version__}); nothing to check here")
        return 0
    print(f"gpu_check on {torch.cuda.get_device_name()} (torch {torch.__version__})")
    print(HEADER)
    failed = False
    for preset in args.presets:
        try:
            print(check_preset(preset, args.batch, args.gpu_tflops).line(), flush=True)
        except Exception as err:  # one family failing must not hide the others' rows
            failed = True
            print(f"{preset:<28} failed: {type(err).__name__}: {str(err)[:200]}", flush=True)
    print(f"MuJoCo EGL renderer (LIBERO): {egl_renderer()}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
