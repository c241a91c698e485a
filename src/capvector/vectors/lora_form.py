"""Exports of a backbone whose frozen base is rebuilt from weight packages (``openvla-oft-mini``):
extracted and merged without ever forming the base.

Such an export holds the tensors that train (projector, heads) and, per base weight it changed,
a low-rank delta over the packages, W = packaged + B @ A (``X.lora_A/B.weight``; config.json's
``base_delta``; ``capvector.io.lora_layers``). The base itself is the same in every export of the
preset, so in θ_aux − θ_sft it cancels: the vector is the difference of the deltas, exactly
low-rank (``[B_aux, −B_sft] @ [A_aux; A_sft]``, compacted), and the dense difference of the trained
tensors. A merge stacks λ·c's factors onto the base export's deltas. Nothing here reads the
packages.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import Tensor

from capvector.io.lora_layers import Factors, compact_factors, split_base_delta, stack_factors
from capvector.io.names import BASE_DELTA
from capvector.io.weights import (
    CapVectorError,
    SafetensorsFolder,
    TensorInfo,
    WeightSource,
    examples,
)
from capvector.vectors.lowrank import LoraFactors
from capvector.vectors.vector import VectorFolder

PACKAGED_BASE = "packages"
"""``backbone_config.base_weights`` of a preset whose base is rebuilt from weight packages."""


def is_lora_form(source: WeightSource) -> bool:
    """An export whose base is left out (rebuilt from the weight packages)."""
    config = source.config.get("backbone_config") or {}
    return source.kind == "export" and config.get("base_weights") == PACKAGED_BASE


class LoraFormExport(WeightSource):
    """A LoRA-form export seen as its trained tensors plus one ``X.weight`` per base delta, whose
    value (``read``) is the delta B @ A and whose ``factors`` are (B, A). ``extra_deltas`` names
    base weights this export leaves at the packaged value (delta 0) that another input changed."""

    def __init__(self, source: SafetensorsFolder, extra_deltas: Mapping[str, TensorInfo] = {}):
        self.source = source
        self.path, self.kind, self.config, self.hub_id = (
            source.path,
            source.kind,
            source.config,
            source.hub_id,
        )
        lora = [k for k in source if ".lora_" in k]
        self.plain = [k for k in source if ".lora_" not in k]
        _, self.deltas = split_base_delta({k: source.read(k) for k in lora})
        self._infos = {k: TensorInfo(torch.float32, (b.shape[0], a.shape[1])) for k, (b, a) in
                       self.deltas.items()}  # fmt: skip
        for key, info in extra_deltas.items():
            self._infos.setdefault(key, info)

    def keys(self) -> list[str]:
        return self.plain + sorted(self._infos)

    def is_delta(self, key: str) -> bool:
        return key in self._infos

    def info(self, key: str) -> TensorInfo:
        return self._infos[key] if key in self._infos else self.source.info(key)

    def factors(self, key: str) -> Factors:
        """(B, A) of a base delta; rank 0 where this export keeps the packaged value."""
        if key in self.deltas:
            return self.deltas[key]
        out, inp = self._infos[key].shape
        return torch.zeros(out, 0), torch.zeros(0, inp)

    def read(self, key: str, rows: slice | None = None) -> Tensor:
        if key not in self._infos:
            return self.source.read(key, rows)
        b, a = self.factors(key)
        return (b if rows is None else b[rows]) @ a


def lora_form_views(sources: Mapping[str, WeightSource]) -> dict[str, WeightSource]:
    """``sources`` unchanged when none is a LoRA-form export; each as a ``LoraFormExport`` over
    the union of their base deltas when all are; an error for a mix."""
    kinds = {name: is_lora_form(s) for name, s in sources.items()}
    if not any(kinds.values()):
        return dict(sources)
    if not all(kinds.values()):
        mixed = ", ".join(f"{n} ({'LoRA form' if k else 'whole'})" for n, k in kinds.items())
        raise CapVectorError(
            f"the inputs mix an export whose base is rebuilt from weight packages with other "
            f"weights: {mixed}; give exports of the same preset"
        )
    views = {n: LoraFormExport(s) for n, s in sources.items()}  # type: ignore[arg-type]
    union = {k: v.info(k) for v in views.values() for k in v.deltas}
    return {n: LoraFormExport(s, union) for n, s in sources.items()}  # type: ignore[arg-type]


def delta_difference(minuend: LoraFormExport, subtrahend: LoraFormExport, key: str) -> LoraFactors:
    """The exact difference of two base deltas as compacted factors (what they share cancels)."""
    b, a = stack_factors(minuend.factors(key), _negated(subtrahend.factors(key)))
    if b.shape[1] == 0:
        return LoraFactors(torch.zeros(b.shape[0], 1), torch.zeros(1, a.shape[1]))
    return LoraFactors(*compact_factors((b, a)))


def _negated(factors: Factors) -> Factors:
    b, a = factors
    return -b, a


def merged_tensors(
    base: LoraFormExport, vectors: Sequence[tuple[VectorFolder, float]]
) -> tuple[dict[str, Tensor], list[tuple[str, Tensor, Tensor, Tensor]]]:
    """The tensors of base + Σ λ·c as a LoRA-form export (base deltas stacked with λ·c's factors,
    compacted; trained tensors summed in float32 and stored in the base's dtype), and per trained
    tensor (key, base, merged, Σλc) for the precision record."""
    plain = {k: base.source.read(k) for k in base.plain}
    deltas: dict[str, list[Factors]] = {k: [base.factors(k)] for k in base.deltas}
    summed: list[tuple[str, Tensor, Tensor, Tensor]] = []
    for key in list(plain):
        touching = [(f.read(key).float(), s) for f, s in vectors if key in f]
        if touching:
            change = sum(s * d for d, s in touching)
            assert isinstance(change, Tensor)
            merged = (plain[key].float() + change).to(plain[key].dtype)
            summed.append((key, plain[key], merged, change))
            plain[key] = merged
    dense = [k for f, _ in vectors for k in f if k not in plain and f.storage(k) != "lora"]
    if dense:
        raise CapVectorError(
            f"the vector holds {len(dense)} whole tensor(s) of weights the base rebuilds from "
            f"weight packages, e.g. {examples(dense)}: extract it from two exports of the same "
            "preset (its base deltas are then low-rank)"
        )
    for folder, scale in vectors:
        for key in folder:
            factors = folder.factors(key)
            if key in plain or factors is None:
                continue
            b, a = factors.scaled()
            deltas.setdefault(key, []).append((b * scale, a))
    out = dict(plain)
    for key, terms in deltas.items():
        b, a = compact_factors(stack_factors(*terms)) if len(terms) > 1 else terms[0]
        module = key.removesuffix(".weight")
        out[f"{module}.lora_A.weight"], out[f"{module}.lora_B.weight"] = a, b
    return out, summed


def delta_config(config: Mapping[str, object]) -> dict[str, object]:
    """config.json of a merged LoRA-form export."""
    return {**config, BASE_DELTA: {"form": "lora", "scaling": 1.0}}


def delta_infos(folders: Iterable[VectorFolder]) -> dict[str, TensorInfo]:
    """Shapes of the low-rank tensors of ``folders``: base weights a merge gives a delta."""
    return {k: f.info(k) for f in folders for k in f if f.storage(k) == "lora"}
