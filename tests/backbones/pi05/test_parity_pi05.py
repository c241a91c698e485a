"""Pi0.5 against the upstream code itself: fixtures written by ``tools/pi05/make_upstream_fixtures.py``
with PyPI ``lerobot==0.4.4`` and with openpi's PyTorch model (commit 15a9616a), see the ``PROVENANCE``
files in ``tests/fixtures/upstream/pi05/{lerobot,openpi}/``, loaded through ``Pi05.from_original``
and compared in fp32. No upstream code runs here.

Tolerance: ``ATOL`` = 1e-5 absolute on every float output (the largest difference measured is 5.7e-6,
on squared loss elements of size ~10; most outputs agree to 1e-6 or exactly); token ids are compared
exactly.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from capvector.backbones import BackboneError, OutputRequest
from capvector.backbones.pi05 import IMAGE_MASK, Pi05, flow_matching_path, resize_with_pad
from capvector.data import keys
from capvector.data.statistics import QUANTILES, Normalizer
from conftest import UPSTREAM_FIXTURES

FIXTURE = UPSTREAM_FIXTURES / "pi05" / "lerobot"
ATOL = 1e-5
# The toy sizes the generating script patched into LeRobot (its config.json still names the
# full-size variants gemma_2b / gemma_300m, so sizes come in as overrides of pi05-tiny), and
# LeRobot 0.4.4's padding of the state to max_state_dim = 32 before it goes into the prompt.
UPSTREAM_SIZES = {
    "vision": {"hidden_size": 32, "intermediate_size": 64, "num_layers": 2, "num_heads": 4, "patch_size": 8},
    "vlm": {"hidden_size": 64, "intermediate_size": 128, "num_layers": 2, "num_heads": 8, "num_kv_heads": 1, "head_dim": 16},
    "expert": {"hidden_size": 32, "intermediate_size": 64, "num_layers": 2, "num_heads": 8, "num_kv_heads": 1, "head_dim": 16},
    "vocab_size": 272,
    "prompt_state_dim": 32,
}  # fmt: skip


def load(folder: Path = FIXTURE, **overrides: object):
    return Pi05.from_original(
        folder,
        preset="pi05-tiny",
        overrides={**UPSTREAM_SIZES, **overrides},
        tokenizer=FIXTURE / "tokenizer",
    )


@pytest.fixture(scope="module")
def imported():
    return load()


@pytest.fixture(scope="module")
def model(imported) -> Pi05:
    return imported.model.eval()


@pytest.fixture(scope="module")
def ref() -> dict:
    refs: dict = load_file(str(FIXTURE / "reference.safetensors"))
    with safe_open(str(FIXTURE / "reference.safetensors"), "pt") as f:
        refs["tasks"] = json.loads(f.metadata()["tasks"])
    return refs


@pytest.fixture(scope="module")
def normalizer(imported) -> Normalizer:
    (entry,) = imported.statistics.values()
    return Normalizer(entry)


@pytest.fixture(scope="module")
def batch(ref, normalizer) -> dict:
    """The raw reference batch through capvector's own normalisation (not LeRobot's numbers)."""
    state = normalizer.normalize("proprio", ref["input.state"].numpy())
    return {
        keys.IMAGES: torch.stack([ref["input.image.0"], ref["input.image.1"]], dim=1),
        keys.PROPRIO: torch.from_numpy(state),
        keys.INSTRUCTION: ref["tasks"],
    }


def assert_close(ours: torch.Tensor, theirs: torch.Tensor) -> None:
    torch.testing.assert_close(ours.detach().float(), theirs.float(), atol=ATOL, rtol=0)


def test_import_reads_the_lerobot_config(imported) -> None:
    c = imported.model.config
    assert (c.chunk_size, c.action_dim, c.proprio_dim, c.num_images) == (5, 7, 8, 2)
    assert (c.image_size, c.num_inference_steps, c.max_action_dim) == (32, 4, 32)
    assert c.tokenizer_max_length == 200
    assert c.loss_include_padded_dims is False  # PI05Policy.forward averages real dims only
    assert imported.upstream_config["config.json"]["type"] == "pi05"
    assert "policy_preprocessor.json" in imported.upstream_config


def test_statistics_are_converted_and_normalise_as_lerobot(imported, ref, normalizer) -> None:
    (name,) = imported.statistics
    entry = imported.statistics[name]
    assert entry["normalization"] == QUANTILES and all(entry["action"]["mask"])
    state = normalizer.normalize("proprio", ref["input.state"].numpy())
    actions = normalizer.normalize("action", ref["input.actions"].numpy())
    assert_close(torch.from_numpy(state), ref["normalized.state"])
    assert_close(torch.from_numpy(actions), ref["normalized.actions"])
    # Neither upstream clips: the fixture holds values beyond [-1, 1] on purpose.
    assert state.min() < -1 and state.max() > 1 and np.abs(actions).max() > 1
    raw = normalizer.unnormalize("action", ref["sample.actions"][..., :7].numpy())
    assert_close(torch.from_numpy(raw), ref["sample.actions_raw"])


def test_prompt_tokens_equal_lerobot(model, batch, ref) -> None:
    ids, valid = model.tokenize(batch[keys.INSTRUCTION], batch[keys.PROPRIO], torch.device("cpu"))
    for row in range(2):
        theirs = ref["tokens"][row][ref["token_mask"][row]]
        assert ids[row][valid[row]].tolist() == theirs.tolist()
    # Row 0's first state value normalises below -1: bin "-1" in the prompt, as upstream.
    text = model.tokenizer.decode(ids[0][valid[0]].tolist())
    assert "State: -1 " in text


def test_vision_features_equal_lerobot(model, batch, ref) -> None:
    images = batch[keys.IMAGES].flatten(0, 1)
    pixels = resize_with_pad(images, model.config.image_size) * 2 - 1
    siglip = model.vision_tower(pixels).reshape(2, 2, -1, 32)
    assert_close(siglip, ref["siglip"])
    features, _ = model.embed_images(batch)
    assert_close(features.reshape(2, 2, -1, 64), ref["image_features"])


def valid_positions(model: Pi05, batch: dict) -> torch.Tensor:
    return model.embed_prefix(batch).valid


def test_prefix_hidden_states_equal_lerobot(model, batch, ref) -> None:
    out = model(batch, OutputRequest(hidden_layers=(0, 1, 2)))
    valid = out.attention_mask
    length = valid.shape[1]
    assert ref["token_mask"][:, : length - 32].equal(valid[:, 32:])  # LeRobot pads to 200
    for layer in (0, 1, 2):
        theirs = ref[f"hidden.{layer}"][:, :length]
        assert_close(out.hidden_states[layer][valid], theirs[valid])


def test_sampled_actions_equal_lerobot(model, batch, ref) -> None:
    cache, _ = model.prefix_cache(model.embed_prefix(batch))
    with torch.no_grad():
        actions = model.integrate(cache, ref["sample.noise"])
    assert_close(actions, ref["sample.actions"])  # all 32 padded dims
    assert_close(model.predict_action(batch, ref["sample.noise"]), ref["sample.actions"][..., :7])


def test_training_loss_equals_lerobot(model, batch, ref, normalizer) -> None:
    actions = normalizer.normalize("action", ref["input.actions"].numpy())
    target = model.pad_actions(torch.from_numpy(actions))
    x_t, u = flow_matching_path(target, ref["loss.noise"], ref["loss.time"])
    with torch.no_grad():
        velocity, _ = model.velocity(model.embed_prefix(batch), x_t, ref["loss.time"])
        assert_close((velocity - u) ** 2, ref["loss.elements"])
        assert_close(model.flow_loss(velocity, u), ref["loss.lerobot"])
        model.config.loss_include_padded_dims = True  # openpi's reduction
        try:
            assert_close(model.flow_loss(velocity, u), ref["loss.all_dims"])
        finally:
            model.config.loss_include_padded_dims = False


def copy_fixture(tmp_path: Path, **config: object) -> Path:
    folder = tmp_path / "policy"
    shutil.copytree(FIXTURE, folder, ignore=shutil.ignore_patterns("reference.safetensors"))
    upstream = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**upstream, **config}))
    return folder


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("empty_cameras", 1, r"empty_cameras=1 is not supported"),
        ("use_relative_actions", True, r"use_relative_actions=True is not supported"),
        ("normalization_mapping", {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"},
         r"normalization_mapping=.*MEAN_STD.* is not supported"),
        ("some_new_field", 3, r"config field\(s\) \['some_new_field'\]"),
        ("image_resolution", [32, 48], r"image_resolution 32x48 is not square"),
    ],
)  # fmt: skip
def test_unsupported_config_fields_are_named(
    tmp_path: Path, field: str, value: object, message: str
) -> None:
    with pytest.raises(BackboneError, match=message):
        load(copy_fixture(tmp_path, **{field: value}))


def test_overrides_win_over_the_checkpoint_config(tmp_path: Path) -> None:
    model = load(FIXTURE, chunk_size=3).model
    assert model.config.chunk_size == 3 and model.config.num_inference_steps == 4


# -- openpi's PyTorch model ------------------------------------------------------------------------

OPENPI = FIXTURE.parent / "openpi"
OPENPI_SIZES = {
    **{k: v for k, v in UPSTREAM_SIZES.items() if k != "prompt_state_dim"},
    "vision": {**UPSTREAM_SIZES["vision"], "patch_size": 28},
}


@pytest.fixture(scope="module")
def openpi_imported():
    return Pi05.from_original(
        OPENPI, preset="pi05-tiny", overrides=OPENPI_SIZES, tokenizer=FIXTURE / "tokenizer"
    )


@pytest.fixture(scope="module")
def openpi_ref() -> dict:
    refs: dict = load_file(str(OPENPI / "reference.safetensors"))
    with safe_open(str(OPENPI / "reference.safetensors"), "pt") as f:
        refs["tasks"] = json.loads(f.metadata()["tasks"])
    return refs


@pytest.fixture(scope="module")
def openpi_batch(openpi_imported, openpi_ref) -> dict:
    (entry,) = openpi_imported.statistics.values()
    state = Normalizer(entry).normalize("proprio", openpi_ref["input.state"].numpy())
    return {
        keys.IMAGES: torch.stack([openpi_ref[f"input.image.{i}"] for i in range(3)], dim=1),
        IMAGE_MASK: openpi_ref["input.image_mask"],
        keys.PROPRIO: torch.from_numpy(state),
        keys.INSTRUCTION: openpi_ref["tasks"],
    }


def test_openpi_import_reads_config_and_norm_stats(openpi_imported, openpi_ref) -> None:
    c = openpi_imported.model.config
    assert (c.chunk_size, c.max_action_dim, c.action_dim, c.proprio_dim) == (5, 32, 7, 8)
    assert (c.num_images, c.image_size, c.loss_include_padded_dims) == (3, 224, True)
    assert list(openpi_imported.statistics) == ["toy_robot"]  # the asset id
    normalizer = Normalizer(openpi_imported.statistics["toy_robot"])
    assert normalizer.normalization == QUANTILES
    # openpi adds 1e-6 to every q99 - q01 where LeRobot (and we) add nothing: ~1e-6 apart.
    state = normalizer.normalize("proprio", openpi_ref["input.state"].numpy())
    actions = normalizer.normalize("action", openpi_ref["input.actions"].numpy())
    assert_close(torch.from_numpy(state), openpi_ref["normalized.state"])
    assert_close(torch.from_numpy(actions), openpi_ref["normalized.actions"])


def test_openpi_outputs_equal_ours(openpi_imported, openpi_batch, openpi_ref) -> None:
    model = openpi_imported.model.eval()
    batch, ref = openpi_batch, openpi_ref
    ids, valid = model.tokenize(batch[keys.INSTRUCTION], batch[keys.PROPRIO], torch.device("cpu"))
    for row in range(2):  # the state unpadded in the prompt, as openpi's TokenizePrompt
        assert ids[row][valid[row]].tolist() == ref["tokens"][row][ref["token_mask"][row]].tolist()
    features, _ = model.embed_images(batch)
    assert_close(features.reshape(2, 3, -1, 64), ref["image_features"])
    out = model(batch, OutputRequest(hidden_layers=(0, 1, 2)))
    length = out.attention_mask.shape[1]
    for layer in (0, 1, 2):
        ours = out.hidden_states[layer][..., :8][out.attention_mask]
        assert_close(ours, ref[f"hidden.{layer}"][:, :length][out.attention_mask])
    assert_close(model.predict_action(batch, ref["sample.noise"]), ref["sample.actions"][..., :7])
    cache, _ = model.prefix_cache(model.embed_prefix(batch))
    with torch.no_grad():
        assert_close(model.integrate(cache, ref["sample.noise"]), ref["sample.actions"])


def test_openpi_training_loss_equals_ours(openpi_imported, openpi_batch, openpi_ref) -> None:
    model, ref = openpi_imported.model.eval(), openpi_ref
    target = model.pad_actions(ref["normalized.actions"])
    x_t, u = flow_matching_path(target, ref["loss.noise"], ref["loss.time"])
    with torch.no_grad():
        velocity, _ = model.velocity(model.embed_prefix(openpi_batch), x_t, ref["loss.time"])
    assert_close((velocity - u) ** 2, ref["loss.elements"])
    assert_close(model.flow_loss(velocity, u), ref["loss.openpi"])  # all 32 dims


def test_openpi_unknown_config_field_is_named(tmp_path: Path) -> None:
    folder = tmp_path / "openpi"
    shutil.copytree(OPENPI, folder, ignore=shutil.ignore_patterns("reference.safetensors"))
    upstream = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**upstream, "discrete_state_input": False}))
    with pytest.raises(BackboneError, match=r"openpi config field\(s\) \['discrete_state_input'\]"):
        Pi05.from_original(folder, preset="pi05-tiny", overrides=OPENPI_SIZES)


def test_a_missing_tensor_is_named_by_its_upstream_key(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    folder = shutil.copytree(FIXTURE, tmp_path / "lerobot")
    state = load_file(str(folder / "model.safetensors"))
    key = "model.paligemma_with_expert.gemma_expert.model.layers.1.mlp.up_proj.weight"
    del state[key]
    save_file(state, str(folder / "model.safetensors"))
    with pytest.raises(
        BackboneError, match=r"lacks 1 tensor.*`" + key.removeprefix("model.").replace(".", r"\.")
    ):
        load(folder)


def test_other_policies_and_extra_tensors_are_refused(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    folder = shutil.copytree(FIXTURE, tmp_path / "pi0")
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "type": "pi0"}))
    with pytest.raises(BackboneError, match="'pi0' policy, not pi05"):
        load(folder)
    folder = shutil.copytree(FIXTURE, tmp_path / "extra")
    state = load_file(str(folder / "model.safetensors"))
    state["model.state_proj.weight"] = torch.zeros(32, 32)  # a Pi0 projection
    save_file(state, str(folder / "model.safetensors"))
    with pytest.raises(BackboneError, match=r"1 unexpected key.*`state_proj\.weight`"):
        load(folder)
