"""Building and loading in the frozen dtype (``backbones.materialize``): the weights a float32
build would have, rounded; what trains in float32 with the export's full precision; and a process's
peak memory while building about the stored weights' size, not the float32 model's."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule
from capvector.training.lora import LoraSettings

PRESETS = ["openvla-oft-tiny", "pi05-tiny", "starvla-tiny-gr00t"]


@pytest.mark.parametrize("preset", PRESETS)
def test_built_in_bf16_holds_the_float32_build_rounded(demo_file: Path, preset: str) -> None:
    spec = RobotDataModule(train_files=[str(demo_file)]).spec
    modules = {}
    for dtype in ("float32", "bfloat16"):
        torch.manual_seed(0)
        modules[dtype] = VLAModule(
            backbone=preset, data_spec=spec, lora=LoraSettings(r=4, alpha=4), frozen_dtype=dtype
        )
    full = dict(modules["float32"].named_parameters())
    for name, param in modules["bfloat16"].named_parameters():
        assert param.dtype == (torch.float32 if param.requires_grad else torch.bfloat16), name
        if ".lora_" in name:  # drawn after the build, by peft, in the base layer's dtype
            continue
        # The float32 build's weights, rounded once (heads that train: rounded, then float32) ...
        reference = full[name].detach().to(torch.bfloat16).to(param.dtype)
        if not torch.equal(param.detach(), reference):
            # ... except where an upstream init draws past torch.nn.init (SigLIP's own variance
            # scaling): other draws of the same distribution, never timm's bf16 erfinv outliers.
            a, b = param.detach().float(), full[name].detach().float()
            assert abs(a.std() - b.std()) <= 0.05 * b.std() + 1e-6, name
            assert a.abs().max() <= 1.1 * b.abs().max() + 1e-6, name
    assert any(not p.requires_grad for p in modules["bfloat16"].parameters())


def test_pretrained_loads_into_bf16_and_keeps_trained_weights_float32(
    demo_file: Path, tmp_path: Path
) -> None:
    dm = RobotDataModule(train_files=[str(demo_file)], batch_size=4)
    source = VLAModule(backbone="pi05-tiny", data_spec=dm.spec)
    folder = source.export(tmp_path / "pre")
    started = VLAModule(
        pretrained=str(folder), data_spec=dm.spec, lora=LoraSettings(r=4, alpha=4),
        frozen_dtype="bfloat16",
    )  # fmt: skip
    exported = source.backbone.state_dict()
    for name, tensor in started.backbone.state_dict(keep_vars=True).items():
        if ".lora_" in name:
            continue
        reference = exported[name.replace(".base_layer.", ".")]
        if tensor.requires_grad:
            assert tensor.dtype == torch.float32 and torch.equal(tensor.detach(), reference), name
        else:
            assert torch.equal(tensor.detach(), reference.to(tensor.dtype)), name


def test_frozen_weights_a_vector_lands_in_get_the_exports_full_precision(
    demo_file: Path, tmp_path: Path
) -> None:
    """Loaded in bf16, then kept in float32 by a callback (MergeCapabilityVector does so in
    setup): configure_model reads them again from the export, so λc is added to θ_pre itself."""
    dm = RobotDataModule(train_files=[str(demo_file)], batch_size=4)
    source = VLAModule(backbone="openvla-oft-tiny", data_spec=dm.spec)
    folder = source.export(tmp_path / "pre")
    started = VLAModule(pretrained=str(folder), data_spec=dm.spec, frozen_dtype="bfloat16")
    exported = source.backbone.state_dict()
    name = next(  # a frozen weight that bf16 cannot hold exactly
        n
        for n, p in started.backbone.named_parameters()
        if not p.requires_grad and not torch.equal(p.float(), exported[n])
    )
    reference = exported[name]
    started.float32_parameters.add(name)
    started.configure_model()
    kept = started.backbone.get_parameter(name)
    assert kept.dtype == torch.float32 and torch.equal(kept.detach(), reference)


# A pi05-3b with fewer layers and a byte vocabulary: ≈ 180 M parameters, built as training builds
# it (LoRA r 32). Peak memory is the RSS high-water mark of a fresh interpreter (ru_maxrss) above
# its RSS once everything is imported: tracemalloc does not see torch's allocations.
MID_SIZE = {
    "tokenizer": "byte", "vocab_size": 260, "vlm": {"num_layers": 1},
    "expert": {"num_layers": 1}, "vision": {"num_layers": 2},
}  # fmt: skip
PEAK_SCRIPT = """
import json, resource, sys
import torch, peft
from capvector.module import VLAModule
from capvector.training.lora import LoraSettings
import transformers.models.gemma.modeling_gemma, transformers.models.siglip.modeling_siglip
def high_water(): return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
baseline = high_water()
dtype, overrides, pretrained = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3] or None
export = sys.argv[4] or None
torch.manual_seed(0)
module = VLAModule(
    backbone=None if pretrained else "pi05-3b", backbone_overrides=None if pretrained else overrides,
    pretrained=pretrained, lora=LoraSettings(r=32, alpha=16), frozen_dtype=dtype,
)
peak = high_water() - baseline
if export:
    module.export(export)
params = list(module.parameters())
print(json.dumps({
    "peak": peak,
    "export_peak": high_water() - baseline,
    "stored": sum(p.numel() * p.element_size() for p in params),
    "float32": sum(p.numel() * 4 for p in params),
    "largest_float32": max(p.numel() * 4 for p in params),
}))
"""


def build_peak(
    dtype: str,
    pretrained: Path | None = None,
    overrides: dict[str, Any] = MID_SIZE,
    export: Path | None = None,
) -> dict[str, int]:
    args = [dtype, json.dumps(overrides), str(pretrained or ""), str(export or "")]
    out = subprocess.run(
        [sys.executable, "-c", PEAK_SCRIPT, *args],
        capture_output=True, text=True, env={"OMP_NUM_THREADS": "1", "PATH": ""},
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_peak_build_memory_is_about_the_bf16_size(tmp_path: Path) -> None:
    """Built in bf16, and loaded in bf16 from an export, a process peaks at the stored size plus
    a module in float32 (here two of its largest tensors), not at the float32 model's size."""

    def check(measured: dict[str, int]) -> None:
        bound = measured["stored"] + 2 * measured["largest_float32"]
        assert measured["peak"] <= bound, measured
        assert measured["peak"] <= 0.8 * measured["float32"], measured

    built = build_peak("bfloat16")
    assert built["stored"] < 0.55 * built["float32"]
    check(built)
    torch.manual_seed(0)
    module = VLAModule(
        backbone="pi05-3b", backbone_overrides=MID_SIZE, lora=LoraSettings(r=32, alpha=16),
        frozen_dtype="bfloat16",
    )  # fmt: skip
    folder = module.export(tmp_path / "pre")
    del module
    check(build_peak("bfloat16", folder))


@pytest.mark.slow
def test_an_export_holds_one_merged_layer_at_a_time_not_a_second_model(tmp_path: Path) -> None:
    """Exporting a LoRA fit merges and casts each layer as it is written: the process grows by a
    few float32 copies of one layer, not by the merged weights of every LoRA target (before,
    a bf16 ``pi05-3b`` export peaked at twice its build). Four layers per tower, so the merged
    targets (≈ the stored size) dwarf one layer."""
    four_layers = {**MID_SIZE, "vlm": {"num_layers": 4}, "expert": {"num_layers": 4}}
    measured = build_peak("bfloat16", overrides=four_layers, export=tmp_path / "export")
    growth = measured["export_peak"] - measured["peak"]
    assert growth <= 0.5 * measured["stored"], measured
    assert (tmp_path / "export" / "model.safetensors").is_file()


def test_a_bf16_export_loads_for_inference_in_bf16(demo_file: Path, tmp_path: Path) -> None:
    """``capvector serve`` and ``evaluate`` under autocast (``load_for_inference(keep_dtype)``): a
    bf16 export's weights stay bf16, as written (a full-size one in float32 is twice the memory),
    and the policy answers as from the float32 load, up to bf16 rounding of the norms."""
    import numpy as np

    from capvector.module import load_for_inference
    from capvector.policy import VLAPolicy

    dm = RobotDataModule(train_files=[str(demo_file)], batch_size=4)
    torch.manual_seed(0)
    source = VLAModule(
        backbone="openvla-oft-tiny", data_spec=dm.spec, lora=LoraSettings(r=4, alpha=4),
        frozen_dtype="bfloat16",
    )  # fmt: skip
    folder = source.export(tmp_path / "bf16")
    (kept, spec), (full, _) = (
        load_for_inference(folder, keep_dtype=True),
        load_for_inference(folder),
    )
    assert spec == source.data_spec and not kept.training
    floating = [p for p in kept.parameters() if p.is_floating_point()]
    assert floating and all(p.dtype == torch.bfloat16 and not p.requires_grad for p in floating)
    assert all(p.dtype == torch.float32 for p in full.parameters() if p.is_floating_point())
    reference = full.state_dict()
    for name, tensor in kept.state_dict().items():
        assert torch.equal(tensor.float(), reference[name].float()), name
    rng = np.random.default_rng(0)
    observation = {
        "images": {c: rng.integers(0, 255, (64, 64, 3), dtype=np.uint8) for c in spec.cameras},
        "proprio": rng.normal(size=spec.proprio_dim).astype(np.float32),
        "instruction": "lift the red cube",
    }
    a = VLAPolicy(kept, spec, "bf16-mixed")(observation)
    b = VLAPolicy(full, spec, "bf16-mixed")(observation)
    assert np.isfinite(a).all() and a.shape == b.shape
    np.testing.assert_allclose(a, b, atol=0.1 * np.abs(b).max() + 1e-3)
