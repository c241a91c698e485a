"""Per-device training memory, from a meta-device build (nothing allocated).

Parameters, gradients and AdamW state follow from what trains and the dtype each parameter is
stored in, as ``VLAModule`` sets them up: LoRA (``inject_lora``) or full fine-tuning, unused and
language-head parameters frozen, frozen parameters stored in ``frozen_dtype`` (``bfloat16`` halves
them, as OpenVLA-OFT keeps its 7.5 B base in bf16) while what trains stays float32 with float32
gradients and AdamW state. Strategies shard them as they do.

Activations are measured, not guessed: one forward pass with the weights on the ``meta`` device
records every tensor autograd saves for the backward pass (``saved_tensors_hooks``), once plainly
and once with the backbone's blocks checkpointed. The trace does what a GPU would do
(``GpuKernels``): under ``bf16-mixed`` it casts as CUDA autocast does (matmul and convolution
inputs to bf16, so autograd saves the bf16 copies, including bf16 copies of float32 frozen
weights; norms, softmax and losses in float32), and with ``attention="efficient"`` SDPA runs as the
memory-efficient kernel, which saves the output and a (B, heads, S) logsumexp instead of the
math path's (B, heads, S, S) attention probabilities. Attention computed outside SDPA (Pi0.5's
``joint_attention``) keeps its matrices on a GPU too, and is counted as such.

Auxiliary objectives (``TrainingSettings.objectives``) are traced as ``VLAModule`` runs them, in
the same step: reasoning co-training's causal text pass with its full-vocabulary logits, their
float32 copy, log-softmax and gradient; spatial alignment's hidden states, teacher features and
projector. Their term is what that step holds beyond the same step without them, plus the
projector's weights and AdamW state.

The batch stays on the CPU with real values (``HostValuesMetaCompute``): forward passes read values
to build prompts (Pi0.5's and StarVLA's discretised state), find token positions and multimodal
RoPE indices (Qwen-VL), which a meta tensor does not have. Only the work that touches weights runs
on the meta device.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import weakref
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.overrides import TorchFunctionMode
from torch.utils import _pytree as pytree
from torch.utils._python_dispatch import TorchDispatchMode, _disable_current_modes

from capvector.backbones.base import VLABackbone, build_backbone, list_presets, preset_config
from capvector.data.batch import Batch
from capvector.errors import CapVectorError
from capvector.objectives.base import OBJECTIVES, Objective, compute_losses
from capvector.profiling.meta import on_meta
from capvector.profiling.settings import TrainingSettings
from capvector.training.lora import (
    FROZEN_DTYPES,
    LoraSettings,
    cast_frozen_parameters,
    set_trainable,
)
from capvector.vectors.merge import match_tensors
from capvector.vectors.vector import CapabilityVector, VectorFolder

STRATEGIES = ("ddp", "fsdp2", "deepspeed_zero2", "deepspeed_zero3")
PRECISIONS = ("32-true", "bf16-mixed", "bf16-true")
ATTENTION_PATHS = ("math", "efficient")
GIB = 1024**3


@dataclass
class MemoryEstimate:
    """All in bytes per device."""

    parameters: float
    gradients: float
    optimizer: float
    activations: float
    activations_checkpointed: float
    working: float = 0.0
    """The traced step's peak beyond activations and gradients: the backward's activation
    gradients and temporaries, the loss, AdamW's temporaries. Never negative: when the peak comes
    after part of the activations is freed (it can, in the backward: issue 58 saw -0.388 GiB for
    openvla-oft-7b at batch 8), it is 0 and the total counts every activation and gradient at
    once, an upper bound by that overlap."""
    working_checkpointed: float = 0.0
    """The same with checkpointing: includes the blocks recomputed in the backward pass."""
    checkpointing: bool = False
    """Whether ``total`` assumes activation checkpointing (``VLAModule(activation_checkpointing)``)."""
    trainable_parameters: float = 0.0
    """Of ``parameters``, the bytes of those that train (float32 unless ``bf16-true``)."""
    objectives: float = 0.0
    """What the auxiliary objectives add to the step: the traced peak with them beyond the peak
    without (their activations, logits, teacher features and gradients), plus their parameters
    (the alignment projector) with AdamW's two moments. 0 without objectives, never negative."""
    objectives_checkpointed: float = 0.0
    """The same with the backbone's blocks checkpointed (the text pass is checkpointed too)."""
    vector: float = 0.0
    """What a capability vector merged at fit start adds: the frozen weights it changes kept in
    float32 beyond their frozen dtype (``keep_in_float32``; the trace runs with them so, so that
    autocast's bf16 copies of them are in the activations) and the orthogonality loss's float32
    copy of c (``vector_copy_bytes``). 0 without one."""

    @property
    def total(self) -> float:
        return self.total_checkpointed if self.checkpointing else self.total_plain

    @property
    def _states(self) -> float:
        return self.parameters + self.vector + self.gradients + self.optimizer

    @property
    def total_plain(self) -> float:
        return self._states + self.activations + self.working + self.objectives

    @property
    def total_checkpointed(self) -> float:
        return (
            self._states
            + self.activations_checkpointed
            + self.working_checkpointed
            + self.objectives_checkpointed
        )

    def table(self) -> str:
        rows: list[tuple[str, float]] = [
            ("parameters", self.parameters),
            ("  of which train", self.trainable_parameters),
            ("capability vector", self.vector),
            ("gradients", self.gradients),
            ("optimizer (AdamW)", self.optimizer),
            ("activations", self.activations),
            ("working memory", self.working),
            ("auxiliary objectives", self.objectives),
            ("total, no checkpointing", self.total_plain),
            ("activations, checkpointed", self.activations_checkpointed),
            ("working memory, checkpointed", self.working_checkpointed),
            ("auxiliary objectives, ckpt", self.objectives_checkpointed),
            ("total, checkpointed", self.total_checkpointed),
        ]
        lines = [f"  {name:<29} {value / GIB:10.3f} GiB" for name, value in rows]
        which = "checkpointed" if self.checkpointing else "no checkpointing"
        lines.append(f"  {'total':<29} {self.total / GIB:10.3f} GiB  ({which})")
        if self.activations != self.activations:  # NaN
            lines.append("  (activations could not be traced on the meta device for this backbone)")
        return "\n".join(lines)


class SavedBytes:
    """Running sum of the bytes autograd has saved so far (see ``saved_activation_bytes``)."""

    def __init__(self, module: torch.nn.Module | None = None) -> None:
        self.total = 0
        # Weights are counted as parameters: autograd often saves a view of one (``W.t()`` in a
        # linear layer), which shares the parameter's storage.
        tensors = [] if module is None else [*module.parameters(), *module.buffers()]
        self._seen: set[int] = {t.untyped_storage()._cdata for t in tensors}

    def pack(self, t: Tensor) -> Tensor:
        storage = t.untyped_storage()
        if storage._cdata not in self._seen and not isinstance(t, torch.nn.Parameter):
            self._seen.add(storage._cdata)
            self.total += storage.nbytes()
        return t


@contextmanager
def saved_activation_bytes(
    store: list[float], module: torch.nn.Module | None = None
) -> Iterator[SavedBytes]:
    """Sum the bytes of storages autograd saves for backward, each storage once (views of one
    tensor share it); parameters, and views of ``module``'s parameters and buffers, excluded
    (they are counted as parameters)."""
    counter = SavedBytes(module)
    with torch.autograd.graph.saved_tensors_hooks(counter.pack, lambda t: t):
        yield counter
    store.append(float(counter.total))


class HostValuesMetaCompute(TorchDispatchMode):
    """CPU tensors keep their values until an op meets a meta tensor; that op runs on meta.

    So the batch, token ids and masks computed from it stay real (prompts, positions and masks
    are built as in training), while everything that involves the meta weights costs nothing.
    A CPU tensor sent to the meta device stays on the CPU (``.to(device)`` of an input); a
    boolean CPU mask that indexes a meta tensor becomes the integer positions it selects.

    A CPU tensor that meets meta weights gets a meta twin of its whole storage, alive as long as
    the CPU storage is: a view (an expanded mask) stays a view, and a mask or RoPE table used by
    every layer is one tensor, as on a GPU, so what autograd saves of it is counted once.
    """

    def __init__(self) -> None:
        super().__init__()
        self._twins: dict[tuple[int, torch.dtype], tuple[Tensor, weakref.ref[Any]]] = {}

    def _meta(self, t: Tensor) -> Tensor:
        if t.is_meta:
            return t
        storage = t.untyped_storage()
        key = (storage._cdata, t.dtype)
        if key not in self._twins:
            # Made outside every mode: the CPU tensor is what a GPU would hold, the twin is not.
            with _disable_current_modes():
                twin = torch.empty(
                    storage.nbytes() // t.element_size(), dtype=t.dtype, device="meta"
                )
            forget = functools.partial(lambda key, _: self._twins.pop(key, None), key)
            self._twins[key] = (twin, weakref.ref(storage, forget))
        with _disable_current_modes():
            return self._twins[key][0].as_strided(t.shape, t.stride(), t.storage_offset())

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        kwargs = kwargs or {}
        if func is torch.ops.aten._to_copy.default and not args[0].is_meta:
            if kwargs.get("device") == torch.device("meta"):
                kwargs = {k: v for k, v in kwargs.items() if k != "device"}
            return func(*args, **kwargs)
        leaves = pytree.tree_leaves((args, kwargs))
        if not any(isinstance(t, Tensor) and t.is_meta for t in leaves):
            return func(*args, **kwargs)
        if func is torch.ops.aten.index.Tensor:  # x[mask]: the mask's values give the shape
            source, indices = args
            args = (source, [position for i in indices for position in _positions(i)])
        args, kwargs = pytree.tree_map_only(Tensor, self._meta, (args, kwargs))
        return func(*args, **kwargs)


def _positions(index: Tensor | None) -> list[Tensor | None]:
    """A boolean CPU mask as the integer index tensors it stands for, one per dimension."""
    if index is None or index.is_meta or index.dtype != torch.bool:
        return [index]
    return list(index.nonzero().unbind(1))


# Autocast's op lists (aten/src/ATen/autocast_mode.cpp), at the level of the torch functions
# model code calls: inputs of these run in bf16 ...
_LOWER_PRECISION = frozenset({
    "linear", "matmul", "__matmul__", "__rmatmul__", "mm", "bmm", "baddbmm", "addmm", "addbmm",
    "addmv", "mv", "einsum", "prelu", "conv1d", "conv2d", "conv3d", "conv_transpose1d",
    "conv_transpose2d", "conv_transpose3d", "scaled_dot_product_attention",
})  # fmt: skip
# ... and of these in float32: losses on both devices; on CUDA also norms, softmax and the like,
# which CPU autocast leaves in their input dtype.
_FLOAT32_LOSSES = frozenset({
    "cross_entropy", "nll_loss", "mse_loss", "l1_loss", "smooth_l1_loss", "huber_loss", "kl_div",
    "binary_cross_entropy_with_logits",
})  # fmt: skip
_FLOAT32 = {
    "cuda": _FLOAT32_LOSSES | {
        "layer_norm", "group_norm", "softmax", "log_softmax", "cosine_similarity", "pow",
        "__pow__", "exp", "log", "rsqrt", "logsumexp", "cumsum", "norm", "softplus",
    },
    "cpu": _FLOAT32_LOSSES,
}  # fmt: skip
AUTOCAST_DEVICES = tuple(_FLOAT32)


class GpuKernels(TorchFunctionMode):
    """Run a traced forward as it would run on a GPU: CUDA autocast's casts (``autocast_dtype``)
    and SDPA as the memory-efficient kernel (``efficient_attention``). ``device="cpu"`` follows
    CPU autocast instead (to check the trace against a CPU run).

    Sits above autograd, as autocast does, so autograd records the casts and saves the cast
    copies. Like autocast, a trainable leaf (LoRA weights, heads) is cast once per forward;
    frozen weights are cast at every use.
    """

    def __init__(
        self, autocast_dtype: torch.dtype | None, efficient_attention: bool, device: str = "cuda"
    ) -> None:
        super().__init__()
        self.autocast_dtype = autocast_dtype
        self.float32_ops = _FLOAT32[device]
        self.efficient_attention = efficient_attention
        self._cast_cache: dict[int, tuple[Tensor, Tensor]] = {}

    def clear_cast_cache(self) -> None:
        self._cast_cache.clear()

    def _cast(self, dtype: torch.dtype, tree: Any) -> Any:
        def cast(t: Tensor) -> Tensor:
            if not t.is_floating_point() or t.dtype == dtype or t.dtype == torch.float64:
                return t
            if t.is_leaf and t.requires_grad:
                if id(t) not in self._cast_cache:
                    self._cast_cache[id(t)] = (t, t.to(dtype))
                return self._cast_cache[id(t)][1]
            return t.to(dtype)

        return pytree.tree_map_only(Tensor, cast, tree)

    def __torch_function__(
        self, func: Any, types: Any, args: Sequence[Any] = (), kwargs: Any = None
    ) -> Any:
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if self.autocast_dtype is not None and torch.is_grad_enabled():
            if name in _LOWER_PRECISION:
                args, kwargs = self._cast(self.autocast_dtype, (args, kwargs))
            elif name in self.float32_ops:
                args, kwargs = self._cast(torch.float32, (args, kwargs))
        if self.efficient_attention and name == "scaled_dot_product_attention":
            return efficient_attention(*args, **kwargs)
        return func(*args, **kwargs)


def efficient_attention(
    query: Tensor,
    key: Tensor,
    value: Tensor,
    attn_mask: Tensor | None = None,
    dropout_p: float = 0.0,
    is_causal: bool = False,
    scale: float | None = None,
    enable_gqa: bool = False,
) -> Tensor:
    """``F.scaled_dot_product_attention`` through the memory-efficient kernel, as on a GPU.

    Autograd then saves what that kernel's backward needs: q, k, v, the bias, the output and a
    float32 (B, heads, S) logsumexp; no (B, heads, S, S) probabilities. A boolean mask becomes an
    additive bias in the query dtype, as SDPA does before calling the kernel.
    """
    if query.dim() != 4:
        return F.scaled_dot_product_attention(
            query, key, value, attn_mask, dropout_p, is_causal, scale=scale, enable_gqa=enable_gqa
        )
    if key.shape[1] != query.shape[1]:  # grouped-query attention: the kernel wants equal heads
        groups = query.shape[1] // key.shape[1]
        key, value = key.repeat_interleave(groups, 1), value.repeat_interleave(groups, 1)
    bias = None
    if attn_mask is not None:
        if attn_mask.dtype == torch.bool:
            bias = torch.zeros(attn_mask.shape, dtype=query.dtype, device=query.device)
            bias = bias.masked_fill(~attn_mask, float("-inf"))
        else:
            bias = attn_mask.to(query.dtype)
        shape = (query.shape[0], query.shape[1], query.shape[2], key.shape[2])
        bias = bias.expand(shape)
    return torch.ops.aten._scaled_dot_product_efficient_attention(
        query, key, value, bias, True, dropout_p, is_causal, scale=scale
    )[0]


def synthetic_batch(
    backbone: VLABackbone, batch_size: int, device: str | torch.device, objectives: bool = False
) -> Batch:
    """A training batch of ``backbone``'s shapes; ``objectives`` adds what the auxiliary objectives
    read (depth and intrinsics for spatial alignment, a text annotation for reasoning)."""
    c = backbone.config
    batch: Batch = {
        "images": torch.rand(
            batch_size, c.num_images, 3, c.image_size, c.image_size, device=device
        ),
        "proprio": torch.zeros(batch_size, c.proprio_dim, device=device),
        "actions": torch.zeros(batch_size, c.chunk_size, c.action_dim, device=device),
        "instruction": ["pick up the red cube and place it on the plate"] * batch_size,
    }
    if objectives:
        size = (batch_size, c.num_images, c.image_size, c.image_size)
        batch["depth"] = torch.ones(size, device=device)
        intrinsics = torch.tensor([[c.image_size, 0, c.image_size / 2], [0, c.image_size, c.image_size / 2], [0, 0, 1.0]])  # fmt: skip
        batch["intrinsics"] = intrinsics.expand(batch_size, c.num_images, 3, 3).to(device)
        batch["annotation"] = ["the gripper moves toward the red cube, left of the plate"] * batch_size  # fmt: skip
    return batch


def lora_settings(rank: int | None) -> LoraSettings | None:
    """The LoRA a ``--lora-rank`` stands for: OpenVLA-OFT's alpha = min(r, 16)."""
    return LoraSettings(r=rank, alpha=min(rank, 16)) if rank else None


def set_storage_dtypes(backbone: VLABackbone, precision: str, frozen_dtype: torch.dtype) -> None:
    """Parameter dtypes as training keeps them: ``bf16-true`` casts everything to bf16; otherwise
    what does not train is stored in ``frozen_dtype`` (``VLAModule(frozen_dtype)``)."""
    if precision == "bf16-true":
        for param in backbone.parameters():
            param.data = param.data.to(torch.bfloat16)
    else:
        cast_frozen_parameters(backbone, frozen_dtype, keep=set())


class LiveBytes(TorchDispatchMode):
    """Bytes of the storages ops allocate that are still alive, and their peak.

    Each new storage is counted when an op returns it and uncounted when it is freed (a weak
    reference's callback: storages keep their Python object while alive). Storages that exist
    when the tracker starts (parameters, AdamW state, the batch) are not counted.
    """

    def __init__(self) -> None:
        super().__init__()
        self.live = 0
        self.peak = 0
        self._refs: dict[int, weakref.ref[Any]] = {}

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        out = func(*args, **(kwargs or {}))
        for t in pytree.tree_leaves(out):
            if isinstance(t, Tensor):
                self._track(t)
        return out

    def _track(self, t: Tensor) -> None:
        storage = t.untyped_storage()
        key = storage._cdata
        if key in self._refs or key in self._existing:
            return
        size = storage.nbytes()
        self.live += size
        self.peak = max(self.peak, self.live)
        self._refs[key] = weakref.ref(storage, functools.partial(self._free, key, size))

    def _free(self, key: int, size: int, _: Any) -> None:
        self.live -= size
        self._refs.pop(key, None)

    def __enter__(self) -> LiveBytes:
        self._existing: set[int] = set()
        return super().__enter__()

    def exclude(self, tensors: Iterator[Tensor] | list[Tensor]) -> None:
        self._existing.update(t.untyped_storage()._cdata for t in tensors)


def measure_activations(
    backbone: VLABackbone,
    batch: Batch,
    checkpointed: bool,
    precision: str = "32-true",
    attention: str = "math",
) -> float:
    """Bytes autograd saves in one forward of ``backbone`` (weights on meta, ``batch`` on the CPU)."""
    return trace_step(backbone, batch, checkpointed, precision, attention, backward=False)[0]


def trace_step(
    backbone: VLABackbone,
    batch: Batch,
    checkpointed: bool,
    precision: str,
    attention: str,
    backward: bool = True,
    device: str = "cuda",
    keep_gradients: bool = True,
    objectives: Sequence[Objective] = (),
) -> tuple[float, float]:
    """(bytes autograd saves in the forward, peak bytes alive during the step) of one training
    step of ``backbone`` with AdamW, the AdamW state already there (a later step): forward,
    backward, ``optimizer.step()``. Parameters and AdamW state are not in the peak.

    ``objectives`` (bound to ``backbone``, on its device) add their weighted losses as
    ``VLAModule.training_step`` does; what of theirs trains is optimized with the backbone.

    ``keep_gradients=False`` drops each gradient as soon as it is complete, as FSDP2 and ZeRO
    free the unsharded gradient once it is reduce-scattered (their shards are counted apart)."""
    autocast = torch.bfloat16 if precision == "bf16-mixed" else None

    def kernels() -> GpuKernels:
        return GpuKernels(autocast, attention == "efficient", device)

    if checkpointed:
        from torch.distributed._composable import checkpoint

        for unit in backbone.shard_units():
            # The backward recomputes on autograd's thread, which the mode does not reach.
            checkpoint(unit, context_fn=lambda: (contextlib.nullcontext(), kernels()))
    if precision == "bf16-true":  # Lightning's bf16-true converts the batch's float tensors
        batch = pytree.tree_map_only(
            Tensor, lambda t: t.to(torch.bfloat16) if t.is_floating_point() else t, batch
        )
    modules = [backbone, *objectives]
    trainable = [p for m in modules for p in m.parameters() if p.requires_grad]
    # foreach=True is AdamW's default on a GPU; its temporaries are part of the peak.
    optimizer = torch.optim.AdamW(trainable, foreach=True)
    for p in trainable:
        optimizer.state[p] = {
            "step": torch.tensor(1.0), "exp_avg": torch.zeros_like(p),
            "exp_avg_sq": torch.zeros_like(p),
        }  # fmt: skip
    if not keep_gradients:
        for p in trainable:
            p.register_post_accumulate_grad_hook(lambda p: setattr(p, "grad", None))
    store: list[float] = []
    with LiveBytes() as live, HostValuesMetaCompute(), kernels() as gpu:
        live.exclude([t for m in modules for t in (*m.parameters(), *m.buffers())])
        live.exclude([t for state in optimizer.state.values() for t in state.values()])
        with saved_activation_bytes(store, backbone):
            losses = compute_losses(backbone, objectives, batch)
            loss = losses["action"]
            for objective in objectives:
                loss = loss + objective.weight * losses[objective.name]
        gpu.clear_cast_cache()  # autocast's cache goes when its region ends, after the forward
        if backward:
            loss.backward()
            del loss
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
    return store[0], float(live.peak)


def stand_in_tokenizer(preset: str) -> dict[str, Any]:
    """A tokenizer for a meta forward pass: a full-size preset's comes with its checkpoint, so it
    borrows its family's tiny-preset one; a preset built from weight packages (the mini) gets its
    own from the packages' folder (a meta build reads no packages itself)."""
    from capvector.backbones.packaged import PACKAGED_TOKENIZERS

    config = preset_config(preset)
    if getattr(config, "tokenizer", None) in PACKAGED_TOKENIZERS:
        return {"tokenizer": str(PACKAGED_TOKENIZERS[config.tokenizer]())}
    if not hasattr(config, "tokenizer") or config.tokenizer:
        return {}
    for name in list_presets():
        other = preset_config(name)
        if type(other) is type(config) and "tiny" in name and getattr(other, "tokenizer", ""):
            return {"tokenizer": other.tokenizer}
    return {}


def _check(settings: TrainingSettings) -> torch.dtype:
    """The storage dtype of what does not train, once the settings are known to be valid."""
    for what, value, choices in [
        ("strategy", settings.strategy, STRATEGIES),
        ("precision", settings.precision, PRECISIONS),
        ("frozen dtype", settings.frozen_dtype, FROZEN_DTYPES),
        ("attention path", settings.attention, ATTENTION_PATHS),
    ]:
        if value not in choices:
            raise CapVectorError(f"unknown {what} {value!r}; choose from {', '.join(choices)}")
    if settings.frozen_dtype != "float32" and settings.precision == "32-true":
        raise CapVectorError(
            f"frozen dtype {settings.frozen_dtype} needs precision bf16-mixed (autocast), as "
            "training does: pass --precision bf16-mixed or --frozen-dtype float32"
        )
    return FROZEN_DTYPES[settings.frozen_dtype]


def make_objective(name: str) -> Objective:
    """The auxiliary objective ``name`` (``OBJECTIVES``) with its defaults (spatial: the geometric
    teacher, 64 features with position embedding, as ``aux_sft.yaml``)."""
    return OBJECTIVES.get(name)()


def meta_backbone(preset: str, lora_rank: int | None, **overrides: Any) -> VLABackbone:
    """``preset`` with its weights on the meta device, trainable as LoRA of ``lora_rank`` or fully."""
    with on_meta():
        backbone = build_backbone(preset, **stand_in_tokenizer(preset), **overrides)
        set_trainable(backbone, lora_settings(lora_rank))
    return backbone


def estimate_memory(
    preset: str, settings: TrainingSettings | None = None, device: str = "cuda"
) -> MemoryEstimate:
    """Per-device bytes for training ``preset`` with AdamW as ``settings`` say (default:
    ``TrainingSettings()``). ``device`` is the autocast policy the trace follows: ``cuda``, or
    ``cpu`` to compare with a CPU run."""
    settings = settings or TrainingSettings()
    if device not in AUTOCAST_DEVICES:
        raise CapVectorError(
            f"unknown device {device!r}; choose from {', '.join(AUTOCAST_DEVICES)}"
        )
    dtype = _check(settings)
    precision, strategy, devices = settings.precision, settings.strategy, settings.devices
    shard_params = strategy in ("fsdp2", "deepspeed_zero3")
    shard_grads = strategy != "ddp" and devices > 1
    names = tuple(settings.objectives)  # the CLI gives a list
    for name in names:  # an unknown name fails before minutes of tracing
        OBJECTIVES.get(name)
    vector = None if settings.vector is None else VectorFolder(settings.vector).load()
    changed = [] if vector is None else vector.changed_keys()  # once: a pass over c's tensors
    kept = 0
    traces, with_objectives = [], []
    for checkpointed in (False, True):
        for attach in (False, True) if names else (False,):
            backbone = meta_backbone(preset, settings.lora_rank)
            objectives = [make_objective(name) for name in names] if attach else []
            for objective in objectives:  # before the cast: reasoning may unfreeze the LM head
                objective.bind(backbone)  # builds projectors
                objective.to("meta")  # gradients must stay on one device
            set_storage_dtypes(backbone, precision, dtype)
            if vector is not None and settings.vector_float32_weights:
                kept = keep_in_float32(backbone, changed)
            batch = synthetic_batch(backbone, settings.batch, "cpu", objectives=bool(names))
            try:
                trace = trace_step(
                    backbone, batch, checkpointed, precision, settings.attention, device=device,
                    keep_gradients=not shard_grads, objectives=objectives,
                )  # fmt: skip
            except (NotImplementedError, RuntimeError):
                # A forward that reads values of meta results (data-dependent shapes downstream
                # of the weights) cannot be traced; then only the weight-related terms are
                # estimated.
                trace = (float("nan"), float("nan"))
            if attach:
                own = sum(
                    p.numel() * p.element_size()
                    for o in objectives for p in o.parameters() if p.requires_grad
                )  # fmt: skip
                # Their gradients are in the traced peak; their weights and AdamW state are not.
                with_objectives.append((trace[1], 3 * own))
            else:
                traces.append(trace)
    params = list(backbone.parameters())
    total = sum(p.numel() * p.element_size() for p in params)
    trainable = sum(p.numel() * p.element_size() for p in params if p.requires_grad)
    param_bytes = (total - kept) / (devices if shard_params else 1)
    if shard_params and devices > 1:
        # FSDP2 all-gathers one unit at a time (plus one prefetched): add the two largest units.
        units = sorted(
            (sum(p.numel() * p.element_size() for p in u.parameters()) for u in backbone.shard_units()),
            reverse=True,
        )  # fmt: skip
        param_bytes += sum(units[:2])
    # Gradients and AdamW's two moments have the dtype of what trains. Unsharded, the traced peak
    # holds the whole gradients; what is beyond the saved activations and those gradients is
    # working memory. Sharded, the trace frees each gradient when complete (reduce-scatter).
    grads = trainable / (devices if shard_grads else 1)
    traced_grads = 0 if shard_grads else trainable
    (saved, peak), (saved_checkpointed, peak_checkpointed) = traces
    extra = [0.0, 0.0]
    for i, (peak_with, own) in enumerate(with_objectives):
        extra[i] = _beyond(peak_with, traces[i][1]) + own
    return MemoryEstimate(
        parameters=param_bytes,
        gradients=grads,
        optimizer=2 * grads,
        activations=saved,
        activations_checkpointed=saved_checkpointed,
        working=_beyond(peak, saved + traced_grads),
        working_checkpointed=_beyond(peak_checkpointed, saved_checkpointed + traced_grads),
        checkpointing=settings.activation_checkpointing,
        trainable_parameters=trainable / (devices if shard_params else 1),
        objectives=extra[0],
        objectives_checkpointed=extra[1],
        vector=0.0 if vector is None else (
            (kept + vector_copy_bytes(vector)) / (devices if shard_params else 1)
        ),
    )  # fmt: skip


def keep_in_float32(backbone: nn.Module, changed: list[str]) -> int:
    """Store the frozen weights a vector changes (its ``changed_keys``) in float32, as
    ``MergeCapabilityVector`` has a fit keep them (its ``float32_weights``) beside frozen weights
    in a lower precision; the bytes that adds."""
    added = 0
    for _, param in match_tensors(backbone, changed).values():
        if not param.requires_grad and param.element_size() < 4:
            added += param.numel() * (4 - param.element_size())
            param.data = param.data.float()
    return added


def vector_copy_bytes(vector: CapabilityVector) -> int:
    """``OrthogonalRegularization``'s copy of c in LoRA mode: float32 factors and dense tensors."""
    factors = sum(f.lora_a.numel() + f.lora_b.numel() for f in vector.lowrank.values())
    return 4 * (factors + sum(t.numel() for t in vector.dense.values()))


def _beyond(peak: float, counted: float) -> float:
    """What of ``peak`` the counted terms do not hold (0 if they hold it all; NaN stays NaN)."""
    return peak - counted if not peak - counted < 0 else 0.0


def assumptions(settings: TrainingSettings) -> list[str]:
    """What the GPU estimate takes for granted, printed next to it."""
    return [
        "AdamW (foreach); what trains, its gradients and both moments in float32"
        + ("" if settings.precision != "bf16-true" else " (bf16 under bf16-true)"),
        f"frozen weights in {settings.frozen_dtype}; CUDA autocast's casts under bf16-mixed",
        f"SDPA as the {settings.attention} kernel; attention outside SDPA keeps its matrices",
        "one synthetic batch of the preset's shapes (its prompt length, images, action chunk)",
        "not counted: the CUDA context and kernels (~0.5-1 GiB), allocator fragmentation and "
        "cache, NCCL buffers, the data loader, other processes on the GPU",
    ]


def describe(estimate: MemoryEstimate, settings: TrainingSettings) -> str:
    header = ", ".join(f"{k}={v}" for k, v in dataclasses.asdict(settings).items())
    notes = "\n".join(f"  assumes: {line}" for line in assumptions(settings))
    return f"per-device memory estimate ({header}):\n{estimate.table()}\n{notes}"


__all__ = [
    "MemoryEstimate",
    "TrainingSettings",
    "describe",
    "estimate_memory",
    "make_objective",
    "meta_backbone",
    "synthetic_batch",
]
