"""VLAModule: loss terms, LoRA, optimisation, checkpoint and export round trips, the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import pytest
import torch

from capvector.backbones import BackboneError, from_pretrained
from capvector.cli import main
from capvector.data.datamodule import RobotDataModule
from capvector.module import OptimizerSettings, VLAModule, load_module
from capvector.training.lora import LoraSettings
from conftest import cpu_trainer, write_demo_file

REPO = Path(__file__).resolve().parents[1]


def datamodule(path: Path, **kwargs) -> RobotDataModule:
    return RobotDataModule(train_files=[str(path)], batch_size=4, **kwargs)


def fit(module: VLAModule, dm: RobotDataModule, root: Path, steps: int = 4) -> L.Trainer:
    trainer = cpu_trainer(steps, root)
    trainer.fit(module, dm)
    return trainer


def test_lora_trains_only_lora_and_heads(demo_file: Path, tmp_path: Path) -> None:
    dm = datamodule(demo_file)
    module = VLAModule(
        backbone="openvla-oft-tiny", data_spec=dm.spec, lora=LoraSettings(r=4, alpha=4)
    )
    trainable = {n for n, p in module.named_parameters() if p.requires_grad}
    assert trainable and all(
        ".lora_" in n or n.startswith(("backbone.action_head.", "backbone.proprio_projector."))
        for n in trainable
    )
    assert any("language_model" in n for n in trainable) and any(
        "featurizer" in n for n in trainable
    )
    assert not any("attn_pool" in n for n in trainable)  # unused head: no LoRA, no dead gradients
    frozen_before = {
        n: p.detach().clone() for n, p in module.named_parameters() if not p.requires_grad
    }
    lora_before = {n: p.detach().clone() for n, p in module.named_parameters() if "lora_B" in n}
    fit(module, dm, tmp_path)
    for name, value in frozen_before.items():
        assert torch.equal(value, module.get_parameter(name)), name
    assert any(not torch.equal(v, module.get_parameter(n)) for n, v in lora_before.items())


def test_export_merges_lora_and_reloads_identically(demo_file: Path, tmp_path: Path) -> None:
    dm = datamodule(demo_file)
    module = VLAModule(
        backbone="openvla-oft-tiny", data_spec=dm.spec, lora=LoraSettings(r=4, alpha=8)
    )
    fit(module, dm, tmp_path)
    folder = module.export(tmp_path / "export")
    config = json.loads((folder / "config.json").read_text())
    assert (
        config["family"] == "openvla-oft"
        and config["backbone_config"]["preset"] == "openvla-oft-tiny"
    )
    stats = json.loads((folder / "dataset_statistics.json").read_text())
    assert set(stats) == {"capvector"}
    reloaded = from_pretrained(folder).eval()
    assert not any("lora" in k or "base_layer" in k for k in reloaded.state_dict())
    batch = next(
        iter(dm.val_dataloader() or torch.utils.data.DataLoader(dm.train_dataset, batch_size=2))
    )
    module.eval()
    torch.testing.assert_close(
        reloaded.predict_action(batch), module.backbone.predict_action(batch), atol=1e-5, rtol=1e-4
    )


def test_checkpoint_round_trip_gives_identical_predictions(demo_file: Path, tmp_path: Path) -> None:
    dm = datamodule(demo_file)
    module = VLAModule(
        backbone="openvla-oft-tiny", data_spec=dm.spec, lora=LoraSettings(r=4, alpha=4)
    )
    trainer = fit(module, dm, tmp_path)
    ckpt = tmp_path / "model.ckpt"
    trainer.save_checkpoint(ckpt)
    saved = torch.load(ckpt, weights_only=False)
    assert saved["capvector"]["lora"] == {"r": 4, "alpha": 4, "scaling": 1.0}
    assert (
        saved["capvector"]["data_spec"]["statistics"] == dm.spec.statistics
    )  # statistics travel along
    restored = load_module(ckpt).eval()
    batch = next(iter(torch.utils.data.DataLoader(dm.train_dataset, batch_size=2)))
    module.eval()
    torch.testing.assert_close(restored(batch), module(batch))


def test_pretrained_start_and_data_mismatch(demo_file: Path, tmp_path: Path) -> None:
    dm = datamodule(demo_file)
    module = VLAModule(backbone="openvla-oft-tiny", data_spec=dm.spec)
    folder = module.export(tmp_path / "pre")
    started = VLAModule(pretrained=str(folder), data_spec=dm.spec)
    assert VLAModule(pretrained=str(folder)).data_spec == dm.spec  # unset: the export's own
    for (name, a), b in zip(
        module.backbone.state_dict().items(), started.backbone.state_dict().values(), strict=False
    ):
        assert torch.equal(a, b), name
    short = RobotDataModule(train_files=[str(demo_file)], chunk_size=4)
    with pytest.raises(BackboneError, match="chunk_size is 8 in the model but 4 in the data"):
        VLAModule(pretrained=str(folder), data_spec=short.spec)
    same = VLAModule(backbone="openvla-oft-tiny", pretrained=str(folder), data_spec=dm.spec)
    assert torch.equal(next(same.parameters()), next(started.parameters()))
    with pytest.raises(BackboneError, match="model.backbone is 'pi05-tiny' but model.pretrained"):
        VLAModule(backbone="pi05-tiny", pretrained=str(folder), data_spec=dm.spec)
    assert VLAModule(data_spec=dm.spec).backbone.config.preset == "openvla-oft-tiny"


def test_schedules() -> None:
    from capvector.module import _schedule

    step = _schedule(OptimizerSettings(schedule="step", decay_steps=[10]), 100)
    assert step(9) == 1.0 and step(10) == pytest.approx(0.1)
    cosine = _schedule(OptimizerSettings(schedule="cosine", warmup_steps=10, min_lr_ratio=0.0), 110)
    assert (
        cosine(0) == pytest.approx(0.1)
        and cosine(10) == pytest.approx(1.0)
        and cosine(110) == pytest.approx(0.0)
    )
    with pytest.raises(ValueError, match="unknown lr schedule"):
        _schedule(OptimizerSettings(schedule="linear"), 10)


def test_cli_fit_writes_checkpoint_and_export(tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(20, 20))
    root = tmp_path / "runs"
    main([
        "fit", "--config", str(REPO / "configs/debug.yaml"), f"--data.train_files=[{data}]",
        "--trainer.max_steps=3", f"--trainer.default_root_dir={root}", "--data.eval_tasks=null",
        f"--trainer.logger.init_args.save_dir={root}", "--trainer.enable_progress_bar=false",
    ])  # fmt: skip
    version = root / "fit" / "version_0"
    assert list((version / "checkpoints").glob("*.ckpt"))
    export = version / "export"
    assert (export / "model.safetensors").is_file() and (
        export / "dataset_statistics.json"
    ).is_file()
    assert (version / "config.yaml").is_file()  # the resolved config travels with the run
    assert (
        main(
            [
                "export",
                "--ckpt",
                str(next((version / "checkpoints").glob("*.ckpt"))),
                "--out",
                str(tmp_path / "e2"),
            ]
        )
        == 0
    )
    assert from_pretrained(tmp_path / "e2").config.chunk_size == 8


def test_cli_errors_are_clear(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(20,))
    assert main(["fit", "--config", str(REPO / "configs/debug.yaml"), f"--data.train_files=[{data}]",
                 "--model.backbone=openvla-oft-tinyy", "--trainer.max_steps=1", "--data.eval_tasks=null"]) == 2  # fmt: skip
    assert "unknown backbone preset 'openvla-oft-tinyy'" in capsys.readouterr().err
    assert (
        main(
            [
                "fit",
                "--config",
                str(REPO / "configs/debug.yaml"),
                f"--data.train_files=[{tmp_path}/nope.hdf5]",
                "--data.generate=null",
            ]
        )
        == 2
    )
    assert "not found" in capsys.readouterr().err
    assert not (tmp_path / "nope.hdf5").exists()
    assert main(["backbone-info", "openvla-oft-7b"]) == 0
    out = capsys.readouterr().out
    assert "7,709,173,191" in out and "151,117,831" in out
    assert main(["frobnicate"]) == 2
