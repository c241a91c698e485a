"""OpenVLA-OFT's configuration: the architecture dataclasses and the registered presets (the
published 7B LIBERO and ALOHA configurations and their ``-tiny`` variants).

Field values follow moojink/openvla-oft (``prismatic/extern/hf/configuration_prismatic.py``,
``prismatic/vla/constants.py``); the model that reads them is ``modeling.py``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from types import MappingProxyType

from capvector.backbones.base import BackboneConfig, nested_config, register_preset
from capvector.data.statistics import BOUNDS_Q99


@nested_config
@dataclass
class ViTConfig:
    """A timm VisionTransformer; the full-size values reproduce timm's DINOv2 / SigLIP models."""

    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    reg_tokens: int = 0
    class_token: bool = True
    no_embed_class: bool = False
    layer_scale_init: float | None = None
    global_pool: str = "token"
    """'map' builds SigLIP's attention-pool head: unused by OFT but part of its checkpoints."""
    act_layer: str = "gelu"
    """timm activation name. OpenVLA-OFT builds both ViTs with ``act_layer=None`` under timm 0.9.10
    (``TIMM_OVERRIDE_ACT_LAYER`` in ``configuration_prismatic.py``), i.e. timm's default exact GELU,
    SigLIP included (timm >= 1.0 registers SigLIP with ``gelu_tanh``; OFT never sees that)."""


@nested_config
@dataclass
class LlamaSpec:
    hidden_size: int = 4096
    intermediate_size: int = 11008
    num_layers: int = 32
    num_heads: int = 32
    num_kv_heads: int = 32
    vocab_size: int = 32064
    rope_theta: float = 10000.0
    max_position_embeddings: int = 2048
    rms_norm_eps: float = 1e-6


@dataclass
class OpenVLAOFTConfig(BackboneConfig):
    family = "openvla-oft"
    # OpenVLA-OFT (prismatic/vla/datasets/rlds/utils/data_utils.py BOUNDS_Q99): clipped to
    # [-1, 1] by the 1st/99th percentiles, the gripper raw; its finetune.py: AdamW 5e-4 with
    # torch's defaults, no warmup (its LIBERO recipe's x0.1 at 100k: configs/backbones/openvla-oft.yaml).
    normalization = BOUNDS_Q99
    optimizer_preset = MappingProxyType({"lr": 5e-4, "betas": (0.9, 0.999), "weight_decay": 0.01})

    featurizer: ViTConfig = field(default_factory=ViTConfig)
    """DINOv2 half of the fused vision backbone."""
    fused_featurizer: ViTConfig = field(default_factory=ViTConfig)
    """SigLIP half of the fused vision backbone."""
    llm: LlamaSpec = field(default_factory=LlamaSpec)
    head_blocks: int = 2
    """Residual blocks of the MLP-ResNet L1 head (2 in OpenVLA-OFT)."""
    tokenizer: str = "byte"
    """'byte' builds a local byte-level tokenizer; a folder path loads a saved HF tokenizer."""
    prompt_template: str = "In: What action should the robot take to {instruction}?\nOut: "
    """The trailing space tokenizes to Llama-2's '▁' (29871), the id OFT's ``predict_action``
    appends to ``...Out:`` and its training prompts carry before the action tokens
    (``PurePromptBuilder``); the parity fixtures check both give the same ids."""
    film: bool = False
    """OFT+: FiLM language conditioning of every ViT block (``prismatic/models/film_vit_wrapper.py``):
    after the attention residual, ``x * (1 + scale(l)) + shift(l)`` with ``l`` the mean input
    embedding of the prompt tokens (BOS, prompt, </s>; not the action slots)."""


def _dinov2(**sizes: int) -> ViTConfig:
    """The DINOv2 half of the fused vision backbone at ``sizes``: 4 register tokens, LayerScale,
    position embeddings without the class token (timm's ``vit_large_patch14_reg4_dinov2``)."""
    return ViTConfig(reg_tokens=4, no_embed_class=True, layer_scale_init=1e-5, **sizes)


def _siglip(**sizes: float) -> ViTConfig:
    """The SigLIP half at ``sizes``: no class token, the attention-pool head
    (timm's ``vit_so400m_patch14_siglip_224``)."""
    return ViTConfig(class_token=False, global_pool="map", **sizes)


@register_preset("openvla-oft-7b")
def openvla_oft_7b() -> OpenVLAOFTConfig:
    """The published LIBERO configuration: 2 cameras at 224 px, 8-d proprio, chunk 8 x 7."""
    return OpenVLAOFTConfig(
        image_size=224,
        featurizer=_dinov2(patch_size=14, embed_dim=1024, depth=24, num_heads=16),
        fused_featurizer=_siglip(
            patch_size=14, embed_dim=1152, depth=27, num_heads=16, mlp_ratio=3.7362
        ),
        llm=LlamaSpec(),
        tokenizer="",  # Llama-2's tokenizer comes with the checkpoint folder
    )  # fmt: skip


@register_preset("openvla-oft-tiny")
def openvla_oft_tiny() -> OpenVLAOFTConfig:
    """Same architecture at toy width: trains on a 2-core CPU in seconds (64 px, 8x8 patches)."""
    return OpenVLAOFTConfig(
        image_size=64,
        featurizer=_dinov2(patch_size=8, embed_dim=48, depth=3, num_heads=4),
        fused_featurizer=_siglip(patch_size=8, embed_dim=48, depth=3, num_heads=4),
        llm=LlamaSpec(
            hidden_size=64, intermediate_size=128, num_layers=4, num_heads=4, num_kv_heads=4,
            vocab_size=320, max_position_embeddings=512,
        ),
    )  # fmt: skip


# ALOHA dimensions: ALOHA_CONSTANTS in prismatic/vla/constants.py (25-step chunks of 14-d actions,
# 14-d proprio) and ALOHA.md's recipe (--num_images_in_input 3, --use_film True).
_ALOHA = dict(action_dim=14, chunk_size=25, proprio_dim=14, num_images=3, film=True)


@register_preset("openvla-oft-aloha-7b")
def openvla_oft_aloha_7b() -> OpenVLAOFTConfig:
    """OFT+ on ALOHA: 3 cameras, 14-d proprio, chunk 25 x 14, FiLM on both ViTs."""
    return dataclasses.replace(openvla_oft_7b(), **_ALOHA)


@register_preset("openvla-oft-aloha-tiny")
def openvla_oft_aloha_tiny() -> OpenVLAOFTConfig:
    """``openvla-oft-aloha-7b`` at the width of ``openvla-oft-tiny``."""
    return dataclasses.replace(openvla_oft_tiny(), **_ALOHA)


__all__ = [
    "LlamaSpec",
    "OpenVLAOFTConfig",
    "ViTConfig",
    "openvla_oft_7b",
    "openvla_oft_aloha_7b",
    "openvla_oft_aloha_tiny",
    "openvla_oft_tiny",
]
