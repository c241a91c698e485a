"""RequeueAtStepEnd: SLURM's warning signal, sent for real (``os.kill``) at the points of a step
where Lightning's own handler leaves a checkpoint that resumes one step off, saves one that
resumes exactly; during a validation it saves none. `tests/test_slurm.py` runs the requeue on a
real cluster."""

from __future__ import annotations

import csv
import os
import signal
from pathlib import Path
from typing import Any

import lightning as L
import pytest
import torch
from lightning.pytorch.demos.boring_classes import BoringModel
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.plugins.environments import SLURMEnvironment

from capvector.callbacks import RequeueAtStepEnd
from capvector.errors import CapVectorError
from conftest import cpu_trainer

STEPS = 12
VALIDATE_EVERY = 4  # validation after steps 4, 8 and 12


class SignalOnce:
    """Sends the requeue signal to this process the first time ``where`` is reached at global
    step ``step`` (the optimizer steps made so far)."""

    def __init__(self, where: str, step: int) -> None:
        self.where, self.step, self.sent = where, step, False

    def __call__(self, where: str, step: int) -> None:
        if where == self.where and step == self.step and not self.sent:
            self.sent = True
            os.kill(os.getpid(), signal.SIGUSR2)


class Model(BoringModel):
    def __init__(self, signal_once: SignalOnce) -> None:
        super().__init__()
        self.signal_once = signal_once

    def training_step(self, batch: Any, batch_idx: int) -> Any:
        out = super().training_step(batch, batch_idx)
        self.log("loss", out["loss"])
        self.signal_once("forward", self.trainer.global_step)  # before the optimizer step
        return out

    def validation_step(self, batch: Any, batch_idx: int) -> Any:
        self.signal_once("validation", self.trainer.global_step)
        return super().validation_step(batch, batch_idx)


class SignallingLogger(CSVLogger):
    """Logs the step's metrics, then signals: after the optimizer step, before the loop counts
    the step (the window of a flaky SLURM test: its resumed fit logged every step one behind)."""

    def __init__(self, signal_once: SignalOnce, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.signal_once = signal_once

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        super().log_metrics(metrics, step)
        if "loss" in metrics and step is not None:
            self.signal_once("logging", step + 1)  # the optimizer has made step + 1 steps


def fit(root: Path, version: int, signal_once: SignalOnce, ckpt: Path | None = None) -> None:
    L.seed_everything(0)
    trainer = cpu_trainer(
        STEPS, root, logger=SignallingLogger(signal_once, root, name="fit", version=version),
        log_every_n_steps=1, limit_val_batches=2, val_check_interval=VALIDATE_EVERY,
        num_sanity_val_steps=0, callbacks=[RequeueAtStepEnd("SIGUSR2")],
        # Lightning's auto-requeue is on, as in the recipe: it must leave the signal to the callback.
        plugins=[SLURMEnvironment(auto_requeue=True, requeue_signal=signal.SIGUSR2)],
    )  # fmt: skip
    trainer.fit(Model(signal_once), ckpt_path=ckpt)


def logged_steps(root: Path, version: int) -> list[int]:
    with (root / f"fit/version_{version}/metrics.csv").open() as f:
        return [int(row["step"]) for row in csv.DictReader(f) if row.get("loss")]


@pytest.fixture(autouse=True)
def _slurm_job(monkeypatch: pytest.MonkeyPatch) -> None:
    """What SLURMEnvironment reads of a one-task job; no job id, so nothing is requeued."""
    for name, value in {"SLURM_NTASKS": "1", "SLURM_PROCID": "0", "SLURM_LOCALID": "0",
                        "SLURM_NODEID": "0", "SLURM_JOB_NAME": "fit"}.items():  # fmt: skip
        monkeypatch.setenv(name, value)
    for name in ("SLURM_JOB_ID", "SLURM_ARRAY_JOB_ID"):
        monkeypatch.delenv(name, raising=False)


@pytest.mark.parametrize("where", ["forward", "logging"])
def test_a_signal_mid_step_saves_at_its_end_and_the_fit_resumes_exactly(
    tmp_path: Path, where: str, capfd: pytest.CaptureFixture[str]
) -> None:
    # In step 6's forward pass, or in step 5's logging (after its optimizer step): saved at the
    # end of step 6, the first step end the signal meets.
    fit(tmp_path, 0, SignalOnce(where, 5))
    assert sorted(p.name for p in tmp_path.glob("hpc_ckpt_*.ckpt")) == ["hpc_ckpt_1.ckpt"]
    saved = torch.load(tmp_path / "hpc_ckpt_1.ckpt", weights_only=False)["global_step"]
    assert saved == 6
    err = capfd.readouterr().err
    assert f"SIGUSR2 at step 6: saved {tmp_path / 'hpc_ckpt_1.ckpt'}; not a SLURM job" in err
    fit(tmp_path, 1, SignalOnce("never", 0), tmp_path / "hpc_ckpt_1.ckpt")
    # Each step the resumed run trains is logged under its own number, the last one included.
    assert logged_steps(tmp_path, 1) == list(range(saved, STEPS))


def test_a_signal_in_a_step_validation_follows_saves_no_checkpoint(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """Saved before the validation, the resumed fit would count it done; the newest step
    checkpoint (CheckpointAfterValidation's, from before it) is where the job resumes."""
    signal_once = SignalOnce("forward", 7)  # step 8's forward pass: validation follows it
    fit(tmp_path, 0, signal_once)
    assert signal_once.sent and not list(tmp_path.glob("hpc_ckpt_*.ckpt"))
    assert "SIGUSR2 at step 8: no new checkpoint (validation)" in capfd.readouterr().err


def test_a_signal_during_validation_saves_no_checkpoint(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    signal_once = SignalOnce("validation", 4)
    fit(tmp_path, 0, signal_once)
    assert signal_once.sent and not list(tmp_path.glob("hpc_ckpt_*.ckpt"))
    assert "no new checkpoint (validation); not a SLURM job" in capfd.readouterr().err


def test_a_misspelt_signal_is_named() -> None:
    with pytest.raises(CapVectorError, match="unknown signal 'USR2'.*'SIGUSR2'"):
        RequeueAtStepEnd("USR2")
