"""Pi0.5-style backbone: masks, embeddings, prompt, flow matching, cached denoising, training, LoRA,
persistence, LeRobot ``pi05_base`` loading and the full-size parameter count."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from capvector.backbones import BackboneError, OutputRequest, build_backbone, from_pretrained
from capvector.backbones.common import discretize_state
from capvector.backbones.pi05 import (
    IMAGE_MASK,
    AdaRMSNorm,
    Pi05,
    build_prompt,
    flow_matching_path,
    make_attention_mask,
    resize_with_pad,
)
from capvector.data import keys
from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule
from capvector.training.lora import LoraSettings

CHUNK, ACTION_DIM, PAD_DIM = 8, 7, 32


def make_batch(
    batch_size: int = 2, instructions: list[str] | None = None, seed: int = 0, actions: bool = True
) -> dict:
    g = torch.Generator().manual_seed(seed)
    instructions = (
        instructions or ["lift the red cube", "stack the red cube on the green cube"][:batch_size]
    )
    batch = {
        keys.IMAGES: torch.rand(batch_size, 2, 3, 64, 64, generator=g),
        keys.PROPRIO: torch.rand(batch_size, 8, generator=g) * 2 - 1,
        keys.INSTRUCTION: instructions,
    }
    if actions:
        batch[keys.ACTIONS] = torch.rand(batch_size, CHUNK, ACTION_DIM, generator=g) * 2 - 1
    return batch


def rows(batch: dict, index: slice) -> dict:
    return {k: v[index] for k, v in batch.items()}


def noise_like(batch: dict, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(len(batch[keys.INSTRUCTION]), CHUNK, PAD_DIM, generator=g)


@pytest.fixture(scope="module")
def tiny() -> Pi05:
    """The tiny preset with its time conditioning switched on, as after pretraining: adaRMS dense
    weights start at zero (adaLN-zero), which would hide every time-dependent path from the tests."""
    torch.manual_seed(0)
    model = build_backbone("pi05-tiny").eval()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, AdaRMSNorm):
                module.dense.weight.normal_(std=0.2)
    return model


# -- architecture ----------------------------------------------------------------------------------


def test_pi05_3b_parameter_count_from_published_shapes() -> None:
    with torch.device("meta"):
        model = build_backbone("pi05-3b")

    def count(module: torch.nn.Module) -> int:
        return sum(p.numel() for p in module.parameters())

    # SigLIP So400m/14 at 224 px, no pooling head:
    #   patch conv 3*14*14*1152 + 1152 = 678,528; positions 256*1152 = 294,912; post-LN 2*1152 = 2,304
    #   per layer: 2 LNs 4*1152 = 4,608; q/k/v/out 4*(1152^2 + 1152) = 5,313,024;
    #              fc1 1152*4304 + 4304 = 4,962,512; fc2 4304*1152 + 1152 = 4,959,360 -> 15,239,504
    #   678,528 + 294,912 + 27 * 15,239,504 + 2,304 = 412,442,352
    assert count(model.vision_tower) == 412_442_352
    # Projector: 1152*2048 + 2048
    assert count(model.multi_modal_projector) == 2_361_344
    # Gemma-2B: embedding 257,152*2048 = 526,647,296 (tied with lm_head: counted once)
    #   per layer: q 2048*2048 + k 2048*256 + v 2048*256 + o 2048*2048 = 9,437,184;
    #              MLP 3*2048*16384 = 100,663,296; 2 RMSNorms 2*2048 -> 110,104,576
    #   526,647,296 + 18 * 110,104,576 + 2048 (final norm) = 2,508,531,712
    assert count(model.language_model) == 2_508_531_712
    # Gemma-300M expert (no embedding; its unused lm_head 257,152*1024 = 263,323,648 is not built):
    #   per layer: q 1024*2048 + k 1024*256 + v 1024*256 + o 2048*1024 = 4,718,592;
    #              MLP 3*1024*4096 = 12,582,912; 2 adaRMS dense 2*(1024*3072 + 3072) = 6,297,600
    #              -> 23,599,104
    #   18 * 23,599,104 + 3,148,800 (adaptive final norm) = 427,932,672
    assert count(model.action_expert) == 427_932_672
    # Projections: action_in 32*1024 + 1024 = 33,792; action_out 1024*32 + 32 = 32,800;
    #   time_mlp_in / time_mlp_out 1024*1024 + 1024 = 1,049,600 each -> 2,165,792
    heads = ("action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out")
    assert sum(count(model.get_submodule(h)) for h in heads) == 2_165_792
    # 412,442,352 + 2,361,344 + 2,508,531,712 + 427,932,672 + 2,165,792
    assert count(model) == 3_353_433_872
    capability = set(model.capability_parameter_names())
    assert sum(p.numel() for n, p in model.named_parameters() if n in capability) == 3_351_268_080
    assert model.num_visual_tokens == 3 * 256
    assert (model.hidden_size, model.num_layers) == (2048, 18)


def test_state_dict_follows_the_checkpoint_key_families(tiny: Pi05) -> None:
    names = set(tiny.state_dict())
    for name in (
        "vision_tower.vision_model.embeddings.patch_embedding.weight",
        "vision_tower.vision_model.encoder.layers.1.mlp.fc2.bias",
        "vision_tower.vision_model.post_layernorm.weight",
        "multi_modal_projector.linear.bias",
        "language_model.embed_tokens.weight",
        "language_model.layers.1.self_attn.k_proj.weight",
        "language_model.layers.0.input_layernorm.weight",
        "language_model.norm.weight",
        "action_expert.layers.1.mlp.gate_proj.weight",
        "action_expert.layers.0.post_attention_layernorm.dense.bias",
        "action_expert.norm.dense.weight",
        "time_mlp_out.bias",
    ):
        assert name in names, name
    # adaRMS has no weight vector; no lm_head (tied) and no expert embedding.
    assert not any(n.startswith("action_expert.") and n.endswith("layernorm.weight") for n in names)
    assert not any("lm_head" in n or n.startswith("action_expert.embed") for n in names)
    # Our own embedding module: the √width scaling is ours, not the installed transformers'.
    assert type(tiny.language_model.embed_tokens) is torch.nn.Embedding


def test_streams_must_share_attention_shapes() -> None:
    with pytest.raises(BackboneError, match="share one attention.*head_dim"):
        build_backbone(
            "pi05-tiny",
            expert={
                "hidden_size": 32,
                "intermediate_size": 64,
                "num_layers": 2,
                "num_heads": 4,
                "num_kv_heads": 1,
                "head_dim": 8,
            },
        )


# -- masks, positions, padding -----------------------------------------------------------------------


def test_block_causal_mask_and_positions(tiny: Pi05) -> None:
    prefix_valid = torch.tensor([[True, True, True, False], [True, False, True, True]])
    mask, positions = tiny.attention_layout(prefix_valid, horizon=2)
    assert mask.shape == (2, 6, 6) and mask.dtype == torch.bool
    P, S = [1, 1, 1, 0, 0, 0], [1, 1, 1, 0, 1, 1]  # rows: valid prefix query / action query
    expected0 = torch.tensor([P, P, P, [0] * 6, S, S], dtype=torch.bool)
    torch.testing.assert_close(mask[0], expected0)
    P1, S1 = [1, 0, 1, 1, 0, 0], [1, 0, 1, 1, 1, 1]
    expected1 = torch.tensor([P1, [0] * 6, P1, P1, S1, S1], dtype=torch.bool)
    torch.testing.assert_close(mask[1], expected1)
    # Padding does not advance positions; actions continue after the valid prefix tokens.
    assert positions.tolist() == [[0, 1, 2, 2, 3, 4], [0, 0, 1, 2, 3, 4]]
    # The rule itself (big_vision make_attn_mask) with a Pi0-like extra block.
    generic = make_attention_mask(torch.ones(1, 4, dtype=torch.bool), torch.tensor([[0, 0, 1, 1]]))
    assert generic[0].int().tolist() == [[1, 1, 0, 0], [1, 1, 0, 0], [1, 1, 1, 0], [1, 1, 1, 1]]


def test_prefix_never_sees_the_actions(tiny: Pi05) -> None:
    batch = make_batch(2, actions=False)
    hidden_a: dict[int, torch.Tensor] = {}
    hidden_b: dict[int, torch.Tensor] = {}
    time = torch.tensor([0.3, 0.9])
    with torch.no_grad():
        prefix = tiny.embed_prefix(batch)
        va, out_a = tiny.velocity(prefix, torch.randn(2, CHUNK, PAD_DIM), time, hidden_a, (1, 2))
        vb, out_b = tiny.velocity(prefix, torch.randn(2, CHUNK, PAD_DIM), time, hidden_b, (1, 2))
    for layer in (1, 2):
        torch.testing.assert_close(hidden_a[layer], hidden_b[layer], atol=0, rtol=0)
    torch.testing.assert_close(out_a, out_b, atol=0, rtol=0)
    assert not torch.allclose(va, vb)  # while the actions do see each other


def test_padding_and_masked_cameras_change_no_output(tiny: Pi05) -> None:
    batch = make_batch(
        2, ["lift", "stack the red cube on top of the green cube, carefully"], actions=False
    )
    noise = noise_like(batch)
    together = tiny.predict_action(batch, noise)
    alone = tiny.predict_action(rows(batch, slice(0, 1)), noise[:1])
    torch.testing.assert_close(together[0], alone[0], atol=1e-5, rtol=1e-4)

    batch[IMAGE_MASK] = torch.tensor([[True, False], [True, True]])
    masked = tiny.predict_action(batch, noise)
    changed = dict(batch, **{keys.IMAGES: batch[keys.IMAGES].clone()})
    changed[keys.IMAGES][:, 1] = torch.rand(2, 3, 64, 64)
    after = tiny.predict_action(changed, noise)
    # A masked camera has no effect, a present one is seen.
    torch.testing.assert_close(after[0], masked[0], atol=1e-5, rtol=1e-4)
    assert not torch.allclose(after[1], masked[1], atol=1e-4)


def test_mismatched_camera_count_is_a_clear_error(tiny: Pi05) -> None:
    batch = make_batch(1)
    batch[keys.IMAGES] = batch[keys.IMAGES][:, :1]
    with pytest.raises(BackboneError, match="1 camera.*num_images=2"):
        tiny(batch)


# -- embeddings and prompt ------------------------------------------------------------------------


def test_embedding_scaling_is_pinned(tiny: Pi05) -> None:
    """Images: projector(SigLIP last hidden state), unscaled; text: embedding · √64 = 8."""
    batch = make_batch(2)
    with torch.no_grad():
        embeds = tiny(batch, OutputRequest(hidden_layers=(0,))).hidden_states[0]
        pixels = batch[keys.IMAGES].flatten(0, 1) * 2 - 1
        features = tiny.vision_tower.vision_model(pixel_values=pixels).last_hidden_state
        projector = tiny.multi_modal_projector.linear
        images = torch.nn.functional.linear(features, projector.weight, projector.bias).reshape(
            2, 128, 64
        )
        ids, valid = tiny.tokenize(
            batch[keys.INSTRUCTION], batch[keys.PROPRIO], torch.device("cpu")
        )
        text = tiny.language_model.embed_tokens.weight[ids] * 8.0
    torch.testing.assert_close(embeds[:, :128], images)
    torch.testing.assert_close(embeds[:, 128:][valid], text[valid])


def test_state_is_discretised_unpadded_into_the_prompt(tiny: Pi05) -> None:
    values = torch.tensor([[-1.5, -1.0, -0.99, -0.0078125, 0.0, 0.5, 0.999, 1.0, 2.0]])
    edges = np.linspace(-1, 1, 256 + 1)[:-1]  # openpi tokenizer.py, LeRobot processor_pi05.py
    expected = np.digitize(values.numpy().astype(np.float64), edges) - 1  # no clamp upstream
    assert discretize_state(values).tolist() == expected.tolist()
    # Below -1 is bin -1 (written "-1"), as upstream; at or above 1 the last bin.
    assert discretize_state(values)[0, [0, 1, 4, 7, 8]].tolist() == [-1, 0, 128, 255, 255]

    assert build_prompt(" pick_up the\nmug ", [0, 128, 255]) == [
        "Task: pick up the mug, State: 0 128 255;\nAction: "
    ]
    assert build_prompt("lift", None) == ["lift", "\n"]  # Pi0 format without a state

    proprio = torch.linspace(-1, 1, 8)[None]
    ids, valid = tiny.tokenize(["lift_cube"], proprio, torch.device("cpu"))
    tok = tiny.tokenizer
    assert ids[0, 0] == tok.bos_token_id and valid.all()
    text = tok.decode(ids[0, 1:].tolist())
    assert text == "Task: lift cube, State: 0 36 73 109 146 182 219 255;\nAction: "
    assert len(text.split("State: ")[1].split(";")[0].split()) == 8  # the 8 real dims, not 32


def test_prompt_state_dim_pads_the_state_as_lerobot_0_4_4() -> None:
    model = build_backbone("pi05-tiny", prompt_state_dim=12, proprio_dim=2)
    ids, valid = model.tokenize(["lift"], torch.tensor([[-1.2, 1.0]]), torch.device("cpu"))
    text = model.tokenizer.decode(ids[0, 1:].tolist())
    assert text == "Task: lift, State: -1 255" + " 128" * 10 + ";\nAction: "


def test_resize_with_pad_keeps_aspect_and_pads_black() -> None:
    wide = torch.ones(1, 3, 32, 64)
    out = resize_with_pad(wide, 64)
    assert out.shape == (1, 3, 64, 64)
    assert out[..., :16, :].abs().sum() == 0 and out[..., 48:, :].abs().sum() == 0
    torch.testing.assert_close(out[..., 16:48, :], torch.ones(1, 3, 32, 64))


def test_missing_tokenizer_is_a_clear_error() -> None:
    model = build_backbone("pi05-tiny", tokenizer="")
    with pytest.raises(BackboneError, match="no tokenizer.*PaliGemma"):
        model.predict_action(make_batch(1, actions=False))


# -- flow matching --------------------------------------------------------------------------------


def test_flow_matching_conventions(tiny: Pi05) -> None:
    actions, noise = torch.randn(2, CHUNK, PAD_DIM), torch.randn(2, CHUNK, PAD_DIM)
    x_t, target = flow_matching_path(actions, noise, torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(x_t[0], noise[0])  # t = 1 is noise
    torch.testing.assert_close(x_t[1], actions[1])  # t = 0 is data
    torch.testing.assert_close(target, noise - actions)

    t = tiny.sample_time(20_000, torch.device("cpu"))
    assert float(t.min()) >= 0.001 and float(t.max()) <= 1.0
    # Beta(1.5, 1): mean 0.6, CDF x^1.5 so median 0.5^(2/3); then * 0.999 + 0.001.
    assert abs(float(t.mean()) - (0.6 * 0.999 + 0.001)) < 0.01
    assert abs(float(t.median()) - (0.5 ** (2 / 3) * 0.999 + 0.001)) < 0.015

    # The MSE averages over the 32 padded dims (openpi); LeRobot's averaging over real dims only.
    velocity, target = torch.zeros(1, CHUNK, PAD_DIM), torch.zeros(1, CHUNK, PAD_DIM)
    target[..., ACTION_DIM:] = 1.0
    target[..., 0] = 2.0
    assert math.isclose(float(tiny.flow_loss(velocity, target)), (25 + 4) / 32, rel_tol=1e-6)
    lerobot = build_backbone("pi05-tiny", loss_include_padded_dims=False)
    assert math.isclose(float(lerobot.flow_loss(velocity, target)), 4 / 7, rel_tol=1e-6)


def test_training_forward_outputs_and_gradients() -> None:
    model = build_backbone("pi05-tiny")
    batch = make_batch(2)
    torch.manual_seed(3)
    out = model(batch, OutputRequest(hidden_layers=(0, 2), lm_logits=True))
    seq = out.attention_mask.shape[1]
    assert out.actions.shape == (2, CHUNK, ACTION_DIM)
    assert set(out.hidden_states) == {0, 2}  # only the requested layers are kept
    assert all(h.shape == (2, seq, 64) for h in out.hidden_states.values())
    assert out.visual_token_mask[:, :128].all() and out.visual_token_mask.sum() == 2 * 128
    assert out.visual_grid == (8, 8)
    assert out.lm_logits.shape == (2, seq, 260)
    # actions = the one-step denoised estimate x_t − t·v, with the same noise and time.
    torch.manual_seed(3)
    with torch.no_grad():
        target = model.pad_actions(batch[keys.ACTIONS])
        noise = torch.randn_like(target)
        time = model.sample_time(2, torch.device("cpu"))
        x_t, _ = flow_matching_path(target, noise, time)
        velocity, _ = model.velocity(model.embed_prefix(batch), x_t, time)
    torch.testing.assert_close(
        out.actions, (x_t - time[:, None, None] * velocity)[..., :ACTION_DIM]
    )

    out.loss.backward()
    for name in (
        "vision_tower.vision_model.encoder.layers.0.self_attn.q_proj.weight",
        "language_model.layers.0.self_attn.k_proj.weight",  # reaches the VLM only through K/V
        "action_expert.layers.0.mlp.up_proj.weight",
        "action_expert.layers.0.input_layernorm.dense.weight",
        "action_in_proj.weight",
        "action_out_proj.weight",
    ):
        grad = model.get_parameter(name).grad
        assert grad is not None and grad.abs().sum() > 0, name
    # adaRMS starts as openpi's PyTorch port: zero dense weight (no time modulation yet, so the time
    # MLP gets no gradient on the first step) and a default-initialised bias (open gates).
    dense = model.action_expert.layers[0].input_layernorm.dense
    assert dense.weight.abs().sum() == 0 and dense.bias.abs().sum() > 0
    assert model.time_mlp_in.weight.grad.abs().sum() == 0
    with pytest.raises(BackboneError, match="hidden layer 3 requested"):
        model(batch, OutputRequest(hidden_layers=(3,)))


def test_shard_units_recompute_whole_joint_layers() -> None:
    """Activation checkpointing of ``shard_units`` (as ``VLAModule`` applies it) recomputes both
    streams of a joint layer and leaves loss and gradients unchanged."""
    from capvector.training.distributed import parallelize

    def run(checkpointing: bool) -> tuple[torch.Tensor, torch.Tensor, int]:
        torch.manual_seed(0)
        model = build_backbone("pi05-tiny")
        calls = []
        model.action_expert.layers[0].mlp.register_forward_hook(lambda *_: calls.append(1))
        units = model.shard_units()
        assert len(units) == 2 + 2 and all(any(True for _ in u.parameters()) for u in units)
        parallelize(model, units, [], None, activation_checkpointing=checkpointing)
        torch.manual_seed(1)
        loss = model(make_batch(2)).loss
        loss.backward()
        return loss.detach(), model.action_expert.layers[0].mlp.up_proj.weight.grad, len(calls)

    plain_loss, plain_grad, plain_calls = run(False)
    loss, grad, calls = run(True)
    torch.testing.assert_close(loss, plain_loss)
    torch.testing.assert_close(grad, plain_grad)
    assert (plain_calls, calls) == (1, 2)  # the expert half is recomputed inside the VLM's unit


# -- inference ------------------------------------------------------------------------------------


def test_prefix_runs_once_and_its_cache_never_grows(
    tiny: Pi05, monkeypatch: pytest.MonkeyPatch
) -> None:
    batch = make_batch(2, actions=False)
    seen: list[tuple[list[tuple[int, ...]], list[int], float]] = []
    step = tiny.denoise_step

    def spy(cache, x_t, time):  # noqa: ANN001, ANN202
        seen.append(
            (
                [tuple(k.shape) for k in cache.keys],
                [k.data_ptr() for k in cache.keys],
                float(time[0]),
            )
        )
        return step(cache, x_t, time)

    calls = {"vision": 0, "vlm": 0, "expert": 0}

    def counter(name: str):  # noqa: ANN202
        def hook(*_args) -> None:  # noqa: ANN002
            calls[name] += 1

        return hook

    hooks = [
        tiny.vision_tower.register_forward_hook(counter("vision")),
        tiny.language_model.layers[0].mlp.register_forward_hook(counter("vlm")),
        tiny.action_expert.layers[0].mlp.register_forward_hook(counter("expert")),
    ]
    monkeypatch.setattr(tiny, "denoise_step", spy)
    try:
        tiny.predict_action(batch)
    finally:
        for hook in hooks:
            hook.remove()
    assert tiny.config.num_inference_steps == 10 and len(seen) == 10
    prefix_len = tiny.embed_prefix(batch).valid.shape[1]
    shapes, pointers = seen[0][0], seen[0][1]
    assert len(shapes) == tiny.num_layers and shapes[0] == (2, 1, prefix_len, 16)
    assert all(s == shapes and p == pointers for s, p, _ in seen)  # same tensors, never grown
    assert [round(t, 6) for _, _, t in seen] == [round(1 - k / 10, 6) for k in range(10)]
    assert calls == {"vision": 1, "vlm": 1, "expert": 10}  # prefix once, expert alone per step


def test_cached_denoising_equals_the_joint_pass(tiny: Pi05) -> None:
    batch = make_batch(2, ["lift", "stack the red cube on the green cube"], actions=False)
    x_t, time = torch.randn(2, CHUNK, PAD_DIM), torch.tensor([0.25, 0.8])
    with torch.no_grad():
        prefix = tiny.embed_prefix(batch)
        joint, _ = tiny.velocity(prefix, x_t, time)
        cache, _ = tiny.prefix_cache(prefix)
        cached = tiny.denoise_step(cache, x_t, time)
    torch.testing.assert_close(cached, joint, atol=1e-5, rtol=1e-4)


def test_euler_integration_schedule(tiny: Pi05, monkeypatch: pytest.MonkeyPatch) -> None:
    """x_1 = ε, x ← x − v/N for N steps: a constant velocity c ends at ε − c."""
    monkeypatch.setattr(tiny, "denoise_step", lambda cache, x, t: torch.full_like(x, 0.5))  # noqa: ARG005
    noise = torch.randn(1, CHUNK, PAD_DIM)
    out = tiny.integrate(cache=None, noise=noise)  # type: ignore[arg-type]
    torch.testing.assert_close(out, noise - 0.5)


# -- config fields ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("rope_theta", 50.0),
        ("rms_norm_eps", 0.5),
        ("min_period", 0.1),
        ("max_period", 100.0),
        ("state_bins", 8),
        ("prompt_state_dim", 32),
        ("tokenizer_max_length", 40),
        ("num_inference_steps", 3),
        ("accumulate_time", True),
        ("time_sampling_beta_alpha", 4.0),
        ("time_sampling_beta_beta", 3.0),
        ("time_sampling_scale", 0.3),
        ("time_sampling_offset", 0.5),
        ("loss_include_padded_dims", False),
    ],
)
def test_every_flow_and_prompt_field_has_an_effect(tiny: Pi05, field: str, value: object) -> None:
    changed = build_backbone("pi05-tiny", **{field: value}).eval()
    changed.load_state_dict(tiny.state_dict())
    batch = make_batch(2)
    noise = noise_like(batch)

    def outputs(model: Pi05) -> tuple[torch.Tensor, torch.Tensor]:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")  # the truncation warning
            torch.manual_seed(0)
            loss = model(batch).loss
            return loss, model.predict_action(batch, noise)

    (loss_a, act_a), (loss_b, act_b) = outputs(tiny), outputs(changed)
    assert not torch.allclose(loss_a, loss_b) or not torch.allclose(act_a, act_b)


def test_truncation_warns() -> None:
    model = build_backbone("pi05-tiny", tokenizer_max_length=20)
    with pytest.warns(UserWarning, match="truncated to tokenizer_max_length=20"):
        ids, _ = model.tokenize(["lift"], torch.zeros(1, 8), torch.device("cpu"))
    assert ids.shape == (1, 20)


# -- training ---------------------------------------------------------------------------------------


def demo_batch(demo_file: Path) -> tuple[RobotDataModule, dict]:
    dm = RobotDataModule(train_files=[str(demo_file)], batch_size=8, augment=False)
    batch = next(iter(torch.utils.data.DataLoader(dm.train_dataset, batch_size=8)))
    return dm, batch


def test_tiny_preset_trains_on_demo_data(demo_file: Path) -> None:
    dm, batch = demo_batch(demo_file)
    module = VLAModule(backbone="pi05-tiny", data_spec=dm.spec)
    assert isinstance(module.backbone, Pi05) and module.backbone.config.action_dim == 7
    optimizer = torch.optim.AdamW(module.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss = module.compute_losses(batch)["action"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses)
    # Flow-matching losses are noisy (random t and ε every step): compare 5-step means. Seeds 0-2
    # give a ratio of 0.54-0.58.
    assert np.mean(losses[-5:]) < 0.75 * np.mean(losses[:5]), losses


def test_lora_trains_only_lora_and_heads_and_exports(demo_file: Path, tmp_path: Path) -> None:
    dm, batch = demo_batch(demo_file)
    module = VLAModule(backbone="pi05-tiny", data_spec=dm.spec, lora=LoraSettings(r=4, alpha=4))
    backbone = module.backbone
    heads = ("action_in_proj.", "action_out_proj.", "time_mlp_in.", "time_mlp_out.")
    trainable = {n for n, p in backbone.named_parameters() if p.requires_grad}
    assert all(".lora_" in n or n.startswith(heads) for n in trainable)
    for stream in ("language_model.", "action_expert."):
        for proj in ("self_attn.q_proj", "self_attn.o_proj", "mlp.down_proj"):
            found = any(n.startswith(stream) and proj in n and ".lora_B." in n for n in trainable)
            assert found, (stream, proj)
    assert not any(n.startswith("vision_tower.") for n in trainable)
    before = {n: p.detach().clone() for n, p in backbone.named_parameters()}
    optimizer = torch.optim.AdamW([p for p in backbone.parameters() if p.requires_grad], lr=1e-2)
    for _ in range(2):
        loss = module.compute_losses(batch)["action"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    changed = {n for n, p in backbone.named_parameters() if not torch.equal(p, before[n])}
    assert changed <= trainable
    assert any("language_model." in n and ".lora_B." in n for n in changed)  # gradient through K/V
    assert any("action_expert." in n and ".lora_B." in n for n in changed)
    assert {"action_out_proj.weight", "time_mlp_in.weight"} <= changed

    # The export merges LoRA into plain keys; it predicts as the LoRA model does.
    module.export(tmp_path / "export")
    loaded = from_pretrained(tmp_path / "export").eval()
    observation = {k: v for k, v in batch.items() if k != keys.ACTIONS}
    noise = noise_like(observation)
    torch.testing.assert_close(
        loaded.predict_action(observation, noise),
        backbone.eval().predict_action(observation, noise),
        atol=1e-5,
        rtol=1e-4,
    )


def test_save_pretrained_round_trip(tiny: Pi05, tmp_path: Path) -> None:
    tiny.save_pretrained(tmp_path / "export")
    loaded = from_pretrained(tmp_path / "export").eval()
    assert isinstance(loaded, Pi05) and loaded.config == tiny.config
    batch = make_batch(2, actions=False)
    noise = noise_like(batch)
    torch.testing.assert_close(
        loaded.predict_action(batch, noise), tiny.predict_action(batch, noise), atol=0, rtol=0
    )


def test_language_model_logits_are_prefix_lm(tiny: Pi05) -> None:
    batch = make_batch(2, actions=False)
    prompts, answers = (
        ["Q: where?\nA: ", "Q: a much longer question?\nA: "],
        ["left", "on the table"],
    )
    with torch.no_grad():
        logits, labels = tiny.language_model_logits(batch, prompts, answers)
        other, _ = tiny.language_model_logits(batch, prompts, ["rear", "on the table"])
        alone, alone_labels = tiny.language_model_logits(
            rows(batch, slice(0, 1)), prompts[:1], answers[:1]
        )
    tok = tiny.tokenizer
    assert logits.shape[:2] == labels.shape and logits.shape[-1] == 260
    for row, answer in enumerate(answers):
        expected = [*tok(answer, add_special_tokens=False)["input_ids"], tok.eos_token_id]
        assert labels[row][labels[row] != -100].tolist() == expected
    start = int((labels[0] != -100).nonzero()[0])
    torch.testing.assert_close(logits[0, :start], other[0, :start])  # the answer is causal
    assert not torch.allclose(logits[0, start:], other[0, start:])
    n = alone_labels.shape[1]
    torch.testing.assert_close(logits[0, :n], alone[0], atol=1e-5, rtol=1e-4)  # padding is ignored


# -- Pi0.5's normalisation (openpi / LeRobot quantiles) ------------------------------------------------


def test_quantile_normalisation_does_not_clip_and_covers_the_gripper() -> None:
    from capvector.data.statistics import QUANTILES, Normalizer, compute_statistics

    rng = np.random.default_rng(0)
    actions = rng.normal(size=(500, 3)).astype(np.float32)
    actions[:, 1] = 0.25  # constant
    entry = compute_statistics(actions, actions[:, :2], 1, normalization=QUANTILES)
    assert entry["normalization"] == QUANTILES and entry["action"]["mask"] == [True] * 3
    norm = Normalizer(entry)
    out = norm.normalize("action", actions)
    q01, q99 = np.quantile(actions, [0.01, 0.99], axis=0).astype(np.float32)
    expected = 2 * (actions[:, [0, 2]] - q01[[0, 2]]) / (q99 - q01)[[0, 2]] - 1  # LeRobot QUANTILES
    np.testing.assert_allclose(out[:, [0, 2]], expected, atol=1e-6)
    assert out.min() < -1 and out.max() > 1  # not clipped, the gripper (last dim) included
    assert (out[:, 1] == -1).all()  # q99 == q01: eps denominator, as LeRobot (OFT would give 0)
    np.testing.assert_allclose(norm.unnormalize("action", out), actions, atol=1e-5)


def test_datamodule_normalization_is_a_per_family_choice(demo_file: Path) -> None:
    oft = RobotDataModule(train_files=[str(demo_file)], batch_size=2, augment=False)
    assert "normalization" not in oft.spec.stats_entry  # OFT's bounds_q99, files unchanged
    assert oft.spec.stats_entry["action"]["mask"][-1] is False
    pi05 = RobotDataModule(
        train_files=[str(demo_file)], batch_size=2, augment=False, normalization="quantiles"
    )
    assert pi05.spec.stats_entry["normalization"] == "quantiles"
    assert all(pi05.spec.stats_entry["action"]["mask"])
    with pytest.raises(ValueError, match="unknown normalization 'minmax'"):
        RobotDataModule(train_files=[str(demo_file)], normalization="minmax")
