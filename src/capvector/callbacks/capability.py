"""The capability-vector callbacks: merge a vector at fit start, keep downstream updates from
undoing it. The math lives in ``capvector.vectors`` and ``capvector.objectives.orthogonality``."""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.utilities.rank_zero import rank_zero_info, rank_zero_warn

from capvector.objectives.orthogonality import OrthogonalityLoss
from capvector.vectors import VectorFolder, apply_vector_, validate_vector
from capvector.vectors.merge import check_scale, check_scale_not_zero
from capvector.vectors.precision import MergePrecision
from capvector.vectors.record import (
    BY_FIT_START,
    MERGED_VECTORS,
    MergedVector,
    check_not_merged,
    check_resumed,
    read_record,
)


class MergeCapabilityVector(L.Callback):
    """θ ← θ + scale·c once, at the start of fit (θ_meta = θ_pre + λ·c).

    The vector is validated in ``setup`` (λ, shapes, dtypes, keys, finite and not all-zero values,
    its tensors as they were written, and that θ_pre does not hold it already), so a bad vector
    stops the run before anything changes. What was merged is recorded in the model itself
    (``VLAModule.merged_vectors``: the vector's fingerprint and λ, saved in checkpoints and
    exports), not in this callback's state: a resumed run never merges again, however the vector's
    path is spelled, and a resume with another vector or λ, or with the vector's tensors changed
    since, is an error naming both. Under FSDP2 each rank adds its own shard of c, no communication.

    Args:
        vector: the vector folder (full, low-rank or PEFT LoRA).
        scale: λ.
        allow_repeat: merge even when θ_pre's record says it already holds this vector.
        allow_large_scale: accept |λ| > 100.
        float32_weights: keep the frozen weights c changes in float32 when the rest is stored in
            ``model.frozen_dtype`` (bf16), so λc is not rounded away. They cost twice their bf16
            size: at 7 B, c of two LoRA fits changes 6.5 B weights, 12 GiB more. False merges
            into the frozen dtype, as ``capvector merge`` does by default; the merge's log line
            says how much of λc that dtype kept.
    """

    def __init__(
        self,
        vector: str,
        scale: float = 1.0,
        allow_repeat: bool = False,
        allow_large_scale: bool = False,
        float32_weights: bool = True,
    ) -> None:
        self.vector = vector
        self.scale = scale
        self.allow_repeat = allow_repeat
        self.allow_large_scale = allow_large_scale
        self.float32_weights = float32_weights
        self._entry: MergedVector | None = None
        self._loaded: Any = None
        self._resumed = False

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit":
            return
        check_scale(self.scale, self.vector, self.allow_large_scale)
        check_scale_not_zero(self.scale, self.vector, "drop the callback or give a non-zero scale")
        folder = VectorFolder(self.vector)
        folder.check_family(pl_module.backbone.config.family, "the model being fit")
        self._entry = MergedVector.of(folder, self.scale, BY_FIT_START)
        check_not_merged(
            pl_module.merged_vectors, self._entry, "the pretrained model", self.allow_repeat
        )
        self._loaded = folder.load()
        validate_vector(pl_module.backbone, self._loaded, self.scale, self.allow_large_scale)
        folder.check_not_zero()
        if self.float32_weights:
            # Before configure_model casts frozen weights: what c changes stays float32; what it
            # leaves at zero (what neither fit trained) keeps the frozen dtype.
            pl_module.float32_parameters.update(self._loaded.changed_keys())

    def on_load_checkpoint(
        self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]
    ) -> None:
        # Called on every resume whatever this callback's state key; the record is the model's.
        assert self._entry is not None
        record = read_record(checkpoint.get("capvector", {}).get(MERGED_VECTORS))
        check_resumed(record, self._entry, str(trainer.ckpt_path))
        self._resumed = True
        self._loaded = None

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Strategies that restore after setup (FSDP2, DeepSpeed) reach this before the checkpoint
        # is read: the merge below is then overwritten by the restored weights and record.
        assert self._entry is not None
        if self._resumed:
            rank_zero_info(f"{self._entry.describe()} was merged before this resume; not again")
            return
        precision = MergePrecision()
        changed = apply_vector_(
            pl_module.backbone, self._loaded, self.scale, precision, self.allow_large_scale
        )
        pl_module.merged_vectors.append(self._entry)
        self._loaded = None
        rank_zero_info(
            f"merged {self.vector} x {self.scale} into {len(changed)} tensors ({precision.dtype} "
            f"keeps λc up to a {precision.relative_error():.2%} relative error)"
        )
        if warning := precision.warning():
            rank_zero_warn(warning)


class OrthogonalRegularization(L.Callback):
    """Adds ``weight`` x the orthogonality penalty of the update Δ = θ − θ_meta along c.

    The loss module is attached in ``setup`` (its anchors are checkpointed with the model) and
    bound to the parameters at train start, after ``MergeCapabilityVector`` has merged, so the
    anchors are taken at θ_meta; anchors restored from a checkpoint are kept.

    Args:
        vector: the capability vector folder (full, low-rank or PEFT adapter).
        weight: μ; the penalty is the squared fraction of c added or undone per tensor.
        mode: ``full`` (full fine-tuning), ``lora`` (downstream LoRA, Δ = s·BA never formed) or
            ``olora`` (c is a LoRA adapter: O-LoRA's penalty on the A matrices).
        normalization: ``squared_projection`` or ``squared_cosine`` (lora modes only).
    """

    def __init__(
        self,
        vector: str,
        weight: float = 1.0,
        mode: str = "full",
        normalization: str = "squared_projection",
    ) -> None:
        self.vector = vector
        self.loss = OrthogonalityLoss(vector, mode=mode, normalization=normalization, weight=weight)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.loss.name not in pl_module.objectives:
            pl_module.add_objective(self.loss)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.loss.bind(pl_module.backbone)

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any
    ) -> None:
        for name, value in self.loss.last_stats.items():
            pl_module.log(f"orth/{name}", value, batch_size=1)
