"""The README's backbone example is real code: it runs and trains through VLAModule."""

from __future__ import annotations

import re
import sys
import types
from pathlib import Path

import pytest
import torch

from capvector.backbones import build_backbone, list_presets
from capvector.data import keys
from capvector.module import VLAModule
from conftest import restored_registry

README = Path(__file__).resolve().parents[1] / "README.md"


def run_backbone_example(monkeypatch: pytest.MonkeyPatch) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    example = next(b for b in blocks if "register_family" in b)
    module = types.ModuleType("readme_example")  # dataclasses look their module up in sys.modules
    monkeypatch.setitem(sys.modules, module.__name__, module)
    exec(compile(example, "README.md", "exec"), module.__dict__)


def test_readme_backbone_example_builds_and_trains(
    monkeypatch: pytest.MonkeyPatch, scoped_registry: None
) -> None:
    run_backbone_example(monkeypatch)
    model = build_backbone("tiny-mlp")
    batch = {
        keys.IMAGES: torch.rand(4, 2, 3, 64, 64),
        keys.PROPRIO: torch.rand(4, 8),
        keys.ACTIONS: torch.rand(4, 8, 7),
        keys.INSTRUCTION: ["lift"] * 4,
    }
    module = VLAModule(backbone="tiny-mlp")
    optimizer = torch.optim.AdamW(module.parameters(), lr=1e-2)
    first = module.compute_losses(batch)["action"].item()
    for _ in range(20):
        loss = module.compute_losses(batch)["action"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert loss.item() < first
    assert model.capability_parameter_names() == ["body.0.weight", "body.0.bias"]


def test_the_example_preset_is_registered_only_inside_its_test(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with restored_registry():
        run_backbone_example(monkeypatch)
        assert "tiny-mlp" in list_presets()
    assert "tiny-mlp" not in list_presets() and "openvla-oft-tiny" in list_presets()


def test_readme_peft_snippet_names_real_functions() -> None:
    """The peft snippet's imports and calls exist (tests/test_vectors_extract.py runs the same
    steps on real folders and compares with `capvector merge`)."""
    block = next(
        b
        for b in re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
        if "PeftModel" in b
    )
    namespace: dict = {}
    exec(compile("\n".join(line for line in block.splitlines() if line.startswith("from")), "README.md", "exec"), namespace)  # fmt: skip
    assert {"PeftModel", "from_pretrained", "VectorFolder", "apply_vector_"} <= set(namespace)
    assert hasattr(namespace["VectorFolder"], "load_outside_adapter")
