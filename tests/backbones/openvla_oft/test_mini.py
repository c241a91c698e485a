"""``openvla-oft-mini``: pretrained weights from the installed packages, checked against
transformers' own Gemma-3 (loaded from the same GGUF) and timm's own EfficientNet-Lite0, trained
with LoRA, and saved without its frozen base.

The model is built once per module (the dequantised Gemma weights are cached under
``$CAPVECTOR_CACHE``, built on first use: about a minute on an idle machine). Gemma's referee loads
a GGUF cut to the preset's first 6 layers, written here from the packaged file's raw blocks, so
transformers dequantises 6 layers and not 18.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from capvector.backbones import OutputRequest, build_backbone, from_pretrained
from capvector.backbones.packaged import (
    EFFICIENTNET_LITE0,
    GEMMA3_270M,
    PackagedFile,
    PackagedWeightsError,
    verified_files,
)
from capvector.data import keys
from capvector.training.lora import LoraSettings, set_trainable

PRESET = "openvla-oft-mini"
STATE_BUDGET = 25 * 2**20
"""Bytes a fit may keep per run: trained weights plus AdamW's two moments (issue 59)."""

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_backbone(PRESET).eval()


def batch(model, actions: bool = True) -> dict:
    c = model.config
    g = torch.Generator().manual_seed(0)
    out = {
        keys.IMAGES: torch.rand(2, c.num_images, 3, c.image_size, c.image_size, generator=g),
        keys.INSTRUCTION: ["put the bowl on the plate", "open the top drawer of the cabinet"],
        keys.PROPRIO: torch.rand(2, c.proprio_dim, generator=g) * 2 - 1,
    }
    if actions:
        out[keys.ACTIONS] = torch.rand(2, c.chunk_size, c.action_dim, generator=g) * 2 - 1
    return out


def test_a_missing_weight_package_is_a_one_line_error_naming_it() -> None:
    source = dataclasses.replace(
        EFFICIENTNET_LITE0, files=(PackagedFile("no-such-weights", "1.0.0", "w.pth"),)
    )
    with pytest.raises(PackagedWeightsError, match=r"no-such-weights==1\.0\.0 is not installed"):
        verified_files(source)


def test_files_that_do_not_hash_as_pinned_are_refused() -> None:
    source = dataclasses.replace(EFFICIENTNET_LITE0, sha256="0" * 64)
    with pytest.raises(PackagedWeightsError, match="is not the pinned 0000"):
        verified_files(source)


def cut_gguf(source: Path, out: Path, layers: int) -> Path:
    """The GGUF with only its first ``layers`` blocks (raw quantised bytes copied, no tokenizer
    arrays: the model loader does not need them, and parsing 262 k strings is slow)."""
    from gguf import GGUFReader, GGUFValueType, GGUFWriter

    reader = GGUFReader(str(source))
    writer = GGUFWriter(str(out), arch="gemma3")
    for name, f in reader.fields.items():
        if name.startswith(("GGUF.", "tokenizer.")) or name == "general.architecture":
            continue
        value = layers if name == "gemma3.block_count" else f.contents()
        if f.types[0] == GGUFValueType.ARRAY:
            writer.add_array(name, value)
        else:
            writer.add_key_value(name, value, f.types[0])
    writer.add_uint32("gemma3.vocab_size", len(reader.fields["tokenizer.ggml.tokens"].data))
    for t in reader.tensors:
        block = t.name.split(".")
        if block[0] != "blk" or int(block[1]) < layers:
            writer.add_tensor(t.name, np.asarray(t.data), raw_dtype=t.tensor_type)
    writer.write_header_to_file()
    writer.write_kv_data_to_file()
    writer.write_tensors_to_file()
    writer.close()
    return out


def test_gemma_layers_match_transformers_loading_the_same_gguf(model, tmp_path: Path) -> None:
    """Referee: transformers' ``Gemma3ForCausalLM`` from the packaged GGUF (``gguf_file=``, its
    own dequantisation and name map) gives our cut model's hidden state at layer k and logits."""
    from transformers import Gemma3ForCausalLM

    joined = tmp_path / "gemma.gguf"
    with joined.open("wb") as out:
        for part in verified_files(GEMMA3_270M):
            out.write(part.read_bytes())
    k = model.config.llm.num_layers
    cut = cut_gguf(joined, tmp_path / "cut.gguf", k)
    joined.unlink()
    referee = Gemma3ForCausalLM.from_pretrained(
        str(tmp_path), gguf_file=cut.name, dtype=torch.float32
    ).eval()
    assert referee.config.num_hidden_layers == k
    ids = model.tokenizer("The robot picks up the red bowl", return_tensors="pt")["input_ids"]
    assert ids[0, 0] == 2  # Gemma's <bos>

    def layer_k(lm: torch.nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
        store = {}
        hook = lm.model.layers[k - 1].register_forward_hook(
            lambda _m, _a, out: store.setdefault("h", out[0] if isinstance(out, tuple) else out)
        )
        with torch.no_grad():
            logits = lm(input_ids=ids).logits
        hook.remove()
        return store["h"], logits

    ours, our_logits = layer_k(model.language_model)
    theirs, their_logits = layer_k(referee)
    torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(our_logits, their_logits, rtol=1e-4, atol=1e-3)


def test_vision_tower_matches_timm_with_the_packaged_weights(model) -> None:
    """Referee: timm's ``tf_efficientnet_lite0`` with the package's tensors (by order) on [-1, 1]
    inputs: the same 1280 x H/32 x W/32 features as our tower on [0, 1] images."""
    import timm

    (path,) = verified_files(EFFICIENTNET_LITE0)
    state = torch.load(path, map_location="cpu", weights_only=True)
    referee = timm.create_model("tf_efficientnet_lite0", pretrained=False).eval()
    referee.load_state_dict(dict(zip(referee.state_dict(), state.values(), strict=True)))
    images = torch.rand(2, 3, 128, 128, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        expected = referee.forward_features(images * 2 - 1)
        ours = model.vision_backbone(images)
        # ImageNet head on our features: the packaged classifier reads them as timm does.
        torch.testing.assert_close(referee.forward_head(expected), referee(images * 2 - 1))
    assert expected.shape == (2, 1280, 4, 4)
    torch.testing.assert_close(ours, expected.flatten(2).transpose(1, 2), rtol=0, atol=0)


def test_forward_returns_the_contract_outputs(model) -> None:
    out = model(batch(model), OutputRequest(hidden_layers=(0, model.alignment_layer, 6)))
    assert torch.isfinite(out.loss)
    assert out.actions.shape == (2, 8, 7)
    assert out.visual_grid == (4, 4) and out.visual_token_mask.sum(1).tolist() == [32, 32]
    assert set(out.hidden_states) == {0, model.alignment_layer, 6}


def test_reasoning_over_the_answers_tokens_is_those_columns_of_gemmas_head(model) -> None:
    """The mini study's aux-SFT arm (vocabulary="answers"): the same hidden states projected on
    the answer tokens' rows of Gemma's tied 262 k-token head alone."""
    prompts = ["Where is the bowl?", "What is the robot doing?"]
    answers = ["The black bowl is at x=-0.08, y=0.21.", "The robot is lifting the bowl."]
    vocabulary = torch.tensor(sorted({i for a in answers for i in model.answer_label_ids(a)}))
    with torch.no_grad():
        full, targets = model.answer_logits(batch(model, actions=False), prompts, answers)
        some, indices = model.answer_logits(
            batch(model, actions=False), prompts, answers, vocabulary
        )
    assert full.shape[1] == 262_144 and some.shape == (len(targets), len(vocabulary))
    torch.testing.assert_close(some, full[:, vocabulary])
    assert torch.equal(vocabulary[indices], targets)


def test_lora_trains_only_lora_projector_and_heads_within_the_state_budget() -> None:
    torch.manual_seed(0)
    model = build_backbone(PRESET)
    set_trainable(model, LoraSettings(r=8, alpha=16))
    trainable = {n: p for n, p in model.named_parameters() if p.requires_grad}
    outside = [
        n
        for n in trainable
        if ".lora_" not in n and not n.startswith(("projector.", "action_head.", "proprio_"))
    ]
    assert not outside, outside[:5]
    model(batch(model)).loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in trainable.values())
    # What a checkpoint holds: the state dict (the packaged base left out) and AdamW's moments.
    state = {k: v.clone() for k, v in model.state_dict().items()}
    assert not [k for k in state if "embed_tokens" in k or k.startswith("vision_backbone.")]
    weights = sum(t.numel() * t.element_size() for t in state.values())
    moments = 2 * sum(p.numel() * 4 for p in trainable.values())
    assert weights + moments <= STATE_BUDGET, (weights, moments)
    # Strict loading of that state (Lightning's resume) keeps the packaged base and restores the rest.
    with torch.no_grad():
        expected = model(batch(model)).loss
        for p in trainable.values():
            p.zero_()
        assert not torch.equal(model(batch(model)).loss, expected)
    model.load_state_dict(state, strict=True)
    with torch.no_grad():
        torch.testing.assert_close(model(batch(model)).loss, expected, rtol=0, atol=0)


def test_export_holds_only_what_differs_from_the_packages_and_loads_back(
    model, tmp_path: Path
) -> None:
    with torch.no_grad():
        model.action_head.model.fc2.bias.add_(0.5)  # a trained head
    folder = model.save_pretrained(tmp_path / "export")
    assert (folder / "model.safetensors").stat().st_size <= STATE_BUDGET
    card = (folder / "README.md").read_text()
    for fact in (GEMMA3_270M.sha256, EFFICIENTNET_LITE0.sha256, "dequantised", "Gemma Terms"):
        assert fact in card, fact
    loaded = from_pretrained(folder).eval()
    observation = batch(model, actions=False)
    torch.testing.assert_close(
        loaded.predict_action(observation), model.predict_action(observation), rtol=0, atol=0
    )


def test_backbone_info_names_the_weights_and_plans_memory_with_gemmas_tokenizer(capsys) -> None:
    from capvector.backbones.packaged import gemma3_270m_tokenizer_folder
    from capvector.profiling.memory import stand_in_tokenizer
    from capvector.workflows.backbone_info import backbone_info_main

    # The planner's traced step tokenizes its prompt with the packages' own Gemma tokenizer (a
    # meta build reads no packages itself), not a byte-level stand-in.
    assert stand_in_tokenizer(PRESET) == {"tokenizer": str(gemma3_270m_tokenizer_folder())}
    assert backbone_info_main([PRESET, "--memory", "--batch", "1"]) == 0
    out = capsys.readouterr().out
    for source in (GEMMA3_270M, EFFICIENTNET_LITE0):
        assert f"pretrained weights: {source.name}" in out
        assert source.sha256 in out
    assert float(re.search(r"total, checkpointed\s+([\d.]+) GiB", out).group(1)) > 0
