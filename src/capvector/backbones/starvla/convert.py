"""Loading a StarVLA run (starVLA/starVLA) into capvector's ``StarVLA`` backbone.

Kept apart from the model file, as transformers keeps its ``convert_*_original_to_hf.py`` scripts:
reading another project's layout is not model code. ``StarVLA.from_original`` is the entry point.

A run folder as StarVLA's trainer writes it (``starVLA/training/train_starvla.py``)::

    <run>/checkpoints/steps_N_pytorch_model.pt | steps_N_model.safetensors   (the framework state dict)
    <run>/config.yaml                  (``AccessTrackedConfig.save_accessed_config``: keys it read)
    <run>/dataset_statistics.json      (``gr00t_lerobot`` datasets' ``save_dataset_statistics``)

``share_tools.read_mode_config`` reads the same two files beside the checkpoint. The VLM's
architecture, tokenizer and image processor come from the Qwen-VL folder the run started from
(``framework.qwenvl.base_vlm``), passed as ``qwen_folder``; its weights are not read.

Every field of ``framework`` in ``config.yaml`` is either mapped onto the capvector config, checked
to hold the only value we implement, or known to have no effect on the model; any other field is an
error that names it. Sections outside ``framework`` are read only where they change the model
(``datasets.vla_data.CoT_prompt`` / ``obs_image_size``, ``trainer.repeated_diffusion_steps``).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from capvector.backbones.base import (
    BackboneError,
    OriginalCheckpoint,
    load_state_dict_strictly,
    merge_nested,
)
from capvector.backbones.common import read_required_json, rename_prefix
from capvector.io.loading import load_safetensors, load_torch

if TYPE_CHECKING:
    from capvector.backbones.starvla import StarVLA

# StarVLA framework (``framework.name``, ``FRAMEWORK_REGISTRY``) -> our head.
FRAMEWORK_HEADS = {"QwenOFT": "oft", "QwenGR00T": "gr00t", "QwenPI_v3": "layerwise"}
# ``GR00T_ActionHeader.DiTConfig``: DiT width and heads by ``action_model_type``.
DIT_SIZES = {"DiT-B": (768, 12), "DiT-L": (1536, 32)}
# StarVLA's QwenOFT query placeholder (``self.action_token``), an ordinary Qwen token.
OFT_QUERY_TOKEN = "\U0001f50d"
# ``gr00t_lerobot`` resizes every camera to 224 x 224 (``_pack_sample``) unless the run sets
# ``datasets.vla_data.obs_image_size``.
DEFAULT_CAMERA_SIZE = 224
# qwen_vl_utils' ``fetch_image`` (called by ``process_vision_info`` in StarVLA's wrappers) first
# resizes to multiples of 28 within these limits, before the Qwen processor's own smart_resize.
QWEN_VL_UTILS_FACTOR = 28
QWEN_VL_UTILS_PIXELS = (4 * 28 * 28, 16384 * 28 * 28)
# QwenPI_v3 reads ``trainer.repeated_diffusion_steps`` with this default; QwenGR00T reads
# ``framework.action_model.repeated_diffusion_steps`` with default 4.
PI_V3_REPEATS_DEFAULT = 16
GR00T_REPEATS_DEFAULT = 4
# LayerwiseFM_ActionHeader builds its state encoder and action decoder MLPs 1024 wide, whatever
# ``action_model.hidden_size`` says.
LAYERWISE_MLP_WIDTH = 1024


@dataclass
class StarVLARun:
    checkpoint: Path
    config: dict[str, Any]
    """config.yaml (``apply_config_compat`` applied: ``action_horizon`` filled from the legacy key)."""
    statistics: dict[str, Any]
    """dataset_statistics.json as written; ``{}`` when absent."""


def read_run(source: str | Path) -> StarVLARun:
    """A checkpoint file, or a run folder (its latest ``checkpoints/steps_N_*``)."""
    path = Path(source)
    if path.is_dir():
        found = sorted(
            (
                p
                for p in (path / "checkpoints").glob("steps_*")
                if p.suffix in (".pt", ".safetensors")
            ),
            key=lambda p: int(re.sub(r"\D", "", p.name.split("_")[1]) or 0),
        )
        if not found:
            raise BackboneError(
                f"{path} has no checkpoints/steps_N_pytorch_model.pt or .safetensors"
            )
        path = found[-1]
    if not path.is_file():
        raise BackboneError(f"StarVLA checkpoint {path} does not exist")
    if path.suffix not in (".pt", ".safetensors"):
        raise BackboneError(f"{path} is not a .pt or .safetensors StarVLA checkpoint")
    run_dir = path.parent.parent
    config_path = run_dir / "config.yaml"
    if not config_path.is_file():
        raise BackboneError(
            f"{config_path} is missing: StarVLA writes config.yaml beside checkpoints/ and the "
            "architecture is read from it (share_tools.read_mode_config needs it too)"
        )
    import yaml

    config = yaml.safe_load(config_path.read_text()) or {}
    _compat(config)
    stats_path = run_dir / "dataset_statistics.json"
    stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
    return StarVLARun(path, config, stats)


def _compat(config: dict[str, Any]) -> None:
    """``share_tools.apply_config_compat``, step 1: ``action_horizon`` is canonical, the legacy
    ``future_action_window_size`` is horizon - 1."""
    am = config.get("framework", {}).get("action_model", {})
    horizon, future = am.get("action_horizon"), am.get("future_action_window_size")
    if horizon is None and future is not None:
        am["action_horizon"] = int(future) + 1


def read_state(path: Path) -> dict[str, Tensor]:
    if path.suffix == ".safetensors":
        return load_safetensors(path)
    state = load_torch(path, weights_only=True)
    if not isinstance(state, Mapping):
        raise BackboneError(f"{path} does not hold a state dict")
    return dict(state)


# -- config.yaml -> StarVLAConfig fields -----------------------------------------------------------

# framework.action_model fields with no effect on the model we build.
_INERT_ACTION_MODEL = {
    "action_hidden_dim",  # OFT/GR00T: overwritten from the VLM width at runtime
    "past_action_window_size",  # checked to be 0 below
    "future_action_window_size",  # action_horizon - 1 (apply_config_compat)
}
_INERT_DIT = {
    "cross_attention_dim",  # the VLM width (GR00T) or the DiT width (PI_v3), set at runtime
    "input_embedding_dim",  # written by populate_layerwise_dit_cfg / ignored by GR00T's DiT
    "num_attention_heads",  # read below where upstream reads it
    "attention_head_dim",
    "num_layers",
    "action_dit_hidden_dim",
}


def _check_value(section: str, config: Mapping[str, Any], key: str, allowed: Any) -> None:
    if key in config and config[key] != allowed:
        raise BackboneError(
            f"StarVLA config field {section}.{key}={config[key]!r} is not supported (only "
            f"{allowed!r} is implemented)"
        )


def _reject_unknown(section: str, config: Mapping[str, Any], known: set[str]) -> None:
    unknown = sorted(set(config) - known)
    if unknown:
        raise BackboneError(
            f"StarVLA config fields {[f'{section}.{k}' for k in unknown]} are not supported by "
            "capvector's importer; they would change the model, so they are not ignored"
        )


def config_overrides(
    run: Mapping[str, Any],
    qwen_folder: Path,
    patch_factor: int,
    statistics: Mapping[str, Any],
) -> dict[str, Any]:
    """StarVLAConfig fields from a run's ``config.yaml`` (everything but the Qwen architecture)."""
    framework = dict(run.get("framework") or {})
    name = framework.get("name")
    if name not in FRAMEWORK_HEADS:
        raise BackboneError(
            f"StarVLA framework.name={name!r} is not supported; capvector imports "
            f"{sorted(FRAMEWORK_HEADS)}"
        )
    _reject_unknown("framework", framework, {"name", "qwenvl", "action_model"})
    _reject_unknown(
        "framework.qwenvl",
        framework.get("qwenvl") or {},
        {"base_vlm", "attn_implementation", "vl_hidden_dim", "num_vl_layers"},
    )
    head = FRAMEWORK_HEADS[name]
    am = dict(framework.get("action_model") or {})
    if "action_horizon" not in am or "action_dim" not in am:
        raise BackboneError(
            "the run's config.yaml has no framework.action_model.action_horizon / action_dim"
        )
    _check_value("framework.action_model", am, "past_action_window_size", 0)
    vla_data = (run.get("datasets") or {}).get("vla_data") or {}
    out: dict[str, Any] = {
        "head": head,
        "action_dim": int(am["action_dim"]),
        "chunk_size": int(am["action_horizon"]),
        "image_size": image_size(vla_data.get("obs_image_size"), qwen_folder, patch_factor),
    }
    if "CoT_prompt" in vla_data:
        # QWen*.build_qwenvl_inputs: the instruction (+ state + OFT suffix) replaces {instruction}.
        out["prompt_template"] = str(vla_data["CoT_prompt"])
    # The data loader put a state into each sample iff its statistics carry one
    # (gr00t_lerobot writes "state" statistics only for the state keys it uses).
    has_state = any(isinstance(v, Mapping) and v.get("state") for v in statistics.values())
    state_dim = int(statistics_state_dim(statistics) or am.get("state_dim") or 0)
    if head == "oft":
        _reject_unknown("framework.action_model", am, {"action_model_type", "action_dim",
                        "action_horizon", *_INERT_ACTION_MODEL})  # fmt: skip
        # MLP_ActionHeader.get_action_model reads action_model_type but always builds the
        # L1RegressionActionHead, so any value (released OFT configs say "DiT-B") means the MLP.
        out["head_args"] = {"query_token": OFT_QUERY_TOKEN}
        if has_state:  # QwenOFT.forward: add_discretized_state_to_instruction
            out.update(state_mode="prompt", proprio_dim=state_dim)
    elif head == "gr00t":
        out["head_args"] = _gr00t_head_args(am)
        if am.get("state_dim") and has_state:
            # QwenGR00T passes the sample's state to FlowmatchingActionHead: a state token.
            out.update(state_mode="head", proprio_dim=int(am["state_dim"]))
    else:
        trainer = run.get("trainer") or {}
        out["head_args"] = _layerwise_head_args(am, trainer)
        if has_state:  # QwenPI_v3: the state goes into the prompt; its state_encoder is unused
            out.update(state_mode="prompt", proprio_dim=state_dim)
    return out


def statistics_state_dim(statistics: Mapping[str, Any]) -> int:
    for entry in statistics.values():
        if isinstance(entry, Mapping) and entry.get("state"):
            return len(entry["state"].get("mean", []))
    return 0


_FLOW_COMMON = {
    "add_pos_embed", "max_seq_len", "noise_beta_alpha", "noise_beta_beta", "noise_s",
    "num_timestep_buckets", "num_inference_timesteps", "num_target_vision_tokens", "state_dim",
    "action_model_type", "action_dim", "action_horizon", "hidden_size", "diffusion_model_cfg",
    "repeated_diffusion_steps", *_INERT_ACTION_MODEL,
}  # fmt: skip
_DIT_KNOWN = {
    "dropout", "final_dropout", "interleave_self_attention", "use_canonical_forward", "norm_type",
    "positional_embeddings", "output_dim", *_INERT_DIT,
}  # fmt: skip


def _flow_args(am: Mapping[str, Any]) -> dict[str, Any]:
    _reject_unknown("framework.action_model", am, _FLOW_COMMON)
    _check_value("framework.action_model", am, "add_pos_embed", True)
    dit = dict(am.get("diffusion_model_cfg") or {})
    _reject_unknown("framework.action_model.diffusion_model_cfg", dit, _DIT_KNOWN)
    section = "framework.action_model.diffusion_model_cfg"
    _check_value(section, dit, "norm_type", "ada_norm")
    _check_value(section, dit, "final_dropout", True)
    # DiT's default is "sinusoidal" (added to the normed tokens in every block), which we do not
    # build; StarVLA's frameworks set None.
    if dit.get("positional_embeddings", "sinusoidal") is not None:
        raise BackboneError(
            f"StarVLA config field {section}.positional_embeddings="
            f"{dit.get('positional_embeddings', 'sinusoidal (the DiT default)')!r} is not "
            "supported (only None is implemented)"
        )
    args: dict[str, Any] = {
        "dropout": float(dit.get("dropout", 0.1)),  # DiT's default
        "num_inference_steps": int(am.get("num_inference_timesteps") or 0),
    }
    for ours, theirs in (
        ("max_seq_len", "max_seq_len"),
        ("noise_beta_alpha", "noise_beta_alpha"),
        ("noise_beta_beta", "noise_beta_beta"),
        ("noise_s", "noise_s"),
        ("num_timestep_buckets", "num_timestep_buckets"),
        ("num_future_tokens", "num_target_vision_tokens"),
    ):
        if theirs in am:
            args[ours] = am[theirs]
    if not args["num_inference_steps"]:
        raise BackboneError("framework.action_model.num_inference_timesteps is missing")
    interleave = dit.get("interleave_self_attention", False)
    if dit.get("use_canonical_forward") is not None:  # DiT.__init__: the alias wins
        interleave = bool(dit["use_canonical_forward"])
    args["interleave_self_attention"] = bool(interleave)
    return args


def _gr00t_head_args(am: Mapping[str, Any]) -> dict[str, Any]:
    args = _flow_args(am)
    dit = dict(am.get("diffusion_model_cfg") or {})
    kind = am.get("action_model_type")
    if "num_attention_heads" in dit and "attention_head_dim" in dit:
        # FlowmatchingActionHead builds DiT(**{**DiTConfig[type], **diffusion_model_cfg}): the
        # run's heads x head_dim win for the DiT; its encoders use DiTConfig[type]'s width, which
        # must agree for the model to run at all.
        heads, head_dim = int(dit["num_attention_heads"]), int(dit["attention_head_dim"])
        width = heads * head_dim
        if kind in DIT_SIZES and DIT_SIZES[kind][0] != width:
            raise BackboneError(
                f"{kind} is {DIT_SIZES[kind][0]} wide but diffusion_model_cfg gives "
                f"{heads} x {head_dim} = {width}"
            )
    elif kind in DIT_SIZES:
        width, heads = DIT_SIZES[kind]
    else:
        raise BackboneError(
            f"StarVLA config field framework.action_model.action_model_type={kind!r} is not "
            f"supported (known DiT sizes: {sorted(DIT_SIZES)})"
        )
    hidden = int(am.get("hidden_size", 1024))
    output_dim = int(dit.get("output_dim", hidden))  # apply_config_compat fills it from hidden_size
    if output_dim != hidden:
        raise BackboneError(
            f"StarVLA config field framework.action_model.diffusion_model_cfg.output_dim="
            f"{output_dim} differs from hidden_size={hidden}: not supported (the DiT output is "
            "the action decoder's input, which we build hidden_size wide)"
        )
    args.update(
        width=width,
        num_heads=heads,
        hidden_size=hidden,
        num_layers=int(dit.get("num_layers", 12)),  # DiT's default
        repeated_diffusion_steps=int(am.get("repeated_diffusion_steps", GR00T_REPEATS_DEFAULT)),
    )
    return args


def _layerwise_head_args(am: Mapping[str, Any], trainer: Mapping[str, Any]) -> dict[str, Any]:
    args = _flow_args(am)
    dit = dict(am.get("diffusion_model_cfg") or {})
    width = dit.get("action_dit_hidden_dim")
    if width is None:
        raise BackboneError(
            "framework.action_model.diffusion_model_cfg.action_dit_hidden_dim is missing: a "
            "full-width QwenPI_v3 head (as wide as the VLM) is not supported"
        )
    head_dim = int(dit.get("attention_head_dim") or 64)  # populate_layerwise_dit_cfg
    args.update(
        width=int(width),
        num_heads=int(width) // head_dim,
        hidden_size=LAYERWISE_MLP_WIDTH,
        # QwenPI_v3.forward reads the trainer section, not action_model.repeated_diffusion_steps.
        repeated_diffusion_steps=int(
            trainer.get("repeated_diffusion_steps", PI_V3_REPEATS_DEFAULT)
        ),
    )
    return args


# -- images ------------------------------------------------------------------------------------------


def smart_resize(
    height: int, width: int, factor: int, min_pixels: int, max_pixels: int
) -> tuple[int, int]:
    """transformers' ``qwen2_vl.image_processing_qwen2_vl.smart_resize`` (same as qwen_vl_utils')."""
    h_bar = round(height / factor) * factor
    w_bar = round(width / factor) * factor
    if h_bar * w_bar > max_pixels:
        beta = math.sqrt((height * width) / max_pixels)
        h_bar = max(factor, math.floor(height / beta / factor) * factor)
        w_bar = max(factor, math.floor(width / beta / factor) * factor)
    elif h_bar * w_bar < min_pixels:
        beta = math.sqrt(min_pixels / (height * width))
        h_bar = math.ceil(height * beta / factor) * factor
        w_bar = math.ceil(width * beta / factor) * factor
    return h_bar, w_bar


def processor_pixel_limits(qwen_folder: Path) -> tuple[int, int]:
    """(min_pixels, max_pixels) of the folder's Qwen image processor (``preprocessor_config.json``)."""
    why = (
        "the Qwen processor's min_pixels/max_pixels decide the image resolution StarVLA trained at"
    )
    path = qwen_folder / "preprocessor_config.json"
    pre = read_required_json(path, why)
    size = pre.get("size") or {}
    low = pre.get("min_pixels") or size.get("shortest_edge")
    high = pre.get("max_pixels") or size.get("longest_edge")
    if low is None or high is None:
        raise BackboneError(
            f"{path} gives no min_pixels/max_pixels (or size.shortest/longest_edge)"
        )
    return int(low), int(high)


def image_size(obs_image_size: Any, qwen_folder: Path, patch_factor: int) -> int:
    """The resolution the Qwen-VL saw: the camera size (``obs_image_size`` or 224) through
    qwen_vl_utils' resize and then the processor's ``smart_resize`` (Qwen3-VL's ``min_pixels``
    upsamples 224-px cameras to 256 px)."""
    if obs_image_size is None:
        height = width = DEFAULT_CAMERA_SIZE
    elif isinstance(obs_image_size, int):
        height = width = obs_image_size
    else:
        width, height = (int(v) for v in obs_image_size)  # PIL's (width, height), resize_images
    height, width = smart_resize(height, width, QWEN_VL_UTILS_FACTOR, *QWEN_VL_UTILS_PIXELS)
    low, high = processor_pixel_limits(qwen_folder)
    height, width = smart_resize(height, width, patch_factor, low, high)
    if height != width:
        raise BackboneError(
            f"the run's images are processed at {width} x {height}; capvector's StarVLA supports "
            "square images only"
        )
    return height


# -- statistics ---------------------------------------------------------------------------------------


def convert_statistics(statistics: Mapping[str, Any]) -> dict[str, Any]:
    """StarVLA's ``dataset_statistics.json`` (per embodiment tag: ``action`` with ``mask``, ``state``,
    counts) -> capvector's schema (``capvector.data.statistics``): ``state`` becomes ``proprio``,
    the rest keeps its name. The mask keeps StarVLA's meaning (False = binary-normalised, not
    de-normalised), which is also ours (False = left raw)."""
    out: dict[str, Any] = {}
    for tag, entry in statistics.items():
        if not isinstance(entry, Mapping):
            raise BackboneError(f"dataset_statistics.json entry {tag!r} is not an object")
        converted: dict[str, Any] = {}
        for key, value in entry.items():
            converted["proprio" if key == "state" else key] = value
        converted.setdefault("proprio", {})
        if "action" not in converted:
            raise BackboneError(f"dataset_statistics.json entry {tag!r} has no action statistics")
        converted["action"] = dict(converted["action"])
        converted["action"].setdefault("mask", [True] * len(converted["action"].get("mean", [])))
        out[tag] = converted
    return out


# -- state dict --------------------------------------------------------------------------------------

# StarVLA framework attribute -> ours. transformers >= 4.52 (StarVLA pins 4.57) names the
# Qwen-VL's submodules model.visual / model.language_model; older runs saved visual.* / model.*.
STARVLA_PREFIXES = (
    ("qwen_vl_interface.model.model.visual.", "vlm.model.visual."),
    ("qwen_vl_interface.model.model.language_model.", "vlm.model.language_model."),
    ("qwen_vl_interface.model.visual.", "vlm.model.visual."),
    ("qwen_vl_interface.model.model.", "vlm.model.language_model."),
    ("qwen_vl_interface.model.lm_head.", "vlm.lm_head."),
    ("action_model.", "action_head."),
    ("project_layers.", "action_head.projectors."),  # QwenPI_v3's per-layer projectors
)


def starvla_key_map(
    state: Mapping[str, Tensor], head: str, *, uses_state_encoder: bool, tied: bool
) -> dict[str, Tensor]:
    """StarVLA framework state dict -> ours. Keys of modules StarVLA builds but never runs are
    dropped by name; any other unknown key is left for the strict loader to report."""
    dropped: list[str] = []
    if not uses_state_encoder:
        # StarVLA builds a state encoder whenever state_dim is set, also when the state goes into
        # the prompt (QwenPI_v3) or is never given.
        dropped.append("action_model.state_encoder.")
    if head == "layerwise":
        # LayerwiseFM's DiT builds GR00T's output projection but its forward skips it
        # (``return_pre_output=True``).
        dropped += ["action_model.model.proj_out_1.", "action_model.model.proj_out_2."]
    mapped: dict[str, Tensor] = {}
    for key, value in state.items():
        if key.startswith(tuple(dropped)):
            continue
        mapped[rename_prefix(key, STARVLA_PREFIXES)] = value
    if tied:
        mapped.pop("vlm.lm_head.weight", None)  # the embedding matrix under a second name
    return mapped


def merged_overrides(
    derived: Mapping[str, Any], overrides: Mapping[str, Any] | None
) -> dict[str, Any]:
    """The run's values, then the caller's (a nested mapping changes only the fields it names)."""
    return merge_nested(dict(derived), dict(overrides or {}))


def load_original(
    cls: type[StarVLA],
    source: str | Path,
    preset: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    qwen_folder: str | Path | None = None,
) -> OriginalCheckpoint:
    """A StarVLA run (its folder or ``checkpoints/steps_N_*`` file) with the Qwen-VL folder it
    started from, read by this module (config.yaml -> config, key map, statistics); or,
    without ``qwen_folder``, a plain transformers Qwen-VL folder as the VLM with a fresh head
    (``from_qwen``).

    For a run, ``preset`` defaults to the full-size preset of the run's framework and Qwen
    version; the run's config.yaml then sets every field it decides, and ``overrides`` last.
    """
    if qwen_folder is None:
        model = cls.from_qwen(source, preset or "starvla-qwen2.5-vl-3b-oft", **(overrides or {}))
        return OriginalCheckpoint(model, {})
    return _from_run(cls, source, Path(qwen_folder), preset, overrides)


def _from_run(
    cls: type[StarVLA],
    source: str | Path,
    qwen_folder: Path,
    preset: str | None,
    overrides: Mapping[str, Any] | None,
) -> OriginalCheckpoint:
    from capvector.backbones.starvla.configuration import QWEN_VERSIONS
    from capvector.backbones.starvla.modeling import (
        _architecture,
        _check_model_type,
        _folder,
        _load_tokenizer,
        _qwen_version,
        _read_image_statistics,
        _starvla_config,
        _tied,
    )

    run = read_run(source)
    root = _folder(qwen_folder)
    model_type = json.loads((root / "config.json").read_text()).get("model_type")
    versions = [k for k, v in QWEN_VERSIONS.items() if v.model_type == model_type]
    if not versions:
        raise BackboneError(
            f"{root} holds a {model_type!r} model; StarVLA runs on {sorted(QWEN_VERSIONS)} import"
        )
    version = QWEN_VERSIONS[versions[0]]
    config_class, model_class = version.classes()
    hf_config = config_class.from_pretrained(str(root))
    vision = hf_config.vision_config
    derived = config_overrides(
        run.config, root, vision.patch_size * vision.spatial_merge_size, run.statistics
    )
    derived["qwen_version"] = versions[0]
    head = derived["head"]
    if preset is None:
        size = "4b" if versions[0] == "qwen3-vl" else "3b"
        preset = f"starvla-{versions[0]}-{size}-{head}"
    config = _starvla_config(preset, merged_overrides(derived, overrides))
    # The run decides every head field: the preset's head_args (e.g. a tiny preset's, or another
    # head's) do not leak in; the caller's head_args still change the fields they name.
    config.head_args = merged_overrides(
        derived["head_args"], (overrides or {}).get("head_args") or {}
    )
    _check_model_type(root, _qwen_version(config.qwen_version), config.qwen_version)
    config.qwen = _architecture(hf_config)
    _read_image_statistics(root, config)
    config.tokenizer = str(root)
    # fp32 as from_qwen; transformers would otherwise build in the folder's dtype (bf16).
    vlm = model_class._from_config(
        hf_config, attn_implementation=config.attn_implementation, dtype=torch.float32
    )
    model = cls(config, vlm=vlm, tokenizer=_load_tokenizer(str(root)))
    # The run's state encoder is dropped only where StarVLA never runs it (decided from the run,
    # not from the model we built): overriding a state-trained GR00T run to state_mode='none'
    # then fails on its unexpected state_encoder keys instead of silently losing the state token.
    state = starvla_key_map(
        read_state(run.checkpoint),
        config.head,
        uses_state_encoder=derived.get("state_mode") == "head",
        tied=_tied(model),
    )
    load_state_dict_strictly(model, state, source=str(run.checkpoint))
    return OriginalCheckpoint(
        model,
        convert_statistics(run.statistics),
        {"config.yaml": run.config, "dataset_statistics.json": run.statistics},
    )
