"""The ``*-mini`` base (``base_weights='packages'``): the vision tower and language model loaded
from the installed weight packages (``capvector.backbones.packaged``), frozen, and left out of
every state dict while they still equal those packages.

A fresh model rebuilds them from the packages, so a checkpoint or export needs only what training
changed: LoRA, projector, heads. Base weights may also carry a low-rank delta over the packages
(``set_base_delta``: the LoRA of the fine-tune an export came from, a merged capability vector),
W = packaged + B @ A: such a weight is left out too while it equals that value, and the export
stores (B, A) (``capvector.io.lora_layers``). A tensor changed any other way (a vector merged into it in
place) is saved whole. Loading a state dict without those tensors keeps the packaged ones (a load
pre-hook puts the model's own values in their place), so Lightning's strict resume and
``from_pretrained`` work unchanged.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import Tensor, nn

from capvector.backbones.base import BackboneError, VLABackbone
from capvector.backbones.packaged import (
    EFFICIENTNET_LITE0,
    GEMMA3_270M,
    efficientnet_lite0_weights,
    gemma3_270m_folder,
    gemma3_270m_weights,
)
from capvector.io.loading import read_json
from capvector.io.lora_layers import Factors

LM_PREFIX = "language_model."
VISION_PREFIX = "vision_backbone.model."
TIED_HEAD = "language_model.lm_head.weight"


def attach_packaged_base(model: VLABackbone, load: bool) -> None:
    """Load (when ``load``; not on the meta device) and freeze the packaged base of ``model``, and
    install the state-dict hooks that leave it out of checkpoints."""
    llm = model.config.llm
    if llm.architecture != "gemma3" or model.config.vision != "efficientnet-lite0":
        raise BackboneError(
            "base_weights='packages' holds Gemma-3-270M and EfficientNet-Lite0: set "
            "llm.architecture='gemma3' and vision='efficientnet-lite0' (the openvla-oft-mini preset)"
        )
    if load:
        _check_architecture(model)
        state = dict(_packaged_tensors(model))
        own = {name: p for name, p in model.state_dict().items() if name.startswith(_PREFIXES)}
        missing = sorted(set(own) - set(state) - {TIED_HEAD})
        if missing:
            raise BackboneError(
                f"the weight packages lack {len(missing)} tensors, e.g. {missing[:3]}"
            )
        with torch.no_grad():
            for name, value in state.items():
                if own[name].shape != value.shape:
                    raise BackboneError(
                        f"packaged {name} is {tuple(value.shape)}, the model's "
                        f"{tuple(own[name].shape)}: the preset does not match the weights"
                    )
                own[name].copy_(value)
    model.vision_backbone.requires_grad_(False)
    model.language_model.get_input_embeddings().requires_grad_(False)
    model.packaged_delta = {}
    model.register_state_dict_post_hook(_drop_packaged)
    model.register_load_state_dict_pre_hook(_keep_packaged)


def provenance() -> list[dict[str, Any]]:
    """Where the base came from, for the model card of every export."""
    return [GEMMA3_270M.provenance(), EFFICIENTNET_LITE0.provenance()]


_PREFIXES = (LM_PREFIX, VISION_PREFIX)


def set_base_delta(model: VLABackbone, deltas: Mapping[str, Factors]) -> None:
    """Base weights (export names ``X.weight``) set to packaged + B @ A, computed in float32 and
    stored in the parameter's dtype; the deltas are kept on the model (``packaged_delta``) for
    the state-dict hook and the next export."""
    packaged = dict(_packaged_tensors(model))
    params = {_local(name, ""): param for name, param in _base_parameters(model)}
    kept: dict[str, Factors] = {}
    with torch.no_grad():
        for key, (b, a) in deltas.items():
            if key not in packaged or key not in params:
                raise BackboneError(
                    f"base delta `{key}` is not a weight of the packaged base: the export is not "
                    f"of this preset ({model.config.preset})"
                )
            if (b.shape[0], a.shape[1]) != tuple(params[key].shape) or b.shape[1] != a.shape[0]:
                raise BackboneError(
                    f"base delta `{key}` is {tuple(b.shape)} @ {tuple(a.shape)}, the weight "
                    f"{tuple(params[key].shape)}: the export is not of this preset"
                )
            kept[key] = (b.float(), a.float())
            params[key].copy_(_with_delta(packaged[key], kept[key]))
    model.packaged_delta = kept


def _with_delta(packaged: Tensor, delta: Factors | None) -> Tensor:
    """The value a base weight has: packaged (+ B @ A in float32)."""
    if delta is None:
        return packaged
    b, a = delta
    return packaged.float() + b @ a


def _check_architecture(model: VLABackbone) -> None:
    """The preset's Gemma numbers against the GGUF header's (``gguf_config.json``)."""
    header = read_json(gemma3_270m_folder() / "gguf_config.json")
    llm = model.config.llm
    ours = {
        "hidden_size": llm.hidden_size,
        "intermediate_size": llm.intermediate_size,
        "num_heads": llm.num_heads,
        "num_kv_heads": llm.num_kv_heads,
        "head_dim": llm.head_dim,
        "rope_theta": llm.rope_theta,
        "sliding_window": llm.sliding_window,
        "vocab_size": llm.vocab_size,
    }
    wrong = {k: (v, header[k]) for k, v in ours.items() if header[k] != v}
    if wrong or not 1 <= llm.num_layers <= header["num_layers"]:
        raise BackboneError(
            f"llm config {wrong or {'num_layers': llm.num_layers}} does not match Gemma-3-270M's "
            f"GGUF header ({header}): keep the openvla-oft-mini preset's numbers"
        )


def _packaged_tensors(model: VLABackbone) -> Iterator[tuple[str, Tensor]]:
    """(state-dict name, packaged value) of every tensor of the base, one at a time."""
    for name, value in gemma3_270m_weights(model.config.llm.num_layers).items():
        yield LM_PREFIX + name, value
    with torch.device("meta"):
        import timm

        keys = list(timm.create_model("tf_efficientnet_lite0", pretrained=False).state_dict())
    for name, value in efficientnet_lite0_weights(keys).items():
        if not name.startswith("classifier."):  # the trunk is built without the classifier
            yield VISION_PREFIX + name, value


def _local(key: str, prefix: str) -> str:
    return key[len(prefix) :].replace(".base_layer.", ".")


def _drop_packaged(
    module: nn.Module, state_dict: dict[str, Any], prefix: str, _metadata: Any
) -> None:
    """State-dict post hook: remove each base tensor that still equals its packaged value, plus
    its base delta if it has one (in the stored dtype, so a bf16 frozen base counts too)."""
    names = {_local(k, prefix): k for k in state_dict if k.startswith(prefix)}
    packaged = dict(_packaged_tensors(module))  # type: ignore[arg-type]
    embedding = LM_PREFIX + "model.embed_tokens.weight"
    packaged[TIED_HEAD] = packaged[embedding]
    deltas = getattr(module, "packaged_delta", {})
    for name, value in packaged.items():
        key = names.get(name)
        if key is not None and _equal(state_dict[key], _with_delta(value, deltas.get(name))):
            del state_dict[key]


def _equal(ours: Tensor, packaged: Tensor) -> bool:
    ours = ours.detach()
    return ours.shape == packaged.shape and torch.equal(ours.cpu(), packaged.to(ours.dtype))


def _keep_packaged(
    module: nn.Module,
    state_dict: dict[str, Any],
    prefix: str,
    _metadata: Any,
    _strict: bool,
    _missing: list[str],
    _unexpected: list[str],
    _errors: list[str],
) -> None:
    """Load pre-hook: a base tensor the state dict leaves out keeps the model's (packaged) value."""
    for name, param in _base_parameters(module):
        key = prefix + name
        if key not in state_dict:
            state_dict[key] = param.detach()


def _base_parameters(module: nn.Module) -> Iterator[tuple[str, Tensor]]:
    """The base's tensors under their state-dict names (peft's ``base_layer`` included): parameters
    (the tied head too) and persistent buffers, as ``state_dict`` lists them."""
    for name, param in module.named_parameters(remove_duplicate=False):
        if name.startswith(_PREFIXES) and ".lora_" not in name:
            yield name, param
    for owner, sub in module.named_modules():
        for name, buffer in sub._buffers.items():
            full = f"{owner}.{name}" if owner else name
            persistent = name not in sub._non_persistent_buffers_set
            if buffer is not None and persistent and full.startswith(_PREFIXES):
                yield full, buffer
