"""LoRA through peft: injection into a backbone, what trains, frozen dtypes (merging LoRA into
plain weights is :mod:`capvector.io.lora_layers`)."""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass

import torch
from torch import nn

from capvector.backbones.base import VLABackbone
from capvector.errors import CapVectorError

ADAPTER = "default"


@dataclass
class LoraSettings:
    """OpenVLA-OFT's LoRA: r 32, alpha min(r, 16), no dropout, gaussian init."""

    r: int = 32
    alpha: float = 16.0
    dropout: float = 0.0
    init: str = "gaussian"

    @property
    def scaling(self) -> float:
        return self.alpha / self.r


def inject_lora(backbone: VLABackbone, settings: LoraSettings) -> None:
    """Add LoRA to the backbone's target modules; only LoRA and the heads stay trainable."""
    from peft import LoraConfig, inject_adapter_in_model

    config = LoraConfig(
        r=settings.r,
        lora_alpha=settings.alpha,
        lora_dropout=settings.dropout,
        init_lora_weights=True if settings.init == "default" else settings.init,
        target_modules=backbone.lora_target_modules,
    )
    inject_adapter_in_model(config, backbone, adapter_name=ADAPTER)
    for name, param in backbone.named_parameters():
        is_lora = ".lora_" in name
        is_head = any(fnmatch.fnmatchcase(name, g) for g in backbone.lora_trainable_modules)
        param.requires_grad_(is_lora or is_head)


FROZEN_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


def frozen_dtype_of(name: str) -> torch.dtype:
    if name not in FROZEN_DTYPES:
        raise CapVectorError(f"model.frozen_dtype {name!r} is not one of {sorted(FROZEN_DTYPES)}")
    return FROZEN_DTYPES[name]


def cast_frozen_parameters(module: nn.Module, dtype: torch.dtype, keep: set[str]) -> list[str]:
    """Store every parameter that does not train in ``dtype``, except those named in ``keep``
    (names without wrapper modules such as peft's ``base_layer``); those and what trains in
    float32 (a backbone built in ``dtype`` has them there too). Returns the names cast to ``dtype``.

    Follows peft's adapter autocasting and OpenVLA-OFT's recipe: the frozen base in bf16, what
    trains in float32 (its gradients and AdamW state too)."""
    cast = []
    for name, param in module.named_parameters():
        if param.requires_grad or name.replace(".base_layer.", ".") in keep:
            if param.is_floating_point() and param.dtype != torch.float32:
                param.data = param.data.float()
            continue
        param.data = param.data.to(dtype)
        cast.append(name)
    return cast


def set_trainable(backbone: VLABackbone, lora: LoraSettings | None) -> None:
    """What trains: LoRA adapters and the backbone's ``lora_trainable_modules`` with ``lora``,
    everything without; parameters no output depends on and the LM head (until a text objective
    needs it) are frozen either way, so DDP needs no ``find_unused_parameters``. Used by
    ``VLAModule`` and by the memory planner, which must count what training trains."""
    if lora is not None:
        inject_lora(backbone, lora)
    frozen = set(backbone.unused_parameter_names()) | set(backbone.language_head_parameter_names())
    for name, param in backbone.named_parameters():
        if name.replace(".base_layer.", ".") in frozen:
            param.requires_grad_(False)
