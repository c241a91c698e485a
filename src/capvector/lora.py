"""LoRA through peft: injection into a backbone and the merged (plain-key) state dict for export."""

from __future__ import annotations

import fnmatch
from collections.abc import Mapping
from dataclasses import dataclass

from torch import Tensor

from capvector.backbones.base import VLABackbone

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


def merge_lora_state_dict(state: Mapping[str, Tensor], scaling: float) -> dict[str, Tensor]:
    """A state dict with LoRA merged in and peft's key changes undone.

    ``X.base_layer.weight`` + scaling * B @ A becomes ``X.weight`` (computed in fp32, stored in the
    base dtype), so exports of LoRA and of full fine-tuning have the same keys and capability
    vectors subtract them directly. Works on plain state dicts, so the same code serves a single
    process and a state dict gathered from FSDP2 shards.
    """
    merged = {k: v for k, v in state.items() if ".lora_" not in k}
    suffix = f".lora_A.{ADAPTER}.weight"
    for key in state:
        if not key.endswith(suffix):
            continue
        prefix = key[: -len(suffix)]
        base_key = f"{prefix}.base_layer.weight"
        lora_b = state[f"{prefix}.lora_B.{ADAPTER}.weight"].float()
        base = merged[base_key]
        merged[base_key] = (base.float() + scaling * (lora_b @ state[key].float())).to(base.dtype)
    return {k.replace(".base_layer.", "."): v for k, v in merged.items()}
