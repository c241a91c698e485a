"""The capability-vector callbacks: merge a vector at fit start, keep downstream updates from
undoing it. The math lives in ``capvector.vectors`` and ``capvector.objectives.orthogonality``."""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.utilities.rank_zero import rank_zero_info

from capvector.objectives.orthogonality import OrthogonalityLoss
from capvector.vectors import apply_vector_, load_vector, validate_vector


class MergeCapabilityVector(L.Callback):
    """θ ← θ + scale·c once, at the start of fit (θ_meta = θ_pre + λ·c).

    The vector is validated in ``setup`` (shapes, dtypes, keys, finite values), so a bad vector
    stops the run before anything changes. The ``merged`` flag is saved in checkpoints: a resumed
    run does not merge again. Under FSDP2 each rank adds its own shard of c, no communication.
    """

    def __init__(self, vector: str, scale: float = 1.0) -> None:
        self.vector = vector
        self.scale = scale
        self.merged = False
        self._loaded: Any = None

    @property
    def state_key(self) -> str:
        return self._generate_state_key(vector=self.vector, scale=self.scale)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "fit" and not self.merged:
            self._loaded = load_vector(self.vector)
            validate_vector(pl_module.backbone, self._loaded, self.scale)

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.merged:
            rank_zero_info(
                f"capability vector {self.vector} was merged before this resume; not again"
            )
            return
        changed = apply_vector_(pl_module.backbone, self._loaded or self.vector, self.scale)
        self.merged = True
        self._loaded = None
        rank_zero_info(f"merged {self.vector} x {self.scale} into {len(changed)} tensors")

    def state_dict(self) -> dict[str, Any]:
        return {"merged": self.merged, "vector": self.vector, "scale": self.scale}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.merged = bool(state_dict["merged"])


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
