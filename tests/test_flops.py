"""``backbone-info --flops``: the meta-device count against ``torch.utils.flop_counter`` on a real
CPU training step, with and without each auxiliary objective."""

from __future__ import annotations

import pytest
import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.flop_counter import FlopCounterMode

from capvector.backbones import build_backbone, list_presets
from capvector.cli import main
from capvector.profiling.flops import FlopsEstimate, estimate_flops, make_objective
from capvector.profiling.memory import synthetic_batch
from capvector.training.lora import set_trainable

TINY_PRESETS = [name for name in list_presets() if "tiny" in name]


def real_step_flops(preset: str, objective_name: str | None, batch_size: int) -> tuple[int, int]:
    """(forward, backward) FLOPs of one real CPU step, counted by FlopCounterMode. SDPA takes the
    math path here: the CPU's flash kernel is not in FlopCounterMode's registry."""
    torch.manual_seed(0)
    model = build_backbone(preset)
    set_trainable(model, None)
    objective = None if objective_name is None else make_objective(objective_name)
    if objective is not None:
        objective.bind(model)
    batch = synthetic_batch(model, batch_size, "cpu", objectives=True)
    with FlopCounterMode(display=False) as counter, sdpa_kernel(SDPBackend.MATH):
        output = model(batch, None if objective is None else objective.request)
        loss = output.loss
        if objective is not None:
            loss = loss + objective.weight * objective(batch, output, model)
        forward = counter.get_total_flops()
        loss.backward()
    return forward, counter.get_total_flops() - forward


@pytest.mark.parametrize("preset", TINY_PRESETS)
def test_flops_match_the_flop_counter_on_a_real_step(preset: str) -> None:
    estimate = estimate_flops(preset, batch_size=2)
    for name in ("action", "spatial", "reasoning"):
        forward, backward = real_step_flops(preset, None if name == "action" else name, 2)
        assert estimate.forward[name] * 2 == pytest.approx(forward, rel=0.01), name
        assert estimate.backward[name] * 2 == pytest.approx(backward, rel=0.01), name
    # Dense layers: the backward computes input and weight gradients, about 2x the forward.
    assert 1.4 < estimate.backward["action"] / estimate.forward["action"] < 2.1
    assert estimate.training("reasoning") > estimate.training("spatial") >= estimate.training()


def test_lora_skips_the_weight_gradients_of_frozen_layers() -> None:
    full = estimate_flops("openvla-oft-tiny", batch_size=2, objectives=())
    lora = estimate_flops("openvla-oft-tiny", batch_size=2, lora_rank=4, objectives=())
    # The adapters add r/hidden of the adapted matmuls (r 4 of 64 here).
    assert lora.forward["action"] == pytest.approx(full.forward["action"], rel=0.1)
    assert lora.backward["action"] < 0.75 * full.backward["action"]


def test_gpu_hours_follow_from_flops_mfu_and_peak() -> None:
    flops = FlopsEstimate(forward={"action": 1e12}, backward={"action": 2e12})
    hours = flops.gpu_hours("action", steps=1000, batch_size=8, devices=2, mfu=0.5, gpu_tflops=1000)
    assert hours == pytest.approx(1000 * 8 * 2 * 3e12 / (0.5 * 1000e12) / 3600)


def test_backbone_info_prints_flops_and_gpu_hours(capsys: pytest.CaptureFixture[str]) -> None:
    argv = [
        "backbone-info",
        "pi05-tiny",
        "--flops",
        "--batch",
        "2",
        "--steps",
        "10",
        "--mfu",
        "0.5",
    ]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "+ reasoning co-training" in out and "GPU-h" in out and "MFU 0.5" in out
