"""Building and loading a backbone with its frozen weights in their storage dtype from the start.

Built in float32 and cast afterwards, a 7.5 B model passes through ≈ 30 GB of host memory on
every rank before it is halved to bf16 (issue 58: ``capvector fit`` of OpenVLA-OFT-7B was killed by
the OOM killer while building). Here every submodule's parameters are cast the moment the
submodule is attached to its parent (``register_module_module_registration_hook``): each module's
own initialisation still runs in float32, as before, so the weights are the float32 build's
rounded to the storage dtype, and the process holds the stored weights plus one module in float32.

Loading an export copies it tensor by tensor into the built model (``load_streaming``), each tensor
cast by ``copy_`` to the dtype its parameter is stored in: never a whole float32 state dict.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.modules.module import register_module_module_registration_hook
from torch.overrides import TorchFunctionMode

from capvector.backbones.base import (
    VLABackbone,
    backbone_class,
    check_fits,
    load_export_config,
)
from capvector.io.hub import local_folder
from capvector.io.lora_layers import split_base_delta
from capvector.io.names import BASE_DELTA
from capvector.io.weights import SafetensorsFolder, WeightSource


def _cast_float32(module: nn.Module, dtype: torch.dtype) -> None:
    for param in module.parameters():
        if param.dtype == torch.float32:
            param.data = param.data.to(dtype)


_deferred = 0
"""How many ``float32_until_attached`` blocks are open: within one, nothing is cast."""


@contextmanager
def float32_until_attached() -> Iterator[None]:
    """Build a module in float32 and cast it only when it is attached to its parent: for an
    upstream module that re-initialises its submodules at the end of its constructor with
    element-wise arithmetic no ``torch.nn.init`` call covers (timm's ``trunc_normal_``: uniform,
    then ``erfinv_``, which in bf16 sends values near ±1 to the ±2 clamp)."""
    global _deferred
    _deferred += 1
    try:
        yield
    finally:
        _deferred -= 1


class _InitInFloat32(TorchFunctionMode):
    """``torch.nn.init`` functions on a low-precision tensor draw in float32 and round once, as
    a float32 build cast afterwards would: transformers' ``post_init`` re-draws every weight after
    the submodules are built (and cast)."""

    def __torch_function__(
        self, func: Any, types: Any, args: Sequence[Any] = (), kwargs: Any = None
    ) -> Any:
        kwargs = kwargs or {}
        target = args[0] if args else None
        if (
            getattr(func, "__module__", None) == "torch.nn.init"
            and isinstance(target, Tensor)
            and target.dtype in (torch.bfloat16, torch.float16)
        ):
            draft = torch.empty(target.shape, dtype=torch.float32, device=target.device)
            func(draft, *args[1:], **kwargs)
            with torch.no_grad():
                target.copy_(draft)
            return target
        return func(*args, **kwargs)


@contextmanager
def stored_in(dtype: torch.dtype) -> Iterator[None]:
    """Within the block, float32 parameters of every module built are stored in ``dtype`` as soon
    as the module is attached to its parent (see ``build_stored_in`` for the root)."""
    if dtype == torch.float32:
        yield
        return

    def cast(parent: nn.Module, name: str, child: nn.Module | None) -> None:
        if child is not None and not _deferred:
            _cast_float32(child, dtype)

    handle = register_module_module_registration_hook(cast)
    try:
        with _InitInFloat32():
            yield
    finally:
        handle.remove()


def build_stored_in(build: Callable[[], nn.Module], dtype: torch.dtype) -> nn.Module:
    """``build()`` with its float32 parameters stored in ``dtype`` (see ``stored_in``)."""
    with stored_in(dtype):
        model = build()
    if dtype != torch.float32:
        _cast_float32(model, dtype)
    return model


def export_key(name: str) -> str | None:
    """The export's name of a model tensor: peft's ``base_layer`` wrapper dropped; LoRA adapters
    (absent from exports, which hold LoRA merged) have none."""
    if ".lora_" in name:
        return None
    return name.replace(".base_layer.", ".")


def load_streaming(
    model: nn.Module,
    source: WeightSource,
    label: str,
    skip: set[str] | frozenset[str] = frozenset(),
) -> None:
    """Copy every tensor of ``source`` (but those in ``skip``) into ``model``'s parameter or buffer
    of the same export name, one tensor at a time; keys and shapes are all checked before anything
    is copied."""
    targets: dict[str, list[torch.Tensor]] = {}
    for name, tensor in model.state_dict(keep_vars=True).items():
        key = export_key(name)
        if key is not None:
            targets.setdefault(key, []).append(tensor)
    expected = {k: tuple(tensors[0].shape) for k, tensors in targets.items()}
    names = [k for k in source if k not in skip]  # a WeightSource, not a mapping
    check_fits(model, expected, {k: tuple(source.info(k).shape) for k in names}, label)
    with torch.no_grad():
        for key, tensors in targets.items():
            value = source.read(key)
            for tensor in tensors:
                tensor.copy_(value)
            del value


def reload_in_float32(model: nn.Module, folder: str, names: set[str]) -> None:
    """Read the parameters named in ``names`` (export names) again from the export ``folder`` into
    their float32 storage. They were loaded while stored in the frozen dtype and are kept in float32
    only once a callback asks (a capability vector lands in them): without this they would keep the
    rounded values, and the merge would add λc to weights the float32 build never had."""
    if not names:
        return
    source = SafetensorsFolder(local_folder(folder, "export folder"))
    available = set(source.keys())
    with torch.no_grad():
        for name, param in model.named_parameters():
            key = export_key(name)
            if key in names and key in available and param.dtype == torch.float32:
                param.copy_(source.read(key))


def load_pretrained(
    folder: str,
    dtype: torch.dtype = torch.float32,
    prepare: Callable[[VLABackbone], None] | None = None,
) -> VLABackbone:
    """The export ``folder`` (local or a hub id) built with its float32 parameters stored in
    ``dtype``, then ``prepare``d (LoRA injected, what trains set back to float32), then loaded
    tensor by tensor: a tensor ``prepare`` keeps in float32 gets the export's full precision."""
    path = local_folder(folder, "export folder")
    config = load_export_config(path)
    cls = backbone_class(config["family"], config["backbone_config"].get("preset"))
    model = build_stored_in(lambda: cls.from_config_dict(config["backbone_config"]), dtype)
    assert isinstance(model, VLABackbone)
    model.load_tokenizer(path)
    if prepare is not None:
        prepare(model)
    source = SafetensorsFolder(path)
    skip: set[str] = set()
    if config.get(BASE_DELTA) is not None:  # base weights = packages + B @ A (io.lora_layers)
        skip = {k for k in source if ".lora_" in k}
        _, deltas = split_base_delta({k: source.read(k) for k in skip})
        model.set_base_delta(deltas)
    load_streaming(model, source, label=str(folder), skip=skip)
    return model
