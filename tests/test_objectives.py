"""Auxiliary objectives: spatial alignment (frozen teachers), reasoning co-training, the callback."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import lightning as L
import pytest
import torch
import yaml
from safetensors.torch import save_file

from capvector.backbones import OutputRequest, build_backbone
from capvector.callbacks import AuxiliaryObjective
from capvector.cli import main
from capvector.data import keys
from capvector.data.datamodule import RobotDataModule
from capvector.errors import CapVectorError
from capvector.module import OptimizerSettings, VLAModule
from capvector.objectives import (
    GeometricTeacher,
    ReasoningCoTraining,
    SpatialAlignment,
    TimmTeacher,
)
from conftest import cpu_trainer, write_demo_file

REPO = Path(__file__).resolve().parents[1]


def datamodule(path: Path, **kwargs) -> RobotDataModule:
    return RobotDataModule(
        train_files=[str(path)], batch_size=4, load_depth=True, load_annotations=True, **kwargs
    )


def fit(
    module: VLAModule, dm: RobotDataModule, root: Path, callbacks: list, steps: int = 4
) -> L.Trainer:
    L.seed_everything(0)
    trainer = cpu_trainer(steps, root, callbacks=callbacks)
    trainer.fit(module, dm)
    return trainer


def first_batch(dm: RobotDataModule, size: int = 4) -> dict:
    return next(iter(torch.utils.data.DataLoader(dm.train_dataset, batch_size=size)))


@pytest.fixture
def tiny_timm_weights(tmp_path: Path) -> Path:
    import timm

    model = timm.create_model(
        "vit_tiny_patch16_224", pretrained=False, num_classes=0, img_size=32, depth=2
    )
    path = tmp_path / "teacher.safetensors"
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(path))
    return path


def test_teacher_is_frozen_outside_optimizer_and_checkpoint(
    demo_file: Path, tmp_path: Path, tiny_timm_weights: Path
) -> None:
    dm = datamodule(demo_file)
    teacher = TimmTeacher(
        "vit_tiny_patch16_224", str(tiny_timm_weights), image_size=32, model_kwargs={"depth": 2}
    )
    before = {k: v.clone() for k, v in teacher.state_dict().items()}
    objective = SpatialAlignment(teacher=teacher, layer=2)
    module = VLAModule(data_spec=dm.spec)
    trainer = fit(module, dm, tmp_path, [AuxiliaryObjective(objective)])
    assert all(torch.equal(v, teacher.state_dict()[k]) for k, v in before.items())
    assert not any(p.requires_grad for p in teacher.parameters())
    optimized = {id(p) for group in trainer.optimizers[0].param_groups for p in group["params"]}
    assert not optimized & {id(p) for p in teacher.parameters()}
    assert {id(p) for p in objective.projector.parameters()} <= optimized  # the projector trains
    state = module.state_dict()
    assert any(k.startswith("objectives.spatial_alignment.projector.") for k in state)
    assert not any("teacher" in k for k in state)


def test_only_the_alignment_layer_is_kept(demo_file: Path) -> None:
    dm = datamodule(demo_file)
    module = VLAModule(data_spec=dm.spec)
    objective = SpatialAlignment()
    objective.bind(module.backbone)
    module.add_objective(objective)
    assert (
        objective.layer == 3
    )  # round(0.75 * 4 layers) of the tiny preset, as 24 of 32 at full size
    assert module.output_request() == OutputRequest(hidden_layers=(3,))


def test_alignment_loss_falls_when_only_the_projector_trains(demo_file: Path) -> None:
    dm = datamodule(demo_file, augment=False)
    backbone = build_backbone("openvla-oft-tiny", **dm.spec.backbone_overrides()).eval()
    batch = first_batch(dm)
    objective = SpatialAlignment(layer=2)
    objective.bind(backbone)
    with torch.no_grad():
        output = backbone(batch, objective.request)  # fixed student features
    optimizer = torch.optim.Adam(objective.projector.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = objective(batch, output, backbone)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_geometric_teacher_reflects_geometry() -> None:
    teacher = GeometricTeacher(feature_dim=32, position_embedding=False)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]).expand(1, 1, 3, 3)
    flat = torch.full((1, 1, 32, 32), 1.0)
    tilted = flat + torch.linspace(0, 0.5, 32).view(1, 1, 1, 32)
    a = teacher({keys.DEPTH: flat, keys.INTRINSICS: K}, (4, 4))
    b = teacher({keys.DEPTH: tilted, keys.INTRINSICS: K}, (4, 4))
    assert a.shape == (1, 16, 32)
    assert (
        torch.nn.functional.cosine_similarity(a, b, dim=-1).mean() < 0.99
    )  # geometry changes targets
    with pytest.raises(ValueError, match="load_depth=true"):
        teacher({keys.IMAGES: torch.zeros(1, 1, 3, 32, 32)}, (4, 4))


def test_geometric_teacher_leaves_missing_depth_out() -> None:
    """Depth sensors report a pixel they could not measure as NaN or 0 (issue 62: a NaN patch
    trained to NaN from step 0). Such pixels drop out of their tokens; a token without any valid
    pixel has no target (NaN); the others are what they were, and the loss stays finite."""
    teacher = GeometricTeacher(feature_dim=32)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]).expand(1, 1, 3, 3)
    clean = (1.0 + torch.linspace(0, 0.5, 32).view(1, 1, 1, 32)).expand(1, 1, 32, 32).clone()
    holed = clean.clone()
    holed[..., 0:8, 0:8] = float("nan")  # token (0, 0) entirely
    holed[..., 16:20, 16:20] = 0.0  # part of token (2, 2)
    a = teacher({keys.DEPTH: clean, keys.INTRINSICS: K}, (4, 4)).view(4, 4, 32)
    b = teacher({keys.DEPTH: holed, keys.INTRINSICS: K}, (4, 4)).view(4, 4, 32)
    assert b[0, 0].isnan().all() and a.isfinite().all()
    rest = torch.ones(4, 4, dtype=torch.bool)
    rest[0, 0] = False
    assert b[rest].isfinite().all()
    # Tokens whose pixels and normals' neighbours are all valid are unchanged, exactly.
    untouched = torch.ones(4, 4, dtype=torch.bool)
    untouched[0:2, 0:2] = untouched[1:3, 1:3] = False
    assert torch.equal(a[untouched], b[untouched])
    assert not torch.allclose(a[2, 2], b[2, 2])  # the 0 patch was left out, not averaged in

    student = torch.randn(1, 16, 32, requires_grad=True)
    cosine = torch.nn.functional.cosine_similarity(student, a.view(1, 16, 32), dim=-1)
    objective = SpatialAlignment(teacher=teacher)
    objective.projector = torch.nn.Identity()
    output = SimpleNamespace(
        hidden_states={0: student}, visual_token_mask=torch.ones(1, 16, dtype=torch.bool),
        visual_grid=(4, 4),
    )  # fmt: skip
    objective.layer = 0
    loss = objective({keys.DEPTH: holed, keys.INTRINSICS: K}, output, None)
    loss.backward()
    assert loss.isfinite() and student.grad.isfinite().all()
    assert student.grad[0, 0].eq(0).all()  # the token without a target pulls nothing
    assert not torch.isclose(loss, 1 - cosine.mean())  # 15 tokens averaged, not 16
    clean_loss = objective({keys.DEPTH: clean, keys.INTRINSICS: K}, output, None)
    assert torch.isclose(clean_loss, 1 - cosine.mean())
    nothing = torch.full_like(clean, float("nan"))
    none = objective({keys.DEPTH: nothing, keys.INTRINSICS: K}, output, None)
    assert none.item() == 0.0 and none.requires_grad  # no target anywhere: no pull


def test_geometric_teacher_sees_the_same_surface_in_a_mirrored_image() -> None:
    # LIBERO's frames are read mirrored against their camera, with fx < 0 (capvector.data.hdf5):
    # the same tilted plane then gives the same per-patch geometry, patch columns mirrored. (On a
    # plane 1/depth is linear in the pixel coordinates, and every finite-difference normal is the
    # plane's, so the mirror is exact up to float32 rounding: 1e-3 here, 2.0 with the normals
    # left to the pixel grid's handedness.)
    teacher = GeometricTeacher(feature_dim=32, position_embedding=False)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    mirrored_K = K.clone()
    mirrored_K[0, 0], mirrored_K[0, 2] = -40.0, 32 - 16
    centres = torch.arange(32) + 0.5
    depth = 1 / (1.0 + 0.01 * centres.view(1, 1, 1, 32) + 0.005 * centres.view(1, 1, 32, 1))
    a = teacher({keys.DEPTH: depth, keys.INTRINSICS: K.expand(1, 1, 3, 3)}, (4, 4))
    b = teacher(
        {keys.DEPTH: depth.flip(-1), keys.INTRINSICS: mirrored_K.expand(1, 1, 3, 3)}, (4, 4)
    )
    assert torch.allclose(a.view(4, 4, 32), b.view(4, 4, 32).flip(1), atol=1e-2)


def test_reasoning_loss_scores_only_answer_tokens(demo_file: Path) -> None:
    dm = datamodule(demo_file)
    backbone = build_backbone("openvla-oft-tiny", **dm.spec.backbone_overrides()).eval()
    batch = first_batch(dm, size=2)
    prompts = [
        "Question: short?\nAnswer: ",
        "Question: a much longer question about the scene?\nAnswer: ",
    ]
    answers = ["the cube is left", "ok"]
    logits, labels = backbone.language_model_logits(batch, prompts, answers)
    tok = backbone.tokenizer
    for row, answer in enumerate(answers):
        expected = [*tok(answer, add_special_tokens=False)["input_ids"], tok.eos_token_id]
        assert labels[row][labels[row] != -100].tolist() == expected
    # Padding is ignored: the short row's loss is the same alone and in the padded batch.
    objective = ReasoningCoTraining()
    alone_batch = {k: v[1:] for k, v in batch.items()}
    alone_logits, alone_labels = backbone.language_model_logits(
        alone_batch, prompts[1:], answers[1:]
    )
    n = alone_labels.shape[1]
    torch.testing.assert_close(logits[1, :n], alone_logits[0], atol=1e-4, rtol=1e-4)
    assert (labels[1, n:] == -100).all()
    loss = objective(
        {**batch, keys.ANNOTATION: answers, keys.INSTRUCTION: ["lift", "lift"]}, None, backbone
    )
    assert torch.isfinite(loss)


def test_reasoning_samples_scores_the_batchs_first_samples_alone(demo_file: Path) -> None:
    dm = datamodule(demo_file)
    backbone = build_backbone("openvla-oft-tiny", **dm.spec.backbone_overrides()).eval()
    batch = first_batch(dm, size=4)
    batch = {**batch, keys.ANNOTATION: ["left", "a longer answer here", "ok", "right of it"]}
    first_two = {k: v[:2] for k, v in batch.items()}
    capped = ReasoningCoTraining(samples=2)(batch, None, backbone)
    torch.testing.assert_close(capped, ReasoningCoTraining()(first_two, None, backbone))
    assert not torch.allclose(capped, ReasoningCoTraining()(batch, None, backbone))
    with pytest.raises(CapVectorError, match="reasoning samples must be at least 1"):
        ReasoningCoTraining(samples=0)


def test_reasoning_answer_vocabulary_is_the_training_annotations_tokens(
    demo_file: Path, tmp_path: Path
) -> None:
    """vocabulary="answers": collected from every annotation of the training set when the fit
    starts, and the loss is the cross-entropy over those tokens' logits alone."""
    import h5py

    dm = datamodule(demo_file)
    module = VLAModule(data_spec=dm.spec)
    objective = ReasoningCoTraining(vocabulary="answers")
    fit(module, dm, tmp_path, [AuxiliaryObjective(objective)], steps=2)
    backbone = module.backbone
    with h5py.File(demo_file) as f:
        texts = [t.decode() for demo in f["data"].values() for t in demo["annotations"][:]]
    expected = sorted({i for text in texts for i in backbone.answer_label_ids(text)})
    assert objective.answer_vocabulary.tolist() == expected
    assert len(expected) < len(backbone.tokenizer) / 10
    batch = {**first_batch(dm, size=2)}
    prompts, answers = objective.text_inputs(batch)[1:]
    with torch.no_grad():
        logits, labels = backbone.language_model_logits(batch, prompts, answers)
        scored = labels[:, 1:] != -100
        columns = logits[:, :-1][scored][:, objective.answer_vocabulary]
        targets = torch.searchsorted(objective.answer_vocabulary, labels[:, 1:][scored])
        expected_loss = torch.nn.functional.cross_entropy(columns, targets)
        torch.testing.assert_close(objective(batch, None, backbone), expected_loss)
    with pytest.raises(CapVectorError, match="collected from the training set"):
        ReasoningCoTraining(vocabulary="answers")(batch, None, backbone)
    with pytest.raises(CapVectorError, match="must be 'full' or 'answers'"):
        ReasoningCoTraining(vocabulary="some")
    no_text = RobotDataModule(train_files=[str(demo_file)], batch_size=4)
    no_text.setup("fit")
    with pytest.raises(CapVectorError, match="does not load annotations"):
        ReasoningCoTraining(vocabulary="answers").bind_data(no_text.train_dataset, backbone)


@pytest.mark.parametrize("preset", ["openvla-oft-tiny", "pi05-tiny"])
def test_reasoning_runs_past_the_tiny_presets_512_positions(
    preset: str, demo_file: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """LIBERO's annotations run to ~650 bytes, a token each: the text pass is longer than the tiny
    preset's 512 positions. Rotary positions have no table to index past, so the loss and its
    gradients are finite, and the tokenizer's warning of "indexing errors" is not given."""
    from transformers.utils import logging as hf_logging

    dm = datamodule(demo_file)
    backbone = build_backbone(preset, **dm.spec.backbone_overrides())
    assert backbone.tokenizer.model_max_length == 512
    answer = "the black bowl is between the plate and the ramekin. " * 14  # 742 bytes
    batch = {**first_batch(dm, size=1), keys.ANNOTATION: [answer]}
    hf_logging.enable_propagation()  # transformers' warnings reach caplog
    try:
        with caplog.at_level(logging.WARNING):
            loss = ReasoningCoTraining()(batch, None, backbone)
    finally:
        hf_logging.disable_propagation()
    loss.backward()
    assert torch.isfinite(loss)
    assert all(torch.isfinite(p.grad).all() for p in backbone.parameters() if p.grad is not None)
    assert "indexing errors" not in caplog.text


def test_reasoning_pass_is_causal_and_leaves_actions_alone(demo_file: Path) -> None:
    dm = datamodule(demo_file)
    backbone = build_backbone("openvla-oft-tiny", **dm.spec.backbone_overrides()).eval()
    batch = first_batch(dm, size=1)
    first, labels = backbone.language_model_logits(
        batch, ["Q: where?\nA: "], ["left of the gripper"]
    )
    second, _ = backbone.language_model_logits(batch, ["Q: where?\nA: "], ["rear of the gripper"])
    answer_start = int((labels[0] != -100).nonzero()[0])
    torch.testing.assert_close(
        first[0, :answer_start], second[0, :answer_start]
    )  # no peeking ahead
    assert not torch.allclose(first[0, answer_start:], second[0, answer_start:])
    with torch.no_grad():
        actions = backbone(batch).actions
    module = VLAModule(data_spec=dm.spec)
    module.backbone.load_state_dict(backbone.state_dict())
    module.add_objective(ReasoningCoTraining())
    module.eval()
    with torch.no_grad():
        torch.testing.assert_close(module(batch), actions)


def test_weight_zero_objectives_leave_plain_sft_bit_identical(
    demo_file: Path, tmp_path: Path
) -> None:
    dm = datamodule(demo_file)  # augmentation on: the random stream must not be disturbed either
    # No weight decay: with it, AdamW would shrink weights that only a weight-0 objective reaches
    # (the LM head gets an all-zero gradient instead of none), which is decay, not the objective.
    settings = OptimizerSettings(weight_decay=0.0)
    plain = VLAModule(data_spec=dm.spec, optimizer=settings)
    start = {k: v.clone() for k, v in plain.state_dict().items()}
    fit(plain, dm, tmp_path / "plain", [])
    aux = VLAModule(data_spec=dm.spec, optimizer=settings)
    aux.load_state_dict(start)
    callbacks = [
        AuxiliaryObjective(SpatialAlignment(weight=0.0)),
        AuxiliaryObjective(ReasoningCoTraining(weight=0.0)),
    ]
    fit(aux, dm, tmp_path / "aux", callbacks)
    for name, value in plain.backbone.state_dict().items():
        assert torch.equal(value, aux.backbone.state_dict()[name]), name


def test_weight_schedule() -> None:
    callback = AuxiliaryObjective(ReasoningCoTraining(weight=0.2), warmup_steps=10, start_step=5)
    assert callback.weight_at(0) == 0.0
    assert callback.weight_at(5) == pytest.approx(0.02)
    assert callback.weight_at(100) == pytest.approx(0.2)


def test_recipe_configs_differ_only_in_auxiliary_callbacks() -> None:
    sft = yaml.safe_load((REPO / "configs/recipes/sft.yaml").read_text())
    aux = yaml.safe_load((REPO / "configs/recipes/aux_sft.yaml").read_text())
    aux_callbacks = aux["trainer"].pop("callbacks")
    sft_callbacks = sft["trainer"].pop("callbacks")
    assert sft == aux
    extra = [c for c in aux_callbacks if c not in sft_callbacks]
    assert {c["class_path"] for c in extra} == {"capvector.callbacks.AuxiliaryObjective"}
    assert len(extra) == 2


def resolved_aux_sft(capsys: pytest.CaptureFixture[str], data: Path, *extra: str) -> dict:
    """aux_sft.yaml with ``extra`` options after it, as `capvector fit --print_config` resolves it."""
    args = ["fit", "--config", str(REPO / "configs/recipes/aux_sft.yaml"), *extra]
    with pytest.raises(SystemExit):
        main([*args, f"--data.train_files=[{data}]", "--print_config"])
    return yaml.safe_load(capsys.readouterr().out)


def objective_callbacks(config: dict) -> list[dict]:
    return [c for c in config["trainer"]["callbacks"] if "objective" in c.get("init_args", {})]


@pytest.mark.parametrize(
    ("config", "objective", "changed"),
    [
        ("aux_sft_layer2.yaml", "SpatialAlignment", {"layer": (None, 2)}),
        (
            "mini_study_aux.yaml",
            "ReasoningCoTraining",
            {"samples": (4, 2), "vocabulary": ("full", "answers")},
        ),
    ],
)
def test_a_lever_config_changes_only_its_objective_settings(
    config: str,
    objective: str,
    changed: dict[str, tuple],
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
) -> None:
    # These configs repeat aux_sft.yaml's callbacks (a config replaces the list): resolved, they
    # differ from it in the `changed` settings of one objective and nothing else.
    data = write_demo_file(tmp_path / "demos.hdf5")
    base = resolved_aux_sft(capsys, data)
    lever = resolved_aux_sft(capsys, data, "--config", str(REPO / "configs/recipes" / config))
    settings = [
        c["init_args"]["objective"]["init_args"]
        for resolved in (base, lever)
        for c in objective_callbacks(resolved)
        if c["init_args"]["objective"]["class_path"].endswith(objective)
    ]
    for key, values in changed.items():
        assert tuple(s.pop(key) for s in settings) == values, key
    assert lever == base


@pytest.mark.parametrize(
    ("config", "kept"),
    [
        ("aux_sft_spatial_only.yaml", "SpatialAlignment"),
        ("aux_sft_reasoning_only.yaml", "ReasoningCoTraining"),
    ],
)
def test_each_single_objective_lever_drops_the_other_objective_and_nothing_else(
    config: str, kept: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # Lever 6 of the LIBERO study: aux-SFT with one of its two objectives; data, optimizer and the
    # kept objective's settings are aux_sft.yaml's.
    data = write_demo_file(tmp_path / "demos.hdf5")
    base = resolved_aux_sft(capsys, data)
    lever = resolved_aux_sft(capsys, data, "--config", str(REPO / "configs/recipes" / config))
    dropped = [
        c
        for c in objective_callbacks(base)
        if not c["init_args"]["objective"]["class_path"].endswith(kept)
    ]
    assert len(dropped) == 1
    base["trainer"]["callbacks"].remove(dropped[0])
    assert lever == base


def test_aux_sft_config_trains_through_the_cli(tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(16, 16))
    main([
        "fit", "--config", str(REPO / "configs/recipes/aux_sft.yaml"), f"--data.train_files=[{data}]",
        "--data.batch_size=4", "--trainer.max_steps=3", "--trainer.log_every_n_steps=1",
        f"--trainer.default_root_dir={tmp_path}",
        f"--trainer.logger.init_args.save_dir={tmp_path}", "--trainer.enable_progress_bar=false",
    ])  # fmt: skip
    metrics = (tmp_path / "fit" / "version_0" / "metrics.csv").read_text().splitlines()[0]
    for column in (
        "train/loss_spatial_alignment",
        "train/loss_reasoning",
        "aux/spatial_alignment_weight",
    ):
        assert column in metrics
