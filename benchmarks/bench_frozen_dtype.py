"""Loss curves with frozen weights in bf16 against float32, on every tiny preset.

Each preset trains LoRA (r 4) under bf16-mixed autocast for ``--steps`` steps twice from the same
initial weights and data order: once with every weight in float32 (``model.frozen_dtype=float32``)
and once with the frozen weights in bf16 (``bfloat16``). Reported: the largest relative difference
between the two loss curves, and between their means over the last 10 steps.

    python benchmarks/bench_frozen_dtype.py [--steps 50] [--presets openvla-oft-tiny ...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import lightning as L
import torch

from capvector.backbones import list_presets
from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule
from capvector.training.lora import LoraSettings


class RecordLoss(L.Callback):
    def __init__(self) -> None:
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: ANN001
        self.losses.append(float(outputs["loss"]))


def curve(preset: str, data: Path, frozen_dtype: str, steps: int) -> list[float]:
    torch.manual_seed(0)
    dm = RobotDataModule(train_files=[str(data)], batch_size=8, augment=False, shuffle=False)
    module = VLAModule(
        backbone=preset,
        data_spec=dm.spec,
        lora=LoraSettings(r=4, alpha=8),
        frozen_dtype=frozen_dtype,
    )
    record = RecordLoss()
    trainer = L.Trainer(
        max_steps=steps, accelerator="cpu", precision="bf16-mixed", logger=False,
        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
        enable_checkpointing=False, callbacks=[record],
    )  # fmt: skip
    trainer.fit(module, dm)
    return record.losses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--presets", nargs="+", default=[p for p in list_presets() if "tiny" in p])
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import write_demo_file

    print(
        "| preset | max relative difference per step | last-10 mean fp32 | bf16 frozen | difference |"
    )
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        data = write_demo_file(Path(tmp) / "demos.hdf5", lengths=(40, 40))
        for preset in args.presets:
            fp32 = torch.tensor(curve(preset, data, "float32", args.steps))
            bf16 = torch.tensor(curve(preset, data, "bfloat16", args.steps))
            step_diff = float(((bf16 - fp32).abs() / fp32.abs()).max())
            a, b = float(fp32[-10:].mean()), float(bf16[-10:].mean())
            print(
                f"| {preset} | {step_diff:.2%} | {a:.4f} | {b:.4f} | {(b - a) / a:+.2%} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
