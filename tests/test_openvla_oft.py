"""OpenVLA-OFT-style backbone: architecture facts, attention, readout, original checkpoint loading."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from capvector.backbones import BackboneError, OutputRequest, build_backbone, list_presets
from capvector.backbones.openvla_oft import OpenVLAOFT
from capvector.data import keys


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


def write_original_folder(model: OpenVLAOFT, root: Path, step: int = 150000) -> Path:
    """A run folder in the layout OpenVLA-OFT's finetune.py saves, with its real key names."""
    root.mkdir(parents=True)
    state = model.state_dict()
    vlm = {}
    for key, value in state.items():
        if key.startswith(("action_head.", "proprio_projector.")):
            continue
        if key.startswith("vision_backbone.") and (".ls1.gamma" in key or ".ls2.gamma" in key):
            key = key.replace(".gamma", ".scale_factor")  # HF renames `gamma` parameters
        vlm[key] = value.clone()
    keys_sorted = sorted(vlm)
    half = len(keys_sorted) // 2
    shards = {
        "model-00001-of-00002.safetensors": keys_sorted[:half],
        "model-00002-of-00002.safetensors": keys_sorted[half:],
    }
    weight_map = {}
    for shard, names in shards.items():
        save_file({k: vlm[k].contiguous() for k in names}, str(root / shard))
        weight_map.update(dict.fromkeys(names, shard))
    (root / "model.safetensors.index.json").write_text(
        json.dumps({"metadata": {}, "weight_map": weight_map})
    )
    for component in ("action_head", "proprio_projector"):
        sub = {
            f"module.{k[len(component) + 1 :]}": v.clone()
            for k, v in state.items()
            if k.startswith(component + ".")
        }
        torch.save(sub, root / f"{component}--{step}_checkpoint.pt")
    stats = {"libero_spatial_no_noops": {"action": {"q01": [0.0] * 7, "q99": [1.0] * 7}}}
    (root / "dataset_statistics.json").write_text(json.dumps(stats))
    model.tokenizer.save_pretrained(str(root))
    return root


def test_from_original_loads_strictly_with_real_key_names(tiny: OpenVLAOFT, tmp_path: Path) -> None:
    root = write_original_folder(tiny, tmp_path / "run--150000_chkpt")
    imported = OpenVLAOFT.from_original(root, preset="openvla-oft-tiny")
    loaded = imported.model
    assert "libero_spatial_no_noops" in imported.statistics
    batch = make_batch()
    torch.testing.assert_close(loaded.eval().predict_action(batch), tiny.predict_action(batch))


def test_from_original_names_a_missing_key(tiny: OpenVLAOFT, tmp_path: Path) -> None:
    root = write_original_folder(tiny, tmp_path / "run")
    head = root / "action_head--150000_checkpoint.pt"
    state = torch.load(head, weights_only=True)
    del state["module.model.fc2.weight"]
    torch.save(state, head)
    with pytest.raises(BackboneError, match=r"1 missing key.*action_head\.model\.fc2\.weight"):
        OpenVLAOFT.from_original(root, preset="openvla-oft-tiny")


def test_from_original_rejects_another_architecture(tiny: OpenVLAOFT, tmp_path: Path) -> None:
    root = write_original_folder(tiny, tmp_path / "run")
    with pytest.raises(BackboneError, match="shape mismatch.*another architecture"):
        OpenVLAOFT.from_original(
            root,
            preset="openvla-oft-tiny",
            overrides=dict(
                head_blocks=2,
                llm={
                    "hidden_size": 32,
                    "intermediate_size": 64,
                    "num_layers": 4,
                    "num_heads": 4,
                    "num_kv_heads": 4,
                    "vocab_size": 320,
                    "max_position_embeddings": 512,
                },
            ),
        )


def test_from_original_merges_a_peft_lora_adapter(tiny: OpenVLAOFT, tmp_path: Path) -> None:
    from peft import LoraConfig, get_peft_model

    root = write_original_folder(tiny, tmp_path / "run")
    target = "language_model.model.layers.0.self_attn.q_proj"
    donor = build_backbone("openvla-oft-tiny")
    donor.load_state_dict(tiny.state_dict())
    peft_model = get_peft_model(
        donor, LoraConfig(r=4, lora_alpha=8, target_modules=[target], init_lora_weights="gaussian")
    )
    with torch.no_grad():
        for name, param in peft_model.named_parameters():
            if "lora_B" in name:
                param.normal_()
    peft_model.save_pretrained(str(root / "lora_adapter"))
    expected = peft_model.merge_and_unload().get_parameter(f"{target}.weight")
    loaded = OpenVLAOFT.from_original(
        root, preset="openvla-oft-tiny", apply_lora_adapter=True
    ).model
    torch.testing.assert_close(loaded.get_parameter(f"{target}.weight"), expected)
    assert not torch.allclose(expected, tiny.get_parameter(f"{target}.weight"))


def test_from_original_reports_an_unreachable_hub_id() -> None:
    with pytest.raises(BackboneError, match="could not be downloaded"):
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
