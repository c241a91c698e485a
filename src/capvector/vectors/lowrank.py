"""Low-rank capability vectors: truncated SVD of each 2-D delta, stored as a PEFT LoRA adapter.

Follows ``mergekit-extract-lora`` (research A2.5): the SVD runs in float32, the singular values are
split evenly between the factors (B = U·√σ, A = √σ·Vᵀ), and every layer gets ``lora_alpha == r`` so
peft's scaling is 1 and ``B @ A`` is the delta itself. Ranks may differ per layer (``rank_pattern``
/ ``alpha_pattern``). Unlike mergekit, the rank can also be chosen per layer by an energy fraction
(the smallest k with Σ_{i≤k} σ_i² ≥ E·Σσ², the rule of peft's ``convert_to_lora``).

A 2-D ``*.weight`` is written under peft's names for its layer type: ``lora_A/B.weight`` for an
``nn.Linear`` weight (out, in), ``lora_embedding_A/B`` for an ``nn.Embedding`` weight (peft's delta
there is (B·A)ᵀ; ``peft/tuners/lora/layer.py: Embedding.get_delta_weight``). Which weights are
embeddings comes from the export's ``embedding_parameters`` (the backbone records them), so
``PeftModel.from_pretrained`` loads the adapter exactly.
"""

from __future__ import annotations

import re
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from capvector.io.lora_layers import LoraFormatError, adapter_scaling, split_lora
from capvector.io.tensors import squared_norm
from capvector.io.weights import (
    ADAPTER_CONFIG,
    ADAPTER_WEIGHTS,
    CapVectorError,
    examples,
    read_json,
)

PEFT_PREFIX = "base_model.model."


@dataclass
class LoraFactors:
    """A low-rank delta ``c = scale · B @ A`` with B: (out, k) and A: (k, in)."""

    lora_b: Tensor
    lora_a: Tensor
    scale: float = 1.0

    @property
    def rank(self) -> int:
        return int(self.lora_a.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.lora_b.shape[0]), int(self.lora_a.shape[1])

    @property
    def dtype(self) -> torch.dtype:
        return self.lora_b.dtype

    def rows(self, rows: slice | None = None) -> Tensor:
        """Rows of the dense delta in float32 (all rows when None)."""
        b = self.lora_b if rows is None else self.lora_b[rows]
        return self.scale * (b.float() @ self.lora_a.float())

    def scaled(self) -> tuple[Tensor, Tensor]:
        """(B·scale, A) in float32: ``B @ A`` is the delta."""
        return self.lora_b.float() * self.scale, self.lora_a.float()

    def norm_sq(self) -> float:
        """‖scale·BA‖_F² from the two r×r Gram matrices, without forming BA."""
        b, a = self.scaled()
        return float(((b.T @ b) * (a @ a.T)).sum())

    def is_finite(self) -> bool:
        return bool(torch.isfinite(self.lora_a).all() and torch.isfinite(self.lora_b).all())


SvdMethod = Literal["exact", "randomized"]
RANDOMIZED_OVERSAMPLING = 10
"""Extra columns of the randomized range finder (Halko, Martinsson & Tropp 2011, §4.2's p)."""
RANDOMIZED_POWER_ITERATIONS = 2


def svd_factors(
    delta: Tensor,
    rank: int | None = None,
    energy: float | None = None,
    method: SvdMethod = "exact",
) -> tuple[LoraFactors, float]:
    """Truncated SVD ``delta ≈ B @ A`` by a fixed ``rank`` or a retained ``energy`` fraction.

    ``exact`` is mergekit's full SVD. ``randomized`` (fixed ``rank`` only: the energy rule needs
    every singular value) finds the top ``rank`` by a randomized range finder with
    ``RANDOMIZED_OVERSAMPLING`` extra columns and ``RANDOMIZED_POWER_ITERATIONS`` power iterations
    (``torch.svd_lowrank``, seeded, so an extraction repeats bit for bit). It is our deviation for
    full-size models: an exact SVD of one 4,096 × 11,008 weight takes about 90 s on a CPU core,
    hours for a 7 B language model, where the range finder takes under a second; θ_aux − θ_sft
    of two LoRA fits has rank ≤ 2r plus rounding noise, the case it is accurate for.

    Returns the factors (float32) and the retained fraction of ‖delta‖_F² (1.0 for a zero delta,
    which is stored at rank 1 with zero factors because peft has no rank-0 layers).
    """
    if (rank is None) == (energy is None):
        raise ValueError("pass exactly one of rank and energy")
    if method == "randomized" and rank is None:
        raise ValueError("the randomized SVD takes a fixed rank, not an energy fraction")
    if method == "randomized":
        total = squared_norm(delta)  # not every σ is computed
        if total == 0.0:
            return _zero_factors(*delta.shape)
        q = min(rank + RANDOMIZED_OVERSAMPLING, *delta.shape)  # type: ignore[operator]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            u, s, v = torch.svd_lowrank(delta.float(), q=q, niter=RANDOMIZED_POWER_ITERATIONS)
        vh = v.T
    else:
        u, s, vh = torch.linalg.svd(delta.float(), full_matrices=False)
        total = float((s.double() ** 2).sum())
    if total == 0.0:
        return _zero_factors(*delta.shape)
    cumulative = (s.double() ** 2).cumsum(0) / total
    if rank is not None:
        k = min(rank, s.numel())
    else:
        k = min(int((cumulative < energy).sum()) + 1, s.numel())
    retained = min(float(cumulative[k - 1]), 1.0)
    root = s[:k].sqrt()
    return LoraFactors(u[:, :k] * root, root[:, None] * vh[:k]), retained


def _zero_factors(rows: int, cols: int) -> tuple[LoraFactors, float]:
    return LoraFactors(torch.zeros(rows, 1), torch.zeros(1, cols)), 1.0


def module_path(key: str) -> str:
    return key.removesuffix(".weight")


def lowrank_candidate(key: str, ndim: int) -> bool:
    """Tensors peft can represent as a LoRA layer: the 2-D ``weight`` of a module."""
    return ndim == 2 and key.endswith(".weight")


def _pattern(path: str) -> str:
    # peft matches pattern keys with re.match(rf"(.*\.)?({key})$", module_name); escaping the dots
    # and anchoring with ^ makes each pattern match exactly one module, not every module whose
    # name ends the same way.
    return "^" + re.escape(path)


def write_adapter(
    folder: Path, factors: Mapping[str, LoraFactors], embeddings: Collection[str] = ()
) -> dict[str, Any]:
    """Write ``adapter_config.json`` + ``adapter_model.safetensors`` that ``PeftModel.from_pretrained``
    loads as-is onto a model whose module names are the vector keys without ``.weight``.
    ``embeddings`` names the keys that are ``nn.Embedding`` weights."""
    from safetensors.torch import save_file

    from capvector.io.weights import write_json

    if not factors:
        raise ValueError("no low-rank tensors to write")
    ranks = {module_path(key): f.rank for key, f in factors.items()}
    r = max(ranks.values())
    smaller = {_pattern(path): k for path, k in ranks.items() if k != r}
    config = {
        "peft_type": "LORA",
        "task_type": None,
        "base_model_name_or_path": None,
        "r": r,
        "lora_alpha": r,
        "rank_pattern": smaller,
        "alpha_pattern": dict(smaller),
        "target_modules": sorted(ranks),
        "lora_dropout": 0.0,
        "bias": "none",
        "fan_in_fan_out": False,
        "use_rslora": False,
        "use_dora": False,
        "init_lora_weights": True,
        "inference_mode": True,
        "modules_to_save": None,
    }
    tensors: dict[str, Tensor] = {}
    for key, f in factors.items():
        b, a = f.scaled()
        prefix = PEFT_PREFIX + module_path(key)
        if key in embeddings:  # peft: lora_embedding_A (r, num_embeddings), _B (dim, r)
            tensors[f"{prefix}.lora_embedding_A"] = b.T.to(f.dtype).contiguous()
            tensors[f"{prefix}.lora_embedding_B"] = a.T.to(f.dtype).contiguous()
        else:
            tensors[f"{prefix}.lora_A.weight"] = a.to(f.dtype).contiguous()
            tensors[f"{prefix}.lora_B.weight"] = b.to(f.dtype).contiguous()
    save_file(tensors, str(folder / ADAPTER_WEIGHTS), metadata={"format": "pt"})
    write_json(folder / ADAPTER_CONFIG, config)
    return config


def read_adapter(folder: Path) -> tuple[dict[str, LoraFactors], dict[str, Tensor]]:
    """A PEFT LoRA adapter folder as deltas: {``X.weight``: factors} and {``X.bias``: dense delta}.

    Handles per-layer ranks and alphas, rsLoRA scaling, ``fan_in_fan_out`` and embedding LoRA
    (both transposed). Adapters that replace weights rather than add to them (DoRA,
    ``modules_to_save``) cannot be a vector and are refused.
    """
    from safetensors.torch import load_file

    config = read_json(folder / ADAPTER_CONFIG)
    if config.get("peft_type") != "LORA":
        raise CapVectorError(
            f"{folder}: peft_type {config.get('peft_type')!r}; only LORA adapters are vectors"
        )
    if config.get("use_dora"):
        raise CapVectorError(
            f"{folder}: DoRA adapters rescale weights and cannot be used as a vector"
        )
    if config.get("modules_to_save"):
        raise CapVectorError(
            f"{folder}: the adapter replaces whole modules ({config['modules_to_save']}), which is "
            "not a delta; merge it with peft and extract a vector from the result"
        )
    weights = folder / ADAPTER_WEIGHTS
    if not weights.is_file():
        raise CapVectorError(f"{folder} has {ADAPTER_CONFIG} but no {ADAPTER_WEIGHTS}")
    try:
        state = load_file(str(weights))
    except Exception as err:
        raise CapVectorError(f"{weights} is not a readable safetensors file ({err})") from err

    unknown = [k for k in state if not k.startswith(PEFT_PREFIX) or ".lora_" not in k]
    if unknown:
        raise CapVectorError(
            f"{weights} has {len(unknown)} tensor(s) that are not LoRA factors, e.g. "
            f"{examples(sorted(unknown))}"
        )
    try:
        _, layers = split_lora(
            {k.removeprefix(PEFT_PREFIX): v for k, v in state.items()},
            adapter_scaling(config),
            fan_in_fan_out=bool(config.get("fan_in_fan_out")),
        )
    except LoraFormatError as err:
        raise CapVectorError(f"{weights}: {err}") from err
    factors: dict[str, LoraFactors] = {}
    biases: dict[str, Tensor] = {}
    for module, layer in layers.items():
        b, a = layer.factors()  # peft's orientation undone: B @ A is the delta in W's layout
        factors[f"{module}.weight"] = LoraFactors(b, a, layer.scaling)
        if layer.bias is not None:
            biases[f"{module}.bias"] = layer.bias.float() * layer.scaling
    return factors, biases
