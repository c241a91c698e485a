"""SLURM's warning signal acted on where a checkpoint of the fit is whole: a training step's end."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from types import FrameType
from typing import Any

import lightning as L

from capvector.callbacks.checkpoint import validation_follows
from capvector.errors import CapVectorError


class RequeueAtStepEnd(L.Callback):
    """Lightning's SLURM auto-requeue (save ``hpc_ckpt_<n>.ckpt``, then ``scontrol requeue`` the
    job, which resumes from it), done at the end of the training step the signal lands in.

    Lightning (2.6, ``_SignalConnector._slurm_sigusr_handler_fn``) saves inside the signal
    handler, wherever the step is. A signal between the optimizer step and the loop's count of
    logged steps (``_batches_that_stepped``) leaves a checkpoint whose resumed run logs every step
    one behind, so the fit's last step is missing from ``metrics.csv``; one during the forward
    pass, one ahead. Saved in ``on_train_batch_end``, where ModelCheckpoint saves its step
    checkpoints, the resumed run goes on exactly. Registered in ``setup``, this handler is on
    the signal before Lightning registers its own, which Lightning then leaves out.

    A step that validation follows, and a signal during a validation (minutes of rollouts, past
    SLURM's warning), requeue at once with no new checkpoint: saved before that validation ends,
    the resumed run would count it done. The job resumes from the newest step checkpoint
    (``CheckpointAfterValidation`` saves the validated step's after its validation) and runs the
    validation again.
    """

    def __init__(self, requeue_signal: str = "SIGUSR2") -> None:
        if requeue_signal not in signal.Signals.__members__:
            raise CapVectorError(
                f"RequeueAtStepEnd: unknown signal {requeue_signal!r}; name one as the signal "
                "module does, e.g. 'SIGUSR2' (what submitit has SLURM send)"
            )
        self.requeue_signal = signal.Signals[requeue_signal]
        self._trainer: L.Trainer | None = None
        self._pending = False
        self._previous: Any = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        # Only the main thread may set handlers; a fit run from another thread keeps Lightning's.
        if stage != "fit" or threading.current_thread() is not threading.main_thread():
            return
        self._trainer = trainer
        self._previous = signal.signal(self.requeue_signal, self._on_signal)

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self._trainer is not None:
            signal.signal(self.requeue_signal, self._previous)
            self._trainer = None

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        trainer = self._trainer
        if trainer is not None and (trainer.validating or trainer.sanity_checking):
            self._requeue(trainer, None)
        else:
            self._pending = True

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        # Every rank decides at the same step: any rank's signal counts (one all-reduce per
        # step with several processes; a single process decides alone).
        if not trainer.strategy.reduce_boolean_decision(self._pending, all=False):
            return
        self._pending = False
        if validation_follows(trainer):
            self._requeue(trainer, None)
            return
        # Lightning's own name and folder: its SLURM resume finds the file, so does the recipe's.
        path = Path(trainer._checkpoint_connector.hpc_save_path(trainer.default_root_dir))
        trainer.save_checkpoint(path)
        self._requeue(trainer, path)

    def _requeue(self, trainer: L.Trainer, checkpoint: Path | None) -> None:
        """Flush the loggers and ask SLURM to requeue the job (rank 0); SLURM then ends this run
        with SIGTERM, which Lightning turns into a clean stop."""
        for logger in trainer.loggers:
            logger.save()
        if not trainer.is_global_zero:
            return
        saved = f"saved {checkpoint}" if checkpoint else "no new checkpoint (validation)"
        said = f"capvector fit: {self.requeue_signal.name} at step {trainer.global_step}: {saved}"
        job = slurm_job_id()
        if job is None:
            print(f"{said}; not a SLURM job, nothing to requeue", file=sys.stderr, flush=True)
            return
        try:
            done = subprocess.run(["scontrol", "requeue", job], capture_output=True, text=True)
            failure = done.stderr.strip() if done.returncode else ""
        except FileNotFoundError:
            failure = "scontrol not found"
        if failure:
            said += (f"; could not requeue SLURM job {job} ({failure}): the fit goes on until "
                     "SLURM ends it, then the recipe run again resumes it")  # fmt: skip
        else:
            said += f"; requeued SLURM job {job}"
        print(said, file=sys.stderr, flush=True)


def slurm_job_id() -> str | None:
    """The job ``scontrol requeue`` takes: an array task as ``<array job>_<task>``, as Lightning
    names it."""
    array = os.environ.get("SLURM_ARRAY_JOB_ID")
    if array is not None:
        return f"{array}_{os.environ['SLURM_ARRAY_TASK_ID']}"
    return os.environ.get("SLURM_JOB_ID")
