"""Training FLOPs per sample and GPU-hours, from a meta-device build (``backbone-info --flops``).

The step is traced as ``VLAModule.training_step`` runs it, with each auxiliary objective attached in
turn; the batch keeps its values on the CPU (``HostValuesMetaCompute`` of
:mod:`capvector.profiling.memory`) while the weights stay on the meta device.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field

from capvector.backbones.base import VLABackbone
from capvector.data.batch import Batch
from capvector.objectives.base import Objective
from capvector.profiling.memory import (
    HostValuesMetaCompute,
    make_objective,
    meta_backbone,
    synthetic_batch,
)

BUILTIN_OBJECTIVES = ("spatial", "reasoning")


@dataclass
class FlopsEstimate:
    """Model FLOPs of one training step per sample, by auxiliary objective attached.

    Forward and backward are counted separately (``torch.utils.flop_counter``: matmuls,
    convolutions and attention; elementwise work is not counted). The backward is traced, not
    assumed 2x: frozen weights need no weight gradients, so a LoRA step costs about 2x the
    forward, full fine-tuning about 3x. Activation checkpointing recomputes the blocks' forward
    on top (hardware FLOPs), which model FLOPs utilisation by convention does not count.
    """

    forward: dict[str, float] = field(default_factory=dict)
    backward: dict[str, float] = field(default_factory=dict)

    def training(self, objective: str = "action") -> float:
        return self.forward[objective] + self.backward[objective]

    def gpu_hours(
        self,
        objective: str,
        steps: int,
        batch_size: int,
        devices: int,
        mfu: float,
        gpu_tflops: float,
    ) -> float:
        """GPU-hours of ``steps`` optimizer steps at ``batch_size`` per device on ``devices``."""
        samples = steps * batch_size * devices
        return samples * self.training(objective) / (mfu * gpu_tflops * 1e12) / 3600

    def table(
        self, steps: int, batch_size: int, devices: int, mfu: float, gpu_tflops: float
    ) -> str:
        names = {"action": "action loss only", "spatial": "+ spatial alignment",
                 "reasoning": "+ reasoning co-training"}  # fmt: skip
        lines = [
            f"training FLOPs per sample (model FLOPs) and GPU-hours for {steps:,} steps x batch "
            f"{batch_size} x {devices} device(s) at MFU {mfu:g} of {gpu_tflops:g} TFLOP/s:",
            f"  {'':<26} {'forward':>10} {'backward':>10} {'train':>10} {'vs SFT':>7} {'GPU-h':>9}",
        ]
        for key, label in names.items():
            if key not in self.forward:
                continue
            hours = self.gpu_hours(key, steps, batch_size, devices, mfu, gpu_tflops)
            lines.append(
                f"  {label:<26} {self.forward[key] / 1e12:9.3f}T {self.backward[key] / 1e12:9.3f}T "
                f"{self.training(key) / 1e12:9.3f}T {self.training(key) / self.training():6.2f}x "
                f"{hours:9.1f}"
            )
        lines.append(
            "  (wall-clock hours = GPU-hours / devices; activation checkpointing adds about one "
            "forward of the blocks)"
        )
        return "\n".join(lines)


def training_step_flops(
    backbone: VLABackbone, batch: Batch, objective: Objective | None = None
) -> tuple[float, float]:
    """(forward, backward) FLOPs of one training step of ``backbone`` (weights on meta or real)
    with ``objective`` added to the loss as ``VLAModule.training_step`` does."""
    from torch.utils.flop_counter import FlopCounterMode

    meta = any(p.is_meta for p in backbone.parameters())
    with (
        FlopCounterMode(display=False) as counter,
        HostValuesMetaCompute() if meta else nullcontext(),
    ):
        request = objective.request if objective is not None else None
        output = backbone(batch, request)
        loss = output.loss
        if objective is not None:
            loss = loss + objective.weight * objective(batch, output, backbone)
        forward = counter.get_total_flops()
        loss.backward()
    return float(forward), float(counter.get_total_flops() - forward)


def estimate_flops(
    preset: str,
    batch_size: int = 8,
    lora_rank: int | None = None,
    objectives: Sequence[str] = BUILTIN_OBJECTIVES,
) -> FlopsEstimate:
    """Training FLOPs per sample of ``preset`` (weights on the meta device), plain and with each
    of ``objectives`` attached. Attention is counted as its matmuls, whichever kernel runs it."""
    estimate = FlopsEstimate()
    for name in ("action", *objectives):
        backbone = meta_backbone(preset, lora_rank)
        objective = None
        if name != "action":
            objective = make_objective(name)
            objective.bind(backbone)  # builds projectors, unfreezes the LM head without LoRA
            objective.to("meta")  # its projector too: gradients must stay on one device
        batch = synthetic_batch(backbone, batch_size, "cpu", objectives=True)
        forward, backward = training_step_flops(backbone, batch, objective)
        estimate.forward[name] = forward / batch_size
        estimate.backward[name] = backward / batch_size
    return estimate


__all__ = ["FlopsEstimate", "estimate_flops", "make_objective", "training_step_flops"]
