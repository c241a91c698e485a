"""An open registry: a backbone from a package outside capvector trains through `capvector fit`.

The package is written into a folder outside ``src/`` and reached the two ways a user would: an
installed distribution's entry point (a ``.dist-info`` folder with ``entry_points.txt``, which
``importlib.metadata`` reads as it reads any installed package), and a ``module:preset`` name.
It also reads its own "original" checkpoints, with an import option of its own that
``capvector import-original`` offers. Nothing in capvector is edited. The runs are subprocesses,
as a user's shell would start them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from conftest import write_demo_file

BACKBONE = """
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from capvector.backbones import (
    BackboneConfig, ImportOption, OutputRequest, VLABackbone, VLAOutput, register_family,
    register_preset,
)
from capvector.data import keys


@dataclass
class PooledMLPConfig(BackboneConfig):
    family = "pooled-mlp"
    width: int = 32


@register_family
class PooledMLP(VLABackbone):
    config_class = PooledMLPConfig
    original_loader = "pooled_vla.convert"
    import_options = (ImportOption("scale", "multiply the original weights by this", type=float),)
    lora_target_modules = ["body.0"]
    lora_trainable_modules = ("head.*",)
    capability_parameters = ("body.*",)
    num_layers = 1
    hidden_size = property(lambda self: self.config.width)

    def __init__(self, config):
        super().__init__(config)
        c = config
        self.body = nn.Sequential(nn.Linear(c.num_images * 3 + c.proprio_dim, c.width), nn.GELU())
        self.head = nn.Linear(c.width, c.chunk_size * c.action_dim)

    def forward(self, batch, request=None):
        pooled = batch[keys.IMAGES].mean(dim=(-1, -2)).flatten(1)
        hidden = self.body(torch.cat([pooled, batch[keys.PROPRIO]], -1))
        actions = self.head(hidden).view(-1, self.config.chunk_size, self.config.action_dim)
        loss = F.l1_loss(actions, batch[keys.ACTIONS]) if keys.ACTIONS in batch else None
        return VLAOutput(actions=actions, loss=loss, hidden_states={1: hidden[:, None]})


@register_preset("pooled-mlp-tiny")
def pooled_mlp_tiny():
    return PooledMLPConfig(image_size=64)
"""

# The "original project" stores the same tensors under `net.` and has no statistics.
CONVERT = """
from safetensors.torch import load_file

from capvector.backbones import OriginalCheckpoint, preset_config


def load_original(cls, source, preset=None, overrides=None, scale: float = 1.0):
    state = load_file(f"{source}/original.safetensors")
    model = cls(preset_config(preset or "pooled-mlp-tiny", **(overrides or {})))
    model.load_state_dict({k.removeprefix("net."): v * scale for k, v in state.items()})
    return OriginalCheckpoint(model, statistics={})
"""


@pytest.fixture(scope="module")
def outside(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("outside")
    package = root / "code" / "pooled_vla"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "model.py").write_text(BACKBONE)
    (package / "convert.py").write_text(CONVERT)
    installed = root / "installed"  # what `pip install` of a package with an entry point leaves
    info = installed / "pooled_vla-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: pooled-vla\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[capvector.backbones]\npooled = pooled_vla.model\n")
    data = write_demo_file(root / "demos.hdf5")
    return {"code": root / "code", "installed": installed, "data": data, "root": root}


def python_path(*paths: Path) -> dict[str, str]:
    """The environment with ``paths`` put before the current PYTHONPATH (which may name the
    capvector under test)."""
    entries = [*map(str, paths), os.environ.get("PYTHONPATH", "")]
    return dict(os.environ, PYTHONPATH=os.pathsep.join(e for e in entries if e))


def capvector(args: list[str], paths: list[Path]) -> subprocess.CompletedProcess:
    env = python_path(*paths)
    command = [sys.executable, "-c", "import sys; from capvector.cli import main; sys.exit(main())"]
    return subprocess.run(command + args, env=env, capture_output=True, text=True, timeout=600)


def fit(out: Path, backbone: str, data: Path, paths: list[Path]) -> Path:
    done = capvector([
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=3",
        "--trainer.enable_progress_bar=false", f"--trainer.default_root_dir={out}",
        "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
        "--trainer.callbacks.save_last=true", f"--model.backbone={backbone}",
        f"--data.train_files=[{data}]", "--data.batch_size=4",
    ], paths)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    (ckpt,) = out.rglob("last.ckpt")
    return ckpt


def test_an_installed_package_registers_its_backbone_by_entry_point(outside, tmp_path) -> None:
    ckpt = fit(
        tmp_path / "fit",
        "pooled-mlp-tiny",
        outside["data"],
        [outside["code"], outside["installed"]],
    )
    export = tmp_path / "export"
    done = capvector(
        ["export", "--ckpt", str(ckpt), "--out", str(export)],
        [outside["code"], outside["installed"]],
    )
    assert done.returncode == 0, done.stderr[-3000:]
    config = json.loads((export / "config.json").read_text())
    assert (
        config["family"] == "pooled-mlp"
        and config["backbone_config"]["preset"] == "pooled-mlp-tiny"
    )


def test_a_module_path_names_a_backbone_without_installing_it(outside, tmp_path) -> None:
    preset = "pooled_vla.model:pooled-mlp-tiny"
    ckpt = fit(tmp_path / "fit", preset, outside["data"], [outside["code"]])
    export = tmp_path / "export"
    done = capvector(["export", "--ckpt", str(ckpt), "--out", str(export)], [outside["code"]])
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((export / "config.json").read_text())["backbone_config"]["preset"] == preset
    # The export finds its module again from the recorded name, in a fresh process.
    check = textwrap.dedent(f"""
        from capvector.backbones import from_pretrained
        model = from_pretrained({str(export)!r})
        assert type(model).__name__ == "PooledMLP", type(model)
    """)
    env = python_path(outside["code"])
    done = subprocess.run([sys.executable, "-c", check], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]


def test_an_unknown_backbone_says_how_to_add_one(outside) -> None:
    done = capvector(
        ["fit", "--model.backbone=pooled-mlp-tiny", f"--data.train_files=[{outside['data']}]"], []
    )
    assert done.returncode != 0
    assert "unknown backbone preset 'pooled-mlp-tiny'" in done.stderr
    assert "your.module:preset" in done.stderr and "capvector.backbones" in done.stderr
    done = capvector(
        ["fit", "--model.backbone=not_a_module:x", f"--data.train_files=[{outside['data']}]"], []
    )
    assert done.returncode != 0 and "cannot import backbone module 'not_a_module'" in done.stderr


def test_an_outside_family_declares_an_import_option_and_receives_it(outside, tmp_path) -> None:
    """`capvector import-original` builds its options from the families' `import_options`: the
    outside family's `--scale` is in the help and reaches its loader; other presets refuse it."""
    import torch
    from safetensors.torch import load_file, save_file

    width, inputs, outputs = 32, 2 * 3 + 8, 8 * 7  # PooledMLPConfig's defaults
    weights = {
        "net.body.0.weight": torch.randn(width, inputs),
        "net.body.0.bias": torch.randn(width),
        "net.head.weight": torch.randn(outputs, width),
        "net.head.bias": torch.randn(outputs),
    }
    original = tmp_path / "original"
    original.mkdir()
    save_file(weights, str(original / "original.safetensors"))
    paths = [outside["code"], outside["installed"]]

    shown = capvector(["import-original", "--help"], paths)
    assert shown.returncode == 0, shown.stderr[-3000:]
    assert "options of pooled-mlp presets" in shown.stdout and "--scale SCALE" in shown.stdout
    assert "--apply-lora-adapter" in shown.stdout  # the built-in families' options too

    export = tmp_path / "export"
    args = ["import-original", "--folder", str(original), "--scale", "2.5"]
    done = capvector([*args, "--preset", "pooled-mlp-tiny", "--out", str(export)], paths)
    assert done.returncode == 0, done.stderr[-3000:]
    imported = load_file(str(export / "model.safetensors"))
    assert imported.keys() == {k.removeprefix("net.") for k in weights}
    for key, value in weights.items():
        torch.testing.assert_close(imported[key.removeprefix("net.")], value * 2.5)

    other = tmp_path / "other"
    done = capvector([*args, "--preset", "openvla-oft-tiny", "--out", str(other)], paths)
    assert done.returncode == 2 and "unrecognized arguments: --scale 2.5" in done.stderr
    assert not other.exists()


# Where the built-in families lived before each became a package (capvector.backbones.<family>
# was a module): exports and checkpoints may record `capvector.backbones.pi05:pi05-tiny`.
PRE_PACKAGE_MODULES = {
    "openvla-oft-tiny": "capvector.backbones.openvla_oft",
    "pi05-tiny": "capvector.backbones.pi05",
    "starvla-tiny-oft": "capvector.backbones.starvla",
}


def test_exports_naming_a_built_in_family_by_its_old_module_path_still_load(tmp_path) -> None:
    """The recorded name is resolved both ways a reader does: `from_pretrained` (the family) and
    `build_backbone` of the recorded preset (what `load_module` does with a checkpoint's), in a
    fresh process; the shipped θ_pre (a plain preset name) loads as well."""
    from capvector.backbones import build_backbone

    folders = {str(Path(__file__).parents[1] / "assets" / "theta_pre"): "openvla-oft-tiny"}
    for preset, module in PRE_PACKAGE_MODULES.items():
        folder = build_backbone(preset).save_pretrained(tmp_path / preset)
        config = json.loads((folder / "config.json").read_text())
        config["backbone_config"]["preset"] = f"{module}:{preset}"
        (folder / "config.json").write_text(json.dumps(config))
        folders[str(folder)] = config["backbone_config"]["preset"]
    check = textwrap.dedent(f"""
        from capvector.backbones import build_backbone, from_pretrained
        for folder, preset in {folders!r}.items():
            model = from_pretrained(folder)
            assert model.config.preset == preset, (folder, model.config.preset)
            assert type(build_backbone(preset)) is type(model), folder
    """)
    done = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
