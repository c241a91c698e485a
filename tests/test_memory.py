"""The meta-device memory estimate against what the same step saves on the CPU."""

from __future__ import annotations

import pytest
import torch

from capvector.backbones import build_backbone, list_presets
from capvector.backbones.starvla import HALF, tiny_qwen_architecture
from capvector.cli import main
from capvector.memory import (
    estimate_memory,
    measure_activations,
    saved_activation_bytes,
    synthetic_batch,
)

TINY_PRESETS = [name for name in list_presets() if "tiny" in name]


@pytest.mark.parametrize("preset", TINY_PRESETS)
def test_meta_activation_estimate_is_close_to_a_real_step(preset: str) -> None:
    """Every family, including those whose forward reads values (prompts with the discretised
    state, Qwen-VL's token positions): the batch keeps its values on the CPU while the weights
    stay on the meta device."""
    estimate = estimate_memory(preset, batch_size=4, precision="32-true", strategy="ddp")
    torch.manual_seed(0)
    model = build_backbone(preset)
    store: list[float] = []
    with saved_activation_bytes(store):
        model(synthetic_batch(model, 4, "cpu")).loss.backward()
    # The meta device takes SDPA's math path (it saves attention weights), the CPU a fused kernel,
    # so the estimate is an upper bound, but of the right size. Attention weights grow with the
    # square of the sequence: openvla-oft-aloha-tiny's ~600 tokens (3 cameras, 25 x 14 action
    # slots) put its bound at ~2.4x.
    assert store[0] <= estimate.activations <= 2.5 * store[0]
    assert estimate.activations_checkpointed < 0.25 * estimate.activations


def test_qwen3_vl_masks_on_meta_features_trace_too() -> None:
    """Qwen3-VL indexes hidden states with the visual-token mask (deepstack), on meta features."""
    qwen3 = dict(
        qwen_version="qwen3-vl", qwen=tiny_qwen_architecture("qwen3-vl"), image_mean=HALF,
        image_std=HALF,
    )  # fmt: skip
    torch.manual_seed(0)
    model = build_backbone("starvla-tiny-gr00t", **qwen3)
    batch = synthetic_batch(model, 2, "cpu")
    store: list[float] = []
    with saved_activation_bytes(store):
        model(batch)
    with torch.device("meta"):
        meta_model = build_backbone("starvla-tiny-gr00t", **qwen3)
    estimate = measure_activations(meta_model, batch, checkpointed=False)
    assert store[0] <= estimate <= 2.0 * store[0]


def test_strategies_shard_what_they_should() -> None:
    ddp = estimate_memory("openvla-oft-tiny", strategy="ddp", devices=4, precision="32-true")
    zero2 = estimate_memory(
        "openvla-oft-tiny", strategy="deepspeed_zero2", devices=4, precision="32-true"
    )
    fsdp = estimate_memory("openvla-oft-tiny", strategy="fsdp2", devices=4, precision="32-true")
    params = sum(p.numel() for p in build_backbone("openvla-oft-tiny").parameters())
    assert ddp.parameters == zero2.parameters == pytest.approx(4 * params)
    assert zero2.optimizer == pytest.approx(ddp.optimizer / 4)
    assert fsdp.parameters < ddp.parameters
    with pytest.raises(ValueError, match="unknown strategy"):
        estimate_memory("openvla-oft-tiny", strategy="fsdp1")


def test_backbone_info_prints_the_estimate(capsys: pytest.CaptureFixture[str]) -> None:
    torch.manual_seed(0)
    assert (
        main(["backbone-info", "openvla-oft-tiny", "--memory", "--batch", "2", "--devices", "2"])
        == 0
    )
    out = capsys.readouterr().out
    assert "activations, checkpointed" in out and "GiB" in out
