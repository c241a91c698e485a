"""peft LoRA layers in state dicts: found, and merged ``W + s·ΔW``, in one place.

Every path that turns LoRA into plain weights goes through here: ``VLAModule.export``, reading a
LoRA checkpoint as a vector source (``io.weights``), reading a PEFT adapter as a vector
(``vectors.lowrank``), and importing OpenVLA-OFT's adapters (``backbones.openvla_oft.convert``). The delta
follows peft's ``get_delta_weight`` (``peft/tuners/lora/layer.py``): ``B @ A`` for Linear and 1×1-B
Conv layers, ``(B @ A)ᵀ`` for Embedding and for ``fan_in_fan_out`` (Conv1D) layers, times the
layer's scaling; a ``lora_B`` bias (``lora_bias=True``) adds ``s · bias`` to the base bias, as
peft's ``merge`` does. Imports nothing of the project but ``io.tensors``, so ``vectors`` stays free
of Lightning.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from capvector.io.tensors import LazyTensors, TensorInfo

_KEY = re.compile(
    r"^(?P<module>.+)\.(?:"
    r"(?P<linear>lora_A|lora_B)(?:\.(?P<adapter>[^.]+))?\.(?P<param>weight|bias)"
    r"|(?P<embedding>lora_embedding_A|lora_embedding_B)(?:\.(?P<embedding_adapter>[^.]+))?"
    r")$"
)
"""Both layouts: a live peft model's ``X.lora_A.default.weight`` / ``X.lora_embedding_A.default``,
and an adapter file's ``X.lora_A.weight`` / ``X.lora_embedding_A`` (no adapter name)."""


class LoraFormatError(ValueError):
    """LoRA tensors that cannot be merged; callers re-raise it as their own error type."""


@dataclass(frozen=True)
class LoraLayer:
    """One LoRA layer's factors as peft stores them, and how its delta is formed."""

    lora_a: Tensor
    lora_b: Tensor
    scaling: float
    transposed: bool = False
    """True for embedding LoRA and ``fan_in_fan_out`` layers: peft's delta is ``(B @ A)ᵀ``."""
    bias: Tensor | None = None
    """``lora_B``'s bias (peft ``lora_bias=True``), added to the base bias times ``scaling``."""

    def factors(self) -> tuple[Tensor, Tensor]:
        """(B', A') in the stored dtype with ``B' @ A'`` the unscaled delta in the base weight's
        layout (2-D; a conv weight's trailing dims flattened into A')."""
        a, b = self.lora_a.flatten(1), self.lora_b.flatten(1)
        return (a.T.contiguous(), b.T.contiguous()) if self.transposed else (b, a)

    def delta(self, rows: slice | None = None, shape: torch.Size | None = None) -> Tensor:
        """``scaling · ΔW`` in float32 (rows of it with ``rows``), reshaped to ``shape``."""
        b, a = self.factors()
        out = (b if rows is None else b[rows]).float() @ a.float()
        out.mul_(self.scaling)  # in place: one float32 copy of the layer alive, not two
        return out if shape is None else out.reshape(shape)

    def merged(self, base: Tensor, rows: slice | None = None) -> Tensor:
        """``base + scaling · ΔW`` computed in float32 (float64 for a float64 base); the caller
        decides the dtype it keeps."""
        base = base if rows is None else base[rows]
        dtype = torch.promote_types(base.dtype, torch.float32)
        # ΔW + base in place (the same bits as base + ΔW), without a float32 copy of the base
        return self.delta(rows, base.shape).to(dtype).add_(base)

    def merged_bias(self, base_bias: Tensor | None) -> Tensor | None:
        if self.bias is None:
            return base_bias
        if base_bias is None:
            raise LoraFormatError("a LoRA bias (lora_B.bias) needs a base bias to add to")
        dtype = torch.promote_types(base_bias.dtype, torch.float32)
        return base_bias.to(dtype) + self.scaling * self.bias.to(dtype)


def split_lora(
    state: Mapping[str, Tensor], scaling: Callable[[str, int], float], fan_in_fan_out: bool = False
) -> tuple[dict[str, Tensor], dict[str, LoraLayer]]:
    """``state`` as (plain tensors with peft's ``base_layer.`` removed, {module: LoraLayer}).

    ``scaling(module, rank)`` gives each layer's scaling (one value for a checkpoint; per layer for
    an adapter with ``alpha_pattern``/``rank_pattern``). DoRA and several adapters are refused.
    """
    parts: dict[str, dict[str, Tensor]] = {}
    adapters: set[str] = set()
    plain: dict[str, Tensor] = {}
    for key, tensor in state.items():
        if ".lora_magnitude_vector" in key:
            raise LoraFormatError(f"`{key}` is a DoRA magnitude; DoRA is not a weight delta")
        match = _KEY.match(key)
        if match is None:
            if ".lora_" in key:
                raise LoraFormatError(f"`{key}` is a LoRA tensor of a kind that is not supported")
            plain[key.replace(".base_layer.", ".")] = tensor
            continue
        adapter = match["adapter"] or match["embedding_adapter"]
        if adapter:
            adapters.add(adapter)
        part = f"{match['linear']}.{match['param']}" if match["linear"] else match["embedding"]
        parts.setdefault(match["module"], {})[part] = tensor
    if len(adapters) > 1:
        raise LoraFormatError(f"several LoRA adapters {sorted(adapters)}; merge them first")
    layers = {}
    for module, p in parts.items():
        embedding = "lora_embedding_A" in p
        a = p.get("lora_embedding_A" if embedding else "lora_A.weight")
        b = p.get("lora_embedding_B" if embedding else "lora_B.weight")
        if a is None or b is None:
            raise LoraFormatError(f"LoRA layer `{module}` lacks its A or B factor")
        layers[module] = LoraLayer(
            a,
            b,
            scaling(module, int(a.shape[0])),
            transposed=embedding or fan_in_fan_out,
            bias=p.get("lora_B.bias"),
        )
    return plain, layers


def merge_lora(
    state: Mapping[str, Tensor],
    scaling: Callable[[str, int], float],
    fan_in_fan_out: bool = False,
    dtype: torch.dtype | None = None,
) -> dict[str, Tensor]:
    """A state dict with every LoRA layer merged into its weight (and bias) and peft's key
    changes undone, the other tensors as they were. A merged layer is computed in float32 and
    kept in float32 (a bf16 base would round much of the update away), or in ``dtype``."""
    return dict(merged_lora_view(state, scaling, fan_in_fan_out, dtype).items())


def merged_lora_view(
    state: Mapping[str, Tensor],
    scaling: Callable[[str, int], float],
    fan_in_fan_out: bool = False,
    dtype: torch.dtype | None = None,
) -> LazyTensors:
    """``merge_lora``'s tensors made when read: an export writes a 7 B model's merged layers one
    at a time instead of holding a second copy of every LoRA target (13 GB in bf16)."""
    plain, layers = split_lora(state, scaling, fan_in_fan_out)
    view = LazyTensors(plain)
    for module, layer in layers.items():
        weight = plain.get(f"{module}.weight")
        if weight is None:
            raise LoraFormatError(f"LoRA layer `{module}` has no base weight `{module}.weight`")
        merged_dtype = dtype or torch.promote_types(weight.dtype, torch.float32)
        view.set(
            f"{module}.weight",
            TensorInfo(merged_dtype, tuple(weight.shape)),
            lambda w=weight, lay=layer, d=merged_dtype: lay.merged(w).to(d),
        )
        bias = plain.get(f"{module}.bias")
        if layer.bias is not None and bias is None:
            raise LoraFormatError("a LoRA bias (lora_B.bias) needs a base bias to add to")
        if bias is not None and (layer.bias is not None or dtype is not None):
            bias_dtype = dtype or torch.promote_types(bias.dtype, torch.float32)
            view.set(
                f"{module}.bias",
                TensorInfo(bias_dtype, tuple(bias.shape)),
                lambda b=bias, lay=layer, d=bias_dtype: lay.merged_bias(b).to(d),
            )
    return view


def adapter_scaling(config: Mapping[str, Any]) -> Callable[[str, int], float]:
    """Each layer's scaling from a PEFT ``adapter_config.json``: ``lora_alpha / r`` (rsLoRA:
    ``/ √r``), with ``alpha_pattern`` overrides matched on the module path as peft matches them;
    ``r`` itself is read from the factor (``rank_pattern`` is already in the shapes)."""
    default_alpha = float(config.get("lora_alpha", config.get("r", 8)))
    alpha_pattern = config.get("alpha_pattern") or {}
    rslora = bool(config.get("use_rslora"))

    def scaling(module: str, rank: int) -> float:
        alpha = next(
            (float(v) for pat, v in alpha_pattern.items() if re.match(rf"(.*\.)?({pat})$", module)),
            default_alpha,
        )
        return alpha / math.sqrt(rank) if rslora else alpha / rank

    return scaling


def constant_scaling(value: float) -> Callable[[str, int], float]:
    """One scaling for every layer (our checkpoints record ``lora.scaling`` = alpha / r)."""
    return lambda module, rank: value


# -- low-rank deltas over a base rebuilt from packages --------------------------------------
#
# A backbone whose frozen base is rebuilt from installed weight packages (``openvla-oft-mini``)
# exports only what differs from those packages. Its base weights may carry a low-rank delta
# W = packaged + B @ A (a LoRA fine-tune, a merged capability vector): the export stores (B, A) under
# an adapter file's names ``X.lora_A.weight`` (A: k x in) and ``X.lora_B.weight`` (B: out x k) with
# scaling 1, so ranks may differ per layer and grow as deltas are stacked.

Factors = tuple[Tensor, Tensor]
"""(B, A) in float32: ``B @ A`` is the delta of the weight, scaling included."""


def stack_factors(*terms: Factors) -> Factors:
    """``Σ B_i @ A_i`` as one pair (ranks add): ``[B_1 B_2 ...] @ [A_1; A_2; ...]``."""
    return torch.cat([b for b, _ in terms], 1), torch.cat([a for _, a in terms], 0)


def compact_factors(factors: Factors, rtol: float = 1e-6) -> Factors:
    """The same delta at its numerical rank: QR of both factors, an SVD of the small core, singular
    values under ``rtol`` times the largest dropped (what two stacked deltas share cancels: θ_aux
    − θ_sft of two fine-tunes of one θ_pre keeps rank ≤ 2r, not 2(r_pre + r)). Splits the singular
    values evenly, as ``mergekit-extract-lora`` does."""
    b, a = factors
    qb, rb = torch.linalg.qr(b.double())
    qa, ra = torch.linalg.qr(a.double().T)
    u, s, vh = torch.linalg.svd(rb @ ra.T)
    keep = max(1, int((s > rtol * s[0]).sum())) if s.numel() and s[0] > 0 else 1
    root = s[:keep].sqrt()
    return (
        (qb @ (u[:, :keep] * root)).float().contiguous(),
        ((root[:, None] * vh[:keep]) @ qa.T).float().contiguous(),
    )


def lora_form_state(
    state: Mapping[str, Tensor],
    scaling: Callable[[str, int], float],
    base_deltas: Mapping[str, Factors],
) -> dict[str, Tensor]:
    """A live LoRA state dict whose base was left out (it equals packages + ``base_deltas``) as
    an export's tensors: plain tensors, and per weight the base delta stacked with the trained
    LoRA (``s·B``, ``A``) under ``X.lora_A/B.weight``. A base weight the state dict does hold (it
    no longer equals packages + delta: a vector was merged into it in place) is written whole,
    its LoRA merged, as ``merge_lora`` does."""
    plain, layers = split_lora(state, scaling)
    deltas = dict(base_deltas)
    for module, layer in layers.items():
        key = f"{module}.weight"
        if layer.bias is not None or layer.transposed:
            raise LoraFormatError(f"LoRA layer `{module}` is not a plain linear LoRA")
        if key in plain:
            plain[key] = layer.merged(plain[key])
            continue
        b, a = layer.factors()
        trained = (b.float() * layer.scaling, a.float())
        deltas[key] = stack_factors(deltas[key], trained) if key in deltas else trained
    for key, (b, a) in deltas.items():
        if key not in plain:
            module = key.removesuffix(".weight")
            plain[f"{module}.lora_A.weight"] = a.contiguous()
            plain[f"{module}.lora_B.weight"] = b.contiguous()
    return plain


def split_base_delta(state: Mapping[str, Tensor]) -> tuple[dict[str, Tensor], dict[str, Factors]]:
    """An export's tensors as (plain tensors, {``X.weight``: (B, A)}): the inverse of
    ``lora_form_state``."""
    plain, layers = split_lora(state, constant_scaling(1.0))
    deltas = {}
    for module, layer in layers.items():
        b, a = layer.factors()
        deltas[f"{module}.weight"] = (b.float(), a.float())
    return plain, deltas
