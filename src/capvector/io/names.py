"""File names of the folders capvector writes, the metadata record of its checkpoints, and the
environment variable ``capvector recipe`` passes to its stages.

One leaf module that imports nothing of the project: the writers (``VLABackbone.save_pretrained``,
``VLAModule``) and the readers (``capvector.vectors``, which must not import Lightning or the
backbones) take their names from here, so a renamed file cannot leave a reader behind.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from capvector.errors import CapVectorError

# An export folder (VLABackbone.save_pretrained, VLAModule.export, capvector merge).
EXPORT_FORMAT = "capvector-export"
EXPORT_CONFIG = "config.json"
EXPORT_WEIGHTS = "model.safetensors"
EXPORT_INDEX = "model.safetensors.index.json"
DATA_SPEC_FILE = "capvector_data_spec.json"
STATISTICS_FILE = "dataset_statistics.json"
MODEL_CARD = "README.md"
SUCCESS_BY_TASK = "val/success_rate_by_task"
"""Per-task success rates are logged as ``<this>/<metric_key>`` beside the overall
``val/success_rate``: under their own folder, as MLflow's file store cannot keep a metric that is
also the folder of another."""
EPISODES_LOG = "episodes.csv"
"""Per-episode rollout outcomes of the validation loop, beside Lightning's ``metrics.csv``."""
EPISODE_COLUMNS = ("step", "task", "seed", "success", "stack", "renderer")
"""``episodes.csv``'s header: each outcome with the simulator stack and renderer behind it."""
VALIDATION_PROGRESS = "rollout validation at step"
"""How the validation loop's progress lines begin (``ProgressLines``), which ``capvector recipe
--status`` reads back from a running fit's log."""
EVALUATE_PROGRESS = "evaluating"
"""How ``capvector evaluate``'s progress lines begin where no bar shows (its output a file, e.g. a
recipe stage's log), which ``capvector recipe --status`` reads back."""

# A capability vector folder (capvector extract / compose), and its PEFT LoRA adapter form.
VECTOR_FORMAT = "capvector-vector"
VECTOR_META = "capability_vector.json"
VECTOR_WEIGHTS = "capability_vector.safetensors"
VECTOR_INDEX = "capability_vector.safetensors.index.json"
ADAPTER_CONFIG = "adapter_config.json"
ADAPTER_WEIGHTS = "adapter_model.safetensors"

# A Lightning checkpoint of VLAModule: its top-level modules, and where the metadata sits.
CHECKPOINT_MODEL_PREFIX = "backbone."
CHECKPOINT_OBJECTIVES_PREFIX = "objectives."
CHECKPOINT_METADATA = "capvector"
MERGED_VECTORS = "merged_vectors"
BASE_DELTA = "base_delta"
"""``config.json`` field of an export whose base is rebuilt from weight packages: present when its
base weights carry low-rank deltas, stored as ``X.lora_A/B.weight`` (``io.lora_layers``)."""

# What `capvector recipe` tells a stage's process besides its fixed torch thread count.
STAGE_CORES = "CAPVECTOR_CORES"
"""The stage's share of the machine's cores, for simulator worker processes (their number does not
change outcomes, unlike torch's thread count)."""


@dataclass(frozen=True)
class CheckpointMetadata:
    """``checkpoint["capvector"]``: what tools outside Lightning need to read a checkpoint.

    ``VLAModule.on_save_checkpoint`` writes it; ``load_module`` and ``io.weights`` read it.
    """

    family: str
    backbone_config: Mapping[str, Any]
    capability_parameters: list[str] = field(default_factory=list)
    embedding_parameters: list[str] = field(default_factory=list)
    lora: Mapping[str, Any] | None = None
    """``{r, alpha, scaling}`` when the checkpoint holds unmerged LoRA layers."""
    data_spec: Mapping[str, Any] = field(default_factory=dict)
    objectives: list[str] = field(default_factory=list)
    merged_vectors: list[Mapping[str, Any]] = field(default_factory=list)
    """``capvector.vectors.record`` entries: the vectors merged into these weights."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_checkpoint(cls, checkpoint: Mapping[str, Any], source: str) -> CheckpointMetadata:
        """The record of a loaded checkpoint; a clear error when it is not a capvector one."""
        meta = checkpoint.get(CHECKPOINT_METADATA) if isinstance(checkpoint, Mapping) else None
        if not isinstance(meta, Mapping):
            raise CapVectorError(
                f"{source} is not a capvector checkpoint (no `{CHECKPOINT_METADATA}` metadata); "
                "train it with `capvector fit` or pass an export folder"
            )
        missing = [k for k in ("family", "backbone_config") if k not in meta]
        if missing:
            raise CapVectorError(
                f"{source}: checkpoint metadata lacks {', '.join(missing)}; it was not written by "
                "capvector's VLAModule"
            )
        known = cls.__dataclass_fields__
        return cls(**{k: v for k, v in meta.items() if k in known and v is not None})
