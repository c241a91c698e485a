"""Attach an auxiliary objective to the module and schedule its weight."""

from __future__ import annotations

import lightning as L

from capvector.data.batch import Batch
from capvector.objectives.base import Objective


class AuxiliaryObjective(L.Callback):
    """Attaches ``objective`` in ``setup`` (before optimizers exist, so its parameters train and
    are checkpointed) and ramps its weight linearly from 0 over ``warmup_steps`` after ``start_step``.
    """

    def __init__(self, objective: Objective, warmup_steps: int = 0, start_step: int = 0) -> None:
        self.objective = objective
        self.base_weight = objective.weight
        self.warmup_steps = warmup_steps
        self.start_step = start_step

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.objective.name in pl_module.objectives:
            return  # setup runs again for validate/test after fit
        self.objective.bind(pl_module.backbone)
        # the datamodule's setup ran before this hook (Lightning's _call_setup_hook)
        dataset = getattr(trainer.datamodule, "train_dataset", None)
        if dataset is not None:
            self.objective.bind_data(dataset, pl_module.backbone)
        pl_module.add_objective(self.objective)

    def weight_at(self, step: int) -> float:
        if step < self.start_step:
            return 0.0
        if self.warmup_steps <= 0:
            return self.base_weight
        return self.base_weight * min(1.0, (step - self.start_step + 1) / self.warmup_steps)

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Batch, batch_idx: int
    ) -> None:
        self.objective.weight = self.weight_at(trainer.global_step)
        pl_module.log(f"aux/{self.objective.name}_weight", self.objective.weight, batch_size=1)
