"""Reading OpenVLA-OFT's own run folders (moojink/openvla-oft) into :class:`OpenVLAOFT`.

A run folder, as ``vla-scripts/finetune.py`` writes it (``save_training_checkpoint``):

- ``config.json`` + ``model.safetensors`` (or shards + index): the merged ``save_pretrained`` of
  ``OpenVLAForActionPrediction`` (``prismatic/extern/hf``), tokenizer files beside them;
- ``action_head--<step>_checkpoint.pt`` and ``proprio_projector--<step>_checkpoint.pt``, state dicts
  of DDP-wrapped modules (``module.`` prefixes);
- OFT+ only: ``vision_backbone--<step>_checkpoint.pt``, the whole FiLM-wrapped vision backbone with
  its unmerged LoRA layers (``vla.module.vision_backbone.state_dict()``). finetune.py's LoRA merge
  does not reach the FiLM-wrapped ViTs, so upstream's inference (``experiments/robot/
  openvla_utils.py: _apply_film_to_vla``) takes the vision backbone from this file, as we do;
- ``lora_adapter/`` (``adapter_config.json``, and the weights unless removed) and
  ``dataset_statistics.json``.

What comes from where (``load_original``):

- ``config.json``: the vision backbone (fused DINOv2 + SigLIP only), its activation and image size,
  the projector, the Llama ``text_config``; fields that change computation and we do not support are
  a ``BackboneError`` naming them; fields without effect here are listed in ``_NO_EFFECT``;
- shapes: action dim, head depth (``action_head``), proprio dim (``proprio_projector``), the ViTs'
  width, depth, patch size, MLP width and register tokens (the tiny fixtures patch timm's sizes);
  FiLM from the presence of ``vision_backbone--*``;
- not in any file: the chunk size and the camera count. Upstream takes them from the command line
  (``prismatic/vla/constants.py`` picks LIBERO / ALOHA / BRIDGE constants from words in ``argv``;
  ``--num_images_in_input``), so we pick the platform whose action and proprio sizes match and use
  its chunk size and its recipe's camera count; ``overrides`` set them otherwise;
- the ViTs' head counts (not in any shape): the preset's.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from torch import Tensor

from capvector.backbones.base import (
    BackboneError,
    OriginalCheckpoint,
    load_state_dict_strictly,
    merge_nested,
    preset_config,
    read_sharded,
)
from capvector.backbones.common import read_required_json
from capvector.data.statistics import BOUNDS, BOUNDS_Q99
from capvector.io.loading import load_safetensors, load_torch
from capvector.io.lora_layers import LoraFormatError, adapter_scaling, merge_lora, split_lora

if TYPE_CHECKING:
    from capvector.backbones.openvla_oft import OpenVLAOFT

# (action_dim, proprio_dim) -> (platform, chunk size, cameras, normalisation). Chunk sizes and
# normalisation types from prismatic/vla/constants.py; cameras from each recipe's
# --num_images_in_input (LIBERO.md: 2, ALOHA.md: 3). BRIDGE has no OFT recipe with several cameras.
_PLATFORMS = {
    (7, 8): ("LIBERO", 8, 2, BOUNDS_Q99),
    (14, 14): ("ALOHA", 25, 3, BOUNDS),
    (7, 7): ("BRIDGE", 5, 1, BOUNDS_Q99),
}
_FUSED_VISION = {
    "dinosiglip-vit-so-224px": ("vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_224"),
    "dinosiglip-vit-so-384px": ("vit_large_patch14_reg4_dinov2.lvd142m", "vit_so400m_patch14_siglip_384"),
}  # fmt: skip
_LLAMA_BACKBONES = ("llama2-", "vicuna-v15-")
# config.json fields that do not change what the model computes here, and why.
_NO_EFFECT = {
    "architectures": "HF bookkeeping",
    "auto_map": "HF bookkeeping",
    "model_type": "checked: openvla",
    "torch_dtype": "weights are cast to the model's dtype",
    "transformers_version": "HF bookkeeping",
    "_name_or_path": "HF bookkeeping",
    "hf_llm_id": "where the base LLM was downloaded from",
    "llm_max_length": "training-time truncation; OFT's prompts stay far below it",
    "n_action_bins": "decoding of discrete action tokens, unused by the L1 head",
    "norm_stats": "the same statistics as dataset_statistics.json, which is read",
    "output_projector_states": "a debugging output of the HF class",
    "pad_token_id": "the tokenizer's <PAD>, read with the tokenizer",
    "pad_to_multiple_of": "the vocabulary it padded is text_config.vocab_size, which is read",
}
# Llama ``text_config`` fields that change the computation, with the only value we support.
_LLAMA_FIXED = {
    "model_type": "llama",
    "hidden_act": "silu",
    "rope_scaling": None,
    "attention_bias": False,
    "tie_word_embeddings": False,
    "pretraining_tp": 1,
}
_SUPPORTED_RESIZE = ("resize-naive",)

# LayerScale parameters are called `gamma` in timm; HF renames parameters containing "gamma", so
# Prismatic stores them as `scale_factor` (modeling_prismatic.py: ls_apply_patch).
_LAYER_SCALE_RENAMES = ((".ls1.scale_factor", ".ls1.gamma"), (".ls2.scale_factor", ".ls2.gamma"))


def load_original(
    cls: type[OpenVLAOFT],
    source: str | Path,
    preset: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    apply_lora_adapter: bool = False,
) -> OriginalCheckpoint:
    """The model, statistics and upstream config of an OpenVLA-OFT run folder (or hub id).

    ``preset`` (default ``openvla-oft-7b``) supplies what no file records (the ViTs' head counts);
    ``overrides`` change named fields after the folder's values are applied.
    ``apply_lora_adapter`` merges ``lora_adapter/`` into the weights (released folders already hold
    merged weights).
    """
    from capvector.backbones.openvla_oft import OpenVLAOFTConfig

    root = resolve_folder(source)
    upstream = read_upstream_config(root)
    vlm = read_original_vlm(root)
    head = read_component(root, "action_head", "action_head.")
    proprio = (
        read_component(root, "proprio_projector", "proprio_projector.")
        if _component_files(root, "proprio_projector")
        else {}
    )
    film_files = _component_files(root, "vision_backbone")
    vision = read_film_vision_backbone(root) if film_files else {}
    state = {**vlm, **vision, **head, **proprio}

    values = config_values(upstream["config.json"], state, film=bool(film_files))
    values = merge_nested(values, overrides or {})
    if (root / "tokenizer_config.json").is_file():
        values["tokenizer"] = str(root)
    config = preset_config(preset or "openvla-oft-7b", **values)
    if not isinstance(config, OpenVLAOFTConfig):
        raise BackboneError(f"preset {preset!r} is not an OpenVLA-OFT preset")
    model = cls(config)
    if apply_lora_adapter:
        merge_peft_adapter(state, root / "lora_adapter")
    load_state_dict_strictly(model, state, source=str(root))
    stats_path = root / "dataset_statistics.json"
    stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
    platform = _PLATFORMS.get((config.action_dim, config.proprio_dim))
    if platform is not None and platform[3] != BOUNDS_Q99:
        # The statistics file does not say which rule made it (upstream picks it by platform);
        # ours carries it, so training and evaluation un-normalise as upstream does.
        stats = {name: {**entry, "normalization": platform[3]} for name, entry in stats.items()}
    return OriginalCheckpoint(model, stats, upstream)


def read_upstream_config(root: Path) -> dict[str, Any]:
    """The upstream config files of a run folder, by file name."""
    why = (
        "an OpenVLA-OFT run folder holds the merged save_pretrained of "
        "OpenVLAForActionPrediction (config.json + model.safetensors)"
    )
    files = {"config.json": read_required_json(root / "config.json", why)}
    adapter = root / "lora_adapter" / "adapter_config.json"
    if adapter.is_file():
        files["lora_adapter/adapter_config.json"] = json.loads(adapter.read_text())
    return files


def config_values(
    upstream: Mapping[str, Any], state: Mapping[str, Tensor], film: bool
) -> dict[str, Any]:
    """OpenVLAOFTConfig fields from ``config.json`` and the shapes of the converted ``state``."""
    known = {
        "vision_backbone_id", "timm_model_ids", "timm_override_act_layers", "image_sizes",
        "use_fused_vision_backbone", "arch_specifier", "llm_backbone_id", "text_config",
        "image_resize_strategy", *_NO_EFFECT,
    }  # fmt: skip
    unknown = sorted(set(upstream) - known)
    if unknown:
        raise BackboneError(
            f"config.json has field(s) {unknown} that capvector's OpenVLA-OFT import does not know; "
            "it cannot tell whether they change the model, so it refuses the checkpoint"
        )
    if upstream.get("model_type") != "openvla":
        raise BackboneError(
            f"config.json model_type {upstream.get('model_type')!r} is not 'openvla'"
        )
    vision_id = upstream.get("vision_backbone_id")
    if vision_id not in _FUSED_VISION or upstream.get("use_fused_vision_backbone") is False:
        raise BackboneError(
            f"config.json vision_backbone_id {vision_id!r} is not supported: capvector's OpenVLA-OFT "
            f"is the fused DINOv2 + SigLIP backbone ({', '.join(_FUSED_VISION)})"
        )
    timm_ids = tuple(upstream.get("timm_model_ids", _FUSED_VISION[vision_id]))
    if timm_ids != _FUSED_VISION[vision_id]:
        raise BackboneError(f"config.json timm_model_ids {list(timm_ids)} are not {vision_id}'s")
    if upstream.get("arch_specifier") != "no-align+fused-gelu-mlp":
        raise BackboneError(
            f"config.json arch_specifier {upstream.get('arch_specifier')!r} is not supported "
            "(only OFT's 'no-align+fused-gelu-mlp' projector)"
        )
    resize = upstream.get("image_resize_strategy", "resize-naive")
    if resize not in _SUPPORTED_RESIZE:
        raise BackboneError(
            f"config.json image_resize_strategy {resize!r} is not supported (only {_SUPPORTED_RESIZE}: "
            "capvector resizes each camera image to the square backbone size)"
        )
    sizes = upstream.get("image_sizes", [224, 224])
    if len(set(sizes)) != 1:
        raise BackboneError(f"config.json image_sizes {sizes}: the two ViTs must share one size")
    llm_id = upstream.get("llm_backbone_id", "")
    if not llm_id.startswith(_LLAMA_BACKBONES):
        raise BackboneError(f"config.json llm_backbone_id {llm_id!r} is not a Llama-2 backbone")
    text = dict(upstream.get("text_config") or {})
    for name, supported in _LLAMA_FIXED.items():
        if (
            name in text
            and text[name] != supported
            and not (name == "pretraining_tp" and text[name] in (0, None))
        ):
            raise BackboneError(
                f"config.json text_config.{name} = {text[name]!r} is not supported (only {supported!r})"
            )
    hidden = text.get("hidden_size", 4096)
    heads = text.get("num_attention_heads", 32)
    if text.get("head_dim") not in (None, hidden // heads):
        raise BackboneError(
            f"config.json text_config.head_dim {text['head_dim']} != hidden / heads"
        )

    # None -> timm 0.9.10's default: `act_layer = get_act_layer(act_layer) or nn.GELU`, exact GELU
    # for both ViTs (vision_transformer.py); a name is passed to timm as upstream does.
    acts = upstream.get("timm_override_act_layers", [None, None])
    values: dict[str, Any] = {
        "image_size": sizes[0],
        "film": film,
        "featurizer": {**_vit_geometry(state, "featurizer"), "act_layer": acts[0] or "gelu"},
        "fused_featurizer": {
            **_vit_geometry(state, "fused_featurizer"),
            "act_layer": acts[1] or "gelu",
        },
        "llm": {
            "hidden_size": hidden,
            "intermediate_size": text.get("intermediate_size", 11008),
            "num_layers": text.get("num_hidden_layers", 32),
            "num_heads": heads,
            "num_kv_heads": text.get("num_key_value_heads") or heads,
            "vocab_size": text.get("vocab_size", 32000),
            "rope_theta": text.get("rope_theta", 10000.0),
            "max_position_embeddings": text.get("max_position_embeddings", 2048),
            "rms_norm_eps": text.get("rms_norm_eps", 1e-6),
        },
    }
    values.update(_head_sizes(state, hidden))
    return values


def _vit_geometry(state: Mapping[str, Tensor], name: str) -> dict[str, Any]:
    """Width, depth, patch size, MLP ratio and register tokens of one ViT from its weights (OFT
    builds them by timm id, so the config does not carry them; our tiny fixtures change them)."""
    prefix = f"vision_backbone.{name}."
    patch = state.get(prefix + "patch_embed.proj.weight")
    if patch is None:
        raise BackboneError(f"the checkpoint has no {prefix}patch_embed.proj.weight")
    dim = patch.shape[0]
    depth = 1 + max(
        int(k[len(prefix) + len("blocks.") :].split(".")[0])
        for k in state
        if k.startswith(prefix + "blocks.")
    )
    hidden = state[prefix + "blocks.0.mlp.fc1.weight"].shape[0]
    ratio = hidden / dim
    if int(dim * ratio) != hidden:  # timm takes int(dim * mlp_ratio)
        ratio = math.nextafter(ratio, math.inf)
    reg = state.get(prefix + "reg_token")
    return {
        "embed_dim": dim,
        "depth": depth,
        "patch_size": patch.shape[-1],
        "mlp_ratio": ratio,
        "reg_tokens": 0 if reg is None else reg.shape[1],
    }


def _head_sizes(state: Mapping[str, Tensor], llm_dim: int) -> dict[str, Any]:
    """Action dim, head depth and proprio dim from the component files; chunk size and cameras from
    the platform those sizes match (no file records them, see the module docstring)."""
    action_dim = state["action_head.model.fc2.weight"].shape[0]
    head_in = state["action_head.model.fc1.weight"].shape[1]
    if head_in != action_dim * llm_dim:
        raise BackboneError(
            f"action_head takes {head_in} inputs, not action_dim x llm width = {action_dim} x {llm_dim}"
        )
    blocks = {
        k.split(".")[3] for k in state if k.startswith("action_head.model.mlp_resnet_blocks.")
    }
    fc1 = state.get("proprio_projector.fc1.weight")
    proprio_dim = 0 if fc1 is None else fc1.shape[1]
    values: dict[str, Any] = {
        "action_dim": action_dim,
        "head_blocks": len(blocks),
        "proprio_dim": proprio_dim,
    }
    platform = _PLATFORMS.get((action_dim, proprio_dim))
    if platform is not None:
        values["chunk_size"], values["num_images"] = platform[1], platform[2]
    return values


def resolve_folder(folder: str | Path) -> Path:
    """The run folder (a hub id was resolved to its snapshot by ``VLABackbone.from_original``)."""
    path = Path(folder)
    if not path.is_dir():
        raise BackboneError(f"checkpoint folder {folder} does not exist")
    return path


def _rename_layer_scale(key: str) -> str:
    for old, new in _LAYER_SCALE_RENAMES:
        if key.startswith("vision_backbone.") and key.endswith(old):
            return key[: -len(old)] + new
    return key


def read_original_vlm(root: Path) -> dict[str, Tensor]:
    """The merged VLM weights, under our names (LayerScale ``scale_factor`` -> ``gamma``)."""
    if (root / "model.safetensors.index.json").is_file():
        raw = read_sharded(root)
    elif (root / "model.safetensors").is_file():
        raw = load_safetensors(root / "model.safetensors")
    else:
        raise BackboneError(
            f"{root} has no merged VLM weights (model.safetensors or model.safetensors.index.json)"
        )
    return {_rename_layer_scale(key): value for key, value in raw.items()}


def _component_files(root: Path, name: str) -> list[Path]:
    return sorted(root.glob(f"{name}--*checkpoint.pt"))


def _load_component(root: Path, name: str) -> dict[str, Tensor]:
    files = _component_files(root, name)
    if not files:
        raise BackboneError(f"{root} has no {name}--<step>_checkpoint.pt file")
    if len(files) > 1:
        raise BackboneError(
            f"{root} has several {name} files ({[f.name for f in files]}); keep one"
        )
    raw = load_torch(files[0], weights_only=True)
    # Saved from DDP-wrapped modules, hence the `module.` prefix (finetune.py's
    # remove_ddp_in_checkpoint strips it the same way).
    return {k.removeprefix("module."): v for k, v in raw.items()}


def read_component(root: Path, name: str, prefix: str) -> dict[str, Tensor]:
    return {prefix + k: v for k, v in _load_component(root, name).items()}


def read_film_vision_backbone(root: Path) -> dict[str, Tensor]:
    """``vision_backbone--*``: the FiLM-wrapped ViTs with unmerged LoRA, under our names.

    Upstream keys look like ``vision_backbone.featurizer.blocks.3.block.attn.qkv.base_layer.weight``
    (``FiLMedPrismaticVisionBackbone.vision_backbone`` -> ``FiLMedVisionTransformerBlock.block`` ->
    peft's ``base_layer``), ``...blocks.3.scale.weight`` for FiLM. LoRA pairs are merged with the
    adapter's scaling; FiLM projections go to ``vision_backbone.<vit>_film.<i>``.
    """
    raw = {
        k.removeprefix("vision_backbone."): v
        for k, v in _load_component(root, "vision_backbone").items()
    }
    try:
        merged = merge_lora(raw, _lora_scaling(root))
    except LoraFormatError as err:
        raise BackboneError(f"{root}: vision_backbone file: {err}") from err
    state: dict[str, Tensor] = {}
    # Merged LoRA weights stay float32, not cast back to the file's bf16: upstream's inference
    # runs the LoRA branch unmerged beside the bf16 base weight, so rounding the sum to bf16 would
    # differ (~1e-2).
    for key, value in merged.items():
        parts = key.split(".")
        if parts[0] not in ("featurizer", "fused_featurizer"):
            raise BackboneError(f"vision_backbone file has key {key} outside the two ViTs")
        if parts[1] == "blocks" and parts[3] in ("scale", "shift"):
            key = f"{parts[0]}_film.{parts[2]}.{'.'.join(parts[3:])}"
        elif parts[1] == "blocks" and parts[3] == "block":
            key = ".".join(parts[:3] + parts[4:])
        state[_rename_layer_scale(f"vision_backbone.{key}")] = value
    return state


def _lora_scaling(root: Path) -> Callable[[str, int], float]:
    """alpha / r of the vision LoRA: from ``lora_adapter/adapter_config.json`` when present, else
    upstream inference's own rule (``_apply_film_to_vla``: ``lora_alpha=min(rank, 16)``)."""
    path = root / "lora_adapter" / "adapter_config.json"
    if path.is_file():
        return _adapter_scaling(path)
    return lambda module, rank: min(rank, 16) / rank


def _adapter_scaling(config_path: Path) -> Callable[[str, int], float]:
    config = json.loads(config_path.read_text())
    if config.get("use_dora"):
        raise BackboneError(
            f"{config_path}: use_dora is not supported (DoRA is not a weight delta)"
        )
    return adapter_scaling(config)


def merge_peft_adapter(state: dict[str, Tensor], adapter_dir: Path) -> None:
    """W += scaling * B @ A for every LoRA pair of a PEFT adapter folder (finetune.py's
    ``lora_adapter/``), in place."""
    config_path = adapter_dir / "adapter_config.json"
    if not config_path.is_file():
        raise BackboneError(f"{adapter_dir} is not a PEFT adapter folder (no adapter_config.json)")
    scaling = _adapter_scaling(config_path)
    weights_path = adapter_dir / "adapter_model.safetensors"
    if weights_path.is_file():
        weights = load_safetensors(weights_path)
    elif (adapter_dir / "adapter_model.bin").is_file():
        weights = load_torch(adapter_dir / "adapter_model.bin", weights_only=True)
    else:
        raise BackboneError(
            f"{adapter_dir} has no adapter weights (adapter_model.safetensors or .bin) to merge"
        )
    try:
        _, layers = split_lora(
            {k.removeprefix("base_model.model."): v for k, v in weights.items()},
            scaling,
            fan_in_fan_out=bool(json.loads(config_path.read_text()).get("fan_in_fan_out")),
        )
        for module, layer in layers.items():
            target = f"{module}.weight"
            if target not in state:
                raise BackboneError(f"LoRA adapter targets {target}, which the checkpoint lacks")
            state[target] = layer.merged(state[target]).to(state[target].dtype)
            if (bias := layer.merged_bias(state.get(f"{module}.bias"))) is not None:
                state[f"{module}.bias"] = bias.to(state[f"{module}.bias"].dtype)
    except LoraFormatError as err:
        raise BackboneError(f"{adapter_dir}: {err}") from err
