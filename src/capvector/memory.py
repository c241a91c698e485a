"""Per-device training memory, estimated from a meta-device build (nothing allocated).

Parameters, gradients and AdamW state follow from parameter counts, the precision and how the
strategy shards them. Activations are measured, not guessed: one forward pass with the weights on
the ``meta`` device records every tensor autograd saves for the backward pass
(``saved_tensors_hooks``), once plainly and once with the backbone's blocks checkpointed.

The batch stays on the CPU with real values (``HostValuesMetaCompute``): forward passes read values
to build prompts (Pi0.5's and StarVLA's discretised state), find token positions and multimodal
RoPE indices (Qwen-VL), which a meta tensor does not have. Only the work that touches weights runs
on the meta device.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from torch.utils import _pytree as pytree
from torch.utils._python_dispatch import TorchDispatchMode

from capvector.backbones.base import VLABackbone, build_backbone, list_presets, preset_config
from capvector.data import keys
from capvector.errors import CapVectorError

STRATEGIES = ("ddp", "fsdp2", "deepspeed_zero2", "deepspeed_zero3")
PRECISIONS = ("32-true", "bf16-mixed", "bf16-true")
GIB = 1024**3


@dataclass
class MemoryEstimate:
    parameters: float
    gradients: float
    optimizer: float
    activations: float
    activations_checkpointed: float
    """All in bytes per device."""

    @property
    def total(self) -> float:
        return self.parameters + self.gradients + self.optimizer + self.activations

    @property
    def total_checkpointed(self) -> float:
        return self.parameters + self.gradients + self.optimizer + self.activations_checkpointed

    def table(self) -> str:
        rows: list[tuple[str, float]] = [
            ("parameters", self.parameters),
            ("gradients", self.gradients),
            ("optimizer (AdamW)", self.optimizer),
            ("activations", self.activations),
            ("activations, checkpointed", self.activations_checkpointed),
            ("total", self.total),
            ("total, checkpointed", self.total_checkpointed),
        ]
        lines = [f"  {name:<26} {value / GIB:10.3f} GiB" for name, value in rows]
        if self.activations != self.activations:  # NaN
            lines.append("  (activations could not be traced on the meta device for this backbone)")
        return "\n".join(lines)


@contextmanager
def saved_activation_bytes(store: list[float]) -> Iterator[None]:
    """Sum the bytes of storages autograd saves for backward, each storage once (views of one
    tensor share it) and parameters excluded (they are counted as parameters)."""
    seen: set[int] = set()
    total = 0

    def pack(t: Tensor) -> Tensor:
        nonlocal total
        storage = t.untyped_storage()
        if storage._cdata not in seen and not isinstance(t, torch.nn.Parameter):
            seen.add(storage._cdata)
            total += storage.nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        yield
    store.append(float(total))


class HostValuesMetaCompute(TorchDispatchMode):
    """CPU tensors keep their values until an op meets a meta tensor; that op runs on meta.

    So the batch, token ids and masks computed from it stay real (prompts, positions and masks
    are built as in training), while everything that involves the meta weights costs nothing.
    A CPU tensor sent to the meta device stays on the CPU (``.to(device)`` of an input); a
    boolean CPU mask that indexes a meta tensor becomes the integer positions it selects.
    """

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        kwargs = kwargs or {}
        if func is torch.ops.aten._to_copy.default and not args[0].is_meta:
            if kwargs.get("device") == torch.device("meta"):
                kwargs = {k: v for k, v in kwargs.items() if k != "device"}
            return func(*args, **kwargs)
        leaves = pytree.tree_leaves((args, kwargs))
        if not any(isinstance(t, Tensor) and t.is_meta for t in leaves):
            return func(*args, **kwargs)
        if func is torch.ops.aten.index.Tensor:  # x[mask]: the mask's values give the shape
            source, indices = args
            args = (source, [position for i in indices for position in _positions(i)])
        args, kwargs = pytree.tree_map_only(Tensor, lambda t: t.to("meta"), (args, kwargs))
        return func(*args, **kwargs)


def _positions(index: Tensor | None) -> list[Tensor | None]:
    """A boolean CPU mask as the integer index tensors it stands for, one per dimension."""
    if index is None or index.is_meta or index.dtype != torch.bool:
        return [index]
    return list(index.nonzero().unbind(1))


def synthetic_batch(
    backbone: VLABackbone, batch_size: int, device: str | torch.device
) -> dict[str, Any]:
    c = backbone.config
    return {
        keys.IMAGES: torch.rand(
            batch_size, c.num_images, 3, c.image_size, c.image_size, device=device
        ),
        keys.PROPRIO: torch.zeros(batch_size, c.proprio_dim, device=device),
        keys.ACTIONS: torch.zeros(batch_size, c.chunk_size, c.action_dim, device=device),
        keys.INSTRUCTION: ["pick up the red cube and place it on the plate"] * batch_size,
    }


def measure_activations(backbone: VLABackbone, batch: dict[str, Any], checkpointed: bool) -> float:
    """Bytes autograd saves in one forward of ``backbone`` (weights on meta, ``batch`` on the CPU)."""
    if checkpointed:
        from torch.distributed._composable import checkpoint

        for unit in backbone.shard_units():
            checkpoint(unit)
    store: list[float] = []
    with HostValuesMetaCompute(), saved_activation_bytes(store):
        backbone(batch)
    return store[0]


def _tiny_tokenizer(preset: str) -> dict[str, Any]:
    """The family's tiny-preset tokenizer, so a full-size preset can run a meta forward pass."""
    config = preset_config(preset)
    if not hasattr(config, "tokenizer") or config.tokenizer:
        return {}
    for name in list_presets():
        other = preset_config(name)
        if type(other) is type(config) and "tiny" in name and getattr(other, "tokenizer", ""):
            return {"tokenizer": other.tokenizer}
    return {}


def estimate_memory(
    preset: str,
    batch_size: int = 8,
    precision: str = "bf16-mixed",
    strategy: str = "fsdp2",
    devices: int = 1,
    lora_rank: int | None = None,
) -> MemoryEstimate:
    """Per-device bytes for training ``preset`` with AdamW; ``batch_size`` is per device."""
    if strategy not in STRATEGIES:
        raise CapVectorError(f"unknown strategy {strategy!r}; choose from {', '.join(STRATEGIES)}")
    if precision not in PRECISIONS:
        raise CapVectorError(
            f"unknown precision {precision!r}; choose from {', '.join(PRECISIONS)}"
        )
    overrides = _tiny_tokenizer(preset)
    activations = []
    for checkpointed in (False, True):
        with torch.device("meta"):
            backbone = build_backbone(preset, **overrides)
            if lora_rank:
                from capvector.lora import LoraSettings, inject_lora

                inject_lora(backbone, LoraSettings(r=lora_rank, alpha=lora_rank))
        batch = synthetic_batch(backbone, batch_size, "cpu")
        try:
            activations.append(measure_activations(backbone, batch, checkpointed))
        except (NotImplementedError, RuntimeError):
            # A forward that reads values of meta results (data-dependent shapes downstream of
            # the weights) cannot be traced; then only the weight-related terms are estimated.
            activations.append(float("nan"))
    total = sum(p.numel() for p in backbone.parameters())
    trainable = sum(p.numel() for p in backbone.parameters() if p.requires_grad)
    param_bytes = 2 if precision == "bf16-true" else 4
    state_bytes = 2 if precision == "bf16-true" else 4
    # bf16-mixed autocasts matmuls, so most saved activations are bf16: about half the fp32 figure.
    act_scale = 0.5 if precision != "32-true" else 1.0
    shard_params = strategy in ("fsdp2", "deepspeed_zero3")
    shard_grads = strategy != "ddp"
    params = total * param_bytes / (devices if shard_params else 1)
    if shard_params and devices > 1:
        # FSDP2 all-gathers one unit at a time (plus one prefetched): add the two largest units.
        units = sorted(
            (sum(p.numel() for p in u.parameters()) for u in backbone.shard_units()), reverse=True
        )
        params += sum(units[:2]) * param_bytes
    grads = trainable * state_bytes / (devices if shard_grads else 1)
    optimizer = 2 * trainable * state_bytes / (devices if shard_grads else 1)
    return MemoryEstimate(
        parameters=params,
        gradients=grads,
        optimizer=optimizer,
        activations=activations[0] * act_scale,
        activations_checkpointed=activations[1] * act_scale,
    )


def describe(estimate: MemoryEstimate, **settings: Any) -> str:
    header = ", ".join(f"{k}={v}" for k, v in settings.items())
    return f"per-device memory estimate ({header}):\n{estimate.table()}"


__all__ = ["MemoryEstimate", "describe", "estimate_memory"]
