"""Every family's tiny preset through the whole recipe: SFT and aux-SFT (both objectives) from θ_pre,
extract, merge, downstream SFT with the orthogonal regularization, with and without LoRA; and a
training loss that does not depend on how the batch is split over processes."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest
import torch

from capvector.backbones import from_pretrained
from capvector.callbacks import AuxiliaryObjective, OrthogonalRegularization
from capvector.data import keys
from capvector.data.datamodule import RobotDataModule, noise_seeds
from capvector.module import VLAModule
from capvector.objectives import ReasoningCoTraining, SpatialAlignment
from capvector.training.lora import LoraSettings
from capvector.vectors import extract, merge
from conftest import cpu_trainer, write_demo_file

PRESETS = [
    "openvla-oft-tiny",
    "pi05-tiny",
    "starvla-tiny-oft",
    "starvla-tiny-gr00t",
    "starvla-tiny-layerwise",
]


def fit(
    module: VLAModule, dm: RobotDataModule, callbacks: list, root: Path, steps: int = 2
) -> list[float]:
    losses: list[float] = []

    class Record(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: ANN001
            losses.append(float(outputs["loss"]))

    cpu_trainer(steps, root, callbacks=[*callbacks, Record()]).fit(module, dm)
    return losses


@pytest.mark.parametrize("preset", PRESETS)
def test_tiny_preset_runs_the_whole_recipe(preset: str, tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    dm = RobotDataModule(
        train_files=[str(data)], batch_size=4, load_depth=True, load_annotations=True
    )
    torch.manual_seed(0)
    VLAModule(backbone=preset, data_spec=dm.spec).export(tmp_path / "pre")
    for name, callbacks in (
        ("sft", []),
        (
            "aux",
            [AuxiliaryObjective(SpatialAlignment()), AuxiliaryObjective(ReasoningCoTraining())],
        ),
    ):
        torch.manual_seed(0)
        module = VLAModule(pretrained=str(tmp_path / "pre"), data_spec=dm.spec)
        losses = fit(module, dm, callbacks, tmp_path / name)
        assert all(torch.isfinite(torch.tensor(losses)))
        if name == "aux":
            assert set(module.objectives) == {"spatial_alignment", "reasoning"}
        module.export(tmp_path / name / "export")
    extract(
        aux=tmp_path / "aux" / "export", sft=tmp_path / "sft" / "export", out=tmp_path / "vector"
    )
    merge(tmp_path / "pre", [(tmp_path / "vector", 1.0)], tmp_path / "meta")
    meta = from_pretrained(tmp_path / "meta")
    pre = from_pretrained(tmp_path / "pre")
    assert any(
        not torch.equal(a, b)
        for a, b in zip(meta.state_dict().values(), pre.state_dict().values(), strict=True)
    )
    for lora, mode in ((None, "full"), (LoraSettings(r=4, alpha=4), "lora")):
        module = VLAModule(pretrained=str(tmp_path / "meta"), data_spec=dm.spec, lora=lora)
        regularization = OrthogonalRegularization(str(tmp_path / "vector"), weight=1.0, mode=mode)
        losses = fit(module, dm, [regularization], tmp_path / f"downstream_{mode}", steps=3)
        assert all(torch.isfinite(torch.tensor(losses)))
        assert regularization.loss.bound and "mean_abs_projection" in regularization.loss.last_stats


@pytest.mark.parametrize("preset", PRESETS)
def test_training_loss_is_the_mean_of_the_halves_of_its_batch(preset: str, tmp_path: Path) -> None:
    """With per-sample noise seeds, the halves a 2-process run gives each rank average to the
    loss of the whole batch, flow-matching noise and time included."""
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    dm = RobotDataModule(train_files=[str(data)], batch_size=4, augment=False)
    batch = next(iter(torch.utils.data.DataLoader(dm.train_dataset, batch_size=4)))
    batch[keys.NOISE_SEED] = noise_seeds(batch[keys.INDEX], epoch=0, seed=0)
    backbone = VLAModule(backbone=preset, data_spec=dm.spec).backbone

    def loss(rows: slice) -> torch.Tensor:
        with torch.no_grad():
            return backbone({k: v[rows] for k, v in batch.items()}).loss

    torch.testing.assert_close(loss(slice(None)), (loss(slice(0, 2)) + loss(slice(2, 4))) / 2)
