"""The backbone contract (``capvector.backbones.base``), checked on every registered preset that
builds on CPU, as timm tests every registered model: what ``forward`` returns, which parameters
train and get gradients, LoRA targets, persistence, FSDP2 units and the text pass.

Presets are whatever the registry lists when the tests are collected (families of other packages
included); those too large for CPU (the full-size presets, built on the meta device only) are left
out by their parameter count. Family-specific behaviour stays in the family test files.
"""

from __future__ import annotations

import fnmatch
import importlib
import inspect
import re
from collections.abc import Mapping
from pathlib import Path

import pytest
import torch
from peft.tuners.tuners_utils import BaseTunerLayer
from torch import Tensor, nn

from capvector.backbones import (
    BackboneError,
    OutputRequest,
    VLABackbone,
    build_backbone,
    from_pretrained,
    list_presets,
    preset_config,
)
from capvector.backbones.base import registered_families
from capvector.data import keys
from capvector.training.distributed import parallelize
from capvector.training.lora import LoraSettings, set_trainable

CPU_PARAMETER_LIMIT = 50_000_000
"""Presets up to this many parameters run here (tiny ones have under 1 M, full-size billions)."""
BATCH = 2
INSTRUCTIONS = ["lift", "stack the red cube on the green cube, carefully"]  # unequal: padding
IGNORE_INDEX = -100


def parameter_count(preset: str) -> int:
    with torch.device("meta"):
        return sum(p.numel() for p in build_backbone(preset).parameters())


PRESET_SIZES = {name: parameter_count(name) for name in list_presets()}
CPU_PRESETS = sorted(name for name, size in PRESET_SIZES.items() if size <= CPU_PARAMETER_LIMIT)


def build(preset: str) -> VLABackbone:
    torch.manual_seed(0)
    return build_backbone(preset)


def make_batch(model: VLABackbone, actions: bool = True, seed: int = 0) -> dict:
    """A batch in the shapes the preset's config asks for (cameras, image size, dims)."""
    c = model.config
    g = torch.Generator().manual_seed(seed)
    batch: dict = {
        keys.IMAGES: torch.rand(BATCH, c.num_images, 3, c.image_size, c.image_size, generator=g),
        keys.INSTRUCTION: INSTRUCTIONS[:BATCH],
    }
    if c.proprio_dim:
        batch[keys.PROPRIO] = torch.rand(BATCH, c.proprio_dim, generator=g) * 2 - 1
    if actions:
        batch[keys.ACTIONS] = torch.rand(BATCH, c.chunk_size, c.action_dim, generator=g) * 2 - 1
    return batch


def predict(model: VLABackbone, batch: Mapping, seed: int = 7) -> Tensor:
    """(B, T, A) actions with the global RNG (flow noise) fixed, so two models can be compared."""
    torch.manual_seed(seed)
    return model.predict_action(batch)


def training_loss(model: VLABackbone, batch: Mapping, seed: int = 3) -> Tensor:
    torch.manual_seed(seed)  # flow heads draw noise and times from the global RNG
    return model(batch).loss


def matching(names: list[str], globs: tuple[str, ...] | list[str]) -> list[str]:
    return [n for n in names if any(fnmatch.fnmatchcase(n, g) for g in globs)]


def test_every_family_has_a_preset_that_runs_here() -> None:
    """timm's habit: a tiny variant of every family, so this file covers every family."""
    families = {preset_config(name).family for name in PRESET_SIZES}
    covered = {preset_config(name).family for name in CPU_PRESETS}
    assert families and families == covered, f"no CPU-sized preset for {families - covered}"


LOADERS = {
    family: cls for family, cls in registered_families().items() if cls.original_loader is not None
}
LOADER_ARGUMENTS = {"cls", "source", "preset", "overrides"}
"""What every ``load_original`` takes; the rest are the family's own options."""


@pytest.mark.parametrize("family", sorted(LOADERS))
def test_import_options_are_exactly_the_loader_options(family: str) -> None:
    """`capvector import-original` offers what ``import_options`` declares; an option the loader
    takes but the family does not declare could not be reached from the command line."""
    cls = LOADERS[family]
    loader = importlib.import_module(cls.original_loader).load_original
    own = set(inspect.signature(loader).parameters) - LOADER_ARGUMENTS
    assert {option.name for option in cls.import_options} == own


@pytest.mark.parametrize("family", sorted(LOADERS))
def test_from_original_refuses_an_undeclared_option(family: str, tmp_path: Path) -> None:
    with pytest.raises(BackboneError, match=r"has no option\(s\) \['colour'\]; its options: \["):
        LOADERS[family].from_original(tmp_path, colour="red")


each_preset = pytest.mark.parametrize("preset", CPU_PRESETS)


@each_preset
def test_training_forward_returns_a_loss_and_only_the_requested_outputs(preset: str) -> None:
    model = build(preset)
    batch = make_batch(model)
    layers = tuple(sorted({0, model.alignment_layer, model.num_layers}))
    out = model(batch, OutputRequest(hidden_layers=layers, lm_logits=True))
    assert out.loss is not None and out.loss.ndim == 0 and out.loss.requires_grad
    assert torch.isfinite(out.loss)
    if out.actions is not None:  # optional while training (heads whose loss is not the L1)
        assert out.actions.shape == (BATCH, model.config.chunk_size, model.config.action_dim)
    assert out.attention_mask is not None and out.attention_mask.dtype == torch.bool
    b, s = out.attention_mask.shape
    assert b == BATCH
    assert set(out.hidden_states) == set(layers)
    for layer, hidden in out.hidden_states.items():
        assert hidden.shape == (BATCH, s, model.hidden_size), layer
    assert out.visual_token_mask is not None and out.visual_token_mask.dtype == torch.bool
    assert out.visual_token_mask.shape == (BATCH, s)
    rows, cols = out.visual_grid
    assert out.visual_token_mask.sum(1).tolist() == [model.config.num_images * rows * cols] * BATCH
    assert out.lm_logits is not None and out.lm_logits.shape[:2] == (BATCH, s)

    with torch.no_grad():
        plain = model(batch)
        one = model(batch, OutputRequest(hidden_layers=(model.num_layers,)))
    assert plain.hidden_states == {} and plain.lm_logits is None
    assert set(one.hidden_states) == {model.num_layers} and one.lm_logits is None
    with pytest.raises(BackboneError, match=f"hidden layer {model.num_layers + 1} requested"):
        model(batch, OutputRequest(hidden_layers=(model.num_layers + 1,)))


@each_preset
def test_predicted_actions_have_the_chunk_shape(preset: str) -> None:
    model = build(preset).eval()
    actions = predict(model, make_batch(model, actions=False))
    assert actions.shape == (BATCH, model.config.chunk_size, model.config.action_dim)
    assert torch.isfinite(actions).all() and not actions.requires_grad


@each_preset
def test_a_wrong_camera_count_is_a_clear_error(preset: str) -> None:
    model = build(preset).eval()
    batch = make_batch(model, actions=False)
    expected = model.config.num_images
    wrong = expected - 1 if expected > 1 else 2
    images = batch[keys.IMAGES]
    batch[keys.IMAGES] = images[:, :1].expand(-1, wrong, -1, -1, -1)
    with pytest.raises(BackboneError, match=rf"{wrong} camera.*num_images={expected}"):
        model(batch)


@each_preset
@pytest.mark.parametrize("lora", [False, True], ids=["full", "lora"])
def test_every_trainable_parameter_gets_a_gradient(preset: str, lora: bool) -> None:
    """What VLAModule trains (``set_trainable``) must all be reached by the action loss: DDP runs
    without ``find_unused_parameters``, and a parameter without a gradient would stop it."""
    model = build(preset)
    set_trainable(model, LoraSettings(r=2, alpha=4) if lora else None)
    trainable = {n: p for n, p in model.named_parameters() if p.requires_grad}
    assert trainable
    training_loss(model, make_batch(model)).backward()
    missing = sorted(n for n, p in trainable.items() if p.grad is None)
    assert not missing, f"{len(missing)} trainable parameter(s) get no gradient: {missing[:8]}"
    assert all(torch.isfinite(p.grad).all() for p in trainable.values())
    frozen = [n for n, p in model.named_parameters() if not p.requires_grad]
    assert all(model.get_parameter(n).grad is None for n in frozen)


@each_preset
def test_lora_targets_exist_and_peft_wraps_them(preset: str) -> None:
    model = build(preset)
    capability = set(model.capability_parameter_names())
    names = [n for n, _ in model.named_modules()]
    set_trainable(model, LoraSettings(r=2, alpha=4))
    wrapped = [n for n, m in model.named_modules() if isinstance(m, BaseTunerLayer)]
    assert wrapped, f"lora_target_modules {model.lora_target_modules!r} matched no module"
    targets = model.lora_target_modules
    if isinstance(targets, str):  # peft: a full-match regex over module names
        expected = [n for n in names if re.fullmatch(targets, n)]
        assert sorted(wrapped) == sorted(expected), "the regex names modules peft cannot wrap"
    else:  # peft: a name matches when it is the target or ends with "." + target
        for target in targets:
            assert any(n == target or n.endswith(f".{target}") for n in wrapped), target
    # LoRA adapts the pretrained part a capability vector covers...
    outside = [n for n in wrapped if f"{n}.weight" not in capability]
    assert not outside, f"LoRA on parameters outside capability_parameters: {outside[:5]}"
    # ...and what is trained from scratch (outside it) trains in full, or it would stay random.
    frozen_heads = [
        n
        for n, p in model.named_parameters()
        if ".lora_" not in n and n.replace(".base_layer.", ".") not in capability
        if not p.requires_grad and n not in set(model.unused_parameter_names())
    ]
    assert not frozen_heads, f"task-head parameters frozen under LoRA: {frozen_heads[:5]}"


@each_preset
def test_named_parameter_lists_name_real_parameters(preset: str) -> None:
    """Globs and names that match nothing would silently train, freeze or merge nothing."""
    model = build(preset)
    names = [n for n, _ in model.named_parameters()]
    for glob in model.capability_parameters:
        assert matching(names, (glob,)), f"capability_parameters glob {glob!r} matches nothing"
    assert model.capability_parameter_names()
    assert matching(names, model.lora_trainable_modules), "lora_trainable_modules match nothing"
    for listed in ("unused_parameter_names", "language_head_parameter_names"):
        unknown = set(getattr(model, listed)()) - set(names)
        assert not unknown, f"{listed} names no parameter: {sorted(unknown)[:5]}"
    embeddings = model.embedding_parameter_names()
    for name in embeddings:
        module = model.get_submodule(name.rpartition(".")[0])
        assert isinstance(module, nn.Embedding) and name in model.state_dict(), name
    assert model.export_config()["embedding_parameters"] == embeddings


@each_preset
def test_alignment_layer_is_a_decoder_layer(preset: str) -> None:
    model = build(preset)
    assert 1 <= model.alignment_layer <= model.num_layers


@each_preset
def test_save_pretrained_then_from_pretrained_gives_identical_outputs(
    preset: str, tmp_path: Path
) -> None:
    model = build(preset).eval()
    loaded = from_pretrained(model.save_pretrained(tmp_path / "export")).eval()
    assert type(loaded) is type(model)
    assert loaded.config == model.config  # tuple fields (StarVLA's image_mean) come back tuples
    ours, theirs = model.state_dict(), loaded.state_dict()
    assert ours.keys() == theirs.keys()
    assert all(torch.equal(ours[k], theirs[k]) for k in ours)
    observation = make_batch(model, actions=False)
    exact = {"rtol": 0, "atol": 0}
    torch.testing.assert_close(predict(loaded, observation), predict(model, observation), **exact)
    batch = make_batch(model)
    with torch.no_grad():
        torch.testing.assert_close(
            training_loss(loaded, batch), training_loss(model, batch), **exact
        )


@each_preset
def test_shard_units_are_disjoint_blocks_that_recompute_exactly(preset: str) -> None:
    """FSDP2 shards each unit and activation checkpointing recomputes it: units are distinct
    submodules with parameters, and recomputing them changes neither loss nor gradients."""
    model = build(preset)
    units = model.shard_units()
    assert units, "shard_units is empty: FSDP2 would shard the backbone as one block"
    submodules = {id(m) for m in model.modules()}
    assert all(id(u) in submodules and u is not model for u in units)
    owners: dict[int, int] = {}
    for index, unit in enumerate(units):
        params = list(unit.parameters())
        assert params, f"shard unit {index} ({type(unit).__name__}) has no parameters"
        for p in params:
            assert owners.setdefault(id(p), index) == index, "two shard units share a parameter"

    def loss_and_grads(checkpointing: bool) -> tuple[Tensor, dict[str, Tensor]]:
        model = build(preset).eval()  # eval: the comparison must not depend on dropout
        parallelize(model, model.shard_units(), [], None, activation_checkpointing=checkpointing)
        loss = training_loss(model, make_batch(model))
        loss.backward()
        return loss.detach(), {n: p.grad for n, p in model.named_parameters() if p.grad is not None}

    (plain_loss, plain_grads), (loss, grads) = loss_and_grads(False), loss_and_grads(True)
    torch.testing.assert_close(loss, plain_loss)
    assert grads.keys() == plain_grads.keys()
    for name, grad in grads.items():
        torch.testing.assert_close(grad, plain_grads[name], msg=name)


@each_preset
def test_language_model_logits_label_only_the_answer_and_are_causal(preset: str) -> None:
    model = build(preset).eval()
    batch = make_batch(model, actions=False)
    with torch.no_grad():
        vocab = model(batch, OutputRequest(lm_logits=True)).lm_logits.shape[-1]
        logits, labels = model.language_model_logits(
            batch, ["Where?", "Which cube?"], ["left", "the red one"]
        )
    assert logits.shape == (*labels.shape, vocab) and labels.shape[0] == BATCH
    answer = labels != IGNORE_INDEX
    assert answer.any(1).all(), "every row needs answer labels"
    assert (labels[answer] >= 0).all() and (labels[answer] < vocab).all()
    # One sample (no padding): the logits up to the first answer token do not see the answer.
    one = {k: v[:1] for k, v in batch.items()}
    with torch.no_grad():
        first, first_labels = model.language_model_logits(one, ["Where?"], ["left"])
        second, _ = model.language_model_logits(one, ["Where?"], ["rear"])
    start = int((first_labels[0] != IGNORE_INDEX).nonzero()[0])
    torch.testing.assert_close(first[0, :start], second[0, :start])
    assert not torch.allclose(first[0, start], second[0, start])  # position start sees "l" / "r"


@each_preset
def test_answer_logits_over_a_vocabulary_are_its_columns_of_the_full_logits(preset: str) -> None:
    """``vocabulary``: the same hidden states projected on those tokens' rows of the head alone,
    and each label its index there. ``answer_label_ids`` are the labels ``text_pass`` scores, so a
    vocabulary built from them covers every answer; a label outside it is an error."""
    model = build(preset).eval()
    batch = make_batch(model, actions=False)
    prompts, answers = ["Where?", "Which cube?"], ["left", "the red one"]
    _, labels = model.text_pass(batch, prompts, answers)
    for row, answer in enumerate(answers):
        assert labels[row][labels[row] != IGNORE_INDEX].tolist() == model.answer_label_ids(answer)
    used = {i for answer in answers for i in model.answer_label_ids(answer)}
    vocabulary = torch.tensor(sorted(used | {0, 5}))  # and two tokens no answer uses
    with torch.no_grad():
        full, targets = model.answer_logits(batch, prompts, answers)
        some, indices = model.answer_logits(batch, prompts, answers, vocabulary)
    assert some.shape == (len(targets), len(vocabulary))
    torch.testing.assert_close(some, full[:, vocabulary])
    assert torch.equal(vocabulary[indices], targets)
    with pytest.raises(BackboneError, match="not in the 2-token answer vocabulary"):
        model.answer_logits(batch, prompts, answers, torch.tensor([0, 5]))


@each_preset
def test_answer_logits_give_the_next_token_loss_of_every_position(preset: str) -> None:
    """The reasoning loss projects only answer positions onto the vocabulary: the same loss, and
    the same gradients, as scoring every position's logits with -100 where no answer token follows."""
    model = build(preset)
    batch = make_batch(model, actions=False)
    prompts, answers = ["Where?", "Which cube?"], ["left", "the red one"]
    params = [p for p in model.parameters() if p.requires_grad]
    torch.manual_seed(0)  # dropout, if a preset has any, draws the same in both passes
    logits, labels = model.language_model_logits(batch, prompts, answers)
    every = torch.nn.functional.cross_entropy(
        logits[:, :-1].flatten(0, 1), labels[:, 1:].flatten(), ignore_index=IGNORE_INDEX
    )
    every_grads = torch.autograd.grad(every, params, allow_unused=True)
    torch.manual_seed(0)
    answer_logits, targets = model.answer_logits(batch, prompts, answers)
    assert targets.shape == (int((labels[:, 1:] != IGNORE_INDEX).sum()),)
    assert answer_logits.shape == (*targets.shape, logits.shape[-1])
    scored = torch.nn.functional.cross_entropy(answer_logits, targets)
    torch.testing.assert_close(scored, every)
    scored_grads = torch.autograd.grad(scored, params, allow_unused=True)
    for param, a, b in zip(params, every_grads, scored_grads, strict=True):
        assert (a is None) == (b is None), param.shape
        if a is not None:
            torch.testing.assert_close(b, a, atol=1e-6, rtol=1e-4)
