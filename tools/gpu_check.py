"""Check CapVector on one CUDA GPU of your own node: one command, no interaction, one table out.

For one full-size preset per family at its recipe's settings (frozen weights built in bf16, LoRA
r 32 alpha 16, ``bf16-mixed`` autocast, AdamW, batch 8), a warm-up and a timed training step:
``torch.cuda.max_memory_allocated`` against the planner's GPU estimate
(``capvector backbone-info PRESET --memory``), samples/s and the model FLOPs utilisation (the
planner's FLOPs per sample, ``--flops``, over the step time and ``--gpu-tflops``); then the GL
renderer MuJoCo's EGL gets (LIBERO renders through it: an NVIDIA renderer, not llvmpipe); last, one
LIBERO-Spatial episode of the first preset through ``capvector evaluate``'s rollout path on the GPU
under bf16 autocast (``evaluate_backbone``; random weights, so it checks that the episode runs and
what a step costs, not success).

    python tools/gpu_check.py [--presets pi05-3b ...] [--batch 8] [--gpu-tflops 989]
        [--libero-steps N]

Without CUDA it says so in one line and exits 0.
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


def libero_episode(
    preset: str, device: str, precision: str = "bf16-mixed", max_steps: int | None = None
) -> str:
    """One LIBERO-Spatial episode (task 0, official initial state 0, LIBERO's protocol; at most
    ``max_steps`` steps after the wait steps, default the suite's) of ``preset`` built at the
    recipe's settings for LIBERO's two cameras, 8-d state and 8 x 7 action chunks."""
    import torch

    from capvector.backbones.base import preset_config
    from capvector.data.episodes import EvalTask
    from capvector.data.spec import DataSpec
    from capvector.module import VLAModule
    from capvector.training.lora import LoraSettings
    from capvector.workflows.evaluate import evaluate_backbone

    config = preset_config(preset)
    spec = DataSpec(
        cameras=["agentview", "robot0_eye_in_hand"], proprio_keys=["ee_states", "gripper_states"],
        image_size=getattr(config, "image_size", 224),
    )  # fmt: skip
    tokenizer = {} if getattr(config, "tokenizer", "x") else {"tokenizer": "byte"}
    module = VLAModule(
        backbone=preset, backbone_overrides=tokenizer, data_spec=spec,
        lora=LoraSettings(r=32, alpha=16), frozen_dtype="bfloat16",
    )  # fmt: skip
    module.eval().to(device)
    options = {"tasks": [0]} if max_steps is None else {"tasks": [0], "max_steps": max_steps}
    task = EvalTask("libero_spatial", episodes=1, options=options)
    start = time.perf_counter()
    (result,) = evaluate_backbone(
        module.backbone, spec, [task], videos=0, batch_size=1, workers=0, precision=precision
    )
    seconds = time.perf_counter() - start
    del module
    if device.startswith("cuda"):
        torch.cuda.empty_cache()
    outcome = "success" if result.success else f"no success ({result.reason}; random weights)"
    return (
        f"LIBERO-Spatial task 0, initial state 0, {preset} on {device} ({precision}): "
        f"{result.steps} steps in {seconds:.1f} s, {outcome}"
    )


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
    parser.add_argument(
        "--libero-steps", type=int, help="cap the LIBERO episode (default: the suite's limit)"
    )
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
    try:
        print(libero_episode(args.presets[0], "cuda", max_steps=args.libero_steps), flush=True)
    except Exception as err:
        failed = True
        print(f"LIBERO episode failed: {type(err).__name__}: {str(err)[:200]}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
