"""OpenVLA-OFT-style backbone: architecture facts, attention, readout, original checkpoint loading."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from capvector.backbones import (
    BackboneError,
    OutputRequest,
    build_backbone,
    from_pretrained,
    list_presets,
)
from capvector.backbones.openvla_oft import OpenVLAOFT
from capvector.cli import main
from capvector.data import keys
from capvector.errors import CapVectorError
from conftest import UPSTREAM_FIXTURES, assert_field_changes_the_model


def make_batch(batch_size: int = 2, instructions: list[str] | None = None, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    instructions = (
        instructions or ["lift the red cube", "stack the red cube on the green cube"][:batch_size]
    )
    return {
        keys.IMAGES: torch.rand(batch_size, 2, 3, 64, 64, generator=g),
        keys.PROPRIO: torch.rand(batch_size, 8, generator=g) * 2 - 1,
        keys.ACTIONS: torch.rand(batch_size, 8, 7, generator=g) * 2 - 1,
        keys.INSTRUCTION: instructions,
    }


@pytest.fixture(scope="module")
def tiny() -> OpenVLAOFT:
    torch.manual_seed(0)
    return build_backbone("openvla-oft-tiny").eval()


@pytest.mark.parametrize("preset", list_presets())
def test_every_preset_builds_on_meta(preset: str) -> None:
    with torch.device("meta"):
        model = build_backbone(preset)
    assert sum(p.numel() for p in model.parameters()) > 0
    assert model.capability_parameter_names(), "a preset must say what a capability vector covers"


def test_openvla_oft_7b_matches_published_parameter_counts() -> None:
    with torch.device("meta"):
        model = build_backbone("openvla-oft-7b")

    def count(module: torch.nn.Module) -> int:
        return sum(p.numel() for p in module.parameters())

    vlm = count(model.vision_backbone) + count(model.projector) + count(model.language_model)
    assert vlm == 7_541_237_184
    assert count(model.action_head) == 151_117_831
    assert count(model.proprio_projector) == 16_818_176
    assert model.num_visual_tokens == 512  # 2 cameras x 16 x 16 patches


def test_openvla_oft_aloha_7b_parameter_counts() -> None:
    """OFT+ on ALOHA: the 7B VLM plus FiLM (two Linear(4096, D) per block of both ViTs), a head
    over 14 x 4096 inputs and a 14-d proprio projector."""
    with torch.device("meta"):
        model = build_backbone("openvla-oft-aloha-7b")

    def count(module: torch.nn.Module) -> int:
        return sum(p.numel() for p in module.parameters())

    vision = model.vision_backbone
    film = count(vision.featurizer_film) + count(vision.fused_featurizer_film)
    assert film == 24 * 2 * (4096 * 1024 + 1024) + 27 * 2 * (4096 * 1152 + 1152) == 456_241_920
    vlm = count(vision) - film + count(model.projector) + count(model.language_model)
    assert vlm == 7_541_237_184  # the same VLM as openvla-oft-7b
    assert count(model.action_head) == 268_644_366
    assert count(model.proprio_projector) == 14 * 4096 + 4096 + 4096 * 4096 + 4096
    assert model.num_visual_tokens == 768  # 3 cameras x 16 x 16 patches
    assert (model.config.chunk_size, model.config.action_dim) == (25, 14)


def test_film_conditions_the_vision_features_on_the_instruction() -> None:
    torch.manual_seed(0)
    model = build_backbone("openvla-oft-aloha-tiny").eval()
    batch = make_batch(1)
    batch[keys.IMAGES] = torch.rand(1, 3, 3, 64, 64)
    batch[keys.PROPRIO] = torch.rand(1, 14)
    batch.pop(keys.ACTIONS)
    seen = []
    model.vision_backbone.register_forward_hook(lambda _m, _a, out: seen.append(out))
    with torch.no_grad():
        model(batch)
        model({**batch, keys.INSTRUCTION: ["open the drawer"]})
    assert not torch.allclose(seen[0], seen[1])
    plain = build_backbone("openvla-oft-tiny")
    assert plain.vision_backbone.featurizer_film is None  # film=False adds nothing


def test_film_padding_changes_nothing() -> None:
    """FiLM averages only real tokens (upstream also averages a padded batch's pad embeddings, see
    _mean_embedding): a short prompt padded beside a long one gets the actions it gets alone."""
    torch.manual_seed(0)
    model = build_backbone("openvla-oft-aloha-tiny").eval()
    batch = make_batch(2, ["lift", "stack the red cube on top of the green cube, carefully"])
    batch[keys.IMAGES] = torch.rand(2, 3, 3, 64, 64)
    batch[keys.PROPRIO] = torch.rand(2, 14)
    batch.pop(keys.ACTIONS)
    with torch.no_grad():
        together = model(batch).actions[0]
        alone = model({k: v[:1] for k, v in batch.items()}).actions[0]
    torch.testing.assert_close(together, alone, atol=1e-5, rtol=1e-4)


def test_unknown_preset_names_close_matches() -> None:
    with pytest.raises(
        BackboneError, match=r"unknown backbone preset 'openvla-oft-tinny'.*openvla-oft-tiny"
    ):
        build_backbone("openvla-oft-tinny")
    with pytest.raises(BackboneError, match="unknown config field"):
        build_backbone("openvla-oft-tiny", hidden=3)


def test_forward_backward_and_requested_outputs(tiny: OpenVLAOFT) -> None:
    model = build_backbone("openvla-oft-tiny")
    out = model(make_batch(), OutputRequest(hidden_layers=(0, 2), lm_logits=True))
    assert out.actions.shape == (2, 8, 7)
    assert set(out.hidden_states) == {0, 2}  # only the requested layers are kept
    n_vis = model.num_visual_tokens
    assert (
        out.visual_token_mask[:, 1 : 1 + n_vis].all() and out.visual_token_mask.sum() == 2 * n_vis
    )
    assert out.visual_grid == (8, 8)
    assert out.lm_logits.shape[-1] == model.config.llm.vocab_size
    out.loss.backward()
    for name in (
        "action_head.model.fc1.weight",
        "projector.fc1.weight",
        "proprio_projector.fc1.weight",
    ):
        grad = model.get_parameter(name).grad
        assert grad is not None and grad.abs().sum() > 0, name
    vision_grad = model.vision_backbone.featurizer.blocks[0].attn.qkv.weight.grad
    assert vision_grad is not None and vision_grad.abs().sum() > 0


def test_attention_is_bidirectional(tiny: OpenVLAOFT) -> None:
    """An early position (first visual token) must depend on a later one (the proprio token)."""
    batch = make_batch(1)
    request = OutputRequest(hidden_layers=(tiny.num_layers,))
    with torch.no_grad():
        first = tiny(batch, request).hidden_states[tiny.num_layers][0, 1]
        batch[keys.PROPRIO] = batch[keys.PROPRIO] + 1.0
        second = tiny(batch, request).hidden_states[tiny.num_layers][0, 1]
    assert not torch.allclose(first, second, atol=1e-6)


def test_padding_changes_nothing(tiny: OpenVLAOFT) -> None:
    """Right padding of a short prompt in a batch with a long one leaves its actions unchanged."""
    batch = make_batch(2, ["lift", "stack the red cube on top of the green cube, carefully"])
    with torch.no_grad():
        together = tiny(batch).actions[0]
        alone = tiny({k: v[:1] for k, v in batch.items()}).actions[0]
    torch.testing.assert_close(together, alone, atol=1e-5, rtol=1e-4)


def test_action_slots_are_zeroed_and_read_one_position_early(tiny: OpenVLAOFT) -> None:
    batch = make_batch(1, ["lift"])
    seen: dict[str, torch.Tensor] = {}

    def record(name: str, take_input: bool):  # noqa: ANN202
        def hook(_module, args, output) -> None:  # noqa: ANN001
            seen[name] = args[0] if take_input else output

        return hook

    hooks = [
        tiny.action_head.register_forward_hook(record("head_in", take_input=True)),
        tiny.language_model.model.norm.register_forward_hook(record("last", take_input=False)),
    ]
    with torch.no_grad():
        out = tiny(batch, OutputRequest(hidden_layers=(0,)))
    for hook in hooks:
        hook.remove()
    prompt_ids = tiny.tokenizer(
        tiny.config.prompt_template.format(instruction="lift"), add_special_tokens=False
    )
    first_slot = (
        1 + tiny.num_visual_tokens + 1 + len(prompt_ids["input_ids"])
    )  # BOS, visual, proprio
    n_slots = 8 * 7
    embeds = out.hidden_states[0][0]
    assert embeds[first_slot : first_slot + n_slots].abs().sum() == 0  # slots carry position only
    assert embeds[first_slot - 1].abs().sum() > 0
    expected = seen["last"][0, first_slot - 1 : first_slot - 1 + n_slots]
    torch.testing.assert_close(seen["head_in"][0], expected)


def test_mismatched_camera_count_is_a_clear_error(tiny: OpenVLAOFT) -> None:
    batch = make_batch(1)
    batch[keys.IMAGES] = batch[keys.IMAGES][:, :1]
    with pytest.raises(BackboneError, match="1 camera.*num_images=2"):
        tiny(batch)


# -- original OpenVLA-OFT checkpoint folders -----------------------------------------------------
# Parity with upstream's outputs is test_parity_openvla_oft.py; these check the loader's
# handling of variations of upstream's run folder (a copy of the LIBERO fixture).

UPSTREAM_LIBERO = UPSTREAM_FIXTURES / "openvla_oft" / "libero"


@pytest.fixture
def upstream_folder(tmp_path: Path) -> Path:
    root = tmp_path / "run--5_chkpt"
    shutil.copytree(UPSTREAM_LIBERO, root)
    return root


def upstream_batch(model: OpenVLAOFT) -> dict:
    batch = make_batch(2)
    batch[keys.IMAGES] = torch.rand(2, 2, 3, 224, 224, generator=torch.Generator().manual_seed(1))
    return batch


def test_from_original_reads_sharded_weights(upstream_folder: Path) -> None:
    """save_pretrained's sharded layout (index + shards) loads like the single file."""
    from safetensors.torch import load_file

    single = OpenVLAOFT.from_original(upstream_folder, preset="openvla-oft-tiny").model.eval()
    state = load_file(str(upstream_folder / "model.safetensors"))
    (upstream_folder / "model.safetensors").unlink()
    names = sorted(state)
    shards = {
        "model-00001-of-00002.safetensors": names[::2],
        "model-00002-of-00002.safetensors": names[1::2],
    }
    weight_map = {}
    for shard, keys_in_shard in shards.items():
        save_file({k: state[k] for k in keys_in_shard}, str(upstream_folder / shard))
        weight_map.update(dict.fromkeys(keys_in_shard, shard))
    (upstream_folder / "model.safetensors.index.json").write_text(
        json.dumps({"metadata": {}, "weight_map": weight_map})
    )
    sharded = OpenVLAOFT.from_original(upstream_folder, preset="openvla-oft-tiny").model.eval()
    batch = upstream_batch(single)
    torch.testing.assert_close(sharded.predict_action(batch), single.predict_action(batch))


def test_from_original_names_a_missing_key(upstream_folder: Path) -> None:
    head = next(upstream_folder.glob("action_head--*"))
    state = torch.load(head, weights_only=True)
    del state["module.model.fc2.bias"]
    torch.save(state, head)
    with pytest.raises(BackboneError, match=r"1 missing key.*action_head\.model\.fc2\.bias"):
        OpenVLAOFT.from_original(upstream_folder, preset="openvla-oft-tiny")


def test_from_original_rejects_another_architecture(upstream_folder: Path) -> None:
    with pytest.raises(BackboneError, match="shape mismatch.*another architecture"):
        OpenVLAOFT.from_original(
            upstream_folder, preset="openvla-oft-tiny", overrides={"llm": {"hidden_size": 32}}
        )


def test_from_original_requires_the_save_pretrained_config(upstream_folder: Path) -> None:
    (upstream_folder / "config.json").unlink()
    with pytest.raises(BackboneError, match="config.json is missing: an OpenVLA-OFT run folder"):
        OpenVLAOFT.from_original(upstream_folder, preset="openvla-oft-tiny")


def test_from_original_merges_a_peft_lora_adapter(upstream_folder: Path) -> None:
    from peft import LoraConfig, get_peft_model

    base = OpenVLAOFT.from_original(upstream_folder, preset="openvla-oft-tiny").model
    target = "language_model.model.layers.0.self_attn.q_proj"
    before = base.get_parameter(f"{target}.weight").detach().clone()
    peft_model = get_peft_model(
        base, LoraConfig(r=4, lora_alpha=8, target_modules=[target], init_lora_weights="gaussian")
    )
    with torch.no_grad():
        for name, param in peft_model.named_parameters():
            if "lora_B" in name:
                param.normal_()
    shutil.rmtree(upstream_folder / "lora_adapter")
    peft_model.save_pretrained(str(upstream_folder / "lora_adapter"))
    expected = peft_model.merge_and_unload().get_parameter(f"{target}.weight")
    loaded = OpenVLAOFT.from_original(
        upstream_folder, preset="openvla-oft-tiny", apply_lora_adapter=True
    ).model
    # The checkpoint's weights are bf16 (as upstream saves them): the merge rounds back to bf16.
    torch.testing.assert_close(
        loaded.get_parameter(f"{target}.weight"), expected.to(torch.bfloat16).float()
    )
    assert not torch.allclose(expected, before)


def test_from_original_reports_an_unreachable_hub_id() -> None:
    with pytest.raises(CapVectorError, match="could not be downloaded"):
        OpenVLAOFT.from_original(
            "nonexistent-org-capvector/nonexistent-model", preset="openvla-oft-tiny"
        )


def test_a_partial_nested_override_changes_only_the_fields_it_names() -> None:
    from capvector.backbones import preset_config
    from capvector.module import VLAModule

    tiny = preset_config("openvla-oft-tiny")
    changed = preset_config("openvla-oft-tiny", featurizer={"embed_dim": 32})
    assert changed.featurizer.embed_dim == 32
    assert (
        dataclasses.replace(changed.featurizer, embed_dim=tiny.featurizer.embed_dim)
        == tiny.featurizer
    )
    module = VLAModule(
        backbone="openvla-oft-tiny", backbone_overrides={"featurizer": {"embed_dim": 32}}
    )
    assert module.backbone.config.featurizer == changed.featurizer


@pytest.mark.parametrize(
    "overrides",
    [
        {"head_blocks": 3},
        {"film": True},
        {"prompt_template": "In: {instruction}\nOut: "},
        {"image_size": 32},
        {"llm": {"rope_theta": 50.0}},
        {"llm": {"rms_norm_eps": 0.5}},
        {"llm": {"num_kv_heads": 2}},
        {"featurizer": {"act_layer": "gelu_tanh"}},
        {"featurizer": {"mlp_ratio": 2.0}},
        {"fused_featurizer": {"global_pool": "avg"}},
        {"fused_featurizer": {"reg_tokens": 2}},
    ],
    ids=lambda o: json.dumps(o),
)
def test_config_fields_have_an_effect(overrides: dict) -> None:
    assert_field_changes_the_model("openvla-oft-tiny", overrides, make_batch())


def test_import_original_writes_a_usable_theta_pre(tmp_path: Path) -> None:
    """An OpenVLA-OFT run folder written by upstream's code -> a capvector export."""
    folder = UPSTREAM_LIBERO
    out = tmp_path / "theta_pre"
    assert (
        main(
            [
                "import-original",
                "--preset",
                "openvla-oft-tiny",
                "--folder",
                str(folder),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert (out / "dataset_statistics.json").is_file()
    model = OpenVLAOFT.from_original(folder, preset="openvla-oft-tiny").model.eval()
    batch = upstream_batch(model)
    torch.testing.assert_close(
        from_pretrained(out).eval().predict_action(batch), model.predict_action(batch)
    )
