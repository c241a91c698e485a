"""A step checkpoint that a fit stopped during validation resumes from without losing it."""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint


class CheckpointAfterValidation(ModelCheckpoint):
    """``ModelCheckpoint`` that, after a training step the validation loop evaluates, saves once
    that validation has ended instead of before it starts.

    Lightning saves a step's checkpoint in ``on_train_batch_end``, before the validation of that
    step; a fit stopped during the validation (a preemption, a session's end: a LIBERO rollout
    evaluation takes minutes) resumes from it and Lightning counts the validation as done, so the
    step's evaluation is never run and its point is missing from the success-vs-steps curve. Saved
    after it, the checkpoint left by a stop during validation is the one before, and the resumed
    fit trains up to the step again and evaluates it.
    """

    _save_after_validation = False

    @property
    def state_key(self) -> str:
        """ModelCheckpoint's key (its class name and settings): the state is the same, so a fit
        checkpointed by either resumes with either and keeps writing ``last.ckpt`` (under another
        key the state is not restored and the next save is ``last-v1.ckpt``)."""
        own = super().state_key
        return ModelCheckpoint.__qualname__ + own.removeprefix(type(self).__qualname__)

    def on_train_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
    ) -> None:
        if validation_follows(trainer) and not self._should_save_on_train_epoch_end(trainer):
            self._save_after_validation = True
            return
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        # What ModelCheckpoint.on_train_batch_end would have saved, now with validation done
        # (Lightning 2.6 defers some saves the same way; 2.5 has no such deferral to reuse).
        if self._save_after_validation and not self._should_skip_saving_checkpoint(trainer):
            self._save_after_validation = False
            candidates = self._monitor_candidates(trainer)
            self._save_topk_checkpoint(trainer, candidates)
            self._save_last_checkpoint(trainer, candidates)


def validation_follows(trainer: L.Trainer) -> bool:
    """Whether the fit's validation loop runs right after the current training batch, with at
    least one batch: the training loop's own decision (``_should_check_val_fx``, asked at the same
    point of the step as the loop asks it)."""
    batches = trainer.num_val_batches
    if not trainer.enable_validation or not (
        sum(batches) if isinstance(batches, list) else batches
    ):
        return False
    loop = trainer.fit_loop
    return bool(loop.epoch_loop._should_check_val_fx(loop._data_fetcher))
