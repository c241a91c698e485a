"""Pi0.5-style backbone: PaliGemma (SigLIP So400m/14 + Gemma-2B) and a Gemma-300M flow-matching
action expert that share one attention per layer.

Follows openpi (``src/openpi/models/pi0.py``, ``gemma.py``, ``tokenizer.py``,
``models_pytorch/pi0_pytorch.py``, ``gemma_pytorch.py``) and LeRobot's port
(``src/lerobot/policies/pi05/{modeling_pi05,processor_pi05,configuration_pi05}.py``); the facts we
rely on are collected in the project's ``research/pi05_lerobot.md``. The config and presets are in
``configuration.py``. Module names follow the checkpoint key families, so LeRobot's and openpi's
checkpoints load through a small prefix map (``convert.py``). Parity with both is tested against
fixtures their own code wrote (``tests/backbones/pi05/test_parity_pi05.py``,
``tools/pi05/make_upstream_fixtures.py``).

Sequence layout (one row)::

    prefix (VLM stream)  = [N_cam x patches image tokens] [BOS "Task: ..., State: ...;\\nAction: "] [pad]
    suffix (expert)      = [T noisy action tokens]

Attention is block-causal ("prefix-LM", big_vision ``make_attn_mask``): the prefix is one
bidirectional block, the T action tokens a second block that sees the valid prefix and itself;
padding and masked cameras are never attended. Every layer runs one attention over the
concatenated Q/K/V of both streams with one RoPE position vector; each stream keeps its own
norms, o_proj and MLP. The expert's norms are adaptive RMSNorms conditioned on the flow time.

Flow matching as openpi: t = 1 is noise, t = 0 is data; the expert predicts the velocity
ε − a. Inference runs the prefix once (its per-layer K/V are cached) and 10 Euler steps of the
expert only.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from capvector.backbones.base import (
    IGNORE_INDEX,
    BackboneError,
    ImportOption,
    OutputRequest,
    VLABackbone,
    VLAOutput,
    draw_flow_noise,
    project_onto_vocabulary,
    register_family,
)
from capvector.backbones.common import (
    answer_ids_then_eos,
    check_cameras,
    discretize_state,
    right_pad,
)
from capvector.backbones.pi05.configuration import GemmaSpec, Pi05Config, SiglipSpec
from capvector.data.batch import Batch


class Pi05Batch(Batch, total=False):
    """A ``Batch`` with the one input only Pi0.5 reads."""

    image_mask: Tensor
    """(B, N_cam) bool, False for a missing camera (its tokens are never attended). Absent means
    every camera is present. (openpi ``Observation.image_masks``.)"""


IMAGE_MASK = "image_mask"
"""``Pi05Batch``'s key, as a constant for the tests and scripts written against it."""

PALIGEMMA_TOKENIZER = (
    "download PaliGemma's tokenizer (google/paligemma-3b-pt-224) where the network allows and pass "
    "its folder"
)
MASK_VALUE = -2.3819763e38
"""The finite large negative openpi/LeRobot put into masked attention logits (no NaN rows)."""


# -- pure functions (masks, prompt, flow matching) ----------------------------------------------


def make_attention_mask(valid: Tensor, ar: Tensor) -> Tensor:
    """(B, L) bool valid tokens, (B, L) int block-start flags -> (B, L, L) bool "query i sees key j".

    big_vision ``make_attn_mask`` (openpi ``pi0.py`` / ``pi0_pytorch.py``): a cumulative sum of the
    flags numbers the blocks; i sees j iff block(j) <= block(i) and both tokens are valid.
    """
    block = torch.cumsum(ar.to(torch.long), dim=1)
    causal = block[:, None, :] <= block[:, :, None]
    return causal & valid[:, None, :] & valid[:, :, None]


def positions_from_valid(valid: Tensor) -> Tensor:
    """(B, L) bool -> (B, L) RoPE positions: cumsum(valid) - 1, so padding does not advance them."""
    return torch.cumsum(valid.to(torch.long), dim=1) - 1


def clean_task(task: str) -> str:
    """openpi/LeRobot prompt cleaning: strip, then ``_`` and newlines become spaces."""
    return task.strip().replace("_", " ").replace("\n", " ")


def build_prompt(task: str, state_bins: Sequence[int] | None) -> list[str]:
    """The text pieces tokenized (each without special tokens) after BOS.

    Pi0.5 (state in the prompt): ``"Task: {task}, State: {b1 b2 ...};\\nAction: "``. Without a
    state the Pi0 format: the task, then "\\n" tokenized separately as openpi does.
    """
    cleaned = clean_task(task)
    if state_bins is None:
        return [cleaned, "\n"]
    state = " ".join(str(int(b)) for b in state_bins)
    return [f"Task: {cleaned}, State: {state};\nAction: "]


def sinusoidal_time_embedding(
    time: Tensor, dim: int, min_period: float, max_period: float
) -> Tensor:
    """(B,) times -> (B, dim) [sin ; cos] features with log-spaced periods (openpi
    ``posemb_sincos``), computed in float64 as LeRobot's ``create_sinusoidal_pos_embedding``."""
    if dim % 2:
        raise BackboneError(f"the time embedding width {dim} must be even")
    fraction = torch.linspace(0.0, 1.0, dim // 2, dtype=torch.float64, device=time.device)
    period = min_period * (max_period / min_period) ** fraction
    angle = time.to(torch.float64)[:, None] * (2 * math.pi / period)[None, :]
    return torch.cat([angle.sin(), angle.cos()], dim=-1)


def flow_matching_path(actions: Tensor, noise: Tensor, time: Tensor) -> tuple[Tensor, Tensor]:
    """x_t = t·ε + (1 − t)·a and the target velocity u = ε − a (openpi convention, t = 1 is noise).

    actions, noise (B, T, D); time (B,).
    """
    t = time.to(actions.dtype)[:, None, None]
    return t * noise + (1 - t) * actions, noise - actions


def resize_with_pad(images: Tensor, size: int) -> Tensor:
    """(N, 3, H, W) in [0, 1] -> (N, 3, size, size): aspect kept, bilinear, centred black padding.

    openpi ``image_tools.resize_with_pad`` (a re-creation of ``tf.image.resize_with_pad``); the pad
    is 0 here and becomes -1 after the [-1, 1] mapping, as in both upstream pipelines.
    """
    height, width = images.shape[-2:]
    if (height, width) == (size, size):
        return images
    ratio = max(width / size, height / size)
    new_h, new_w = int(height / ratio), int(width / ratio)
    resized = F.interpolate(images, size=(new_h, new_w), mode="bilinear", align_corners=False)
    top, extra_h = divmod(size - new_h, 2)
    left, extra_w = divmod(size - new_w, 2)
    return F.pad(resized.clamp(0, 1), (left, left + extra_w, top, top + extra_h), value=0.0)


def rope_cos_sin(positions: Tensor, head_dim: int, theta: float) -> tuple[Tensor, Tensor]:
    """(B, L) positions -> cos, sin (B, 1, L, head_dim) in float32.

    Computed from the config rather than kept in a buffer, so a model built on the meta device
    and materialised later has correct values.
    """
    exponent = torch.arange(0, head_dim, 2, dtype=torch.float32, device=positions.device) / head_dim
    inv_freq = 1.0 / (theta**exponent)
    freqs = positions.to(torch.float32)[..., None] * inv_freq
    angles = torch.cat([freqs, freqs], dim=-1)[:, None]
    return angles.cos(), angles.sin()


def apply_rope(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """Half-split rotation (HF Gemma ``apply_rotary_pos_emb`` = openpi ``_apply_rope``), in fp32."""
    from transformers.models.gemma.modeling_gemma import rotate_half

    xf = x.to(torch.float32)
    return (xf * cos + rotate_half(xf) * sin).to(x.dtype)


def joint_attention(q: Tensor, k: Tensor, v: Tensor, mask: Tensor, scaling: float) -> Tensor:
    """Scaled dot-product attention over the joint sequence, softmax in float32.

    q (B, H, Lq, D); k, v (B, H_kv, Lk, D); mask (B, Lq, Lk) bool -> (B, Lq, H * D).
    """
    from transformers.models.gemma.modeling_gemma import repeat_kv

    groups = q.shape[1] // k.shape[1]
    k, v = repeat_kv(k, groups), repeat_kv(v, groups)
    scores = torch.matmul(q.to(torch.float32), k.to(torch.float32).transpose(-1, -2)) * scaling
    scores = scores.masked_fill(~mask[:, None], MASK_VALUE)
    # Queries that may see nothing (padding) get a uniform softmax upstream, i.e. they read every
    # key, action tokens included. Zeroing those rows keeps every prefix position, padding too,
    # independent of the actions, and the same in the joint and the cached pass; no real token
    # ever reads a padding position, so the outputs are unchanged.
    probs = torch.softmax(scores, dim=-1) * mask.any(dim=-1)[:, None, :, None]
    probs = probs.to(v.dtype)
    out = torch.matmul(probs, v)
    return out.transpose(1, 2).reshape(q.shape[0], q.shape[2], -1)


# -- modules -------------------------------------------------------------------------------


class AdaRMSNorm(nn.Module):
    """RMSNorm whose scale, shift and residual gate come from the flow-time condition (Pi0.5).

    normed = x·rsqrt(mean(x²) + eps) in fp32; [scale, shift, gate] = dense(cond);
    output = normed·(1 + scale) + shift. No learned weight (checkpoint keys ``….dense.{weight,bias}``).
    As openpi's PyTorch port (``transformers_replace/…/modeling_gemma.py``) only the dense weight
    is zero-initialised: the time conditioning starts at zero while the blocks' gates (bias) do not.
    """

    def __init__(self, dim: int, cond_dim: int, eps: float) -> None:
        super().__init__()
        self.eps = eps
        self.dense = nn.Linear(cond_dim, 3 * dim)
        nn.init.zeros_(self.dense.weight)

    def forward(self, x: Tensor, cond: Tensor) -> tuple[Tensor, Tensor]:
        """x (B, L, dim), cond (B, cond_dim) -> normed (B, L, dim), gate (B, 1, dim)."""
        xf = x.to(torch.float32)
        normed = xf * torch.rsqrt(xf.pow(2).mean(-1, keepdim=True) + self.eps)
        scale, shift, gate = self.dense(cond).unsqueeze(1).chunk(3, dim=-1)
        normed = normed * (1 + scale.to(torch.float32)) + shift.to(torch.float32)
        return normed.to(x.dtype), gate.to(x.dtype)


class GemmaStreamLayer(nn.Module):
    """One stream's half of a joint layer, made of transformers' Gemma modules.

    Only the projections of ``GemmaAttention`` are used: the attention itself runs over both
    streams in ``JointDecoderLayer``. ``cond_dim`` set = adaptive norms (the action expert).
    """

    def __init__(self, gemma_config: Any, layer_idx: int, cond_dim: int | None, eps: float) -> None:
        from transformers.models.gemma.modeling_gemma import GemmaAttention, GemmaMLP, GemmaRMSNorm

        super().__init__()
        width = gemma_config.hidden_size
        self.self_attn = GemmaAttention(gemma_config, layer_idx)
        self.mlp = GemmaMLP(gemma_config)
        self.adaptive = cond_dim is not None
        if cond_dim is None:
            self.input_layernorm: nn.Module = GemmaRMSNorm(width, eps=eps)
            self.post_attention_layernorm: nn.Module = GemmaRMSNorm(width, eps=eps)
        else:
            self.input_layernorm = AdaRMSNorm(width, cond_dim, eps)
            self.post_attention_layernorm = AdaRMSNorm(width, cond_dim, eps)

    def _norm(
        self, norm: nn.Module, x: Tensor, cond: Tensor | None
    ) -> tuple[Tensor, Tensor | None]:
        if self.adaptive:
            return norm(x, cond)
        return norm(x), None

    def project_qkv(
        self, x: Tensor, cond: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """x (B, L, W) -> q (B, H, L, D), k, v (B, H_kv, L, D) and the attention-branch gate."""
        h, gate = self._norm(self.input_layernorm, x, cond)
        attn = self.self_attn
        shape = (*x.shape[:2], -1, attn.head_dim)
        q = attn.q_proj(h).view(shape).transpose(1, 2)
        k = attn.k_proj(h).view(shape).transpose(1, 2)
        v = attn.v_proj(h).view(shape).transpose(1, 2)
        return q, k, v, gate

    def finish(
        self, x: Tensor, attn_out: Tensor, gate: Tensor | None, cond: Tensor | None
    ) -> Tensor:
        """Own o_proj, (gated) residual, post-attention norm, GeGLU MLP, (gated) residual."""
        out = self.self_attn.o_proj(attn_out.to(self.self_attn.o_proj.weight.dtype))
        x = x + (out if gate is None else gate * out)
        h, gate = self._norm(self.post_attention_layernorm, x, cond)
        out = self.mlp(h)
        return x + (out if gate is None else gate * out)


class JointDecoderLayer(GemmaStreamLayer):
    """The VLM's layer L, whose ``forward`` runs the whole joint layer L with the expert's layer.

    Driving the joint layer from one module's ``forward`` makes it a unit for FSDP2 and activation
    checkpointing (``shard_units``) while every parameter keeps its checkpoint name; the expert's
    layers are passed in and stay with the root FSDP unit.
    """

    def forward(
        self,
        prefix: Tensor | None,
        suffix: Tensor | None,
        cond: Tensor | None,
        expert: GemmaStreamLayer,
        mask: Tensor,
        cos: Tensor,
        sin: Tensor,
        cached: tuple[Tensor, Tensor] | None = None,
    ) -> tuple[Tensor | None, Tensor | None, Tensor, Tensor]:
        """One layer over the streams present: prefix (B, S, W_vlm), suffix (B, T, W_exp).

        openpi ``gemma.py`` Block / ``compute_layer_complete``: each stream norms and projects its
        own Q/K/V; they are concatenated along the sequence, rotated with one position vector
        (cos, sin of the query tokens) and attend once under ``mask`` (B, L_q, L_k); the output
        is split back and each stream applies its own o_proj and MLP. ``cached`` (K, V) of the
        prefix are prepended to the keys (read, never extended). Returns both streams and this
        call's K, V (RoPE applied).
        """
        streams = [(self, prefix, None), (expert, suffix, cond)]
        qs, ks, vs, gates = [], [], [], []
        for layer, x, c in streams:
            if x is None:
                gates.append(None)
                continue
            q, k, v, gate = layer.project_qkv(x, c)
            qs.append(q)
            ks.append(k.to(q.dtype))
            vs.append(v.to(q.dtype))
            gates.append(gate)
        q = apply_rope(torch.cat(qs, dim=2), cos, sin)
        k = apply_rope(torch.cat(ks, dim=2), cos, sin)
        v = torch.cat(vs, dim=2)
        keys_all, values_all = k, v
        if cached is not None:
            keys_all = torch.cat([cached[0].to(k.dtype), k], dim=2)
            values_all = torch.cat([cached[1].to(v.dtype), v], dim=2)
        out = joint_attention(q, keys_all, values_all, mask, self.self_attn.scaling)
        parts = iter(out.split([x.shape[1] for _, x, _ in streams if x is not None], dim=1))
        updated = [
            None if x is None else layer.finish(x, next(parts), gate, c)
            for (layer, x, c), gate in zip(streams, gates, strict=True)
        ]
        return updated[0], updated[1], k, v


class GemmaStream(nn.Module):
    """Decoder layers + final norm of one stream (+ the token embedding for the VLM).

    The embedding is a plain ``nn.Embedding``: the Gemma √width scaling is applied by
    ``Pi05.embed_prefix`` itself, whatever the installed transformers' Gemma embedding does.
    """

    def __init__(
        self, spec: GemmaSpec, eps: float, vocab_size: int | None, cond_dim: int | None
    ) -> None:
        from transformers import GemmaConfig
        from transformers.models.gemma.modeling_gemma import GemmaRMSNorm

        super().__init__()
        gemma_config = GemmaConfig(
            vocab_size=vocab_size or 1,
            hidden_size=spec.hidden_size,
            intermediate_size=spec.intermediate_size,
            num_hidden_layers=spec.num_layers,
            num_attention_heads=spec.num_heads,
            num_key_value_heads=spec.num_kv_heads,
            head_dim=spec.head_dim,
            hidden_act="gelu_pytorch_tanh",  # GeGLU with tanh-approximated GELU, as openpi
            rms_norm_eps=eps,
            attention_bias=False,
            bos_token_id=None,  # token ids are the tokenizer's business; the expert has no vocab
            eos_token_id=None,
            pad_token_id=None,
        )
        if vocab_size is not None:
            self.embed_tokens = nn.Embedding(vocab_size, spec.hidden_size)
            # Unit-RMS token vectors after the √width scaling (Gemma's scaling assumes this size).
            nn.init.normal_(self.embed_tokens.weight, std=spec.hidden_size**-0.5)
        layer_class = GemmaStreamLayer if cond_dim is not None else JointDecoderLayer
        self.layers = nn.ModuleList(
            layer_class(gemma_config, i, cond_dim, eps) for i in range(spec.num_layers)
        )
        self.norm: nn.Module = (
            GemmaRMSNorm(spec.hidden_size, eps=eps)
            if cond_dim is None
            else AdaRMSNorm(spec.hidden_size, cond_dim, eps)
        )


class SiglipTower(nn.Module):
    """SigLIP built from its config through transformers (no download), without the pooling head.

    transformers 4.x wraps the encoder in ``SiglipVisionModel.vision_model``, 5.x does not; we keep
    the ``vision_model.`` level in our names either way, so keys match the PaliGemma checkpoints
    and our exports do not depend on the installed transformers.
    """

    def __init__(self, spec: SiglipSpec, image_size: int) -> None:
        from transformers import SiglipVisionConfig, SiglipVisionModel

        super().__init__()
        config = SiglipVisionConfig(
            hidden_size=spec.hidden_size,
            intermediate_size=spec.intermediate_size,
            num_hidden_layers=spec.num_layers,
            num_attention_heads=spec.num_heads,
            image_size=image_size,
            patch_size=spec.patch_size,
            hidden_act="gelu_pytorch_tanh",
            layer_norm_eps=spec.layer_norm_eps,
            vision_use_head=False,  # PaliGemma uses all patch tokens; there is no pooling head
        )
        config._attn_implementation = "sdpa"
        model = SiglipVisionModel(config)
        self.vision_model: nn.Module = getattr(model, "vision_model", model)

    def forward(self, pixels: Tensor) -> Tensor:
        """(N, 3, H, W) in [-1, 1] -> (N, patches, width): the post-layernorm last hidden state."""
        return self.vision_model(pixel_values=pixels).last_hidden_state


class MultiModalProjector(nn.Module):
    """PaliGemma's ``multi_modal_projector``: one Linear from SigLIP width to Gemma width."""

    def __init__(self, vision_dim: int, llm_dim: int) -> None:
        super().__init__()
        self.linear = nn.Linear(vision_dim, llm_dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.linear(x)


@dataclass
class Prefix:
    """The embedded prefix (VLM stream). S = N_cam * patches + text length."""

    embeds: Tensor
    """(B, S, W_vlm) image features (unscaled) then text embeddings · √W_vlm."""
    valid: Tensor
    """(B, S) bool: False at text padding and at the tokens of masked cameras."""
    visual: Tensor
    """(B, S) bool: True at image-token positions (masked cameras included)."""


@dataclass(frozen=True)
class PrefixCache:
    """The prefix's per-layer keys and values (RoPE applied) and the suffix's attention layout.

    Computed once per ``sample_actions`` call and only read by the denoising steps: each step
    concatenates it with the suffix K/V locally, so it never grows (openpi patched transformers'
    cache for this; LeRobot clones a ``DynamicCache`` every step).
    """

    keys: tuple[Tensor, ...]
    """Per layer (B, H_kv, S, D)."""
    values: tuple[Tensor, ...]
    suffix_mask: Tensor
    """(B, T, S + T) bool: the suffix rows of the joint attention mask."""
    suffix_positions: Tensor
    """(B, T) RoPE positions of the action tokens: valid prefix tokens + arange(T)."""


@register_family
class Pi05(VLABackbone):
    config_class = Pi05Config
    original_loader = "capvector.backbones.pi05.convert"
    import_options = (
        ImportOption(
            "tokenizer", "a PaliGemma tokenizer folder (pi05 folders carry none)", type=Path
        ),
    )
    missing_tokenizer_hint = (
        f"set tokenizer to PaliGemma's tokenizer folder (from_original(..., tokenizer=...)) or "
        f"load a capvector export that contains one; {PALIGEMMA_TOKENIZER}"
    )

    # peft full-match regex: the linear layers of both Gemma streams (attention and MLP), as openpi's
    # LoRA variants (``gemma_2b_lora`` + ``gemma_300m_lora``). SigLIP and the adaRMS condition
    # layers stay frozen there too. Left out: what only the LM output reads (see
    # ``language_head_parameter_names``), whose LoRA would get no gradient and stop DDP.
    @property
    def lora_target_modules(self) -> str:  # type: ignore[override]
        linear = r"(self_attn\.(q|k|v|o)_proj|mlp\.(gate|up|down)_proj)"
        last = self.num_layers - 1
        return (
            rf"action_expert\.layers\.\d+\.{linear}"
            rf"|language_model\.layers\.(?!{last}\.)\d+\.{linear}"
            rf"|language_model\.layers\.{last}\.self_attn\.(q|k|v)_proj"
        )

    lora_trainable_modules = (
        "action_in_proj.*",
        "action_out_proj.*",
        "time_mlp_in.*",
        "time_mlp_out.*",
    )
    # A capability vector covers PaliGemma (SigLIP, projector, Gemma-2B with its tied embedding)
    # and the Gemma-300M expert with its adaRMS layers: the pretrained transformer the paper merges
    # vectors into. Left out are the four small projections outside the transformer (2.2 M of
    # 3.35 B): action_in/out_proj read and write one embodiment's (padded) action layout and
    # time_mlp_in/out feed the flow time in; they are the task heads plain SFT re-fits per task,
    # which is also why they stay trainable under LoRA.
    capability_parameters = (
        "vision_tower.*",
        "multi_modal_projector.*",
        "language_model.*",
        "action_expert.*",
    )

    def __init__(self, config: Pi05Config) -> None:
        super().__init__(config)
        self.config: Pi05Config = config
        self._validate(config)
        self._tokenizer = _load_tokenizer(config.tokenizer) if config.tokenizer else None
        if self._tokenizer is not None and len(self._tokenizer) > config.vocab_size:
            raise BackboneError(
                f"the tokenizer has {len(self._tokenizer)} ids but vocab_size is {config.vocab_size}; "
                "set vocab_size to at least the tokenizer's size"
            )
        eps = config.rms_norm_eps
        expert_width = config.expert.hidden_size
        self.vision_tower = SiglipTower(config.vision, config.image_size)
        self.multi_modal_projector = MultiModalProjector(
            config.vision.hidden_size, config.vlm.hidden_size
        )
        self.language_model = GemmaStream(
            config.vlm, eps, vocab_size=config.vocab_size, cond_dim=None
        )
        self.action_expert = GemmaStream(config.expert, eps, vocab_size=None, cond_dim=expert_width)
        # Pi0.5 projections (openpi pi0.py with pi05=True): no state_proj, the time enters through
        # adaRMS only; these keep LeRobot's names.
        self.action_in_proj = nn.Linear(config.max_action_dim, expert_width)
        self.action_out_proj = nn.Linear(expert_width, config.max_action_dim)
        self.time_mlp_in = nn.Linear(expert_width, expert_width)
        self.time_mlp_out = nn.Linear(expert_width, expert_width)

    @staticmethod
    def _validate(config: Pi05Config) -> None:
        vlm, expert = config.vlm, config.expert
        shared = ("num_layers", "num_heads", "num_kv_heads", "head_dim")
        differ = [
            f"{n} ({getattr(vlm, n)} vs {getattr(expert, n)})"
            for n in shared
            if getattr(vlm, n) != getattr(expert, n)
        ]
        if differ:
            raise BackboneError(
                "the VLM and the action expert share one attention per layer, so they need equal "
                f"{', '.join(shared)}; they differ in {', '.join(differ)}"
            )
        if config.image_size % config.vision.patch_size:
            raise BackboneError(
                f"image_size {config.image_size} is not a multiple of the patch size {config.vision.patch_size}"
            )
        if config.action_dim > config.max_action_dim:
            raise BackboneError(
                f"action_dim {config.action_dim} exceeds max_action_dim {config.max_action_dim}; raise max_action_dim"
            )
        if config.num_inference_steps < 1:
            raise BackboneError(
                f"num_inference_steps must be >= 1, got {config.num_inference_steps}"
            )

    # -- contract ----------------------------------------------------------------------------

    @property
    def num_layers(self) -> int:
        return self.config.vlm.num_layers

    @property
    def hidden_size(self) -> int:
        return self.config.vlm.hidden_size

    def make_tokenizer(self, folder: str) -> Any:
        return _load_tokenizer(folder)

    def language_head_parameter_names(self) -> list[str]:
        """The action expert reads only the VLM's keys and values, so the last VLM layer's
        attention output and MLP and the final norm feed the LM logits (and hidden state
        ``num_layers``) alone: frozen until a text objective trains them, as OFT's ``lm_head``
        (the embedding is tied but also embeds the prompt, so it trains with the actions)."""
        last = f"language_model.layers.{self.num_layers - 1}."
        lm_only = tuple(
            f"{last}{part}." for part in ("self_attn.o_proj", "post_attention_layernorm", "mlp")
        )
        return [
            n
            for n, _ in self.named_parameters()
            if n.startswith((*lm_only, "language_model.norm."))
        ]

    def shard_units(self) -> list[nn.Module]:
        """SigLIP's encoder layers and the joint decoder layers (each VLM layer runs its joint
        layer with the expert, so checkpointing one recomputes both streams)."""
        return [*self.vision_tower.vision_model.encoder.layers, *self.language_model.layers]

    @property
    def grid(self) -> int:
        """Patches per image side."""
        return self.config.image_size // self.config.vision.patch_size

    @property
    def num_visual_tokens(self) -> int:
        return self.config.num_images * self.grid**2

    def forward(self, batch: Batch, request: OutputRequest | None = None) -> VLAOutput:
        """With target actions: the flow-matching loss at a random time, and as ``actions`` the
        one-step denoised estimate x_t − t·v (= a when v is exact), un-padded. Without targets:
        the sampled chunk (as ``predict_action``). Hidden states and logits are of the VLM stream
        over the prefix (the prefix never attends to the suffix, so they do not depend on it)."""
        request = request or OutputRequest()
        for index in request.hidden_layers:
            if not 0 <= index <= self.num_layers:
                raise BackboneError(f"hidden layer {index} requested; valid: 0..{self.num_layers}")
        prefix = self.embed_prefix(batch)
        hidden: dict[int, Tensor] = {0: prefix.embeds} if 0 in request.hidden_layers else {}
        loss = None
        if "actions" in batch:
            target = self.pad_actions(batch["actions"].to(prefix.embeds.dtype))
            # ε and t per sample from "noise_seed" when the batch has it (see draw_flow_noise).
            noise, time = draw_flow_noise(target, self.sample_time, batch.get("noise_seed"))
            x_t, velocity_target = flow_matching_path(target, noise, time)
            velocity, prefix_out = self.velocity(prefix, x_t, time, hidden, request.hidden_layers)
            loss = self.flow_loss(velocity, velocity_target)
            denoised = x_t - time.to(x_t.dtype)[:, None, None] * velocity
            actions = denoised[..., : self.config.action_dim].contiguous()
        else:
            cache, prefix_out = self.prefix_cache(prefix, hidden, request.hidden_layers)
            actions = self.integrate(cache, self._noise(prefix))[..., : self.config.action_dim]
            actions = actions.contiguous()
        logits = None
        if request.lm_logits:
            logits = self.language_head(prefix_out)
        return VLAOutput(
            actions=actions,
            loss=loss,
            hidden_states=hidden,
            visual_token_mask=prefix.visual,
            attention_mask=prefix.valid,
            visual_grid=(self.grid, self.grid),
            lm_logits=logits,
        )

    @torch.no_grad()
    def predict_action(self, batch: Batch, noise: Tensor | None = None) -> Tensor:
        """(B, T, A) normalised actions; ``noise`` (B, T, max_action_dim) fixes the start x_1."""
        return self.sample_actions(batch, noise)

    def sample_actions(
        self, batch: Batch, noise: Tensor | None = None, num_steps: int | None = None
    ) -> Tensor:
        """Prefix once, then ``num_steps`` (default ``num_inference_steps``) Euler steps -> (B, T, A)."""
        prefix = self.embed_prefix(batch)
        cache, _ = self.prefix_cache(prefix)
        start = self._noise(prefix) if noise is None else noise.to(prefix.embeds)
        return self.integrate(cache, start, num_steps)[..., : self.config.action_dim].contiguous()

    # -- flow matching -----------------------------------------------------------------------

    def sample_time(self, batch_size: int, device: torch.device) -> Tensor:
        """(B,) training times t = Beta(α, β)·scale + offset in [offset, scale + offset]."""
        c = self.config
        beta = torch.distributions.Beta(
            torch.tensor(c.time_sampling_beta_alpha), torch.tensor(c.time_sampling_beta_beta)
        )
        return (beta.sample((batch_size,)) * c.time_sampling_scale + c.time_sampling_offset).to(
            device
        )

    def flow_loss(self, velocity: Tensor, target: Tensor) -> Tensor:
        """Unweighted MSE between predicted and target velocities (B, T, max_action_dim).

        Default (openpi ``pi0.py compute_loss``): averaged over all padded dims. The padded dims'
        target is ε itself, so the expert learns to keep them on the path x_t = t·ε that it was
        trained on; with LeRobot's averaging over real dims only, those outputs are untrained and
        the Euler steps feed off-path values back through ``action_in_proj``. It also matches the
        objective ``pi05_base`` was trained with. The price is a loss scaled by about
        action_dim / max_action_dim relative to LeRobot's, which matters for weighting auxiliary
        terms (AdamW alone is insensitive to it). Frames past an episode end are not masked by
        either upstream; our datasets never yield such frames.
        """
        if not self.config.loss_include_padded_dims:
            velocity = velocity[..., : self.config.action_dim]
            target = target[..., : self.config.action_dim]
        return F.mse_loss(velocity.to(torch.float32), target.to(torch.float32))

    def pad_actions(self, actions: Tensor) -> Tensor:
        """(B, T, A) -> (B, T, max_action_dim) zero-padded."""
        if actions.shape[1:] != (self.config.chunk_size, self.config.action_dim):
            raise BackboneError(
                f"actions have shape {tuple(actions.shape[1:])} per sample but the backbone was built "
                f"for chunk_size={self.config.chunk_size}, action_dim={self.config.action_dim}"
            )
        return F.pad(actions, (0, self.config.max_action_dim - actions.shape[-1]))

    def _noise(self, prefix: Prefix) -> Tensor:
        b = prefix.embeds.shape[0]
        shape = (b, self.config.chunk_size, self.config.max_action_dim)
        return torch.randn(shape, device=prefix.embeds.device, dtype=prefix.embeds.dtype)

    def integrate(self, cache: PrefixCache, noise: Tensor, num_steps: int | None = None) -> Tensor:
        """Forward Euler from t = 1 (x = noise) to t = 0 with dt = −1/N: (B, T, max_action_dim).

        openpi loops ``while t >= -dt / 2``, which is exactly N steps at t = 1 − k/N; we loop over
        k so no rounding of t can add or drop a step. The step's t is 1 + k·dt (LeRobot
        ``modeling_pi05.py`` ``sample_actions``) or, with ``accumulate_time``, the float32 running
        sum openpi keeps (``pi0_pytorch.py`` ``time += dt``).
        """
        steps = num_steps or self.config.num_inference_steps
        dt = -1.0 / steps
        running = torch.tensor(1.0, dtype=torch.float32, device=noise.device)
        x = noise
        for k in range(steps):
            if self.config.accumulate_time:
                time = running.expand(x.shape[0])
                running = running + torch.tensor(dt, dtype=torch.float32, device=noise.device)
            else:
                time = torch.full((x.shape[0],), 1.0 + k * dt, device=x.device, dtype=torch.float32)
            x = x + dt * self.denoise_step(cache, x, time)
        return x

    def denoise_step(self, cache: PrefixCache, x_t: Tensor, time: Tensor) -> Tensor:
        """The expert alone over the T action tokens, reading the cached prefix K/V: v_t (B, T, D)."""
        tokens, cond = self.embed_suffix(x_t, time)
        _, suffix, _ = self._joint_layers(
            None, tokens, cond, cache.suffix_mask, cache.suffix_positions, cache=cache
        )
        return self._velocity_head(suffix, cond)

    def velocity(
        self,
        prefix: Prefix,
        x_t: Tensor,
        time: Tensor,
        hidden: dict[int, Tensor] | None = None,
        hidden_layers: Sequence[int] = (),
    ) -> tuple[Tensor, Tensor]:
        """Training path: prefix and suffix through the joint layers in one pass.

        Returns the velocity (B, T, max_action_dim) and the VLM's final-normed prefix (B, S, W).
        """
        tokens, cond = self.embed_suffix(x_t, time)
        mask, positions = self.attention_layout(prefix.valid, tokens.shape[1])
        prefix_out, suffix, _ = self._joint_layers(
            prefix.embeds, tokens, cond, mask, positions, hidden=hidden, hidden_layers=hidden_layers
        )
        return self._velocity_head(suffix, cond), self.language_model.norm(prefix_out)

    def prefix_cache(
        self,
        prefix: Prefix,
        hidden: dict[int, Tensor] | None = None,
        hidden_layers: Sequence[int] = (),
    ) -> tuple[PrefixCache, Tensor]:
        """The VLM stack alone over the prefix: its per-layer K/V and final-normed output (B, S, W)."""
        horizon = self.config.chunk_size
        mask, positions = self.attention_layout(prefix.valid, horizon)
        s = prefix.valid.shape[1]
        prefix_out, _, kv = self._joint_layers(
            prefix.embeds, None, None, mask[:, :s, :s], positions[:, :s],
            hidden=hidden, hidden_layers=hidden_layers,
        )  # fmt: skip
        cache = PrefixCache(
            keys=tuple(k for k, _ in kv),
            values=tuple(v for _, v in kv),
            suffix_mask=mask[:, s:, :],
            suffix_positions=positions[:, s:],
        )
        return cache, self.language_model.norm(prefix_out)

    def attention_layout(self, prefix_valid: Tensor, horizon: int) -> tuple[Tensor, Tensor]:
        """Joint mask (B, S + T, S + T) and RoPE positions (B, S + T) for a prefix and T actions.

        Prefix flags are all 0 (one bidirectional block); the Pi0.5 suffix is [1, 0, ..., 0], one
        block of action tokens (no state token, unlike Pi0).
        """
        b, s = prefix_valid.shape
        device = prefix_valid.device
        valid = torch.cat(
            [prefix_valid, torch.ones(b, horizon, dtype=torch.bool, device=device)], dim=1
        )
        ar = torch.zeros(b, s + horizon, dtype=torch.long, device=device)
        ar[:, s] = 1
        return make_attention_mask(valid, ar), positions_from_valid(valid)

    # -- embeddings ----------------------------------------------------------------------------

    def embed_prefix(self, batch: Batch) -> Prefix:
        """Image tokens then the prompt (with the discretised state): the VLM stream's input."""
        visual, visual_valid = self.embed_images(batch)
        ids, text_valid = self.tokenize(batch["instruction"], batch.get("proprio"), visual.device)
        embeds = torch.cat([visual, self.embed_text(ids).to(visual.dtype)], dim=1)
        valid = torch.cat([visual_valid, text_valid], dim=1)
        is_visual = torch.zeros_like(valid)
        is_visual[:, : visual.shape[1]] = True
        return Prefix(embeds=embeds, valid=valid, visual=is_visual)

    def embed_images(self, batch: Batch) -> tuple[Tensor, Tensor]:
        """Images -> SigLIP -> projector, not scaled: (B, N_cam * patches, W_vlm) and validity."""
        images: Tensor = batch["images"]
        b, n_cam = images.shape[:2]
        check_cameras(images, self.config.num_images)
        proj = self.multi_modal_projector.linear
        flat = resize_with_pad(images.flatten(0, 1), self.config.image_size)
        features = self.vision_tower((flat * 2 - 1).to(proj.weight.dtype))  # [0, 1] -> [-1, 1]
        # openpi patches transformers so PaliGemma's division by √width is gone: images enter
        # unscaled. We never call PaliGemma's get_image_features, so no version can add it back.
        visual = self.multi_modal_projector(features).reshape(b, -1, proj.out_features)
        camera_valid = cast(Pi05Batch, batch).get("image_mask")
        if camera_valid is None:
            camera_valid = torch.ones(b, n_cam, dtype=torch.bool, device=images.device)
        return visual, camera_valid.to(torch.bool).repeat_interleave(self.grid**2, dim=1)

    def embed_text(self, ids: Tensor) -> Tensor:
        """(B, L) ids -> (B, L, W_vlm) embeddings · √W_vlm (Gemma's scaling, applied by us)."""
        embed = self.language_model.embed_tokens
        return embed(ids) * math.sqrt(embed.embedding_dim)

    def embed_suffix(self, x_t: Tensor, time: Tensor) -> tuple[Tensor, Tensor]:
        """Action tokens action_in_proj(x_t) (B, T, W_exp) and the adaRMS condition (B, W_exp):
        swish(time_mlp_out(swish(time_mlp_in(sincos(t))))), openpi pi0.py ``embed_suffix``."""
        dtype = self.action_in_proj.weight.dtype
        width = self.config.expert.hidden_size
        features = sinusoidal_time_embedding(
            time, width, self.config.min_period, self.config.max_period
        )
        cond = F.silu(self.time_mlp_out(F.silu(self.time_mlp_in(features.to(dtype)))))
        return self.action_in_proj(x_t.to(dtype)), cond

    def _velocity_head(self, suffix: Tensor, cond: Tensor) -> Tensor:
        # The expert's final norm is adaptive too; its gate has nothing to gate.
        out, _ = self.action_expert.norm(suffix, cond)
        horizon = self.config.chunk_size
        return self.action_out_proj(out[:, -horizon:].to(self.action_out_proj.weight.dtype))

    def tokenize(
        self, instructions: Sequence[str], proprio: Tensor | None, device: torch.device
    ) -> tuple[Tensor, Tensor]:
        """Right-padded prompt ids (B, L) and their valid mask, L = longest prompt in the batch.

        The state is discretised from the un-padded proprio vector (padding it to 32 first would
        add tokens; LeRobot fixed exactly that). openpi pads every prompt to ``max_token_len``; we
        pad to the batch's longest, which changes no output (padding is never attended).
        """
        tok = self.require_tokenizer()
        bins = None
        if self.config.proprio_dim:
            if proprio is None:
                raise BackboneError(
                    f"the batch has no `proprio` but the backbone writes a "
                    f"{self.config.proprio_dim}-d state into the prompt; set proprio_dim=0 to drop it"
                )
            if proprio.shape[-1] != self.config.proprio_dim:
                raise BackboneError(
                    f"proprio has {proprio.shape[-1]} dims but proprio_dim={self.config.proprio_dim}"
                )
            if self.config.prompt_state_dim:
                proprio = F.pad(
                    proprio, (0, max(0, self.config.prompt_state_dim - proprio.shape[-1]))
                )
            bins = discretize_state(proprio, self.config.state_bins).tolist()
        limit = self.config.tokenizer_max_length
        rows = []
        for i, instruction in enumerate(instructions):
            pieces = build_prompt(instruction, None if bins is None else bins[i])
            ids = [tok.bos_token_id]
            for piece in pieces:
                ids += tok(piece, add_special_tokens=False)["input_ids"]
            if len(ids) > limit:
                warnings.warn(
                    f"prompt of {len(ids)} tokens truncated to tokenizer_max_length={limit}",
                    stacklevel=2,
                )
                ids = ids[:limit]
            rows.append(ids)
        pad_id = tok.pad_token_id if tok.pad_token_id is not None else 0
        return right_pad(rows, pad_id, device)

    # -- text objectives -------------------------------------------------------------------------

    @property
    def alignment_layer(self) -> int:
        """Spatial Forcing aligns pi0's layer 12 of 18: two thirds of the depth."""
        return max(1, round(2 * self.num_layers / 3))

    def language_head(self, hidden: Tensor, vocabulary: Tensor | None = None) -> Tensor:
        # tied to the token embedding, as PaliGemma's
        weight = self.language_model.embed_tokens.weight
        return project_onto_vocabulary(hidden, weight, vocabulary=vocabulary)

    def answer_label_ids(self, answer: str) -> list[int]:
        return answer_ids_then_eos(self.require_tokenizer(), answer)

    def text_pass(
        self, batch: Batch, prompts: list[str], answers: list[str]
    ) -> tuple[Tensor, Tensor]:
        """PaliGemma's own prefix-LM pass through the VLM stream only (the expert is not run).

        ``[images] [BOS prompt]`` form one bidirectional block and every answer token (then EOS)
        starts its own block, i.e. causal: the layout of PaliGemma and of openpi's FAST postfix
        (``tokenizer.py`` ``FASTTokenizer``). Hidden states after the final norm (``language_head``
        projects them on the tied embedding); labels are the answer ids at their own positions and
        IGNORE_INDEX elsewhere.
        """
        tok = self.require_tokenizer()
        visual, visual_valid = self.embed_images(batch)
        rows, ar_rows, label_rows = [], [], []
        for prompt, answer in zip(prompts, answers, strict=True):
            prompt_ids = [tok.bos_token_id, *tok(prompt, add_special_tokens=False)["input_ids"]]
            answer_ids = self.answer_label_ids(answer)
            rows.append(prompt_ids + answer_ids)
            ar_rows.append([0] * len(prompt_ids) + [1] * len(answer_ids))
            label_rows.append([IGNORE_INDEX] * len(prompt_ids) + answer_ids)
        device = visual.device
        pad_id = tok.pad_token_id if tok.pad_token_id is not None else 0
        ids, text_valid = right_pad(rows, pad_id, device)
        text_ar, _ = right_pad(ar_rows, 0, device)
        text_labels, _ = right_pad(label_rows, IGNORE_INDEX, device)
        embeds = torch.cat([visual, self.embed_text(ids).to(visual.dtype)], dim=1)
        valid = torch.cat([visual_valid, text_valid], dim=1)
        ar = torch.cat([torch.zeros_like(visual_valid, dtype=torch.long), text_ar], dim=1)
        out, _, _ = self._joint_layers(
            embeds, None, None, make_attention_mask(valid, ar), positions_from_valid(valid)
        )
        labels = torch.cat(
            [torch.full_like(visual_valid, IGNORE_INDEX, dtype=torch.long), text_labels], dim=1
        )
        return self.language_model.norm(out), labels

    # -- the joint transformer -----------------------------------------------------------------

    def _joint_layers(
        self,
        prefix: Tensor | None,
        suffix: Tensor | None,
        cond: Tensor | None,
        mask: Tensor,
        positions: Tensor,
        cache: PrefixCache | None = None,
        hidden: dict[int, Tensor] | None = None,
        hidden_layers: Sequence[int] = (),
    ) -> tuple[Tensor | None, Tensor | None, list[tuple[Tensor, Tensor]]]:
        """All joint layers over the streams present (see ``JointDecoderLayer``).

        Returns both streams before their final norms and this call's per-layer K/V. VLM layer
        outputs listed in ``hidden_layers`` are stored in ``hidden`` (1-based, before the final
        norm), as ``keep_hidden_states`` does for single-stream families.
        """
        cos, sin = rope_cos_sin(positions, self.config.vlm.head_dim, self.config.rope_theta)
        kv: list[tuple[Tensor, Tensor]] = []
        for i, layer in enumerate(self.language_model.layers):
            cached = None if cache is None else (cache.keys[i], cache.values[i])
            expert = self.action_expert.layers[i]
            prefix, suffix, k, v = layer(prefix, suffix, cond, expert, mask, cos, sin, cached)
            kv.append((k, v))
            if hidden is not None and prefix is not None and (i + 1) in hidden_layers:
                hidden[i + 1] = prefix
        return prefix, suffix, kv


def _load_tokenizer(spec: str) -> Any:
    from capvector.backbones.tokenizers import byte_level_tokenizer, saved_tokenizer

    if spec == "byte":
        return byte_level_tokenizer()
    return saved_tokenizer(spec, PALIGEMMA_TOKENIZER)


__all__ = [
    "IMAGE_MASK",
    "MASK_VALUE",
    "AdaRMSNorm",
    "GemmaStream",
    "GemmaStreamLayer",
    "JointDecoderLayer",
    "MultiModalProjector",
    "Pi05",
    "Pi05Batch",
    "Prefix",
    "PrefixCache",
    "SiglipTower",
    "apply_rope",
    "build_prompt",
    "clean_task",
    "flow_matching_path",
    "joint_attention",
    "make_attention_mask",
    "positions_from_valid",
    "resize_with_pad",
    "rope_cos_sin",
    "sinusoidal_time_embedding",
]
