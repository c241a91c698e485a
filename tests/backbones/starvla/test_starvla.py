"""StarVLA-style backbone: the Qwen-VL wrapper, the three heads, loading paths and the contract."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from capvector.backbones import (
    BackboneError,
    OutputRequest,
    build_backbone,
    from_pretrained,
    list_presets,
    preset_config,
)
from capvector.backbones.base import draw_flow_noise
from capvector.backbones.starvla import (
    HALF,
    HEADS,
    HeadDims,
    StarVLA,
    build_head,
    tiny_qwen_architecture,
    tiny_qwen_tokenizer,
)
from capvector.data import keys
from capvector.data.datamodule import RobotDataModule
from capvector.data.hdf5 import HDF5RobotDataset
from capvector.module import VLAModule, load_module
from capvector.training.lora import LoraSettings
from conftest import CAMERAS, assert_field_changes_the_model, cpu_trainer

REPO = Path(__file__).resolve().parents[3]
PROPRIO_KEYS = ["robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"]
FULL_SIZE = sorted(p for p in list_presets() if p.startswith("starvla-") and "tiny" not in p)


def make_batch(batch_size: int = 2, instructions: list[str] | None = None, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    instructions = instructions or ["lift the red cube", "stack the red cube on the green cube"]
    return {
        keys.IMAGES: torch.rand(batch_size, 2, 3, 64, 64, generator=g),
        keys.PROPRIO: torch.rand(batch_size, 8, generator=g) * 2 - 1,
        keys.ACTIONS: torch.rand(batch_size, 8, 7, generator=g) * 2 - 1,
        keys.INSTRUCTION: instructions[:batch_size],
    }


def predict(model: StarVLA, batch: dict, seed: int = 7) -> torch.Tensor:
    """Actions with the flow heads' noise fixed, so two models can be compared."""
    torch.manual_seed(seed)
    return model.predict_action({k: v for k, v in batch.items() if k != keys.ACTIONS})


def tiny(head: str, head_args: dict | None = None, **overrides: object) -> StarVLA:
    """A tiny preset; ``head_args`` are merged into the preset's (an override replaces the dict)."""
    preset = f"starvla-tiny-{head}"
    merged = {**preset_config(preset).head_args, **(head_args or {})}
    return build_backbone(preset, head_args=merged, **overrides).eval()


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


# -- presets -------------------------------------------------------------------------------------

# (VLM, head) parameters: the VLMs match Qwen's published checkpoints exactly. The layerwise head
# on Qwen3-VL-4B equals StarVLA's QwenPI_v3 (action_model 538,678,305 + project_layers 94,593,024,
# its docstring) minus what StarVLA builds but never runs: the DiT output projection
# (2,099,200 + 26,650) and a state encoder for a state that goes into the prompt (1,057,792).
EXPECTED_COUNTS = {
    "starvla-qwen2.5-vl-3b-oft": (3_754_622_976, 42_012_679),
    "starvla-qwen2.5-vl-3b-gr00t": (3_754_622_976, 154_385_927),
    "starvla-qwen2.5-vl-3b-layerwise": (3_754_622_976, 611_176_455),
    "starvla-qwen3-vl-4b-oft": (4_437_815_808, 65_623_047),
    "starvla-qwen3-vl-4b-gr00t": (4_437_815_808, 160_677_383),
    "starvla-qwen3-vl-4b-layerwise": (4_437_815_808, 538_678_305 + 94_593_024 - 3_183_642),
}


@pytest.mark.parametrize("preset", FULL_SIZE)
def test_full_size_presets_build_on_meta(preset: str) -> None:
    with torch.device("meta"):
        model = build_backbone(preset)
    assert (count(model.vlm), count(model.action_head)) == EXPECTED_COUNTS[preset]
    qwen3 = "qwen3" in preset
    cls = "Qwen3VLForConditionalGeneration" if qwen3 else "Qwen2_5_VLForConditionalGeneration"
    assert type(model.vlm).__name__ == cls  # chosen by qwen_version, not by a path
    assert (model.num_layers, model.hidden_size) == ((36, 2560) if qwen3 else (36, 2048))
    # 224-px views: 7x7 tokens per camera for Qwen3-VL (16-px patches), 8x8 for Qwen2.5-VL.
    assert model.visual_grid == ((7, 7) if qwen3 else (8, 8))
    capability = model.capability_parameter_names()
    assert capability and all(n.startswith("vlm.") for n in capability)


def test_unknown_names_are_clear_errors() -> None:
    with pytest.raises(BackboneError, match=r"unknown action head 'dit'.*'gr00t'"):
        build_backbone("starvla-tiny-oft", head="dit")
    with pytest.raises(BackboneError, match=r"head_args \['depth'\].*GR00THeadConfig"):
        build_backbone("starvla-tiny-gr00t", head_args={"depth": 3})
    with pytest.raises(BackboneError, match="unknown qwen_version 'qwen2-vl'"):
        build_backbone("starvla-tiny-oft", qwen_version="qwen2-vl")
    with pytest.raises(BackboneError, match="narrower than the VLM"):
        build_backbone("starvla-tiny-layerwise", head_args={"width": 64})
    with pytest.raises(BackboneError, match="multiple of patch x merge = 16"):
        build_backbone("starvla-tiny-oft", image_size=72)
    with pytest.raises(BackboneError, match="'oft' head has no state input"):
        build_backbone("starvla-tiny-oft", state_mode="head")


# -- training ------------------------------------------------------------------------------------


@pytest.mark.parametrize("head", HEADS)
def test_each_head_learns_on_demo_data(head: str, demo_file: Path) -> None:
    data = HDF5RobotDataset([demo_file], CAMERAS, PROPRIO_KEYS, chunk_size=8)
    batch = next(iter(torch.utils.data.DataLoader(data, batch_size=4)))
    model = build_backbone(f"starvla-tiny-{head}", proprio_dim=data.proprio_dim).train()

    def loss_with_fixed_noise() -> float:
        torch.manual_seed(100)  # the flow heads' noise and t, the same before and after
        with torch.no_grad():
            return model(batch).loss.item()

    before = loss_with_fixed_noise()
    optimizer = torch.optim.AdamW(model.parameters(), lr=3e-3)
    for _ in range(40):
        loss = model(batch).loss
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = loss_with_fixed_noise()
    assert after < 0.9 * before, (before, after)


@pytest.mark.parametrize("head", ["gr00t", "layerwise"])
def test_flow_heads_sample_with_the_configured_steps(head: str) -> None:
    model = tiny(head, head_args={"num_inference_steps": 3, "repeated_diffusion_steps": 5})
    calls: list[int] = []
    model.action_head.action_encoder.register_forward_hook(
        lambda _m, args, _o: calls.append(args[0].shape[0])
    )
    vlm_calls: list[int] = []
    model.vlm.model.register_forward_hook(lambda *_: vlm_calls.append(1))
    batch = make_batch()
    actions = predict(model, batch)
    assert actions.shape == (2, 8, 7) and torch.isfinite(actions).all()
    assert calls == [2, 2, 2]  # three Euler steps
    calls.clear()
    vlm_calls.clear()
    model.train()
    model(batch).loss.backward()
    # One VLM pass serves the 5 repeated noise samples of the loss; training does not sample.
    assert vlm_calls == [1] and calls == [10]


def test_flow_head_ignores_vlm_padding() -> None:
    """The DiT cross-attention masks padded VLM positions (StarVLA passes no mask)."""
    head = build_head(
        "gr00t",
        {"width": 32, "num_heads": 2, "hidden_size": 32, "num_layers": 2, "dropout": 0.0},
        HeadDims(vlm_width=16, vlm_layers=2, action_dim=3, chunk_size=4),
    )
    hidden = torch.randn(1, 6, 16)
    mask = torch.tensor([[False, False, True, True, True, True]])
    noisy, timestep = torch.randn(1, 4, 3), torch.tensor([500])
    first = head.velocity(hidden, mask, noisy, timestep, None)
    second = head.velocity(hidden + 5 * ~mask[..., None], mask, noisy, timestep, None)
    torch.testing.assert_close(first, second)


def test_flow_time_distribution_and_dropout() -> None:
    dims = HeadDims(vlm_width=16, vlm_layers=2, action_dim=3, chunk_size=4)
    small = {"width": 16, "num_heads": 2, "hidden_size": 16, "num_layers": 2}
    head = build_head("gr00t", {**small, "noise_s": 0.5}, dims)
    small_layerwise = {k: v for k, v in small.items() if k != "num_layers"}
    layerwise = build_head("layerwise", {**small_layerwise, "width": 8, "noise_s": 0.5}, dims)
    torch.manual_seed(0)
    t = head.sample_time(20000, torch.device("cpu"))
    torch.manual_seed(0)
    t_layerwise = layerwise.sample_time(20000, torch.device("cpu"))
    torch.manual_seed(0)
    u = torch.distributions.Beta(torch.tensor(1.5), torch.tensor(1.0)).sample((20000,))
    # StarVLA's formulas: GR00T clips u at s, t = (s - u) / s in [0, 1] (GR00T_ActionHeader);
    # the layerwise head does not clip, so t goes below 0 when u > s (LayerwiseFM_ActionHeader).
    torch.testing.assert_close(t, (0.5 - u.clamp(max=0.5)) / 0.5, rtol=0, atol=0)
    torch.testing.assert_close(t_layerwise, (0.5 - u) / 0.5, rtol=0, atol=0)
    assert t.min() >= 0 and t.max() <= 1 and t_layerwise.min() < 0
    dropped = build_head("gr00t", {**small, "dropout": 0.5}, dims)
    hidden, mask = torch.randn(1, 5, 16), torch.ones(1, 5, dtype=torch.bool)
    args = (hidden, mask, torch.randn(1, 4, 3), torch.tensor([10]), None)
    assert not torch.allclose(dropped.velocity(*args), dropped.velocity(*args))
    dropped.eval()
    torch.testing.assert_close(dropped.velocity(*args), dropped.velocity(*args))


def test_seeded_flow_noise_follows_the_sample() -> None:
    """With seeds, sample b's noise and t depend on seeds[b] only and its k copies stay with it
    (rows as ``x.repeat(k, ...)``); the global RNG is left as it was. Without: the global RNG."""
    dims = HeadDims(vlm_width=16, vlm_layers=2, action_dim=3, chunk_size=4)
    head = build_head("gr00t", {"width": 16, "num_heads": 2, "hidden_size": 16}, dims)
    seeds = torch.tensor([11, 12, 13])
    like = torch.zeros(2 * 3, 4, 3)  # 2 copies of 3 samples
    state = torch.get_rng_state()
    noise, t = draw_flow_noise(like, head.sample_time, seeds)
    assert torch.equal(torch.get_rng_state(), state)
    for b in range(3):  # one sample alone, as on a rank that holds only it
        alone = draw_flow_noise(like[:2], head.sample_time, seeds[b : b + 1])
        torch.testing.assert_close((noise[b::3], t[b::3]), alone, rtol=0, atol=0)
    assert not torch.equal(noise[0], noise[3]) and t[0] != t[3]  # each copy its own draw
    torch.manual_seed(0)
    unseeded = draw_flow_noise(like, head.sample_time)
    torch.manual_seed(0)
    upstream = (torch.randn_like(like), head.sample_time(6, torch.device("cpu")))
    torch.testing.assert_close(unseeded, upstream, rtol=0, atol=0)
    with pytest.raises(BackboneError, match="4 noise seeds for 6 rows"):
        draw_flow_noise(like, head.sample_time, torch.arange(4))


# -- the Qwen-VL wrapper ---------------------------------------------------------------------------


def test_action_query_is_one_added_special_token() -> None:
    model = tiny("oft")
    tok = model.tokenizer
    query = model.action_head.query_token
    assert tok.encode(query, add_special_tokens=False) == [tok.convert_tokens_to_ids(query)]
    assert len(tok.encode("🔍", add_special_tokens=False)) > 1  # why StarVLA's emoji is not used
    ids, _ = model.tokenize([model.prompt_text("lift")], 2, torch.device("cpu"))
    assert int((ids == tok.convert_tokens_to_ids(query)).sum()) == 8  # chunk_size queries
    # Flow heads read the whole sequence: no query tokens in their prompt.
    assert "<|action_query|>" not in tiny("gr00t").prompt_text("lift")


def test_forward_returns_the_contract_outputs() -> None:
    model = tiny("oft")
    batch = make_batch(instructions=["lift", "stack the red cube on the green cube, carefully"])
    with torch.no_grad():
        out = model(batch, OutputRequest(hidden_layers=(0, 2, 4), lm_logits=True))
    assert out.actions.shape == (2, 8, 7) and out.loss.ndim == 0
    assert set(out.hidden_states) == {0, 2, 4}  # only the requested layers
    assert out.visual_grid == (4, 4)
    assert out.visual_token_mask.sum(1).tolist() == [model.num_visual_tokens] * 2  # 2 x 16
    assert not out.attention_mask[0, 0] and out.attention_mask[1].all()  # left padding
    # Layer L is reported before the final norm; the LM logits come from Qwen's own head after it.
    normed = model.vlm.model.language_model.norm(out.hidden_states[4])
    torch.testing.assert_close(out.lm_logits, model.vlm.lm_head(normed))
    assert out.lm_logits.shape[-1] == model.vlm.config.text_config.vocab_size


def test_left_padding_changes_nothing() -> None:
    model = tiny("oft")
    batch = make_batch(instructions=["lift", "stack the red cube on top of the green cube"])
    together = predict(model, batch)[0]
    alone = predict(model, {k: v[:1] for k, v in batch.items()})[0]
    torch.testing.assert_close(together, alone, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("version", ["qwen2.5-vl", "qwen3-vl"])
def test_images_are_patchified_as_transformers_does(version: str) -> None:
    from transformers import Qwen2VLImageProcessor

    mean = HALF if version == "qwen3-vl" else (0.48145466, 0.4578275, 0.40821073)
    std = HALF if version == "qwen3-vl" else (0.26862954, 0.26130258, 0.27577711)
    model = tiny(
        "oft", qwen_version=version, qwen=tiny_qwen_architecture(version), image_mean=mean,
        image_std=std,
    )  # fmt: skip
    pixels = torch.randint(0, 256, (2, 2, 3, 64, 64), dtype=torch.uint8)
    ours, grid = model.pixel_values(pixels.float() / 255)
    processor = Qwen2VLImageProcessor(
        patch_size=8, merge_size=2, temporal_patch_size=2, image_mean=list(mean),
        image_std=list(std), do_resize=False,
    )  # fmt: skip
    reference = processor(list(pixels.flatten(0, 1)), return_tensors="pt")
    torch.testing.assert_close(ours, reference["pixel_values"], atol=1e-5, rtol=1e-5)
    assert grid.tolist() == reference["image_grid_thw"].tolist()


def test_qwen3_vl_variant_trains_through_deepstack() -> None:
    model = tiny(
        "gr00t", qwen_version="qwen3-vl", qwen=tiny_qwen_architecture("qwen3-vl"),
        image_mean=HALF, image_std=HALF,
    ).train()  # fmt: skip
    assert type(model.vlm).__name__ == "Qwen3VLForConditionalGeneration"
    model(make_batch()).loss.backward()
    deepstack = model.vlm.model.visual.deepstack_merger_list[0].linear_fc2.weight.grad
    assert deepstack is not None and deepstack.abs().sum() > 0


def test_state_in_the_prompt_and_as_a_head_token() -> None:
    prompt_model = tiny("oft", state_mode="prompt")
    state = torch.tensor([-1.5, -1.0, -0.5, 0.0, 0.1, 0.8, 1.0, 0.999])
    # StarVLA's share_tools.state2str_transform, unclipped: -1 below the range.
    expected = np.digitize(state.numpy(), np.linspace(-1, 1, 257)[:-1]) - 1
    assert expected[0] == -1
    text = prompt_model.prompt_text("lift", state)
    assert f"lift [STATE] {' '.join(map(str, expected))} [ACTION] Please predict" in text
    coarse = tiny(
        "gr00t", state_mode="prompt", state_bins=16, prompt_template="Task: {instruction}"
    )
    expected = np.digitize(state.numpy(), np.linspace(-1, 1, 17)[:-1]) - 1
    assert (
        coarse.prompt_text("lift", state)
        == f"Task: lift [STATE] {' '.join(map(str, expected))} [ACTION]"
    )
    batch = make_batch(1)
    changed = {**batch, keys.PROPRIO: batch[keys.PROPRIO] + 0.5}
    assert not torch.allclose(predict(prompt_model, batch), predict(prompt_model, changed))

    head_model = tiny("gr00t", state_mode="head")
    assert head_model.action_head.state_encoder is not None
    assert "[STATE]" not in head_model.prompt_text("lift")
    assert not torch.allclose(predict(head_model, batch), predict(head_model, changed))
    with pytest.raises(BackboneError, match="needs `proprio` in the batch"):
        head_model({k: v for k, v in batch.items() if k != keys.PROPRIO})


@pytest.mark.parametrize("attention", ["sdpa", "eager"])
def test_bidirectional_queries_only_change_the_query_block(attention: str) -> None:
    causal = tiny("oft", attn_implementation=attention)
    both = tiny("oft", head_args={"bidirectional_queries": True}, attn_implementation=attention)
    both.load_state_dict(causal.state_dict())
    batch = make_batch(instructions=["lift", "stack the red cube on the green cube"])
    request = OutputRequest(hidden_layers=(4,))
    with torch.no_grad():
        a = causal(batch, request).hidden_states[4][0]
        b = both(batch, request).hidden_states[4][0]
    ids, _ = causal.tokenize([causal.prompt_text("lift")], 2, a.device)
    first_query = int((ids[0] == causal._token_ids.query).nonzero()[0])
    padding = a.shape[0] - ids.shape[1]  # row 0 is left padded in the batch
    first_query += padding
    torch.testing.assert_close(a[padding:first_query], b[padding:first_query])
    assert not torch.allclose(a[first_query], b[first_query])  # now sees the later queries
    with pytest.raises(BackboneError, match="needs a 4-D attention mask"):
        tiny("oft", head_args={"bidirectional_queries": True}, attn_implementation="flex")


def test_action_token_ids_are_resolved_from_the_tokenizer() -> None:
    model = tiny("gr00t")
    size = len(model.tokenizer)
    ids = model.add_action_tokens([f"<robot_action_{i}>" for i in range(100)])
    assert ids == range(size, size + 100)
    assert model.tokenizer.encode("<robot_action_7><robot_action_8>", add_special_tokens=False) == [
        size + 7,
        size + 8,
    ]
    assert model.config.qwen["text_config"]["vocab_size"] == 384  # grown, padded to 64
    assert model.vlm.get_input_embeddings().num_embeddings == 384
    assert predict(model, make_batch()).shape == (2, 8, 7)


def test_language_model_logits_label_only_the_answer() -> None:
    model = tiny("oft")
    batch = make_batch()
    prompts, answers = ["Where?", "A longer question?"], ["the cube is left", "ok"]
    logits, labels = model.language_model_logits(batch, prompts, answers)
    assert logits.shape[:2] == labels.shape and logits.shape[-1] == 320
    tok = model.tokenizer
    for row, answer in enumerate(answers):
        expected = tok.encode(answer + "<|im_end|>", add_special_tokens=False)
        assert labels[row][labels[row] != -100].tolist() == expected
    # Left padding is ignored: the short row alone gives the same logits at its real tokens.
    alone, alone_labels = model.language_model_logits(
        {k: v[1:] for k, v in batch.items()}, prompts[1:], answers[1:]
    )
    n = alone.shape[1]
    torch.testing.assert_close(logits[1, -n:], alone[0], atol=1e-4, rtol=1e-4)
    assert torch.equal(labels[1, -n:], alone_labels[0]) and (labels[1, :-n] == -100).all()
    # Causal: the prompt's logits do not see the answer.
    one = {k: v[:1] for k, v in batch.items()}
    first, first_labels = model.language_model_logits(one, ["Where?"], ["left"])
    second, _ = model.language_model_logits(one, ["Where?"], ["rear"])
    start = int((first_labels[0] != -100).nonzero()[0])
    torch.testing.assert_close(first[0, :start], second[0, :start])
    assert not torch.allclose(first[0, start:], second[0, start:])


# -- loading -------------------------------------------------------------------------------------


def write_qwen_folder(model: StarVLA, root: Path, tokenizer: object | None = None) -> Path:
    """A transformers Qwen-VL folder as the hub has them: weights, config, tokenizer, processor."""
    model.vlm.save_pretrained(str(root))
    (tokenizer or tiny_qwen_tokenizer()).save_pretrained(str(root))
    mean, std = model.config.image_mean, model.config.image_std
    (root / "preprocessor_config.json").write_text(
        json.dumps({"image_mean": list(mean), "image_std": list(std), "patch_size": 8})
    )
    return root


@pytest.mark.parametrize("head", ["oft", "layerwise"])
def test_from_qwen_folder_and_head_safetensors(head: str, tmp_path: Path) -> None:
    source = tiny(head)
    root = write_qwen_folder(source, tmp_path / "qwen")  # a tokenizer without the query token
    head_file = source.save_head_weights(tmp_path / "head.safetensors")
    loaded = StarVLA.from_qwen(root, f"starvla-tiny-{head}", head_weights=head_file).eval()
    assert loaded.config.tokenizer == str(root)
    # A model rebuilt from the config alone (a Lightning checkpoint) reloads it from there.
    lazy = tiny(head, tokenizer=str(root))
    assert lazy.tokenizer.get_vocab() == loaded.tokenizer.get_vocab()
    batch = make_batch()
    torch.testing.assert_close(predict(loaded, batch), predict(source, batch))


def test_from_qwen_grows_the_vocabulary_for_the_query_token(tmp_path: Path) -> None:
    arch = tiny_qwen_architecture("qwen2.5-vl")
    arch["text_config"]["vocab_size"] = len(tiny_qwen_tokenizer())  # no room for one more token
    root = write_qwen_folder(tiny("oft", qwen=arch), tmp_path / "qwen")
    model = StarVLA.from_qwen(root, "starvla-tiny-oft")
    assert model.config.qwen["text_config"]["vocab_size"] == 320  # padded to a multiple of 64
    export = model.save_pretrained(tmp_path / "export")
    reloaded = from_pretrained(export).eval()
    batch = make_batch()
    torch.testing.assert_close(predict(reloaded, batch), predict(model.eval(), batch))


def test_from_qwen_errors_name_the_problem(tmp_path: Path) -> None:
    source = tiny("oft")
    root = write_qwen_folder(source, tmp_path / "qwen")
    with pytest.raises(
        BackboneError, match=r"holds a 'qwen2_5_vl' model.*qwen_version='qwen2.5-vl'"
    ):
        StarVLA.from_qwen(root, "starvla-tiny-oft", qwen_version="qwen3-vl")
    head_file = source.save_head_weights(tmp_path / "head.safetensors")
    state = load_file(str(head_file))
    del state["model.fc2.weight"]
    save_file(state, str(head_file))
    with pytest.raises(BackboneError, match=r"1 missing key.*`model\.fc2\.weight`"):
        StarVLA.from_qwen(root, "starvla-tiny-oft", head_weights=head_file)
    weights = load_file(str(root / "model.safetensors"))
    del weights["model.norm.weight"]
    save_file(weights, str(root / "model.safetensors"), metadata={"format": "pt"})
    with pytest.raises(BackboneError, match=r"1 missing keys.*language_model\.norm\.weight"):
        StarVLA.from_qwen(root, "starvla-tiny-oft")


# StarVLA runs written by StarVLA itself are loaded and compared in test_parity_starvla.py.


# -- Lightning: LoRA, export, checkpoints, CLI ---------------------------------------------------


def test_lora_trains_only_lora_and_heads_and_exports_identically(
    demo_file: Path, tmp_path: Path
) -> None:
    dm = RobotDataModule(train_files=[str(demo_file)], batch_size=4)
    module = VLAModule(
        backbone="starvla-tiny-oft", data_spec=dm.spec, lora=LoraSettings(r=4, alpha=4)
    )
    trainable = {n for n, p in module.named_parameters() if p.requires_grad}
    assert all(".lora_" in n or n.startswith("backbone.action_head.") for n in trainable)
    for part in ("language_model.layers.0.self_attn.q_proj", "visual.blocks.0.attn.qkv", "merger"):
        assert any(part in n and ".lora_" in n for n in trainable), part
    frozen = {n: p.detach().clone() for n, p in module.named_parameters() if not p.requires_grad}
    lora_b = {n: p.detach().clone() for n, p in module.named_parameters() if "lora_B" in n}
    cpu_trainer(3, tmp_path).fit(module, dm)
    assert all(torch.equal(v, module.get_parameter(n)) for n, v in frozen.items())
    assert any(not torch.equal(v, module.get_parameter(n)) for n, v in lora_b.items())
    export = module.export(tmp_path / "export")
    weights = load_file(str(export / "model.safetensors"))
    assert "vlm.lm_head.weight" not in weights  # tied to the embeddings: stored once
    assert not any("lora" in k or "base_layer" in k for k in weights)
    reloaded = from_pretrained(export).eval()
    batch = next(iter(torch.utils.data.DataLoader(dm.train_dataset, batch_size=2)))
    module.eval()
    torch.testing.assert_close(
        predict(reloaded, batch), predict(module.backbone, batch), atol=1e-5, rtol=1e-4
    )


def test_save_pretrained_round_trip_of_a_flow_head(tmp_path: Path) -> None:
    model = tiny("layerwise", state_mode="head")
    reloaded = from_pretrained(model.save_pretrained(tmp_path / "export")).eval()
    assert reloaded.config.head_args == model.config.head_args  # every head field is recorded
    batch = make_batch()
    torch.testing.assert_close(predict(reloaded, batch), predict(model, batch))


def test_cli_composes_the_config_fragment(tmp_path: Path) -> None:
    from capvector.cli import main
    from conftest import write_demo_file

    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    root = tmp_path / "runs"
    main([
        "fit", "--config", str(REPO / "configs/debug.yaml"),
        "--config", str(REPO / "configs/backbones/starvla-tiny-gr00t.yaml"),
        f"--data.train_files=[{data}]", "--data.batch_size=4", "--trainer.max_steps=2",
        "--data.eval_tasks=null",
        f"--trainer.default_root_dir={root}", f"--trainer.logger.init_args.save_dir={root}",
        "--trainer.enable_progress_bar=false",
    ])  # fmt: skip
    version = root / "fit" / "version_0"
    config = json.loads((version / "export" / "config.json").read_text())
    assert config["family"] == "starvla" and config["backbone_config"]["head"] == "gr00t"
    # The Lightning checkpoint reloads strictly (the tied lm_head is restored from the embeddings).
    restored = load_module(next((version / "checkpoints").glob("*.ckpt"))).eval()
    assert isinstance(restored.backbone, StarVLA)


@pytest.mark.parametrize("head", ["gr00t", "layerwise"])
def test_flow_heads_sample_only_when_actions_are_asked_for(head: str) -> None:
    """Training never runs the sampler (every denoising step) to throw its actions away; a
    held-out L1 asks for them (one sampler run), inference always gets them."""
    model = tiny(head).eval()
    batch = make_batch()
    calls = []
    sample = model.action_head.sample

    def counted(*args, **kwargs):
        calls.append(1)
        return sample(*args, **kwargs)

    model.action_head.sample = counted
    with torch.no_grad():
        torch.manual_seed(0)
        trained = model(batch)
        assert trained.actions is None and trained.loss.ndim == 0 and not calls
        torch.manual_seed(0)
        asked = model(batch, OutputRequest(actions=True))
        assert len(calls) == 1 and asked.actions.shape == (2, 8, 7)
        torch.testing.assert_close(asked.loss, trained.loss)  # same seeded noise
        assert torch.isfinite(asked.actions).all()
        inference = {k: v for k, v in batch.items() if k != keys.ACTIONS}
        assert model.predict_action(inference).shape == (2, 8, 7) and len(calls) == 2


@pytest.mark.parametrize(
    ("preset", "overrides"),
    [
        ("starvla-tiny-gr00t", {"prompt_template": "task: {instruction}"}),
        ("starvla-tiny-gr00t", {"image_mean": (0.5, 0.5, 0.5)}),
        ("starvla-tiny-gr00t", {"image_std": (0.5, 0.5, 0.5)}),
        ("starvla-tiny-gr00t", {"state_mode": "head"}),
        ("starvla-tiny-gr00t", {"head_args": {"num_inference_steps": 2}}),
        ("starvla-tiny-gr00t", {"head_args": {"noise_s": 0.5}}),
        ("starvla-tiny-gr00t", {"head_args": {"num_future_tokens": 2}}),
        ("starvla-tiny-gr00t", {"qwen": {"text_config": {"rms_norm_eps": 0.5}}}),
        ("starvla-tiny-gr00t", {"qwen_version": "qwen3-vl"}),
        ("starvla-tiny-layerwise", {"head_args": {"num_inference_steps": 2}}),
        ("starvla-tiny-oft", {"state_mode": "prompt"}),
        ("starvla-tiny-oft", {"state_mode": "prompt", "state_bins": 8}),
        ("starvla-tiny-oft", {"head_args": {"num_blocks": 1}}),
    ],
    ids=lambda v: v if isinstance(v, str) else json.dumps(v),
)
def test_config_fields_have_an_effect(preset: str, overrides: dict) -> None:
    assert_field_changes_the_model(preset, overrides, make_batch())
