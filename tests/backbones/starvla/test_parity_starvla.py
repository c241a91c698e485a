"""Parity with StarVLA itself: runs written by StarVLA's own code, loaded through
``StarVLA.from_original``, must compute what StarVLA computed.

The fixtures under ``tests/fixtures/upstream/starvla/`` were produced by
``tools/starvla/make_upstream_fixtures.py`` in a scratch environment with StarVLA's pinned stack
(see PROVENANCE there); no StarVLA code is needed here. Each ``<variant>/run`` is a run folder as
StarVLA's trainer writes it; ``reference.safetensors`` holds the fixed batch and StarVLA's outputs.
All comparisons are in fp32 with ``TOL`` absolute tolerance.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from capvector.backbones.base import BackboneError
from capvector.backbones.starvla import StarVLA
from capvector.data import keys
from conftest import UPSTREAM_FIXTURES

FIXTURES = UPSTREAM_FIXTURES / "starvla"
QWEN = {"qwen2.5-vl": "Qwen2.5-VL-tiny", "qwen3-vl": "Qwen3-VL-tiny"}
INSTRUCTIONS = ["pick up the red block", "open the top drawer please"]  # as in the tool
TOL = 1e-5
VARIANTS = sorted(p.name for p in FIXTURES.glob("*") if (p / "reference.safetensors").is_file())
FLOW_VARIANTS = [v for v in VARIANTS if not v.endswith("-oft")]  # the OFT (L1) head draws nothing


def qwen_folder(variant: str) -> Path:
    version = "qwen3-vl" if variant.startswith("qwen3-vl") else "qwen2.5-vl"
    return FIXTURES / "qwen" / version / QWEN[version]


def load(variant: str, **overrides: object) -> tuple[StarVLA, dict, dict[str, torch.Tensor]]:
    imported = StarVLA.from_original(
        FIXTURES / variant / "run", overrides=overrides, qwen_folder=qwen_folder(variant)
    )
    ref = load_file(str(FIXTURES / variant / "reference.safetensors"))
    return imported.model.eval(), imported.statistics, ref


def batch_of(ref: dict[str, torch.Tensor]) -> dict:
    images = ref["images"].permute(0, 1, 4, 2, 3).float() / 255  # (B, N, 3, H, W) in [0, 1]
    batch = {keys.IMAGES: images, keys.INSTRUCTION: INSTRUCTIONS}
    if "states" in ref:
        batch[keys.PROPRIO] = ref["states"]
    return batch


def max_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    return (a.double() - b.double()).abs().max().item()


@pytest.fixture(scope="module", params=VARIANTS)
def variant(request: pytest.FixtureRequest) -> str:
    return request.param


def test_fixtures_exist() -> None:
    assert "qwen2.5-vl-oft" in VARIANTS, f"no StarVLA fixtures under {FIXTURES}"


def test_tokens_vision_and_hidden_states_match(variant: str) -> None:
    model, _, ref = load(variant)
    batch = batch_of(ref)
    layers = sorted(int(k.split(".")[1]) for k in ref if k.startswith("hidden_states."))
    with torch.no_grad():
        enc = model.encode(batch, [0], all_layers=True)
        pixel_values, grid = model.pixel_values(batch[keys.IMAGES])
        vision = model.vlm.model.get_image_features(pixel_values, grid)
    # The prompt, the chat template and the query tokens tokenise to StarVLA's ids exactly.
    assert torch.equal(enc.input_ids, ref["input_ids"])
    assert torch.equal(grid, ref["image_grid_thw"])
    assert torch.equal(enc.head_input.mask, ref["attention_mask"].bool())
    torch.testing.assert_close(
        pixel_values.double().sum(), ref["pixel_values_sum"][0], atol=1e-2, rtol=1e-5
    )
    vision = getattr(vision, "pooler_output", vision)
    vision = torch.cat(list(vision))  # per-image embeds (transformers 5: pooler_output)
    assert max_diff(vision, ref["vision_features"]) < TOL
    mask = enc.head_input.mask
    # HF's hidden_states as StarVLA reads them: the embeddings, then what its heads consume.
    ours = (enc.requested[0], *enc.head_input.layers)
    assert torch.equal(enc.head_input.layers[-1], enc.head_input.last_hidden)
    for layer in layers:
        assert max_diff(ours[layer][mask], ref[f"hidden_states.{layer}"][mask]) < TOL, layer


def test_loss_and_actions_match(variant: str) -> None:
    model, _, ref = load(variant)
    batch = batch_of(ref)
    head = model.action_head
    state = batch.get(keys.PROPRIO) if model.config.state_mode == "head" else None
    with torch.no_grad():
        cond = model.encode(batch, all_layers=head.uses_all_layers).head_input
        if "loss_noise" in ref:
            loss = head.flow_loss(cond, ref["actions"], state, ref["loss_noise"], ref["loss_time"])
            actions = head.sample(cond, state, noise=ref["predict_noise"])
        else:
            loss, actions = head.loss_and_actions(cond, ref["actions"], state)
    assert abs(loss.item() - ref["loss"].item()) < TOL
    assert max_diff(actions, ref["actions_pred"]) < TOL


def test_statistics_come_back_in_capvector_schema(variant: str) -> None:
    _, stats, ref = load(variant)
    (entry,) = stats.values()
    assert entry["action"]["mask"] == [True] * 6 + [False]
    assert len(entry["action"]["q99"]) == 7
    assert bool(entry["proprio"]) == ("states" in ref)


def test_run_config_decides_the_architecture() -> None:
    model, _, _ = load("qwen2.5-vl-oft")
    assert (model.config.chunk_size, model.config.action_dim, model.config.image_size) == (4, 7, 56)
    assert model.action_head.query_token == "\U0001f50d"  # StarVLA's own query, one Qwen token
    # Qwen3-VL's processor min_pixels upsamples the 56-px cameras (to 96 px here, as 224 -> 256
    # for Qwen3-VL-4B): the resolution comes from the Qwen folder's preprocessor_config.json.
    qwen3, _, ref = load("qwen3-vl-oft")
    assert qwen3.config.image_size == 96 and ref["images"].shape[-2] == 56
    # A nested override changes only the field it names.
    model, _, _ = load("qwen2.5-vl-oft", head_args={"bidirectional_queries": True})
    assert model.action_head.query_token == "\U0001f50d"
    assert model.action_head.bidirectional_queries


@pytest.mark.parametrize(
    ("variant", "path", "value", "message"),
    [
        ("qwen2.5-vl-oft", "framework.action_model.use_film", True, r"action_model\.use_film"),
        ("qwen2.5-vl-oft", "framework.reduce_in_full_precision", True, "reduce_in_full"),
        ("qwen2.5-vl-oft", "framework.name", "QwenFast", "framework.name='QwenFast'"),
        (
            "qwen2.5-vl-gr00t",
            "framework.action_model.diffusion_model_cfg.positional_embeddings",
            "sinusoidal",
            "positional_embeddings='sinusoidal'",
        ),
        (
            "qwen2.5-vl-gr00t",
            "framework.action_model.diffusion_model_cfg.norm_type",
            "layer_norm",
            "norm_type='layer_norm'",
        ),
        ("qwen2.5-vl-gr00t", "framework.action_model.add_pos_embed", False, "add_pos_embed"),
        (
            "qwen2.5-vl-pi-v3",
            "framework.action_model.past_action_window_size",
            2,
            "past_action_window_size=2",
        ),
    ],
)
def test_unsupported_config_field_is_named(
    tmp_path: Path, variant: str, path: str, value: object, message: str
) -> None:
    import shutil

    import yaml

    run = tmp_path / "run"
    shutil.copytree(FIXTURES / variant / "run", run)
    config = yaml.safe_load((run / "config.yaml").read_text())
    node = config
    *parents, leaf = path.split(".")
    for key in parents:
        node = node[key]
    node[leaf] = value
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    with pytest.raises(BackboneError, match=message):
        StarVLA.from_original(run, qwen_folder=qwen_folder(variant))


def test_run_values_reach_the_model() -> None:
    """Fields the run's config.yaml decides, per framework (not the preset's defaults)."""
    gr00t, _, _ = load("qwen2.5-vl-gr00t-state")
    args = gr00t.config.head_args
    assert (gr00t.config.state_mode, gr00t.config.proprio_dim) == ("head", 7)
    assert (args["width"], args["num_heads"], args["num_layers"]) == (16, 2, 2)
    assert args["interleave_self_attention"] and args["repeated_diffusion_steps"] == 3
    # Another head's tiny preset as the base: its head_args do not leak into the run's head.
    other = StarVLA.from_original(
        FIXTURES / "qwen2.5-vl-pi-v3" / "run",
        preset="starvla-tiny-gr00t",
        qwen_folder=qwen_folder("qwen2.5-vl-pi-v3"),
    ).model
    assert other.config.head == "layerwise" and "num_layers" not in other.config.head_args
    plain, _, _ = load("qwen2.5-vl-gr00t")
    assert plain.config.state_mode == "none" and plain.action_head.state_encoder is None
    pi, _, _ = load("qwen2.5-vl-pi-v3-interleave")
    args = pi.config.head_args
    # QwenPI_v3: the state goes into the prompt, its repeats come from the trainer section, its
    # MLPs are 1024 wide whatever action_model.hidden_size says.
    assert pi.config.state_mode == "prompt" and args["repeated_diffusion_steps"] == 3
    # The fixed states reach below -1 and above 1, so the equal token ids of the PI_v3 variants
    # also check the state bins at both ends (-1 and 255, as np.digitize).
    states = load_file(str(FIXTURES / "qwen2.5-vl-pi-v3" / "reference.safetensors"))["states"]
    assert states.min() < -1 and states.max() > 1
    bins = pi.state_bins(states[0])
    assert bins.min() >= -1 and bins.max() <= 255 and (bins == -1).any() == (states[0] < -1).any()
    assert args["interleave_self_attention"] and args["hidden_size"] == 1024


def test_missing_and_unknown_keys_are_named(tmp_path: Path) -> None:
    import shutil

    run = tmp_path / "run"
    shutil.copytree(FIXTURES / "qwen2.5-vl-oft" / "run", run)
    ckpt = next((run / "checkpoints").iterdir())
    state = torch.load(ckpt, weights_only=True)
    del state["action_model.model.fc2.weight"]
    state["action_model.vl_self_attention.weight"] = torch.zeros(1)
    torch.save(state, ckpt)
    with pytest.raises(BackboneError, match=r"1 missing key.*fc2\.weight.*1 unexpected"):
        StarVLA.from_original(run, qwen_folder=qwen_folder("qwen2.5-vl-oft"))


@pytest.mark.parametrize(
    ("variant", "wrong"),
    [
        # Before the fix: an interleaved PI_v3 run loaded and then always cross-attended.
        ("qwen2.5-vl-pi-v3-interleave", {"head_args": {"interleave_self_attention": False}}),
        # Before the fix: a GR00T run trained with state lost its state token.
        ("qwen2.5-vl-gr00t-state", {"state_mode": "none", "proprio_dim": 0}),
    ],
)
def test_the_fixtures_catch_the_known_differences(variant: str, wrong: dict) -> None:
    ref = load_file(str(FIXTURES / variant / "reference.safetensors"))
    run = FIXTURES / variant / "run"
    # Loading the run as the old importer did: the state encoder's keys are then unexpected.
    if "state_mode" in wrong:
        with pytest.raises(BackboneError, match="unexpected key.*state_encoder"):
            StarVLA.from_original(run, overrides=wrong, qwen_folder=qwen_folder(variant))
        return
    model = StarVLA.from_original(run, overrides=wrong, qwen_folder=qwen_folder(variant)).model
    model.eval()
    with torch.no_grad():
        cond = model.encode(batch_of(ref), all_layers=True).head_input
        actions = model.action_head.sample(cond, None, noise=ref["predict_noise"])
    assert max_diff(actions, ref["actions_pred"]) > 1e-3


def test_query_token_choice_keeps_upstream_tokenisation() -> None:
    """StarVLA's emoji query sits inside one Qwen pre-token (``>🔍🔍🔍🔍<``); a special token splits
    the text around it, and ``<action>`` after the queries is then pre-tokenised as ``<action``,
    which Qwen's BPE merges as ``<a`` + ...: other ids than upstream's. So the importer keeps the
    emoji (an ordinary single token of Qwen's vocabulary), and the ids equal StarVLA's."""
    variant = "qwen2.5-vl-oft"
    ref = load_file(str(FIXTURES / variant / "reference.safetensors"))
    special = {"head_args": {"query_token": "<|action_query|>"}}
    model = StarVLA.from_original(
        FIXTURES / variant / "run", overrides=special, qwen_folder=qwen_folder(variant)
    ).model
    ids, _ = model.tokenize([model.prompt_text(t) for t in INSTRUCTIONS], 2, torch.device("cpu"))
    tok = model.tokenizer
    emoji_ids = set(tok.encode("\U0001f50d", add_special_tokens=False))
    rest = [i for i in ids[0].tolist() if i not in (model._token_ids.query, tok.pad_token_id)]
    upstream = [i for i in ref["input_ids"][0].tolist() if i not in emoji_ids | {tok.pad_token_id}]
    assert rest != upstream
    assert "<a" in tok.convert_ids_to_tokens(rest)
    assert "<a" not in tok.convert_ids_to_tokens(upstream[-12:])


@pytest.mark.parametrize("flow_variant", FLOW_VARIANTS)
def test_flow_draws_from_the_global_rng_match_upstream(flow_variant: str) -> None:
    """Without noise seeds, the flow heads draw noise then time from the global RNG in StarVLA's
    order and with its formulas (GR00T: u clipped at s; layerwise: not), so the same torch seed
    gives StarVLA's loss and actions: the tool seeded 2 before forward() and 3 before
    predict_action()."""
    model, _, ref = load(flow_variant)
    assert "loss_noise" in ref
    batch, head = batch_of(ref), model.action_head
    state = batch.get(keys.PROPRIO) if model.config.state_mode == "head" else None
    with torch.no_grad():
        cond = model.encode(batch, all_layers=head.uses_all_layers).head_input
        torch.manual_seed(2)
        loss = head.loss(cond, ref["actions"], state)
        torch.manual_seed(3)
        actions = head.sample(cond, state)
    assert abs(loss.item() - ref["loss"].item()) < TOL
    assert max_diff(actions, ref["actions_pred"]) < TOL
