"""Per-family training defaults live in the family's ``configuration.py`` (as LeRobot's
``configuration_pi05.py`` carries ``normalization_mapping`` and ``get_optimizer_preset``): a fit
that names only the preset trains with its family's normalisation and optimizer, a config may
override them, and the backbone YAMLs say what the code says."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from capvector.backbones import preset_config
from capvector.backbones.base import registered_families
from capvector.cli import main
from capvector.data.statistics import BOUNDS_Q99, QUANTILES
from conftest import write_demo_file

REPO = Path(__file__).resolve().parents[1]


def fit(tmp_path: Path, *extra: str) -> dict:
    """A one-step fit of the given options (no backbone YAML); its last checkpoint."""
    demos = tmp_path / "demos.hdf5"
    if not demos.exists():
        write_demo_file(demos)
    out = tmp_path / "run"
    args = [
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=1", f"--trainer.default_root_dir={out}",
        "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={out}", f"--data.train_files=[{demos}]",
        "--data.batch_size=2", "--data.load_depth=false",
        "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint", "--trainer.callbacks.save_last=true",
        *extra,
    ]  # fmt: skip
    assert main(args) == 0
    (last,) = out.rglob("last.ckpt")
    return torch.load(last, map_location="cpu", weights_only=False)


def test_a_pi05_fit_without_its_yaml_uses_pi05s_normalisation_and_optimizer(
    tmp_path: Path,
) -> None:
    checkpoint = fit(tmp_path, "--model.backbone=pi05-tiny")
    assert checkpoint["datamodule_hyper_parameters"]["normalization"] == QUANTILES
    group = checkpoint["optimizer_states"][0]["param_groups"][0]
    assert tuple(group["betas"]) == (0.9, 0.95) and group["weight_decay"] == 1e-10
    assert group["initial_lr"] == 2.5e-5  # openpi's peak; the first step is in its warmup
    assert checkpoint["lr_schedulers"][0]["base_lrs"][0] == 2.5e-5


def test_a_config_overrides_the_familys_defaults(tmp_path: Path) -> None:
    checkpoint = fit(
        tmp_path, "--model.backbone=pi05-tiny", f"--data.normalization={BOUNDS_Q99}",
        "--model.optimizer.lr=0.001",
    )  # fmt: skip
    assert checkpoint["datamodule_hyper_parameters"]["normalization"] == BOUNDS_Q99
    group = checkpoint["optimizer_states"][0]["param_groups"][0]
    assert group["initial_lr"] == 0.001 and tuple(group["betas"]) == (0.9, 0.999)


def test_an_openvla_oft_fit_keeps_openvla_ofts_defaults(tmp_path: Path) -> None:
    checkpoint = fit(tmp_path, "--model.backbone=openvla-oft-tiny")
    assert checkpoint["datamodule_hyper_parameters"]["normalization"] == BOUNDS_Q99
    group = checkpoint["optimizer_states"][0]["param_groups"][0]
    assert group["initial_lr"] == 5e-4 and tuple(group["betas"]) == (0.9, 0.999)


@pytest.mark.parametrize("path", sorted((REPO / "configs/backbones").glob("*.yaml")), ids=str)
def test_backbone_yamls_say_what_the_family_code_says(path: Path) -> None:
    config = yaml.safe_load(path.read_text())
    family = type(preset_config(config["model"]["backbone"]))
    if "normalization" in config.get("data", {}):
        assert config["data"]["normalization"] == family.normalization
    optimizer = config["model"].get("optimizer", {})
    for key, value in optimizer.items():  # what the YAML adds (OFT's LIBERO decay) is its own
        if key in family.optimizer_preset:
            expected = family.optimizer_preset[key]
            assert (list(expected) if isinstance(expected, tuple) else expected) == value, key


def test_every_family_preset_names_optimizer_settings_fields() -> None:
    from dataclasses import fields

    from capvector.module import OptimizerSettings

    names = {f.name for f in fields(OptimizerSettings)}
    for cls in registered_families().values():
        assert set(cls.config_class.optimizer_preset) <= names, cls.config_class.family
        OptimizerSettings(**cls.config_class.optimizer_preset)
