"""One LoRA merge for every path, refereed by peft's own ``merge_and_unload``.

The paths: export (``VLAModule.export`` merges a live peft state dict), a LoRA checkpoint read as a
vector source (``io.weights.CheckpointSource``), a PEFT adapter read as a vector
(``vectors.lowrank.read_adapter``) and OpenVLA-OFT's adapter import (``merge_peft_adapter``). Each
must give peft's merged weights, including a ``lora_B`` bias, embedding LoRA and
``fan_in_fan_out`` (GPT-2's Conv1D) layers.
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from peft import LoraConfig, get_peft_model
from torch import nn
from transformers.pytorch_utils import Conv1D

from capvector.backbones.openvla_oft.convert import merge_peft_adapter
from capvector.io.lora_layers import constant_scaling, merge_lora
from capvector.io.names import CheckpointMetadata
from capvector.io.weights import CheckpointSource
from capvector.vectors.lowrank import read_adapter

R, ALPHA = 2, 3.0


class Net(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.emb = nn.Embedding(10, 6)
        self.lin = nn.Linear(6, 5)
        self.conv1d = Conv1D(4, 5)  # GPT-2 layout: weight (in, out), peft needs fan_in_fan_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv1d(self.lin(self.emb(x)))


CASES = {
    "linear with lora_B bias": LoraConfig(
        r=R, lora_alpha=ALPHA, target_modules=["lin"], lora_bias=True, init_lora_weights=False
    ),
    "embedding": LoraConfig(
        r=R, lora_alpha=ALPHA, target_modules=["emb", "lin"], init_lora_weights=False
    ),
    "fan_in_fan_out": LoraConfig(
        r=R, lora_alpha=ALPHA, target_modules=["conv1d"], fan_in_fan_out=True,
        init_lora_weights=False,
    ),
}  # fmt: skip


@pytest.fixture(params=list(CASES))
def peft_model(request: pytest.FixtureRequest) -> tuple[nn.Module, dict[str, torch.Tensor]]:
    torch.manual_seed(0)
    base = Net()
    model = get_peft_model(base, copy.deepcopy(CASES[request.param]))
    with torch.no_grad():  # non-zero B and bias, so every part of the delta shows
        for name, param in model.named_parameters():
            if "lora_" in name:
                param.normal_()
    expected = copy.deepcopy(model).merge_and_unload().state_dict()
    return model, expected


def _inner_state(model: nn.Module) -> dict[str, torch.Tensor]:
    """The live (unmerged) peft state dict without peft's wrapper prefix, as our modules hold it."""
    return {
        k.removeprefix("base_model.model."): v.detach().clone()
        for k, v in model.state_dict().items()
    }


def _assert_weights(merged: dict[str, torch.Tensor], expected: dict[str, torch.Tensor]) -> None:
    assert set(merged) == set(expected)
    for key, value in expected.items():
        torch.testing.assert_close(merged[key].float(), value, rtol=1e-6, atol=1e-6, msg=key)


def _fan_in_fan_out(model: nn.Module) -> bool:
    return bool(model.peft_config["default"].fan_in_fan_out)


def test_export_merge_equals_peft(peft_model) -> None:
    model, expected = peft_model
    merged = merge_lora(
        _inner_state(model), constant_scaling(ALPHA / R), fan_in_fan_out=_fan_in_fan_out(model)
    )
    _assert_weights(merged, expected)


def test_checkpoint_source_equals_peft(peft_model, tmp_path: Path) -> None:
    model, expected = peft_model
    state = {f"backbone.{k}": v for k, v in _inner_state(model).items()}
    path = tmp_path / "lora.ckpt"
    lora = {"scaling": ALPHA / R, "fan_in_fan_out": _fan_in_fan_out(model)}
    meta = CheckpointMetadata(family="peft-test", backbone_config={"preset": "net"}, lora=lora)
    torch.save({"state_dict": state, "capvector": meta.to_dict()}, path)
    source = CheckpointSource(path)
    names = source.keys()
    _assert_weights({k: source.read(k) for k in names}, expected)
    rows = slice(1, 3)  # vectors read large weights a block of rows at a time
    for key in names:
        if source.info(key).shape and source.info(key).shape[0] >= 3:
            torch.testing.assert_close(source.read(key, rows).float(), expected[key][rows])


def test_adapter_folder_paths_equal_peft(peft_model, tmp_path: Path) -> None:
    model, expected = peft_model
    model.save_pretrained(tmp_path / "adapter")  # peft writes the adapter folder itself
    base = merge_lora(_inner_state(model), constant_scaling(0.0))  # scaling 0: the base alone

    factors, biases = read_adapter(tmp_path / "adapter")
    as_vector = dict(base)
    for key, delta in factors.items():
        as_vector[key] = base[key] + delta.rows().reshape(base[key].shape)
    for key, delta in biases.items():
        as_vector[key] = base[key] + delta
    _assert_weights(as_vector, expected)

    imported = dict(base)
    merge_peft_adapter(imported, tmp_path / "adapter")
    _assert_weights(imported, expected)


def test_checkpoint_metadata_errors_name_what_is_missing(tmp_path: Path) -> None:
    from capvector.errors import CapVectorError

    path = tmp_path / "x.ckpt"
    torch.save({"state_dict": {"backbone.w": torch.zeros(1)}}, path)
    with pytest.raises(CapVectorError, match="not a capvector checkpoint .no `capvector`"):
        CheckpointSource(path)
    torch.save({"state_dict": {"backbone.w": torch.zeros(1)}, "capvector": {"family": "x"}}, path)
    with pytest.raises(CapVectorError, match="metadata lacks backbone_config"):
        CheckpointSource(path)
