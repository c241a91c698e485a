"""Pi0.5's configuration: the SigLIP and Gemma sizes, the flow-matching settings, and the
registered presets (``pi05-3b``, the published architecture, and ``pi05-tiny``).

Field values follow openpi (``Pi0Config(pi05=True)``, ``gemma.py``, ``siglip.py``) and LeRobot's
``configuration_pi05.py``; the model that reads them is ``modeling.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

from capvector.backbones.base import BackboneConfig, nested_config, register_preset
from capvector.data.statistics import QUANTILES


@nested_config
@dataclass
class SiglipSpec:
    """SigLIP vision tower; the defaults are So400m/14 (openpi ``siglip.py`` "So400m/14")."""

    hidden_size: int = 1152
    intermediate_size: int = 4304
    num_layers: int = 27
    num_heads: int = 16
    patch_size: int = 14
    layer_norm_eps: float = 1e-6


@nested_config
@dataclass
class GemmaSpec:
    """One Gemma stream; the defaults are openpi's ``gemma_2b`` (``gemma.py`` ``get_config``)."""

    hidden_size: int = 2048
    intermediate_size: int = 16384
    num_layers: int = 18
    num_heads: int = 8
    num_kv_heads: int = 1
    head_dim: int = 256


@dataclass
class Pi05Config(BackboneConfig):
    family = "pi05"
    # openpi and LeRobot normalise Pi0.5's states and actions with q01/q99 quantiles, every
    # dimension, without clipping (LeRobot configuration_pi05.py normalization_mapping: QUANTILES).
    normalization = QUANTILES
    # openpi's defaults (src/openpi/training/config.py, optimizer.py; LeRobot's
    # get_optimizer_preset likewise): AdamW betas (0.9, 0.95), weight decay 1e-10, 1k warmup
    # steps, cosine from 2.5e-5 down to 2.5e-6.
    optimizer_preset = MappingProxyType(
        {"lr": 2.5e-5, "betas": (0.9, 0.95), "weight_decay": 1e-10, "schedule": "cosine",
         "warmup_steps": 1000, "min_lr_ratio": 0.1}
    )  # fmt: skip

    vision: SiglipSpec = field(default_factory=SiglipSpec)
    vlm: GemmaSpec = field(default_factory=GemmaSpec)
    """The PaliGemma language model (prefix stream)."""
    expert: GemmaSpec = field(
        default_factory=lambda: GemmaSpec(hidden_size=1024, intermediate_size=4096)
    )
    """The action expert (suffix stream): openpi ``gemma_300m``. Heads, KV heads and head_dim
    must equal the VLM's because both streams share one attention."""
    vocab_size: int = 257_152
    rope_theta: float = 10_000.0
    rms_norm_eps: float = 1e-6
    max_action_dim: int = 32
    """Actions are zero-padded to this width inside the model (openpi/LeRobot ``max_action_dim``)."""
    tokenizer: str = ""
    """'byte' builds a local byte-level tokenizer; a folder loads a saved HF tokenizer (PaliGemma's
    for the full model); '' means it comes with the checkpoint folder."""
    tokenizer_max_length: int = 200
    """Prompts longer than this are truncated (with a warning), as openpi's ``max_token_len``."""
    state_bins: int = 256
    """The normalised proprio state is discretised into this many bins over [-1, 1] and written
    into the prompt (Pi0.5's discrete state input)."""
    prompt_state_dim: int = 0
    """0: the prompt holds the state as it is, as openpi (``TokenizePrompt`` runs before
    ``PadStatesAndActions``) and LeRobot since commit f0d2b37. N: the state is zero-padded to N dims
    first, as LeRobot <= 0.4.4 did (``pad_vector(state, max_state_dim)`` in ``processor_pi05.py``),
    which adds N - P "128" tokens; set it to the checkpoint's ``max_state_dim`` for a policy trained
    with LeRobot <= 0.4.4 (its folder does not record which version wrote it)."""
    num_inference_steps: int = 10
    """Euler steps from t = 1 (noise) to t = 0 at inference."""
    accumulate_time: bool = False
    """The Euler steps' t as openpi computes it, a float32 running sum of dt (True), or as LeRobot,
    1 + k·dt (False). They differ by about 1e-7, which the 4e-3 minimum period of the time
    embedding turns into about 3e-5 in the sampled actions; the openpi import sets it."""
    time_sampling_beta_alpha: float = 1.5
    time_sampling_beta_beta: float = 1.0
    time_sampling_scale: float = 0.999
    time_sampling_offset: float = 0.001
    """Training times t = Beta(alpha, beta) * scale + offset (openpi ``sample_time``)."""
    min_period: float = 4e-3
    max_period: float = 4.0
    """Periods of the sinusoidal time embedding."""
    loss_include_padded_dims: bool = True
    """Average the flow-matching MSE over all ``max_action_dim`` dims, padded ones included, as
    openpi (True), or over the real ``action_dim`` only, as LeRobot (False). See ``flow_loss``."""


@register_preset("pi05-3b")
def pi05_3b() -> Pi05Config:
    """The published architecture (openpi ``Pi0Config(pi05=True)``): 224 px, horizon 50, 3 cameras.

    ``chunk_size``, ``action_dim``, ``proprio_dim`` and ``num_images`` follow the data when trained
    through ``VLAModule``; the architecture does not depend on them.
    """
    return Pi05Config(image_size=224, chunk_size=50, num_images=3, action_dim=7, proprio_dim=8)


@register_preset("pi05-tiny")
def pi05_tiny() -> Pi05Config:
    """Same architecture at toy width (64 px, 8x8 patches, 2 layers): trains on a CPU in seconds.

    As in the full model the expert's attention inner width (4 x 16) differs from its width (32).
    """
    return Pi05Config(
        image_size=64,
        vision=SiglipSpec(hidden_size=32, intermediate_size=64, num_layers=2, num_heads=4, patch_size=8),
        vlm=GemmaSpec(hidden_size=64, intermediate_size=128, num_layers=2, num_heads=4, num_kv_heads=1, head_dim=16),
        expert=GemmaSpec(hidden_size=32, intermediate_size=64, num_layers=2, num_heads=4, num_kv_heads=1, head_dim=16),
        vocab_size=260,  # the byte-level tokenizer's ids
        tokenizer="byte",
    )  # fmt: skip


__all__ = ["GemmaSpec", "Pi05Config", "SiglipSpec", "pi05_3b", "pi05_tiny"]
