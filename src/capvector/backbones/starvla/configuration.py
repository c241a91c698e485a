"""StarVLA's configuration: the config dataclass, the Qwen-VL versions it builds, and the
registered presets (Qwen2.5-VL-3B / Qwen3-VL-4B with each head, and ``starvla-tiny-*``).

Field values follow starVLA/starVLA's LIBERO configs and the Qwen-VL ``config.json`` files; the
model that reads them is ``modeling.py``, the heads ``heads.py``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from functools import partial
from types import MappingProxyType
from typing import Any

from capvector.backbones.base import BackboneConfig, BackboneError, register_preset

OPENAI_CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
OPENAI_CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
HALF = (0.5, 0.5, 0.5)

STATE_MODES = ("none", "prompt", "head")
"""Values of ``StarVLAConfig.state_mode``."""


@dataclass(frozen=True)
class QwenVersion:
    model_type: str
    """``model_type`` in a transformers ``config.json`` of this version (checked, never sniffed)."""
    config_class: str
    model_class: str
    head_reads_final_norm: bool = True
    """Whether the last hidden state StarVLA's heads read (``hidden_states[-1]`` of the
    ``*ForConditionalGeneration`` output under its pinned transformers 4.57) has the final RMSNorm
    applied. It has for Qwen2.5-VL; for Qwen3-VL it is the last decoder layer's raw output, and
    the earlier entries include the DeepStack visual features added after a layer (measured on
    the upstream fixtures). We follow it so imported heads see what they were trained on."""

    def classes(self) -> tuple[Any, Any]:
        import transformers

        return getattr(transformers, self.config_class), getattr(transformers, self.model_class)


QWEN_VERSIONS = {
    "qwen2.5-vl": QwenVersion(
        "qwen2_5_vl", "Qwen2_5_VLConfig", "Qwen2_5_VLForConditionalGeneration"
    ),
    "qwen3-vl": QwenVersion(
        "qwen3_vl", "Qwen3VLConfig", "Qwen3VLForConditionalGeneration", head_reads_final_norm=False
    ),
}


@dataclass
class StarVLAConfig(BackboneConfig):
    family = "starvla"
    # StarVLA's LIBERO recipe (examples/simBenchmarks/LIBERO, run_libero_train.sh): AdamW betas
    # (0.9, 0.95), weight decay 1e-8, 5k warmup, cosine down to 1e-6. StarVLA trains the VLM at 1e-5
    # and the head at 1e-4; VLAModule has one learning rate, so this is the VLM's. Normalisation:
    # OpenVLA-OFT's bounds_q99 (the default), as every StarVLA fit here has used.
    optimizer_preset = MappingProxyType(
        {"lr": 1e-5, "betas": (0.9, 0.95), "weight_decay": 1e-8, "schedule": "cosine",
         "warmup_steps": 5000, "min_lr_ratio": 0.1}
    )  # fmt: skip

    qwen_version: str = "qwen2.5-vl"
    """'qwen2.5-vl' or 'qwen3-vl': which transformers classes build the VLM. StarVLA picks the
    wrapper by substring-matching the checkpoint path, which breaks on renamed folders."""
    qwen: dict[str, Any] = field(default_factory=dict)
    """The VLM architecture in transformers' vocabulary (``text_config``, ``vision_config``,
    ``tie_word_embeddings``). ``from_qwen`` fills it from the checkpoint's ``config.json``."""
    head: str = "oft"
    """An action head of ``heads.ACTION_HEADS``: 'oft', 'gr00t', 'layerwise', or ``module:Class``
    for a head of another package."""
    head_args: dict[str, Any] = field(default_factory=dict)
    """Fields of the head's config dataclass; the built model writes back every resolved field."""
    state_mode: str = "none"
    """'none' (StarVLA's default), 'prompt' (state as bin indices in the text, pi0.5 style, as
    StarVLA's QwenOFT / QwenPI_v3) or 'head' (a state token in the flow heads' DiT, as QwenGR00T)."""
    state_bins: int = 256
    """Uniform bins over [-1, 1] for ``state_mode='prompt'``."""
    prompt_template: str = "{instruction}"
    """The user text; ``{instruction}`` becomes the instruction (+ state + head suffix). StarVLA's
    ``datasets.vla_data.CoT_prompt`` plays this role in its LIBERO configs."""
    image_mean: tuple[float, float, float] = OPENAI_CLIP_MEAN
    image_std: tuple[float, float, float] = OPENAI_CLIP_STD
    """Per-channel normalisation of the Qwen image processor (CLIP statistics for Qwen2.5-VL, 0.5
    for Qwen3-VL); ``from_qwen`` reads them from ``preprocessor_config.json``."""
    tokenizer: str = "tiny"
    """'tiny' builds a local Qwen-style byte tokenizer; a folder loads a saved tokenizer when first
    needed; '' means it comes with the checkpoint (``from_qwen`` / ``from_pretrained``)."""
    attn_implementation: str = "sdpa"
    """transformers' attention kernel ('sdpa', 'eager', 'flash_attention_2'), honoured as set:
    StarVLA's ``QWen3.py`` overwrites its configured value with 'sdpa'."""


# -- presets -------------------------------------------------------------------------------------

# Qwen/Qwen2.5-VL-3B-Instruct config.json: 3,754,622,976 parameters (checked in the tests).
QWEN2_5_VL_3B: dict[str, Any] = {
    "text_config": {
        "vocab_size": 151936, "hidden_size": 2048, "intermediate_size": 11008,
        "num_hidden_layers": 36, "num_attention_heads": 16, "num_key_value_heads": 2,
        "max_position_embeddings": 128000, "rms_norm_eps": 1e-6, "sliding_window": 32768,
        "max_window_layers": 70, "use_sliding_window": False,
        "rope_parameters": {"rope_type": "default", "mrope_section": [16, 24, 24], "rope_theta": 1e6},
    },
    "vision_config": {
        "depth": 32, "hidden_size": 1280, "intermediate_size": 3420, "num_heads": 16,
        "out_hidden_size": 2048, "patch_size": 14, "spatial_merge_size": 2,
        "temporal_patch_size": 2, "window_size": 112, "fullatt_block_indexes": [7, 15, 23, 31],
        "tokens_per_second": 2, "hidden_act": "silu",
    },
    "tie_word_embeddings": True,
}  # fmt: skip

# Qwen/Qwen3-VL-4B-Instruct config.json: 4,437,815,808 parameters (StarVLA's QwenPI_v3 docstring).
QWEN3_VL_4B: dict[str, Any] = {
    "text_config": {
        "vocab_size": 151936, "hidden_size": 2560, "intermediate_size": 9728,
        "num_hidden_layers": 36, "num_attention_heads": 32, "num_key_value_heads": 8,
        "head_dim": 128, "max_position_embeddings": 262144, "rms_norm_eps": 1e-6,
        "rope_parameters": {
            "rope_type": "default", "mrope_section": [24, 20, 20], "mrope_interleaved": True,
            "rope_theta": 5e6,
        },
    },
    "vision_config": {
        "depth": 24, "hidden_size": 1024, "intermediate_size": 4096, "num_heads": 16,
        "out_hidden_size": 2560, "patch_size": 16, "spatial_merge_size": 2,
        "temporal_patch_size": 2, "num_position_embeddings": 2304,
        "deepstack_visual_indexes": [5, 11, 17], "hidden_act": "gelu_pytorch_tanh",
    },
    "tie_word_embeddings": True,
}  # fmt: skip

_TINY_TEXT = {
    "vocab_size": 320, "hidden_size": 64, "intermediate_size": 128, "num_hidden_layers": 4,
    "num_attention_heads": 4, "num_key_value_heads": 2, "max_position_embeddings": 2048,
    "rms_norm_eps": 1e-6, "bos_token_id": None, "eos_token_id": None,
}  # fmt: skip
_TINY_VISION = {
    "depth": 2, "hidden_size": 32, "intermediate_size": 64, "num_heads": 2, "out_hidden_size": 64,
    "patch_size": 8, "spatial_merge_size": 2, "temporal_patch_size": 2,
}  # fmt: skip
_TINY_QWEN: dict[str, dict[str, Any]] = {
    "qwen2.5-vl": {
        "text_config": {
            **_TINY_TEXT,
            "rope_parameters": {"rope_type": "default", "mrope_section": [2, 3, 3], "rope_theta": 1e6},
        },
        "vision_config": {
            **_TINY_VISION, "window_size": 32, "fullatt_block_indexes": [1], "hidden_act": "silu",
            "tokens_per_second": 2,
        },
        "tie_word_embeddings": True,
    },
    "qwen3-vl": {
        "text_config": {
            **_TINY_TEXT, "head_dim": 16,
            "rope_parameters": {
                "rope_type": "default", "mrope_section": [4, 2, 2], "mrope_interleaved": True,
                "rope_theta": 5e6,
            },
        },
        "vision_config": {
            **_TINY_VISION, "num_position_embeddings": 64, "deepstack_visual_indexes": [0],
            "hidden_act": "gelu_pytorch_tanh",
        },
        "tie_word_embeddings": True,
    },
}  # fmt: skip


def tiny_qwen_architecture(qwen_version: str) -> dict[str, Any]:
    """A toy Qwen-VL of either version (64 wide, 4 layers, 8-px patches): 16 tokens per 64-px image."""
    if qwen_version not in _TINY_QWEN:
        raise BackboneError(f"unknown qwen_version {qwen_version!r}; use {sorted(QWEN_VERSIONS)}")
    return copy.deepcopy(_TINY_QWEN[qwen_version])


# The tiny presets' head sizes: small enough to train in seconds on a 2-core CPU.
_TINY_FLOW = {
    "width": 32, "num_heads": 2, "hidden_size": 32, "dropout": 0.0, "num_future_tokens": 4,
    "max_seq_len": 16,
}  # fmt: skip
_TINY_HEAD_ARGS: dict[str, dict[str, Any]] = {
    "oft": {},
    "gr00t": {**_TINY_FLOW, "num_layers": 2, "repeated_diffusion_steps": 4},
    "layerwise": dict(_TINY_FLOW),
}
HEADS = ("oft", "gr00t", "layerwise")


def _full_size(qwen_version: str, head: str) -> StarVLAConfig:
    """LIBERO setup of StarVLA's tables: 2 cameras at 224 px, chunk 8 x 7, state off."""
    qwen3 = qwen_version == "qwen3-vl"
    return StarVLAConfig(
        qwen_version=qwen_version,
        qwen=copy.deepcopy(QWEN3_VL_4B if qwen3 else QWEN2_5_VL_3B),
        head=head,
        image_size=224,
        image_mean=HALF if qwen3 else OPENAI_CLIP_MEAN,
        image_std=HALF if qwen3 else OPENAI_CLIP_STD,
        tokenizer="",  # Qwen's tokenizer comes with the checkpoint folder (from_qwen)
    )


def _tiny(head: str) -> StarVLAConfig:
    """The same architecture at toy width: trains on a 2-core CPU in seconds (64-px images)."""
    return StarVLAConfig(
        qwen_version="qwen2.5-vl",
        qwen=tiny_qwen_architecture("qwen2.5-vl"),
        head=head,
        head_args=dict(_TINY_HEAD_ARGS[head]),
        image_size=64,
        tokenizer="tiny",
    )


# The presets: each head on each full-size VLM (``starvla-qwen2.5-vl-3b-oft``, ...) and on the
# toy VLM (``starvla-tiny-oft``, ...).
_FULL_SIZE_VLMS = {"qwen2.5-vl": "3b", "qwen3-vl": "4b"}
for _head in HEADS:
    for _version, _size in _FULL_SIZE_VLMS.items():
        register_preset(f"starvla-{_version}-{_size}-{_head}")(partial(_full_size, _version, _head))
    register_preset(f"starvla-tiny-{_head}")(partial(_tiny, _head))


__all__ = [
    "HALF",
    "HEADS",
    "OPENAI_CLIP_MEAN",
    "OPENAI_CLIP_STD",
    "QWEN2_5_VL_3B",
    "QWEN3_VL_4B",
    "QWEN_VERSIONS",
    "STATE_MODES",
    "QwenVersion",
    "StarVLAConfig",
    "tiny_qwen_architecture",
]
