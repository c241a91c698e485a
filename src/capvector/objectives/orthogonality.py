"""Orthogonal regularisation: keep the downstream update Δ = θ − θ_meta from undoing c.

Per vector tensor c_l the penalty is on ⟨Δ_l, c_l⟩ (research B4), normalised per tensor:

- ``squared_projection``: ⟨Δ, c⟩² / ‖c‖², the energy of Δ along ĉ;
- ``squared_cosine``: ⟨Δ, c⟩² / (‖Δ‖²‖c‖² + eps), scale-free (needs ‖Δ‖, so LoRA terms only).

Three ways to get Δ:

- ``full`` (full fine-tuning): ⟨Δ, c⟩ = ⟨θ, c⟩ − ⟨θ_meta, c⟩. The scalars ⟨θ_meta, c⟩ ("anchors") are
  computed once by ``bind`` and saved in checkpoints; no copy of θ_meta is kept.
- ``lora``: Δ = s·B A of a peft LoRA layer, never formed: ⟨sBA, c⟩ = s·Σ((Bᵀc) ∘ A), or with a
  low-rank c = B_c A_c, s·Σ((BᵀB_c) ∘ (A A_cᵀ)) in O(r·k·(d_in + d_out)); ‖sBA‖² = s²·Σ((BᵀB) ∘ (AAᵀ)).
  Trainable parameters the vector covers that are not LoRA layers (e.g. a fully trained projector)
  get ``full`` terms.
- ``olora``: O-LoRA's loss (Wang et al. 2023, cmnfriend/O-LoRA ``uie_trainer_lora.py``) between the
  vector's A_c and the new LoRA A: Σ|A_c A_newᵀ|. A_c·A_newᵀ = 0 is sufficient for ⟨BA, B_cA_c⟩ = 0
  and also stops the update from reading the inputs c reads (research B1). It needs a low-rank
  vector (``capvector extract --rank``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor, nn

from capvector.objectives.base import Objective
from capvector.vectors import CapabilityVector, CapVectorError, load_vector, match_tensors

Mode = Literal["full", "lora", "olora"]
Normalization = Literal["squared_projection", "squared_cosine"]
MODES = ("full", "lora", "olora")
NORMALIZATIONS = ("squared_projection", "squared_cosine")

_CHUNK = 1 << 22
"""Elements per chunk of the float64-accumulated inner products (bounds their temporary memory)."""
_BATCHED_MAX = 1 << 16
"""``full`` terms up to this size share one autograd node (their float64 c copies stay small)."""


def _inner64(theta: Tensor, c: Tensor | None, c_b: Tensor | None, c_a: Tensor | None) -> Tensor:
    """⟨θ, c⟩ accumulated in float64, chunk by chunk; c dense or c = c_b @ c_a."""
    total = torch.zeros((), dtype=torch.float64, device=theta.device)
    if c is not None:
        flat_theta, flat_c = theta.reshape(-1), c.reshape(-1)
        for start in range(0, flat_theta.numel(), _CHUNK):
            part = (
                flat_theta[start : start + _CHUNK].float() * flat_c[start : start + _CHUNK].float()
            )
            total += part.sum(dtype=torch.float64)
        return total
    assert c_b is not None and c_a is not None
    # ⟨θ, B_c A_c⟩ = Σ((B_cᵀθ) ∘ A_c); rows of θ are taken a chunk at a time.
    rows = max(1, _CHUNK // max(1, theta.shape[1]))
    projected = torch.zeros(c_b.shape[1], theta.shape[1], dtype=torch.float32, device=theta.device)
    for start in range(0, theta.shape[0], rows):
        projected += c_b[start : start + rows].T @ theta[start : start + rows].float()
    return (projected * c_a).sum(dtype=torch.float64)


def _local(param: Tensor | None) -> Tensor:
    """This rank's shard of an FSDP2 parameter; plain tensors pass."""
    from torch.distributed.tensor import DTensor

    assert param is not None
    return param.to_local() if isinstance(param, DTensor) else param


def _full(tensor: Tensor) -> Tensor:
    """A (small) LoRA factor gathered from its FSDP2 shards, differentiably; plain tensors pass."""
    from torch.distributed.tensor import DTensor

    return tensor.full_tensor() if isinstance(tensor, DTensor) else tensor


class _FrozenInnerProduct(torch.autograd.Function):
    """⟨θ, c⟩ for a constant c. Autograd of ``(θ.float() * c).sum()`` would keep a float32 copy of
    every bf16 parameter alive until backward; this keeps only (a reference to) c."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, theta: Tensor, c: Tensor | None, c_b: Tensor | None, c_a: Tensor | None
    ) -> Tensor:
        ctx.save_for_backward(c, c_b, c_a)
        ctx.theta_dtype = theta.dtype
        return _inner64(theta.detach(), c, c_b, c_a)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None, None]:  # type: ignore[override]
        c, c_b, c_a = ctx.saved_tensors
        dense = c.float() if c is not None else c_b @ c_a
        return (grad.float() * dense).to(ctx.theta_dtype), None, None, None


@dataclass
class _BatchedVector:
    """The small ``full`` terms' c, laid out once at bind for ``_BatchedFrozenInnerProducts``."""

    rows: Tensor
    """(terms, N) float64 CSR: row i holds c_i at θ_i's place in the concatenation of every θ."""
    cs: list[Tensor]
    """c_i in θ_i's shape and dtype (this rank's shard under FSDP2), for backward."""
    flat: Tensor
    """(N,) the concatenated θ, and ``flat64`` the same in float64: kept from step to step, since
    allocating megabytes afresh every step costs more here (page faults) than the arithmetic."""
    flat64: Tensor

    @classmethod
    def of(cls, cs: list[Tensor], thetas: list[Tensor]) -> _BatchedVector:
        values = torch.cat([c.reshape(-1).double() for c in cs])
        # int32 indices halve what the mat-vec reads (measured 0.35 vs 0.45 ms on the tiny OFT).
        index = torch.int32 if values.numel() < 2**31 else torch.int64
        lengths = torch.tensor([0] + [c.numel() for c in cs], device=values.device)
        with warnings.catch_warnings():  # "sparse CSR support is in beta": matvec is all we use
            warnings.simplefilter("ignore", UserWarning)
            rows = torch.sparse_csr_tensor(
                lengths.cumsum(0).to(index),
                torch.arange(values.numel(), device=values.device, dtype=index),
                values,
                size=(len(cs), values.numel()),
            )
        return cls(
            rows,
            [c.reshape(t.shape).to(t.dtype) for c, t in zip(cs, thetas, strict=True)],
            torch.cat([t.detach().reshape(-1) for t in thetas]),
            torch.empty_like(values),
        )


class _BatchedFrozenInnerProducts(torch.autograd.Function):
    """[⟨θ_i, c_i⟩] (float64) for many small tensors behind one autograd node.

    A tiny model has ~150 covered tensors of a few thousand elements: per-tensor ops and autograd
    nodes cost more than the arithmetic (benchmarks/bench_steps.py). Forward is one concatenation
    and one sparse mat-vec in float64 (products of float32 values are exact there, so ⟨θ, c⟩ −
    anchor keeps its precision); backward is one foreach multiply ``grad_i · c_i``.
    """

    @staticmethod
    def forward(ctx: Any, vector: _BatchedVector, *thetas: Tensor) -> Tensor:  # type: ignore[override]
        ctx.vector = vector  # constants: nothing to save for autograd
        torch.cat([t.reshape(-1) for t in thetas], out=vector.flat)
        return vector.rows @ vector.flat64.copy_(vector.flat)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        # One tensor per term, not views of one flat buffer: small tensors reuse the allocator's
        # pages, while a fresh multi-megabyte buffer page-faults on every step (measured slower).
        # 0-dim tensors, not Python floats: each float would be wrapped in a tensor (1.5x slower).
        return None, *torch._foreach_mul(ctx.vector.cs, list(grad.float().unbind()))


@dataclass
class _Term:
    index: int
    key: str
    kind: str
    """"full" (θ − anchor), "lora" (s·BA) or "olora" (Σ|A_c A_newᵀ|)."""
    param: Tensor | None = None
    layer: nn.Module | None = None
    local_c: Tensor | None = None
    """``full`` terms of an FSDP2 parameter: c's slice matching this rank's shard, cut once."""


def _is_lora_layer(module: nn.Module | None, adapter: str) -> bool:
    # Duck-typed peft ``LoraLayer`` (importing peft costs seconds; this module must stay light).
    lora_a = getattr(module, "lora_A", None)
    return isinstance(lora_a, nn.ModuleDict) and adapter in lora_a and hasattr(module, "scaling")


class OrthogonalityLoss(Objective):
    """Σ over vector tensors of the normalised squared projection of the update on c.

    ``forward`` returns the unweighted penalty (the caller multiplies by ``weight``) and fills
    ``last_stats`` with detached scalars for logging: ``mean_abs_projection`` (mean |⟨Δ, c⟩|/‖c‖²,
    the fraction of c added or undone), ``mean_abs_cos`` (LoRA terms) and ``num_terms``.

    Call ``bind(backbone)`` once the backbone holds θ_meta (after the vector was merged): it pairs
    vector tensors with parameters and records the anchors of ``full`` terms. Anchors are buffers
    saved in checkpoints; ``bind`` keeps anchors that were loaded (``anchored`` flags), so resuming
    never re-anchors at a trained θ.

    Args:
        vector: a vector folder (full, low-rank or PEFT), a ``CapabilityVector`` or {name: c}.
        mode: ``"full"``, ``"lora"`` or ``"olora"`` (see the module docstring).
        normalization: ``"squared_projection"`` or ``"squared_cosine"`` (not in ``full`` mode:
            ‖Δ‖ would need a copy of θ_meta).
        weight: the loss weight, for the caller.
        eps: added to the cosine's denominator.
        adapter_name: the peft adapter holding the downstream LoRA.
    """

    def __init__(
        self,
        vector: str | Path | Mapping[str, Tensor] | CapabilityVector,
        mode: Mode = "full",
        normalization: Normalization = "squared_projection",
        weight: float = 1.0,
        eps: float = 1e-12,
        adapter_name: str = "default",
        name: str = "orthogonality",
    ) -> None:
        super().__init__(name=name, weight=weight)
        if mode not in MODES:
            raise CapVectorError(f"mode must be one of {MODES}, got {mode!r}")
        if normalization not in NORMALIZATIONS:
            raise CapVectorError(
                f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}"
            )
        if mode == "full" and normalization == "squared_cosine":
            raise CapVectorError(
                "squared_cosine needs ‖Δ‖ = ‖θ − θ_meta‖, which full mode cannot compute without a "
                "copy of θ_meta; use squared_projection, or mode='lora'"
            )
        self.mode = mode
        self.normalization = normalization
        self.eps = eps
        self.adapter_name = adapter_name

        vec = load_vector(vector)
        vec.check()
        self.keys: list[str] = vec.keys()
        norms = []
        for i, key in enumerate(self.keys):
            if key in vec.lowrank:
                b, a = vec.lowrank[key].scaled()
                self.register_buffer(f"c_b_{i}", b.contiguous(), persistent=False)
                self.register_buffer(f"c_a_{i}", a.contiguous(), persistent=False)
            else:
                dense = vec.dense[key].detach()
                # full terms read c in chunks and keep its stored dtype (memory); LoRA terms use it
                # in matmuls with float32 factors, so they get it in float32 once.
                dense = dense if mode == "full" else dense.float()
                self.register_buffer(f"c_{i}", dense.contiguous(), persistent=False)
            norms.append(vec.norm_sq(key))
        self.register_buffer(
            "c_norm_sq", torch.tensor(norms, dtype=torch.float64), persistent=False
        )
        self._zero = {i for i, n in enumerate(norms) if n == 0.0}
        self.register_buffer("anchors", torch.zeros(len(self.keys), dtype=torch.float64))
        self.register_buffer("anchored", torch.zeros(len(self.keys), dtype=torch.bool))
        self._terms: list[_Term] = []
        self._full_terms: list[_Term] = []
        self._full_positions: list[int] = []
        self.frozen: list[str] = []
        """Vector keys left out by ``bind``: their parameters are frozen, so Δ = 0 there."""
        self.last_stats: dict[str, Tensor] = {}

    # -- pairing ----------------------------------------------------------------------------

    def _vector(self, i: int) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        return (
            self._buffers.get(f"c_{i}"),
            self._buffers.get(f"c_b_{i}"),
            self._buffers.get(f"c_a_{i}"),
        )

    def bind(self, backbone: nn.Module) -> OrthogonalityLoss:
        """Pair every vector tensor with the backbone's parameter or LoRA layer; set missing anchors.

        ``X.weight`` pairs with the parameter ``X.weight`` or, under peft, ``X.base_layer.weight``,
        whose LoRA layer ``X`` gives Δ in ``lora``/``olora`` mode. Raises ``CapVectorError`` when a
        vector tensor has no parameter of the same shape.
        """
        get_base = getattr(backbone, "get_base_model", None)
        model = get_base() if callable(get_base) else backbone  # a PeftModel wraps the backbone
        resolved = match_tensors(model, self.keys)
        modules = dict(model.named_modules())
        terms, frozen = [], []
        for i, key in enumerate(self.keys):
            name, param = resolved[key]
            c, c_b, c_a = self._vector(i)
            shape = tuple(c.shape) if c is not None else (c_b.shape[0], c_a.shape[1])  # type: ignore[union-attr]
            if tuple(param.shape) != shape:
                raise CapVectorError(
                    f"vector tensor `{key}` has shape {shape} but the model's `{name}` has "
                    f"{tuple(param.shape)}; the vector belongs to another architecture or preset"
                )
            # peft puts the frozen weight of LoRA layer X at X.base_layer.weight.
            owner = name.removesuffix(".base_layer.weight")
            layer = modules.get(owner) if owner != name else None
            if _is_lora_layer(layer, self.adapter_name):
                if self.mode == "full":
                    raise CapVectorError(
                        f"`{owner}` is a LoRA layer: its update is s·B·A, not a change of "
                        f"`{name}`; use mode='lora' (or 'olora') for LoRA fine-tuning"
                    )
                if getattr(layer, "fan_in_fan_out", False) or getattr(layer, "use_dora", {}).get(
                    self.adapter_name
                ):
                    raise CapVectorError(
                        f"`{owner}`: fan_in_fan_out and DoRA LoRA layers are not supported"
                    )
                if self.mode == "olora" and c_b is None:
                    raise CapVectorError(
                        f"mode='olora' needs the vector in low-rank form, but `{key}` is dense; "
                        "extract it with --rank or --energy"
                    )
                terms.append(_Term(i, key, self.mode, layer=layer))
            elif self.mode == "full" or param.requires_grad:
                terms.append(_Term(i, key, "full", param=param))
            else:
                frozen.append(key)
        fallback = [t.key for t in terms if t.kind == "full"]
        if self.normalization == "squared_cosine" and fallback:
            warnings.warn(
                f"{len(fallback)} trainable non-LoRA tensor(s) (e.g. `{fallback[0]}`) use "
                "squared_projection: their cosine would need a copy of θ_meta",
                stacklevel=2,
            )
        self._terms = terms
        self.frozen = frozen
        self._prepare_full_terms()
        with torch.no_grad():
            full = [t.index for t in self._full_terms]
            if full:
                missing = ~self.anchored[full]
                inners = self._full_inners().to(self.anchors.device)
                index = torch.tensor(full, device=self.anchors.device)
                self.anchors[index] = torch.where(missing, inners, self.anchors[index])
                self.anchored[index] = True
        return self

    def _prepare_full_terms(self) -> None:
        """Cut c to each FSDP2 shard once and group the small dense ``full`` terms for batching."""
        from torch.distributed.tensor import DTensor, distribute_tensor

        self._full_terms = [t for t in self._terms if t.kind == "full"]
        for t in self._full_terms:
            c, c_b, c_a = self._vector(t.index)
            if isinstance(t.param, DTensor):
                dense = c if c is not None else c_b @ c_a  # type: ignore[operator]
                t.local_c = distribute_tensor(
                    dense.to(t.param.to_local().device), t.param.device_mesh, t.param.placements,
                    src_data_rank=None,
                ).to_local()  # fmt: skip
            else:
                t.local_c = c
        small = [
            i for i, t in enumerate(self._full_terms)
            if t.local_c is not None and t.local_c.numel() <= _BATCHED_MAX
        ]  # fmt: skip
        self._batched = [self._full_terms[i] for i in small]
        self._batched_vector = (
            _BatchedVector.of(
                [t.local_c for t in self._batched],  # type: ignore[misc]
                [_local(t.param) for t in self._batched],
            )
            if self._batched
            else None
        )
        self._single = [t for i, t in enumerate(self._full_terms) if i not in set(small)]
        # _full_inners computes [batched..., single...]; this puts them back in _full_terms order.
        order = small + [i for i in range(len(self._full_terms)) if i not in set(small)]
        device = self.c_norm_sq.device
        identity = order == list(range(len(order)))
        self._unpermute = None if identity else torch.argsort(torch.tensor(order)).to(device)
        self._full_positions = [
            i for i, t in enumerate(self._full_terms) if t.index not in self._zero
        ]
        self._full_indices = torch.tensor(
            [self._full_terms[i].index for i in self._full_positions], dtype=torch.long
        ).to(device)
        self._full_c_sq = self.c_norm_sq[self._full_indices].float()
        self._sharded = torch.tensor(
            [isinstance(t.param, DTensor) for t in self._full_terms], dtype=torch.bool
        ).to(device)
        self._any_sharded = bool(self._sharded.any())

    def _full_inners(self) -> Tensor:
        """⟨θ, c⟩ of every ``full`` term (float64, in ``_full_terms`` order), summed over shards.

        Each rank takes its shard's inner products with the matching slices of c; one all-reduce
        sums the sharded terms. Gradients reach the local shards only, as c restricted to them:
        exactly the one-process gradient, with no extra communication in the backward pass.
        """
        device = self.c_norm_sq.device
        parts = []
        if self._batched:
            thetas = [_local(t.param) for t in self._batched]
            parts.append(_BatchedFrozenInnerProducts.apply(self._batched_vector, *thetas))
        if self._single:
            singles = []
            for t in self._single:
                _, c_b, c_a = self._vector(t.index)
                c_b, c_a = (None, None) if t.local_c is not None else (c_b, c_a)
                singles.append(_FrozenInnerProduct.apply(_local(t.param), t.local_c, c_b, c_a))
            parts.append(torch.stack(singles).to(device))
        inners = torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64, device=device)
        if self._unpermute is not None:
            inners = inners[self._unpermute]
        if self._any_sharded:
            summed = torch.where(self._sharded, inners.detach(), 0.0)
            torch.distributed.all_reduce(summed, group=self._mesh_group())
            inners = inners + (summed - torch.where(self._sharded, inners.detach(), 0.0))
        return inners

    def _mesh_group(self) -> Any:
        from torch.distributed.tensor import DTensor

        meshes = {t.param.device_mesh for t in self._full_terms if isinstance(t.param, DTensor)}
        if len(meshes) != 1:
            raise CapVectorError(
                "orthogonal regularization needs every sharded parameter on one mesh"
            )
        return meshes.pop().get_group()

    def reset_anchors(self) -> None:
        """Forget the anchors, so the next ``bind`` takes the current θ as θ_meta."""
        self.anchored.zero_()
        self.anchors.zero_()

    @property
    def bound(self) -> bool:
        return bool(self._terms)

    # -- loss -------------------------------------------------------------------------------

    def forward(
        self, batch: Any = None, output: Any = None, backbone: nn.Module | None = None
    ) -> Tensor:
        """The unweighted penalty, summed over tensors; binds to ``backbone`` on first use."""
        if not self._terms:
            if backbone is None:
                raise RuntimeError(
                    f"{type(self).__name__}: call bind(backbone) before the first forward"
                )
            self.bind(backbone)
        device = self.c_norm_sq.device
        total = torch.zeros((), dtype=torch.float32, device=device)
        projections: list[Tensor] = []
        cosines: list[Tensor] = []
        if self._full_positions:
            index, c_sq = self._full_indices, self._full_c_sq
            inner = self._full_inners()
            if len(self._full_positions) < len(self._full_terms):  # some c_l are zero
                inner = inner[self._full_positions]
            inner = (inner - self.anchors[index]).float()
            total = total + (inner.square() / c_sq).sum()
            projections.append(inner.detach().abs() / c_sq)
        lora_projections = []
        for t in self._terms:
            if t.index in self._zero or t.kind == "full":
                continue
            c, c_b, c_a = self._vector(t.index)
            c_sq = self.c_norm_sq[t.index].float()
            a, b, s = self._lora_factors(t)
            if t.kind == "olora":
                term = (c_a @ a.T).abs().sum()  # type: ignore[operator]
                with torch.no_grad():  # for the stats only
                    inner = s * _lora_inner(b, a, c, c_b, c_a)
            else:
                inner = s * _lora_inner(b, a, c, c_b, c_a)
                delta_sq = s * s * ((b.T @ b) * (a @ a.T)).sum()
                if self.normalization == "squared_cosine":
                    term = inner.square() / (c_sq * delta_sq + self.eps)
                else:
                    term = inner.square() / c_sq
                with torch.no_grad():
                    cosines.append(inner.abs() / (c_sq * delta_sq + self.eps).sqrt())
            total = total + term.to(total.device)
            lora_projections.append((inner.detach().abs() / c_sq).to(device))
        if lora_projections:
            projections.append(torch.stack(lora_projections))
        every = torch.cat(projections) if projections else torch.zeros(0, device=device)
        stats = {"num_terms": torch.tensor(float(every.numel()), device=device)}
        if projections:
            stats["mean_abs_projection"] = every.mean()
        if cosines:
            stats["mean_abs_cos"] = torch.stack([x.to(device) for x in cosines]).mean()
        self.last_stats = stats
        return total

    def _lora_factors(self, t: _Term) -> tuple[Tensor, Tensor, float]:
        layer = t.layer
        assert layer is not None
        a = _full(layer.lora_A[self.adapter_name].weight).float()  # type: ignore[index]
        b = _full(layer.lora_B[self.adapter_name].weight).float()  # type: ignore[index]
        return a, b, float(layer.scaling[self.adapter_name])  # type: ignore[index]

    # -- dtype safety -----------------------------------------------------------------------

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> OrthogonalityLoss:
        # Device moves apply, dtype casts do not: bf16-true precision calls module.to(bf16), which
        # would round c and the anchors so that ⟨θ_meta, c⟩ − anchor is no longer 0 at the start.
        for key, buf in self._buffers.items():
            if buf is None:
                continue
            moved = fn(buf)
            self._buffers[key] = moved if moved.dtype == buf.dtype else buf.to(moved.device)
        if recurse:
            for child in self.children():
                child._apply(fn)
        return self

    def extra_repr(self) -> str:
        return (
            f"mode={self.mode!r}, normalization={self.normalization!r}, weight={self.weight}, "
            f"tensors={len(self.keys)}, bound={self.bound}"
        )


def _lora_inner(
    b: Tensor, a: Tensor, c: Tensor | None, c_b: Tensor | None, c_a: Tensor | None
) -> Tensor:
    """⟨B A, c⟩ without forming B A: Σ((Bᵀc) ∘ A), or Σ((BᵀB_c) ∘ (A A_cᵀ)) for c = B_c A_c."""
    if c is not None:
        return ((b.T @ c) * a).sum()
    return ((b.T @ c_b) * (a @ c_a.T)).sum()  # type: ignore[operator]
