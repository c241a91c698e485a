"""The meta-device memory estimate against what the same step saves on the CPU."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from capvector.backbones import build_backbone, list_presets
from capvector.backbones.starvla import HALF, tiny_qwen_architecture
from capvector.cli import main
from capvector.errors import CapVectorError
from capvector.objectives.base import compute_losses
from capvector.profiling.memory import (
    MemoryEstimate,
    efficient_attention,
    estimate_memory,
    lora_settings,
    make_objective,
    measure_activations,
    saved_activation_bytes,
    synthetic_batch,
)
from capvector.profiling.settings import TrainingSettings
from capvector.training.lora import cast_frozen_parameters, set_trainable

TINY_PRESETS = [name for name in list_presets() if "tiny" in name]


@pytest.mark.parametrize("preset", TINY_PRESETS)
def test_meta_activation_estimate_is_close_to_a_real_step(preset: str) -> None:
    """Every family, including those whose forward reads values (prompts with the discretised
    state, Qwen-VL's token positions): the batch keeps its values on the CPU while the weights
    stay on the meta device."""
    estimate = estimate_memory(
        preset, TrainingSettings(batch=4, precision="32-true", strategy="ddp")
    )
    torch.manual_seed(0)
    model = build_backbone(preset)
    store: list[float] = []
    with saved_activation_bytes(store, model):
        model(synthetic_batch(model, 4, "cpu")).loss.backward()
    # The estimate runs SDPA as the memory-efficient kernel, the CPU its flash kernel: neither
    # keeps the attention matrix.
    assert 0.9 * store[0] <= estimate.activations <= 1.1 * store[0]
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
    def on_4(strategy: str) -> MemoryEstimate:
        settings = TrainingSettings(strategy=strategy, devices=4, precision="32-true")
        return estimate_memory("openvla-oft-tiny", settings)

    ddp, zero2, fsdp = on_4("ddp"), on_4("deepspeed_zero2"), on_4("fsdp2")
    params = sum(p.numel() for p in build_backbone("openvla-oft-tiny").parameters())
    assert ddp.parameters == zero2.parameters == pytest.approx(4 * params)
    assert zero2.optimizer == pytest.approx(ddp.optimizer / 4)
    assert fsdp.parameters < ddp.parameters
    with pytest.raises(ValueError, match="unknown strategy"):
        estimate_memory("openvla-oft-tiny", TrainingSettings(strategy="fsdp1"))


def test_backbone_info_prints_the_estimate(capsys: pytest.CaptureFixture[str]) -> None:
    torch.manual_seed(0)
    assert (
        main(["backbone-info", "openvla-oft-tiny", "--memory", "--batch", "2", "--devices", "2"])
        == 0
    )
    out = capsys.readouterr().out
    assert "activations, checkpointed" in out and "GiB" in out


def profiled_peak(step) -> float:  # noqa: ANN001
    """What the CPU allocator holds at most during ``step`` beyond before: torch.profiler's
    memory events (the referee, independent of the planner's own counting)."""
    import json
    import os
    import tempfile

    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        step()
    with tempfile.TemporaryDirectory() as folder:
        prof.export_chrome_trace(os.path.join(folder, "t.json"))
        with open(os.path.join(folder, "t.json")) as f:
            events = json.load(f)["traceEvents"]
    return max(e["args"]["Total Allocated"] for e in events if e.get("name") == "[memory]")


@pytest.mark.parametrize("frozen_dtype", ["float32", "bfloat16"])
@pytest.mark.parametrize("preset", TINY_PRESETS)
def test_planner_total_is_within_25_percent_of_a_real_step(preset: str, frozen_dtype: str) -> None:
    """LoRA, bf16-mixed, frozen weights in ``frozen_dtype`` (cast by hand as VLAModule will), AdamW:
    the estimate (following CPU autocast) against the parameters, AdamW state and the allocator's
    peak during a real CPU step."""
    settings = TrainingSettings(2, "bf16-mixed", "ddp", lora_rank=4, frozen_dtype=frozen_dtype)
    estimate = estimate_memory(preset, settings, device="cpu")
    assert_no_negative_term(estimate)
    torch.manual_seed(0)
    model = build_backbone(preset)
    set_trainable(model, lora_settings(4))
    cast_frozen_parameters(model, getattr(torch, frozen_dtype), keep=set())
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], foreach=True)
    batch = synthetic_batch(model, 2, "cpu")

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss = model(batch).loss
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)

    step()  # AdamW state
    static = sum(p.nbytes for p in model.parameters()) + sum(
        t.nbytes for s in optimizer.state.values() for t in s.values() if t.dim()
    )
    measured = static + profiled_peak(step)
    assert 0.75 * measured <= estimate.total <= 1.25 * measured


def test_frozen_dtype_stores_what_does_not_train_in_it() -> None:
    settings = TrainingSettings(2, "bf16-mixed", "ddp", lora_rank=4)
    fp32 = estimate_memory("openvla-oft-tiny", replace(settings, frozen_dtype="float32"))
    bf16 = estimate_memory("openvla-oft-tiny", replace(settings, frozen_dtype="bfloat16"))
    backbone = build_backbone("openvla-oft-tiny")
    set_trainable(backbone, lora_settings(4))
    trainable = sum(p.numel() for p in backbone.parameters() if p.requires_grad)
    frozen = sum(p.numel() for p in backbone.parameters() if not p.requires_grad)
    assert fp32.parameters == 4 * (trainable + frozen)
    assert bf16.parameters == 4 * trainable + 2 * frozen
    assert bf16.trainable_parameters == fp32.trainable_parameters == 4 * trainable
    assert bf16.gradients == fp32.gradients == 4 * trainable
    assert bf16.optimizer == fp32.optimizer == 8 * trainable
    # float32 frozen weights under autocast: autograd saves their bf16 copies; bf16 ones not.
    assert bf16.activations < fp32.activations
    with pytest.raises(CapVectorError, match="needs precision bf16-mixed"):
        estimate_memory(
            "openvla-oft-tiny", TrainingSettings(precision="32-true", frozen_dtype="bfloat16")
        )


def test_efficient_attention_keeps_no_attention_matrix() -> None:
    """SDPA as a GPU's memory-efficient kernel saves q, k, v, the output and a float32 (B, H, S)
    logsumexp; the math path saves the (B, H, S, S) probabilities too."""
    b, h, s, d = 2, 4, 64, 8
    q, k, v = (torch.randn(b, h, s, d, device="meta", requires_grad=True) for _ in range(3))
    saved: dict[str, list[float]] = {"math": [], "efficient": []}
    with saved_activation_bytes(saved["math"]):
        torch.nn.functional.scaled_dot_product_attention(q, k, v)
    with saved_activation_bytes(saved["efficient"]):
        efficient_attention(q, k, v)
    qkvo = 4 * b * h * s * d * 4
    # + the logsumexp (s is a multiple of 32) and the two 8-byte RNG scalars
    assert saved["efficient"][0] == qkvo + b * h * s * 4 + 16
    assert saved["math"][0] >= qkvo - b * h * s * d * 4 + b * h * s * s * 4
    math = estimate_memory("openvla-oft-tiny", TrainingSettings(2, attention="math"))
    efficient = estimate_memory("openvla-oft-tiny", TrainingSettings(2, attention="efficient"))
    assert efficient.activations < math.activations


def test_activation_checkpointing_selects_the_total() -> None:
    plain = estimate_memory("pi05-tiny", TrainingSettings(2))
    checkpointed = estimate_memory("pi05-tiny", TrainingSettings(2, activation_checkpointing=True))
    assert plain.total == plain.total_plain
    assert checkpointed.total == checkpointed.total_checkpointed < plain.total


def test_backbone_info_takes_the_new_options(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["backbone-info", "openvla-oft-tiny", "--memory", "--batch", "2", "--lora-rank", "4",
            "--frozen-dtype", "bfloat16", "--attention", "math", "--activation-checkpointing"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "frozen_dtype=bfloat16" in out and "attention=math" in out
    assert "(checkpointed)" in out
    assert "assumes: SDPA as the math kernel" in out and "not counted: the CUDA context" in out


def assert_no_negative_term(estimate: MemoryEstimate) -> None:
    terms = estimate.table().split("\n")
    values = [float(line.split()[-2]) for line in terms if line.strip().endswith("GiB")]
    assert values and all(v >= 0 for v in values), terms


@pytest.mark.parametrize("preset", TINY_PRESETS)
def test_no_term_is_negative(preset: str) -> None:
    """Issue 58: "working memory -0.388 GiB" (openvla-oft-7b, batch 8, LoRA r 32, bf16 frozen).
    Where the step's peak comes after part of the activations is freed, working memory is 0. The
    issue's settings here; batch 2 with and without bf16 in the planner test above."""
    settings = TrainingSettings(8, lora_rank=4, frozen_dtype="bfloat16")
    assert_no_negative_term(estimate_memory(preset, settings))


def test_objectives_term_is_what_the_objectives_cost_in_a_real_step() -> None:
    """Issue 58: the planner counted the backbone's step only, so aux-SFT at full size (pi05-3b)
    measured 1.30x its estimate. The aux estimate exceeds the SFT one by its objectives term, and
    that term matches what attaching both objectives costs a real CPU step (the allocator's peak
    from torch.profiler, plus the projector and its AdamW state)."""
    base = TrainingSettings(2, "bf16-mixed", "ddp", lora_rank=4, frozen_dtype="bfloat16")
    sft = estimate_memory("pi05-tiny", base, device="cpu")
    aux_settings = replace(base, objectives=("spatial", "reasoning"))
    aux = estimate_memory("pi05-tiny", aux_settings, device="cpu")
    assert_no_negative_term(aux)
    assert sft.objectives == sft.objectives_checkpointed == 0
    assert aux.objectives > 0 and aux.objectives_checkpointed > 0
    assert aux.total - sft.total == pytest.approx(aux.objectives)

    def measured(names: tuple[str, ...]) -> float:
        torch.manual_seed(0)
        model = build_backbone("pi05-tiny")
        set_trainable(model, lora_settings(4))
        objectives = [make_objective(name) for name in names]
        for objective in objectives:
            objective.bind(model)
        cast_frozen_parameters(model, torch.bfloat16, keep=set())
        modules = [model, *objectives]
        trainable = [p for m in modules for p in m.parameters() if p.requires_grad]
        optimizer = torch.optim.AdamW(trainable, foreach=True)
        batch = synthetic_batch(model, 2, "cpu", objectives=True)

        def step() -> None:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                losses = compute_losses(model, objectives, batch)
                loss = losses["action"] + sum(o.weight * losses[o.name] for o in objectives)
            loss.backward()
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)

        step()  # AdamW state
        static = sum(p.nbytes for m in modules for p in m.parameters()) + sum(
            t.nbytes for s in optimizer.state.values() for t in s.values() if t.dim()
        )
        return static + profiled_peak(step)

    cost = measured(("spatial", "reasoning")) - measured(())
    assert cost > 0
    assert 0.85 * cost <= aux.objectives <= 1.15 * cost


def test_backbone_info_takes_objectives(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["backbone-info", "pi05-tiny", "--memory", "--batch", "1", "--lora-rank", "4",
            "--objectives", "spatial", "reasoning"]  # fmt: skip
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "objectives=['spatial', 'reasoning']" in out
    line = next(row for row in out.splitlines() if row.strip().startswith("auxiliary objectives "))
    assert float(line.split()[-2]) > 0
    with pytest.raises(CapVectorError, match="spatail"):
        estimate_memory("pi05-tiny", TrainingSettings(objectives=("spatail",)))
