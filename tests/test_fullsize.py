"""Opt-in (``-m fullsize``, left out of `make test`): one training step of the full-size pi05-3b
on the CPU as ``capvector fit`` runs it with LoRA, frozen weights built in bf16. Needs ≈ 10 GB of
RAM and minutes; `benchmarks/bench_full_size.py` records the numbers."""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import pytest

from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule
from capvector.training.lora import LoraSettings
from conftest import write_demo_file

pytestmark = pytest.mark.fullsize


class Record(L.Callback):
    def __init__(self) -> None:
        self.losses: list[float] = []
        self.with_grad: set[str] = set()

    def on_after_backward(self, trainer: L.Trainer, module: L.LightningModule) -> None:
        self.with_grad |= {n for n, p in module.named_parameters() if p.grad is not None}

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:  # noqa: ANN001
        self.losses.append(float(outputs["loss"]))


def test_pi05_3b_trains_one_step_with_lora_on_cpu(tmp_path: Path) -> None:
    demos = write_demo_file(tmp_path / "demos.hdf5", lengths=(10,), image_size=224)
    dm = RobotDataModule(train_files=[str(demos)], batch_size=1, augment=False)
    module = VLAModule(
        backbone="pi05-3b", backbone_overrides={"tokenizer": "byte"}, data_spec=dm.spec,
        lora=LoraSettings(r=32, alpha=16), frozen_dtype="bfloat16",
    )  # fmt: skip
    assert sum(p.numel() for p in module.parameters()) > 3e9
    record = Record()
    trainer = L.Trainer(
        max_steps=1, accelerator="cpu", precision="bf16-mixed", logger=False,
        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
        enable_checkpointing=False, callbacks=[record], default_root_dir=tmp_path,
    )  # fmt: skip
    trainer.fit(module, dm)
    assert len(record.losses) == 1 and math.isfinite(record.losses[0])
    trainable = {n for n, p in module.named_parameters() if p.requires_grad}
    assert record.with_grad and record.with_grad <= trainable
    assert any(".lora_" in n for n in record.with_grad)
    frozen = [p for p in module.parameters() if not p.requires_grad]
    assert all(str(p.dtype) == "torch.bfloat16" for p in frozen)
