"""Conversion of LeRobot's pi05 policy folders (openpi's PyTorch key layout) into ``Pi05``.

Kept apart from the model file, as HF keeps ``convert_*_original_to_hf.py`` beside ``modeling_*``:
loading another project's layout is not model code. ``Pi05.from_original`` (``VLABackbone.from_original``) is the entry point and
delegates to ``load_lerobot_policy``.

A LeRobot policy folder (``PI05Policy.save_pretrained`` + the processors' ``save_pretrained``):

- ``config.json``: the serialised ``PI05Config`` (LeRobot
  ``src/lerobot/policies/pi05/configuration_pi05.py``); every field is mapped onto ``Pi05Config``,
  required to hold the one value we implement, or listed in ``_RUNTIME_FIELDS`` with the reason it
  does not describe the model. Any other field is an error naming it.
- ``model.safetensors``: openpi's PyTorch key names under LeRobot's ``model.`` prefix, written by
  ``safetensors.torch.save_model``, which keeps one of PaliGemma's tied tensors (``lm_head``).
- ``policy_preprocessor.json`` + ``policy_preprocessor_step_K_normalizer_processor.safetensors``:
  the dataset statistics (``<feature>.<stat>`` tensors) the normaliser step uses.

An openpi PyTorch folder (``examples/convert_jax_model_to_pytorch.py``, ``scripts/train_pytorch.py``)
is read by ``load_openpi_checkpoint``: ``model.safetensors`` (the same keys without ``model.``),
the converter's five-field ``config.json`` and ``assets/<asset_id>/norm_stats.json``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from capvector.backbones.base import (
    BackboneError,
    OriginalCheckpoint,
    load_state_dict_strictly,
    merge_nested,
    preset_config,
)
from capvector.backbones.common import rename_prefix
from capvector.io.loading import load_safetensors

if TYPE_CHECKING:
    from capvector.backbones.pi05 import Pi05

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
PREPROCESSOR_FILE = "policy_preprocessor.json"
TRAIN_CONFIG_FILE = "train_config.json"
DEFAULT_DATASET_NAME = "lerobot"
"""Statistics key when the folder does not name its dataset (``train_config.json``)."""

# -- state-dict keys --------------------------------------------------------------------------

# openpi / LeRobot key prefix -> ours. Everything below a prefix keeps its name (layers.L.self_attn.
# q_proj.weight, ….input_layernorm.dense.bias, vision_model.encoder.layers.L.mlp.fc1.bias, ...).
_ORIGINAL_PREFIXES = (
    ("paligemma_with_expert.paligemma.model.vision_tower.", "vision_tower."),
    ("paligemma_with_expert.paligemma.model.multi_modal_projector.", "multi_modal_projector."),
    ("paligemma_with_expert.paligemma.model.language_model.", "language_model."),
    ("paligemma_with_expert.gemma_expert.model.", "action_expert."),
    ("action_in_proj.", "action_in_proj."),
    ("action_out_proj.", "action_out_proj."),
    ("time_mlp_in.", "time_mlp_in."),
    ("time_mlp_out.", "time_mlp_out."),
)
# PaliGemma ties its embedding to lm_head; the file often holds only lm_head (LeRobot #2307, and
# every folder LeRobot's save_pretrained writes: save_model keeps one tensor of a tied pair).
_ORIGINAL_LM_HEAD = "paligemma_with_expert.paligemma.lm_head.weight"
_EMBEDDING = "language_model.embed_tokens.weight"
# Present because the expert is built as GemmaForCausalLM (openpi gemma_pytorch.py), never used.
_ORIGINAL_UNUSED = (
    "paligemma_with_expert.gemma_expert.lm_head.weight",
    "paligemma_with_expert.gemma_expert.model.embed_tokens.weight",
)
_LEROBOT_PREFIX = "model."
"""LeRobot's ``PI05Policy`` holds the openpi module as ``self.model``."""


def original_to_capvector(state: Mapping[str, Tensor], source: str) -> dict[str, Tensor]:
    """openpi/LeRobot pi05 keys -> ours. Unknown keys are kept as they are, so the strict load
    reports them as unexpected."""
    out: dict[str, Tensor] = {}
    lm_head = None
    for raw_key, value in state.items():
        key = raw_key.removeprefix(_LEROBOT_PREFIX)
        if key in _ORIGINAL_UNUSED:
            continue
        if key == _ORIGINAL_LM_HEAD:
            lm_head = value
            continue
        out[rename_prefix(key, _ORIGINAL_PREFIXES)] = value
    if lm_head is not None:
        if _EMBEDDING in out and not torch.equal(out[_EMBEDDING], lm_head):
            raise BackboneError(
                f"{source} holds both `{_ORIGINAL_LM_HEAD}` and the token embedding and they differ; "
                "PaliGemma ties them, so this backbone cannot represent the checkpoint"
            )
        out.setdefault(_EMBEDDING, lm_head)
    return out


def capvector_to_original(key: str) -> str:
    """Our key -> its openpi/LeRobot name (without LeRobot's ``model.`` prefix)."""
    if key == _EMBEDDING:
        return _ORIGINAL_LM_HEAD
    return rename_prefix(key, ((new, old) for old, new in _ORIGINAL_PREFIXES))


# -- config.json ------------------------------------------------------------------------------

# PI05Config fields with the same name and meaning in Pi05Config.
_SAME_NAME_FIELDS = (
    "chunk_size",
    "max_action_dim",
    "num_inference_steps",
    "time_sampling_beta_alpha",
    "time_sampling_beta_beta",
    "time_sampling_scale",
    "time_sampling_offset",
    "min_period",
    "max_period",
    "tokenizer_max_length",
)
# Fields read below into other Pi05Config fields (or checked against what we implement).
_MAPPED_FIELDS = ("type", "input_features", "output_features", "image_resolution")
# Fields that must hold the value we implement: (value, what to do otherwise). LeRobot fields added
# after 0.4.4 (MEM, relative actions, RTC training) are accepted at their off values.
_REQUIRED_VALUES: dict[str, tuple[Any, str]] = {
    "n_obs_steps": (1, "Pi0.5 reads one observation step"),
    "empty_cameras": (
        0,
        "add the empty cameras to the data as black images with image_mask False instead",
    ),
    "rtc_config": (None, "real-time chunking is not implemented"),
    "use_peft": (False, "merge the PEFT adapter into the weights with LeRobot first"),
    "paligemma_variant": ("gemma_2b", "only PaliGemma's Gemma-2B stream is implemented"),
    "action_expert_variant": ("gemma_300m", "only the Gemma-300M action expert is implemented"),
    "use_visual_memory": (False, "MEM visual memory is not implemented"),
    "use_proprioceptive_memory": (False, "MEM proprioceptive memory is not implemented"),
    "use_relative_actions": (False, "relative actions are not implemented"),
    "rtc_training_max_delay": (0, "real-time chunking training is not implemented"),
}
# Fields that only describe settings of the MEM / relative-action features refused above.
_INERT_FIELDS = (
    "memory_frames",
    "memory_stride",
    "memory_temporal_attention_every",
    "relative_exclude_joints",
    "action_feature_names",
)
# The lists above and below cover every field PI05Config and its PreTrainedConfig base have had in
# LeRobot's history up to commit 7427f31 (2026-08).
# Fields that do not describe the model: where it runs and in which precision, how many of the
# predicted actions a LeRobot rollout executes (capvector's evaluation has its own replanning
# setting), hub metadata, and LeRobot's training-loop presets (capvector's recipes set these).
_RUNTIME_FIELDS = (
    "device",
    "dtype",
    "use_amp",
    "push_to_hub",
    "repo_id",
    "private",
    "tags",
    "license",
    "pretrained_path",
    "pretrained_revision",
    "n_action_steps",
    "gradient_checkpointing",
    "compile_model",
    "compile_mode",
    "freeze_vision_encoder",
    "train_expert_only",
    "optimizer_lr",
    "optimizer_betas",
    "optimizer_eps",
    "optimizer_weight_decay",
    "optimizer_grad_clip_norm",
    "scheduler_warmup_steps",
    "scheduler_decay_steps",
    "scheduler_decay_lr",
    "max_state_dim",  # see ``prompt_state_dim``: the folder does not say whether it padded the state
)
# LeRobot's default mapping (configuration_pi05.py): quantile normalisation of state and action,
# images as they are. The only one our data pipeline implements for Pi0.5 (see statistics.py).
_NORMALIZATION = {"VISUAL": "IDENTITY", "STATE": "QUANTILES", "ACTION": "QUANTILES"}


def config_from_lerobot(upstream: Mapping[str, Any], source: str) -> dict[str, Any]:
    """``Pi05Config`` field values read from a LeRobot ``PI05Config`` dict (its config.json)."""
    if upstream.get("type", "pi05") != "pi05":
        raise BackboneError(
            f"{source} is a {upstream['type']!r} policy, not pi05 (Pi0 has a state token and other "
            "projections; it does not load into this backbone)"
        )
    known = {
        *_SAME_NAME_FIELDS,
        *_MAPPED_FIELDS,
        *_REQUIRED_VALUES,
        *_INERT_FIELDS,
        *_RUNTIME_FIELDS,
        "normalization_mapping",
    }
    unknown = sorted(set(upstream) - known)
    if unknown:
        raise BackboneError(
            f"{source} has LeRobot config field(s) {unknown} that the Pi0.5 import does not know; "
            "they may change the model, so it refuses rather than ignore them"
        )
    for name, (value, advice) in _REQUIRED_VALUES.items():
        if name in upstream and upstream[name] != value:
            raise BackboneError(
                f"{source}: {name}={upstream[name]!r} is not supported (only {value!r}); {advice}"
            )
    mapping = upstream.get("normalization_mapping", _NORMALIZATION)
    if dict(mapping) != _NORMALIZATION:
        raise BackboneError(
            f"{source}: normalization_mapping={dict(mapping)} is not supported; only LeRobot's "
            f"Pi0.5 default {_NORMALIZATION} (quantiles, as openpi) is implemented"
        )

    values: dict[str, Any] = {
        name: upstream[name] for name in _SAME_NAME_FIELDS if name in upstream
    }
    if "image_resolution" in upstream:
        height, width = upstream["image_resolution"]
        if height != width:  # LeRobot refuses these as well (modeling_pi05.py PI05Pytorch)
            raise BackboneError(
                f"{source}: image_resolution {height}x{width} is not square; PaliGemma takes "
                "square images (image_size)"
            )
        values["image_size"] = int(height)
    features = {**upstream.get("input_features", {}), **upstream.get("output_features", {})}
    cameras = [k for k, f in features.items() if f.get("type") == "VISUAL"]
    if cameras:
        values["num_images"] = len(cameras)
    states = [(k, f) for k, f in features.items() if f.get("type") == "STATE"]
    if len(states) > 1:
        raise BackboneError(f"{source}: {len(states)} STATE features; Pi0.5 reads one state vector")
    if states:
        values["proprio_dim"] = int(np.prod(states[0][1]["shape"]))
    actions = [f for f in features.values() if f.get("type") == "ACTION"]
    if actions:
        values["action_dim"] = int(np.prod(actions[0]["shape"]))
    other = sorted(
        k for k, f in features.items() if f.get("type") not in ("VISUAL", "STATE", "ACTION")
    )
    if other:
        raise BackboneError(f"{source}: input/output feature(s) {other} are not supported")
    # LeRobot's PI05Policy.forward averages the flow loss over the real action dims only.
    values["loss_include_padded_dims"] = False
    return values


# -- statistics -------------------------------------------------------------------------------


def read_lerobot_statistics(root: Path, action_dim: int, proprio_dim: int) -> dict[str, Any]:
    """The normaliser step's statistics in capvector's schema (``capvector.data.statistics``),
    ``{}`` when the folder has no preprocessor (weights-only folders, e.g. ``pi05_base``)."""
    from capvector.data.lerobot import statistics_from_lerobot
    from capvector.data.statistics import QUANTILES

    path = root / PREPROCESSOR_FILE
    if not path.is_file():
        return {}
    steps = json.loads(path.read_text()).get("steps", [])
    files = [s["state_file"] for s in steps if s.get("registry_name") == "normalizer_processor"]
    if not files:
        return {}
    if len(files) > 1:
        raise BackboneError(f"{path} has {len(files)} normaliser steps; expected one")
    flat = load_safetensors(root / files[0])
    stats: dict[str, dict[str, np.ndarray]] = {}
    for key, value in flat.items():
        feature, _, stat = key.rpartition(".")
        stats.setdefault(feature, {})[stat] = value.to(torch.float64).numpy()
    name = DEFAULT_DATASET_NAME
    train_config = root / TRAIN_CONFIG_FILE
    if train_config.is_file():
        name = json.loads(train_config.read_text()).get("dataset", {}).get("repo_id") or name
    # LeRobot normalises every dimension, the gripper too (no OFT mask), without clipping.
    entry = statistics_from_lerobot(
        stats, num_trajectories=0, state_key="observation.state", normalization=QUANTILES
    )
    if entry is None:
        raise BackboneError(
            f"{root / files[0]} lacks q01/q99 (or mean/std/min/max) of `action` or "
            "`observation.state`; QUANTILES normalisation needs them"
        )
    dims = (len(entry["action"]["q01"]), len(entry["proprio"]["q01"]))
    if dims != (action_dim, proprio_dim):
        raise BackboneError(
            f"{root / files[0]} describes (action, state) dims {dims} but config.json says "
            f"{(action_dim, proprio_dim)}"
        )
    return {name: entry}


# -- openpi ------------------------------------------------------------------------------------

# config.json of openpi's examples/convert_jax_model_to_pytorch.py: {action_dim, action_horizon,
# paligemma_variant, action_expert_variant, precision}.
_OPENPI_REQUIRED = {
    "paligemma_variant": "gemma_2b",
    "action_expert_variant": "gemma_300m",
}
# openpi's PyTorch preprocessing always feeds these three cameras at 224 px
# (src/openpi/models_pytorch/preprocessing_pytorch.py IMAGE_KEYS, IMAGE_RESOLUTION).
_OPENPI_CAMERAS = 3
_OPENPI_IMAGE_SIZE = 224
NORM_STATS_FILE = "norm_stats.json"


def is_openpi_config(upstream: Mapping[str, Any]) -> bool:
    """openpi's converter writes ``action_horizon``; LeRobot's PI05Config has ``chunk_size``."""
    return "action_horizon" in upstream and "type" not in upstream


def config_from_openpi(upstream: Mapping[str, Any], source: str) -> dict[str, Any]:
    """``Pi05Config`` values from the converter's config.json. openpi's ``action_dim`` is the padded
    model width (``max_action_dim`` here); the real dims come from the norm stats. It does not record
    ``pi05`` or ``discrete_state_input``: a ``pi05_libero``-style model trained without the state
    (``discrete_state_input=False``) needs ``overrides={"proprio_dim": 0}``."""
    unknown = sorted(
        set(upstream) - {"action_dim", "action_horizon", "precision", *_OPENPI_REQUIRED}
    )
    if unknown:
        raise BackboneError(
            f"{source} has openpi config field(s) {unknown} the import does not know"
        )
    for name, value in _OPENPI_REQUIRED.items():
        if name in upstream and upstream[name] != value:
            raise BackboneError(
                f"{source}: {name}={upstream[name]!r} is not supported (only {value!r})"
            )
    values: dict[str, Any] = {
        "num_images": _OPENPI_CAMERAS,
        "image_size": _OPENPI_IMAGE_SIZE,
        # openpi pi0.py compute_loss / train_pytorch.py: the MSE over all action_dim (padded) dims.
        "loss_include_padded_dims": True,
        # pi0_pytorch.py sample_actions: `time += dt` on a float32 tensor.
        "accumulate_time": True,
    }
    if "action_horizon" in upstream:
        values["chunk_size"] = int(upstream["action_horizon"])
    if "action_dim" in upstream:
        values["max_action_dim"] = int(upstream["action_dim"])
    return values


def read_openpi_statistics(root: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``assets/<asset_id>/norm_stats.json`` (``openpi.shared.normalize.save``) in capvector's schema,
    keyed by the asset id, and the norm stats as read; ``({}, {})`` without an assets folder."""
    files = sorted((root / "assets").glob(f"*/{NORM_STATS_FILE}"))
    if not files:
        return {}, {}
    if len(files) > 1:
        raise BackboneError(
            f"{root}/assets holds norm stats of {len(files)} assets "
            f"({[f.parent.name for f in files]}); keep the one the model was trained with"
        )
    raw = json.loads(files[0].read_text())
    stats = raw.get("norm_stats", {})
    missing = [k for k in ("actions", "state") if not {"q01", "q99"} <= set(stats.get(k, {}))]
    if missing:
        raise BackboneError(f"{files[0]} lacks q01/q99 of {missing}; Pi0.5 normalises by quantiles")

    def convert(entry: Mapping[str, Any]) -> dict[str, list[float]]:
        return {
            k: np.asarray(v, np.float64).reshape(-1).tolist()
            for k, v in entry.items()
            if v is not None
        }

    from capvector.data.statistics import QUANTILES

    action = convert(stats["actions"])
    entry = {
        # openpi's norm stats have mean/std/q01/q99 (no min/max) and normalise every dimension.
        "action": {**action, "mask": [True] * len(action["q01"])},
        "proprio": convert(stats["state"]),
        "num_transitions": 0,
        "num_trajectories": 0,
        "normalization": QUANTILES,
    }
    return {files[0].parent.name: entry}, {str(files[0].relative_to(root)): raw}


# -- the loader -------------------------------------------------------------------------------


def load_original(
    cls: type[Pi05],
    source: str | Path,
    preset: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    tokenizer: str | Path | None = None,
) -> OriginalCheckpoint:
    """Load a LeRobot pi05 policy folder or an openpi PyTorch checkpoint strictly, with its
    config and statistics.

    The folder is what LeRobot's ``PI05Policy.save_pretrained`` and its processors'
    ``save_pretrained`` write: ``model.safetensors`` (openpi PyTorch key names, optionally under
    ``model.``), ``config.json`` (``PI05Config``: chunk size, action and state dims, cameras,
    ``max_action_dim``, inference steps, time sampling, image resolution, tokenizer length,
    normalisation mapping) and ``policy_preprocessor*`` (the dataset statistics, returned
    converted to capvector's schema). ``preset`` gives the architecture sizes; ``overrides``
    changes named fields last (e.g. ``{"chunk_size": 10}`` to fine-tune with another horizon,
    ``{"prompt_state_dim": 32}`` for a LeRobot <= 0.4.4 policy). An openpi folder
    (``convert_jax_model_to_pytorch.py`` / ``train_pytorch.py``: the same keys without
    ``model.``, a five-field ``config.json``, ``assets/<asset_id>/norm_stats.json``) gives the
    horizon, ``max_action_dim`` and, from the norm stats, the action and state dims; openpi always
    feeds 3 cameras at 224 px. PaliGemma's tokenizer is not
    part of these folders: pass ``tokenizer=<folder>`` (a ``google/paligemma-3b-pt-224``
    download) or keep its files beside the weights.
    """
    from capvector.backbones.pi05 import Pi05Config

    root = Path(source)
    tokenizer = None if tokenizer is None else str(tokenizer)
    preset = preset or "pi05-3b"
    if not root.is_dir():
        raise BackboneError(f"checkpoint folder {source} does not exist")
    weights = root / WEIGHTS_FILE
    if not weights.is_file():
        raise BackboneError(f"{root} has no {WEIGHTS_FILE} (the LeRobot pi05 layout)")
    upstream: dict[str, Any] = {}
    values: dict[str, Any] = {}
    openpi_stats: dict[str, Any] = {}
    files: dict[str, Any] = {}
    if (root / CONFIG_FILE).is_file():
        upstream = json.loads((root / CONFIG_FILE).read_text())
    if is_openpi_config(upstream):
        values = config_from_openpi(upstream, str(root / CONFIG_FILE))
        openpi_stats, files = read_openpi_statistics(root)
        if openpi_stats:  # the real (unpadded) dims the model was trained on
            (entry,) = openpi_stats.values()
            values["action_dim"] = len(entry["action"]["q01"])
            values["proprio_dim"] = len(entry["proprio"]["q01"])
    elif upstream:
        values = config_from_lerobot(upstream, str(root / CONFIG_FILE))
    if tokenizer is not None:
        values["tokenizer"] = str(tokenizer)
    elif (root / "tokenizer_config.json").is_file():
        values["tokenizer"] = str(root)
    config = preset_config(preset, **merge_nested(values, overrides or {}))
    if not isinstance(config, Pi05Config):
        raise BackboneError(f"preset {preset!r} is not a pi05 preset")
    model = cls(config)
    state = original_to_capvector(load_safetensors(weights), source=str(weights))
    missing = sorted(set(model.state_dict()) - set(state))
    if missing:
        names = ", ".join(f"`{capvector_to_original(k)}`" for k in missing[:3])
        more = " ..." if len(missing) > 3 else ""
        raise BackboneError(
            f"{weights} lacks {len(missing)} tensor(s) of the pi05 layout, e.g. {names}{more}. "
            f"Is it a complete pi05 checkpoint of the same size as preset {preset!r}?"
        )
    load_state_dict_strictly(model, state, source=str(weights))
    statistics = openpi_stats or read_lerobot_statistics(
        root, config.action_dim, config.proprio_dim
    )
    files[CONFIG_FILE] = upstream
    if (root / PREPROCESSOR_FILE).is_file():
        files[PREPROCESSOR_FILE] = json.loads((root / PREPROCESSOR_FILE).read_text())
    return OriginalCheckpoint(model, statistics, files)
