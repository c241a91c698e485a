"""``capvector backbone-info``: parameter counts of a preset, and with --memory / --flops the
training memory and FLOPs (:mod:`capvector.profiling`)."""

from __future__ import annotations

from capvector.profiling.settings import TrainingSettings
from capvector.tool_cli import run_tool


def backbone_info_main(argv: list[str]) -> int:
    return run_tool(backbone_info_cli, argv, "backbone-info")


def backbone_info_cli(
    preset: str | None = None,
    /,
    *,
    list: bool = False,
    memory: bool = False,
    flops: bool = False,
    settings: TrainingSettings,
    steps: int = 100_000,
    mfu: float = 0.4,
    gpu_tflops: float = 989.0,
) -> None:
    """Parameter counts per component from a meta-device build (no memory, no download); with
    --memory the per-device training memory, with --flops the training FLOPs and GPU-hours.

    Args:
        preset: a registered preset; omit with --list
        list: list the registered presets
        memory: estimate per-device training memory
        flops: training FLOPs per sample, GPU-hours
        settings: the training run (each field an option: --batch, --precision, ...)
        steps: optimizer steps (--flops)
        mfu: model FLOPs utilisation (--flops)
        gpu_tflops: peak dense TFLOP/s (H100 bf16: 989)
    """
    from capvector.backbones import build_backbone, list_presets
    from capvector.profiling.meta import on_meta

    if list or not preset:
        print("\n".join(list_presets()))
        return
    if memory:  # first: it checks the settings, so a typo fails before anything is printed
        from capvector.profiling.memory import describe, estimate_memory

        estimate = describe(estimate_memory(preset, settings), settings)
    with on_meta():
        model = build_backbone(preset)
    print(f"{preset} ({type(model).__name__})")
    rows = [
        (name, sum(p.numel() for p in child.parameters())) for name, child in model.named_children()
    ]
    capability = set(model.capability_parameter_names())
    in_vector = sum(p.numel() for n, p in model.named_parameters() if n in capability)
    total = sum(count for _, count in rows)
    width = max(len(name) for name, _ in rows)
    for name, count in rows:
        print(f"  {name:<{width}}  {count:>15,}")
    print(f"  {'total':<{width}}  {total:>15,}")
    print(f"  {'capability':<{width}}  {in_vector:>15,}  (parameters a capability vector covers)")
    for source in model.weight_provenance():  # a preset built from pretrained weight packages
        print(f"pretrained weights: {source['weights']}")
        print(f"  packages  {', '.join(source['packages'])}")
        print(f"  sha256    {source['sha256']}")
        print(f"  licence   {source['license']}")
        print(f"  origin    {source['origin']}")
    if memory:
        print(estimate)
    if flops:
        from capvector.profiling.flops import estimate_flops

        batch, devices = settings.batch, settings.devices
        counted = estimate_flops(preset, batch_size=batch, lora_rank=settings.lora_rank)
        print(
            counted.table(
                steps=steps, batch_size=batch, devices=devices, mfu=mfu, gpu_tflops=gpu_tflops
            )
        )
