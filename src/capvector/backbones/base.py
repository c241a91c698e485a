"""The backbone contract every VLA family implements, and the preset registry.

A backbone is an ``nn.Module`` that turns a batch (``capvector.data.batch.Batch``) into an action
loss and whatever auxiliary objectives need: hidden states of requested layers, a mask of the
visual-token positions and, when asked, language-model logits. Objectives only use this contract, never a
family's internals, so every objective works with every backbone.

A VLA family is a config dataclass (subclass of ``BackboneConfig``) with preset functions decorated
with ``@register_preset``, a module (subclass of ``VLABackbone``) and, to read the original
project's checkpoints, a loader module. The built-in families keep them in one package each,
``backbones/<family>/{configuration,modeling,convert}.py``; a family of another package lives
wherever that package likes.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import importlib
import json
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar, TypeVar

import torch
from torch import Tensor, nn

from capvector.data.batch import Batch
from capvector.data.statistics import BOUNDS_Q99
from capvector.errors import CapVectorError
from capvector.io.hub import local_folder
from capvector.io.loading import COPY_AGAIN, load_safetensors, read_json
from capvector.io.lora_layers import split_base_delta
from capvector.io.modelcard import render_model_card, write_model_card
from capvector.io.names import (
    BASE_DELTA,
    EXPORT_CONFIG,
    EXPORT_FORMAT,
    EXPORT_INDEX,
    EXPORT_WEIGHTS,
)
from capvector.io.outputs import Inputs, atomic_directory
from capvector.io.tensors import LazyTensors, tensor_info
from capvector.io.weights import write_safetensors
from capvector.registry import Registry

IGNORE_INDEX = -100
"""Label of the positions a text loss skips (``torch.nn.functional.cross_entropy``'s default)."""


def project_onto_vocabulary(
    hidden: Tensor, weight: Tensor, bias: Tensor | None = None, vocabulary: Tensor | None = None
) -> Tensor:
    """``hidden @ weight.T + bias``, a language head's logits; with ``vocabulary``, only the
    rows of ``weight`` (and ``bias``) of those token ids (``VLABackbone.language_head``)."""
    if vocabulary is not None:
        weight = weight[vocabulary]
        bias = None if bias is None else bias[vocabulary]
    return torch.nn.functional.linear(hidden, weight, bias)


EMBEDDING_PARAMETERS = "embedding_parameters"


class BackboneError(CapVectorError):
    """Bad backbone input: unknown preset, wrong checkpoint, mismatched keys. The message says what to do."""


@dataclass
class BackboneConfig:
    """Fields every family shares. Families add their own architecture fields in a subclass."""

    family: ClassVar[str] = ""
    # The family's training defaults, as LeRobot's configuration_pi05.py carries
    # normalization_mapping and get_optimizer_preset: a fit uses them unless its config says
    # otherwise (data.normalization; model.optimizer, all of it).
    normalization: ClassVar[str] = BOUNDS_Q99
    """How states and actions are normalised (``capvector.data.statistics``), by default."""
    optimizer_preset: ClassVar[Mapping[str, Any]] = MappingProxyType({})
    """``model.optimizer``'s fields (AdamW, schedule) when a fit's config sets none; a field left
    out takes ``OptimizerSettings``' default."""

    preset: str = ""
    """The registered preset this config started from (filled in by ``preset_config``)."""
    action_dim: int = 7
    """A: dimensions of one action (7 = 6-DoF end-effector delta + gripper)."""
    chunk_size: int = 8
    """T: actions predicted per forward pass and executed open-loop."""
    proprio_dim: int = 8
    """P: proprioceptive state size (0 disables the proprio input)."""
    num_images: int = 2
    """N_cam: cameras per sample, in the dataset's camera order."""
    image_size: int = 224
    """Images are resized to this square size inside the backbone (no-op when they already match)."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class OutputRequest:
    """What objectives ask a forward pass to keep besides the action loss."""

    hidden_layers: tuple[int, ...] = ()
    """Hidden-state indices to keep: 0 = input embeddings, k = output of decoder layer k (1-based,
    before the final norm). Only these are kept."""
    lm_logits: bool = False
    actions: bool = False
    """Predicted actions as well as the loss when the batch has targets (a held-out L1). Without
    targets (inference) actions always come back; with targets a head returns them only when they
    cost nothing beyond the loss (an L1 head) or when asked: a flow head would sample for them."""

    def merged(self, other: OutputRequest) -> OutputRequest:
        layers = tuple(sorted(set(self.hidden_layers) | set(other.hidden_layers)))
        return OutputRequest(
            hidden_layers=layers,
            lm_logits=self.lm_logits or other.lm_logits,
            actions=self.actions or other.actions,
        )


@dataclass
class VLAOutput:
    """What a forward pass returns. Shapes: B batch, S sequence, H hidden, T chunk, A action dim."""

    actions: Tensor | None
    """(B, T, A) predicted actions in normalised action space; None in a training forward whose
    head would have to sample for them (see ``OutputRequest.actions``)."""
    loss: Tensor | None = None
    """Scalar action loss, when the batch carries target actions."""
    hidden_states: dict[int, Tensor] = field(default_factory=dict)
    """Requested layers only: layer index -> (B, S, H)."""
    visual_token_mask: Tensor | None = None
    """(B, S) bool: True at visual-token positions, in camera order, row-major patches."""
    attention_mask: Tensor | None = None
    """(B, S) bool: True at real (non-padding) tokens."""
    visual_grid: tuple[int, int] | None = None
    """(rows, cols) of visual tokens per camera: objectives reshape per-camera tokens with it."""
    lm_logits: Tensor | None = None
    """(B, S, V) language-model logits, when requested."""


ConfigT = TypeVar("ConfigT", bound=BackboneConfig)


@dataclass
class OriginalCheckpoint:
    """What every family's ``VLABackbone.from_original`` returns."""

    model: VLABackbone
    statistics: dict[str, Any]
    """Normalisation statistics in capvector's ``dataset_statistics.json`` schema
    (``capvector.data.statistics``), converted from the upstream files; ``{}`` when the checkpoint
    carries none."""
    upstream_config: dict[str, Any] = field(default_factory=dict)
    """The upstream config files that were read, by file name, kept for provenance."""


@dataclass(frozen=True)
class ImportOption:
    """A keyword argument of a family's ``load_original`` besides the source, preset and overrides,
    declared in ``VLABackbone.import_options`` so that ``capvector import-original`` offers it as
    ``--<name>`` (underscores become dashes) for that family's presets."""

    name: str
    help: str
    type: Callable[[str], Any] = str
    """Turns the argument's text into the value (``str``, ``int``, ``float``); ``Path`` for a file
    or folder the import reads; ``bool`` makes a flag that passes True when given."""


class VLABackbone(nn.Module, ABC):
    """Base class of every VLA backbone. Subclasses set ``config_class`` and implement the methods."""

    config_class: ClassVar[type[BackboneConfig]] = BackboneConfig
    lora_target_modules: ClassVar[str | list[str]] = []
    """peft ``target_modules`` (a list of names or a full-match regex) for LoRA fine-tuning."""
    lora_trainable_modules: ClassVar[tuple[str, ...]] = ()
    """Globs of parameters trained from scratch (heads, projectors) that stay trainable under LoRA."""
    original_loader: ClassVar[str | None] = None
    """Module with ``load_original`` for the original project's checkpoints (``from_original``)."""
    import_options: ClassVar[tuple[ImportOption, ...]] = ()
    """The loader's own options (OpenVLA-OFT's ``apply_lora_adapter``), offered by
    ``capvector import-original``; ``from_original`` accepts these and no others."""
    capability_parameters: ClassVar[tuple[str, ...]] = ("*",)
    """Globs of the parameters a capability vector covers by default: the pretrained VLM, not task
    heads that a pretrained model does not have."""

    def __init__(self, config: BackboneConfig) -> None:
        super().__init__()
        self.config = config

    @abstractmethod
    def forward(self, batch: Batch, request: OutputRequest | None = None) -> VLAOutput:
        """Predict the action chunk; compute the action loss when ``batch`` has target actions."""

    @torch.no_grad()
    def predict_action(self, batch: Batch) -> Tensor:
        """(B, T, A) actions in normalised space for a batch without targets."""
        return self(batch).actions

    @property
    @abstractmethod
    def num_layers(self) -> int:
        """Decoder layers of the language model whose hidden states objectives may request."""

    @property
    @abstractmethod
    def hidden_size(self) -> int:
        """Width of the hidden states returned in ``VLAOutput.hidden_states``."""

    def unused_parameter_names(self) -> list[str]:
        """Parameters no output depends on (kept for checkpoint compatibility); VLAModule freezes
        them so DDP needs no ``find_unused_parameters``."""
        return []

    def language_head_parameter_names(self) -> list[str]:
        """The LM head, used only by text objectives: frozen until one is attached."""
        return []

    def shard_units(self) -> list[nn.Module]:
        """The blocks FSDP2 shards one by one and activation checkpointing recomputes (vision
        blocks, decoder layers, expert layers). The backbone itself is the root unit."""
        return []

    @property
    def alignment_layer(self) -> int:
        """Default hidden-state layer for spatial alignment: deep but not deepest, 3/4 of the depth
        (Spatial Forcing aligns OFT's layer 24 of 32; Pi0.5 overrides it with pi0's 12 of 18)."""
        return round(0.75 * self.num_layers)

    def text_pass(
        self, batch: Batch, prompts: list[str], answers: list[str]
    ) -> tuple[Tensor, Tensor]:
        """(B, S, H) final hidden states of a causal pass over the observation, ``prompts`` and
        ``answers``, and (B, S) token ids at their own positions, -100 everywhere but on the
        answer tokens (position i's hidden state predicts the label at i + 1).

        Used by multimodal-reasoning co-training; families with a language head override it and
        ``language_head``.
        """
        raise BackboneError(f"{type(self).__name__} has no language-model head for text objectives")

    def answer_label_ids(self, answer: str) -> list[int]:
        """The token ids ``text_pass`` scores for ``answer``: its tokens and the token that ends
        it. Families with a language head override it, and build ``text_pass``'s labels with it."""
        raise BackboneError(f"{type(self).__name__} has no language-model head for text objectives")

    def language_head(self, hidden: Tensor, vocabulary: Tensor | None = None) -> Tensor:
        """Vocabulary logits of final hidden states (``text_pass``'s), any leading shape; with
        ``vocabulary`` (sorted token ids), only those columns, in that order."""
        raise BackboneError(f"{type(self).__name__} has no language-model head for text objectives")

    def language_model_logits(
        self, batch: Batch, prompts: list[str], answers: list[str]
    ) -> tuple[Tensor, Tensor]:
        """(B, S, V) logits at every position of ``text_pass`` and its (B, S) labels."""
        hidden, labels = self.text_pass(batch, prompts, answers)
        return self.language_head(hidden), labels

    def answer_logits(
        self,
        batch: Batch,
        prompts: list[str],
        answers: list[str],
        vocabulary: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """(N, V) logits of the N positions whose next token is an answer label, and those (N,)
        labels: the next-token loss of ``language_model_logits`` without projecting every visual
        and prompt position onto the vocabulary (Gemma's 262 k: most of the mini's text pass).

        With ``vocabulary`` (sorted token ids that hold every label), the logits are only its
        columns and each label is its index there: a softmax over those tokens alone.
        """
        hidden, labels = self.text_pass(batch, prompts, answers)
        scored = labels[:, 1:] != IGNORE_INDEX
        targets = labels[:, 1:][scored]
        if vocabulary is not None:
            vocabulary = vocabulary.to(targets.device)
            index = torch.searchsorted(vocabulary, targets).clamp(max=len(vocabulary) - 1)
            missing = targets[vocabulary[index] != targets]
            if len(missing):
                raise BackboneError(
                    f"answer token ids {sorted(set(missing.tolist()))[:10]} are not in the "
                    f"{len(vocabulary)}-token answer vocabulary; build it from every answer the "
                    "objective scores"
                )
            targets = index
        return self.language_head(hidden[:, :-1][scored], vocabulary), targets

    _tokenizer: Any = None
    missing_tokenizer_hint: ClassVar[str] = (
        "load a checkpoint folder that contains one (from_pretrained / from_original) or set "
        "tokenizer to a tokenizer folder"
    )
    """What to do when the backbone has no tokenizer, for the error ``require_tokenizer`` raises."""

    @property
    def tokenizer(self) -> Any:
        """The tokenizer that turns instructions into ids, when the family has one."""
        return self._tokenizer

    def require_tokenizer(self) -> Any:
        """The tokenizer, for a family that cannot run without one."""
        if self.tokenizer is None:
            raise BackboneError(f"this backbone has no tokenizer: {self.missing_tokenizer_hint}")
        return self.tokenizer

    def make_tokenizer(self, folder: str) -> Any:
        """Build the family's tokenizer from saved files (families with a tokenizer override this)."""
        return None

    @property
    def saves_tokenizer(self) -> bool:
        """Whether exports carry the tokenizer's files (not when the config rebuilds it from an
        installed package: the mini's 33 MB Gemma tokenizer would outweigh its trained weights)."""
        return True

    def load_tokenizer(self, folder: str | Path) -> None:
        """Load tokenizer files saved beside the weights, when there are any."""
        if (Path(folder) / "tokenizer_config.json").is_file():
            self._tokenizer = self.make_tokenizer(str(folder))

    def weight_provenance(self) -> list[dict[str, Any]]:
        """Where pretrained weights built into the model at construction came from (packages,
        versions, SHA-256, licence terms); written into the model card of every export."""
        return []

    @property
    def base_delta(self) -> dict[str, tuple[Tensor, Tensor]] | None:
        """For a backbone whose frozen base is rebuilt from installed packages and left out of its
        state dict: the low-rank deltas its base weights carry over those packages (export name
        ``X.weight`` -> (B, A), W = packaged + B @ A; empty when none). ``None`` for a backbone
        whose exports hold whole weights."""
        return None

    def set_base_delta(self, deltas: Mapping[str, tuple[Tensor, Tensor]]) -> None:
        """Set base weights to packaged + B @ A (what an export's ``base_delta`` holds)."""
        raise BackboneError(
            f"{type(self).__name__} ({self.config.preset}) saves whole weights; an export with a "
            "base_delta needs a backbone whose base is rebuilt from weight packages"
        )

    def capability_parameter_names(self) -> list[str]:
        names = [name for name, _ in self.named_parameters()]
        return [
            n for n in names if any(fnmatch.fnmatchcase(n, g) for g in self.capability_parameters)
        ]

    # -- persistence -------------------------------------------------------------------------

    def export_config(self) -> dict[str, Any]:
        return {
            "format": EXPORT_FORMAT,
            "family": self.config_class.family,
            "backbone_config": self.config.to_dict(),
            "capability_parameters": list(self.capability_parameters),
            EMBEDDING_PARAMETERS: self.embedding_parameter_names(),
        }

    def embedding_parameter_names(self) -> list[str]:
        """Weights of ``nn.Embedding`` modules: a low-rank vector stores them under peft's
        embedding-LoRA names (``lora_embedding_A/B``), since peft reads linear names as linear."""
        return [f"{name}.weight" for name, m in self.named_modules() if isinstance(m, nn.Embedding)]

    def save_pretrained(
        self,
        folder: str | Path,
        state_dict: Mapping[str, Tensor] | None = None,
        extra_json: Mapping[str, Any] | None = None,
        config_extra: Mapping[str, Any] | None = None,
        overwrite: bool = False,
        card_facts: Mapping[str, Any] | None = None,
        base_model: str | None = None,
        inputs: Inputs = (),
    ) -> Path:
        """Write ``model.safetensors`` + ``config.json`` (+ tokenizer files) + a model card
        (``README.md``) atomically.

        ``state_dict`` defaults to this module's own; pass a LoRA-merged one from the caller.
        ``extra_json`` maps file names to JSON-serialisable content written beside the weights;
        ``config_extra`` adds fields to ``config.json``. ``card_facts`` (what made the weights:
        steps, objectives, the command) and ``base_model`` go into the model card. ``inputs`` are
        the paths the weights came from: ``folder`` must not be, hold or lie inside one of them.
        """
        from capvector.data.statistics import check_finite_statistics
        from capvector.io.names import STATISTICS_FILE

        statistics = (extra_json or {}).get(STATISTICS_FILE)
        if statistics is not None:  # the last guard: evaluation would normalise with them
            check_finite_statistics(statistics, f"{folder}/{STATISTICS_FILE}")
        tensors = state_dict if state_dict is not None else self.state_dict()
        if not isinstance(tensors, LazyTensors):  # the writer moves each to the CPU as it writes
            tensors = LazyTensors({k: v.detach() for k, v in tensors.items()})
        with atomic_directory(folder, overwrite, inputs) as tmp:
            write_safetensors(tmp / EXPORT_WEIGHTS, tensors)
            config = {**self.export_config(), **(config_extra or {})}
            (tmp / EXPORT_CONFIG).write_text(json.dumps(config, indent=2))
            for name, content in (extra_json or {}).items():
                (tmp / name).write_text(json.dumps(content, indent=2))
            if self.tokenizer is not None and self.saves_tokenizer:
                self.tokenizer.save_pretrained(str(tmp))
            write_model_card(tmp, self._model_card(tensors, card_facts or {}, base_model))
        return Path(folder)

    def _model_card(
        self, tensors: Mapping[str, Tensor], facts: Mapping[str, Any], base_model: str | None
    ) -> str:
        family = self.config_class.family
        command = facts.get("command")
        return render_model_card(
            f"{family} ({self.config.preset})",
            f"A {family} vision-language-action model in capvector's export layout "
            "(`model.safetensors` + `config.json`): load it with "
            "`capvector.backbones.from_pretrained(folder)` or use it as `--model.pretrained`.",
            {
                "family": family,
                "preset": self.config.preset,
                "parameters": sum(tensor_info(tensors, k).numel for k in tensors),
                "chunk × action dim": f"{self.config.chunk_size} × {self.config.action_dim}",
                "cameras": self.config.num_images,
                **{
                    f"pretrained weights: {source['weights']}": (
                        f"from {', '.join(source['packages'])}; SHA-256 {source['sha256']}; "
                        f"{source['license']}; origin {source['origin']}"
                    )
                    for source in self.weight_provenance()
                },
                **{k: v for k, v in facts.items() if k != "command"},
            },
            base_model=base_model,
            tags=["vision-language-action", family],
            command=command,
        )

    @classmethod
    def from_original(
        cls,
        source: str | Path,
        preset: str | None = None,
        overrides: Mapping[str, Any] | None = None,
        **options: Any,
    ) -> OriginalCheckpoint:
        """Load a checkpoint in the original project's own layout, strictly.

        ``source`` is what the upstream code wrote (a run folder or checkpoint file). The
        architecture comes from the upstream config files that travel with it; ``preset`` names the
        preset those values start from and ``overrides`` changes named fields (a nested mapping
        changes only the fields it names). A config field we do not support is an error naming it.
        ``options`` are the ones the family declares in ``import_options`` (OpenVLA-OFT's
        ``apply_lora_adapter``, Pi0.5's ``tokenizer``, StarVLA's ``qwen_folder``). The conversion
        code lives in the module ``original_loader`` names (the family's ``convert.py``), whose
        ``load_original(cls, source, preset, overrides, **options)`` documents them.
        """
        if cls.original_loader is None:
            raise BackboneError(
                f"{cls.__name__} has no loader for an original project's checkpoint; use "
                "capvector.backbones.from_pretrained for a capvector export folder"
            )
        declared = [option.name for option in cls.import_options]
        unknown = sorted(set(options) - set(declared))
        if unknown:
            raise BackboneError(
                f"{cls.__name__}.from_original has no option(s) {unknown}; its options: {declared}"
            )
        loader = importlib.import_module(cls.original_loader)
        source = local_folder(source, "original checkpoint")  # a hub id: its snapshot
        return loader.load_original(cls, source, preset, overrides, **options)

    @classmethod
    def from_config_dict(cls, config: Mapping[str, Any]) -> VLABackbone:
        known = {f.name for f in dataclasses.fields(cls.config_class)}
        return cls(_config_from_dict(cls.config_class, config, known))


# -- registry --------------------------------------------------------------------------------

# The registry is open: a backbone defined anywhere registers itself with ``register_family`` and
# ``register_preset`` when its module is imported. Modules are found three ways, all lazily so that
# `import capvector` stays light: the built-in families below; installed packages that declare an
# entry point in ENTRY_POINT_GROUP (``[project.entry-points."capvector.backbones"] my_vla =
# "my_pkg.my_vla"``); and a preset named ``module:preset`` (``my_pkg.my_vla:my-preset``), which
# imports the module first. The qualified name is what configs, checkpoints and exports record,
# so they load again wherever the module is importable.
_BUILTIN_FAMILY_MODULES = (
    "capvector.backbones.openvla_oft",
    "capvector.backbones.pi05",
    "capvector.backbones.starvla",
)
ENTRY_POINT_GROUP = "capvector.backbones"
FAMILIES: Registry[type[VLABackbone]] = Registry(
    "backbone family", modules=_BUILTIN_FAMILY_MODULES, group=ENTRY_POINT_GROUP,
    base=VLABackbone, error=BackboneError, plugin="backbone",
)  # fmt: skip
PRESETS: Registry[Callable[[], BackboneConfig]] = Registry(
    "backbone preset", modules=_BUILTIN_FAMILY_MODULES, group=ENTRY_POINT_GROUP,
    error=BackboneError, plugin="backbone",
)  # fmt: skip

B = TypeVar("B", bound=type[VLABackbone])


def register_family(cls: B) -> B:
    """Class decorator: makes a backbone class buildable from its config class."""
    return FAMILIES.register(cls.config_class.family)(cls)


def register_preset(name: str) -> Callable[[Callable[[], ConfigT]], Callable[[], ConfigT]]:
    """Decorator for a function returning the config of a named preset (timm style)."""
    return PRESETS.register(name)


def list_presets() -> list[str]:
    return PRESETS.names()


def preset_config(preset: str, /, **overrides: Any) -> BackboneConfig:
    """The config of ``preset`` (a registered name, or ``module:name`` for a backbone defined in
    any importable module) with ``overrides`` applied; unknown names give a clear error."""
    config = PRESETS.get(preset)()
    known = {f.name for f in dataclasses.fields(config)}
    values = merge_nested(config.to_dict(), overrides)
    # Recorded as given: a module-qualified name lets checkpoints and exports find the module again.
    values["preset"] = preset if ":" in preset else values.get("preset") or preset
    return _config_from_dict(type(config), values, known, preset)


def merge_nested(base: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``overrides`` applied; a mapping inside ``overrides`` changes only the fields it
    names (``{"featurizer": {"embed_dim": 32}}`` keeps the featurizer's depth and heads)."""
    merged = dict(base)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            value = merge_nested(merged[key], value)
        merged[key] = value
    return merged


def _config_from_dict(
    config_class: type[ConfigT],
    values: Mapping[str, Any],
    known: set[str],
    source: str | None = None,
) -> ConfigT:
    unknown = sorted(set(values) - known)
    if unknown:
        where = f" of preset {source!r}" if source else ""
        raise BackboneError(
            f"unknown config field(s) {unknown}{where} ({config_class.__name__}); "
            f"valid fields: {sorted(known)}"
        )
    kwargs = {}
    for f in dataclasses.fields(config_class):
        if f.name not in values:
            continue
        value = values[f.name]
        sub = _nested_dataclass(f.type)
        if sub is not None and isinstance(value, Mapping):
            value = _config_from_dict(sub, value, {g.name for g in dataclasses.fields(sub)}, source)
        elif isinstance(value, list) and str(f.type).startswith("tuple"):
            value = tuple(value)  # JSON (config.json, YAML) stores tuples as lists
        kwargs[f.name] = value
    return config_class(**kwargs)


def _nested_dataclass(annotation: Any) -> Any:
    """The dataclass named by a field annotation (annotations are strings under __future__)."""
    if isinstance(annotation, str):
        for candidate in _NESTED_CONFIGS:
            if annotation == candidate.__name__:
                return candidate
        return None
    return annotation if dataclasses.is_dataclass(annotation) else None


_NESTED_CONFIGS: list[type] = []


def nested_config(cls: type[ConfigT]) -> type[ConfigT]:
    """Class decorator for dataclasses used as fields of a backbone config (restored from JSON)."""
    _NESTED_CONFIGS.append(cls)
    return cls


def backbone_class(family: str, preset: str | None = None) -> type[VLABackbone]:
    """The class of ``family``; ``preset`` (as a config records it) names the module to import
    when the family is defined outside the package."""
    module, sep, _ = (preset or "").rpartition(":")
    return FAMILIES.get(f"{module}:{family}" if sep else family)


def build_backbone(preset: str, /, **overrides: Any) -> VLABackbone:
    """Build a preset with random weights (use ``torch.device('meta')`` to only count parameters)."""
    config = preset_config(preset, **overrides)
    return backbone_class(config.family, config.preset)(config)


def registered_families() -> dict[str, type[VLABackbone]]:
    """Every registered family by name: the built-in ones and those of installed entry points."""
    return FAMILIES.entries()


def load_export_config(folder: str | Path) -> dict[str, Any]:
    """The ``config.json`` of an export folder: a local one, or a hub id's snapshot."""
    path = local_folder(folder, "export folder") / EXPORT_CONFIG
    if not path.is_file():
        raise BackboneError(f"{folder} has no {EXPORT_CONFIG}: it is not a capvector export folder")
    config = read_json(path)
    if config.get("format") != EXPORT_FORMAT:
        raise BackboneError(
            f"{path} is not a capvector export (format {config.get('format')!r}); for an original "
            "project's checkpoint use that family's loader, e.g. OpenVLAOFT.from_original"
        )
    return config


def from_pretrained(folder: str | Path, **overrides: Any) -> VLABackbone:
    """Load a capvector export folder (what ``save_pretrained`` / ``capvector merge`` write): a
    local folder, or a hub id (``org/name[@revision]``) read through the hub cache
    (``capvector.io.hub``)."""
    folder = local_folder(folder, "export folder")
    config = load_export_config(folder)
    cls = backbone_class(config["family"], config["backbone_config"].get("preset"))
    model = cls.from_config_dict(merge_nested(config["backbone_config"], overrides))
    model.load_tokenizer(folder)
    state = (
        load_safetensors(Path(folder) / EXPORT_WEIGHTS)
        if _single_file(folder)
        else read_sharded(folder)
    )
    if config.get(BASE_DELTA) is not None:
        state, deltas = split_base_delta(state)
        model.set_base_delta(deltas)
    load_state_dict_strictly(model, state, source=str(folder))
    return model


def _single_file(folder: str | Path) -> bool:
    return (Path(folder) / EXPORT_WEIGHTS).is_file()


def read_sharded(folder: str | Path, index_name: str = EXPORT_INDEX) -> dict[str, Tensor]:
    """All tensors of a sharded safetensors folder (HF layout: index JSON + shards). Every shard
    the index names must be there before any is read."""
    index_path = Path(folder) / index_name
    if not index_path.is_file():
        raise BackboneError(f"{folder} has neither {EXPORT_WEIGHTS} nor {index_name}")
    weight_map = read_json(index_path).get("weight_map")
    if not isinstance(weight_map, dict) or not weight_map:
        raise BackboneError(f"{index_path} has no `weight_map`; it is not a safetensors index")
    shards = sorted({str(shard) for shard in weight_map.values()})
    missing = [shard for shard in shards if not (Path(folder) / shard).is_file()]
    if missing:
        raise BackboneError(
            f"{index_path} names {len(missing)} shard(s) missing from {folder}, e.g. "
            f"{_examples(missing)}: the folder is incomplete; {COPY_AGAIN}"
        )
    state: dict[str, Tensor] = {}
    for shard in shards:
        state.update(load_safetensors(Path(folder) / shard))
    return state


def load_state_dict_strictly(model: nn.Module, state: Mapping[str, Tensor], source: str) -> None:
    """Load with every key and shape checked first; errors name the offending keys."""
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    check_fits(model, expected, {k: tuple(v.shape) for k, v in state.items()}, source)
    model.load_state_dict(dict(state), strict=True)


def check_fits(
    model: nn.Module,
    expected: Mapping[str, tuple[int, ...]],
    found: Mapping[str, tuple[int, ...]],
    source: str,
) -> None:
    """Raise naming the missing, unexpected and mis-shaped keys when the tensors ``found`` in
    ``source`` (name -> shape) are not exactly those ``model`` ``expected``."""
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    mismatched = [
        f"{k}: checkpoint {found[k]} vs model {expected[k]}"
        for k in sorted(set(expected) & set(found))
        if found[k] != expected[k]
    ]
    problems = []
    if missing:
        problems.append(f"{len(missing)} missing key(s), e.g. {_examples(missing)}")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected key(s), e.g. {_examples(unexpected)}")
    if mismatched:
        problems.append(f"{len(mismatched)} shape mismatch(es), e.g. {_examples(mismatched)}")
    if problems:
        raise BackboneError(
            f"{source} does not fit {type(model).__name__}: " + "; ".join(problems) + ". "
            "Is it a checkpoint of another architecture or preset? Build the model with the preset "
            "the checkpoint was trained with."
        )


def _examples(items: Sequence[str], n: int = 3) -> str:
    return ", ".join(f"`{x}`" for x in items[:n]) + (" ..." if len(items) > n else "")


@contextmanager
def keep_hidden_states(
    layers: Sequence[nn.Module], indices: Sequence[int], store: dict[int, Tensor]
) -> Iterator[None]:
    """Record the outputs of decoder layers ``indices`` (1-based) into ``store`` during a forward.

    Hooks keep only the requested layers instead of asking the model for all of them.
    """
    handles = []
    for index in indices:
        if index == 0:
            continue  # the caller stores the input embeddings itself
        if not 1 <= index <= len(layers):
            raise BackboneError(f"hidden layer {index} requested; valid: 0..{len(layers)}")

        def hook(_module: nn.Module, _args: Any, output: Any, index: int = index) -> None:
            store[index] = output[0] if isinstance(output, tuple) else output

        handles.append(layers[index - 1].register_forward_hook(hook))
    try:
        yield
    finally:
        for handle in handles:
            handle.remove()


def draw_flow_noise(
    like: Tensor,
    sample_time: Callable[[int, torch.device], Tensor],
    seeds: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Flow-matching training draws: noise ε (B', ...) shaped like ``like`` and times (B',) from
    ``sample_time(n, device)``.

    Without ``seeds`` both come from the global RNG, as openpi and StarVLA draw them. With
    ``seeds`` (B,) (``batch["noise_seed"]``) sample b's draws come from the CPU generator seeded with
    ``seeds[b]`` alone; B' must then be k·B laid out as ``x.repeat(k, ...)`` (row c·B + b is copy c
    of sample b), so the k copies of a flow head's repeated batch stay with their sample. We deviate
    from upstream here because the global stream differs per rank: only noise tied to the sample
    makes a run sharded over N processes draw what one process draws on the same global batch, and
    so gives the same loss curve. The global RNG state is left untouched.
    """
    if seeds is None:
        return torch.randn_like(like), sample_time(like.shape[0], like.device)
    copies, rest = divmod(like.shape[0], seeds.shape[0])
    if rest or not copies:
        raise BackboneError(
            f"{seeds.shape[0]} noise seeds for {like.shape[0]} rows: the rows must be k copies "
            "of the batch"
        )
    noises, times = [], []
    cpu = torch.device("cpu")
    with torch.random.fork_rng(devices=[]):
        for seed in seeds.tolist():
            torch.random.default_generator.manual_seed(seed)
            noises.append(torch.randn((copies, *like.shape[1:])))
            times.append(sample_time(copies, cpu))
    noise = torch.stack(noises, dim=1).flatten(0, 1).to(like)
    return noise, torch.stack(times, dim=1).flatten(0, 1).to(like.device)
