"""MergeCapabilityVector and OrthogonalRegularization in real fits in this process; their DDP and
FSDP2 fits are in test_capability_distributed.py (a file of its own, so that the two halves run on
both test workers at once)."""

from __future__ import annotations

import csv
import json
import shutil
import warnings
from pathlib import Path

import lightning as L
import pytest
import torch
from safetensors.torch import load_file, save_file

from capvector.callbacks import MergeCapabilityVector, OrthogonalRegularization
from capvector.data.datamodule import RobotDataModule
from capvector.errors import CapVectorError
from capvector.eval.device import native_bf16_cpu
from capvector.module import VLAModule
from capvector.vectors import extract, merge
from conftest import cpu_trainer, run_fit_script, write_demo_file

run = run_fit_script


def build_setup(root: Path) -> dict[str, Path]:
    """θ_init (the start of every run below and in test_capability_distributed.py), a vector
    c = θ_2steps − θ_init, and θ_init + 0.5·c, in ``root``."""
    data = write_demo_file(root / "demos.hdf5", lengths=(20, 20))
    run(root / "donor", data, "--steps", "2", "--export-initial", str(root / "initial"))
    extract(aux=root / "donor" / "export", sft=root / "initial", out=root / "vector")
    merge(root / "initial", [(root / "vector", 0.5)], root / "merged")
    return {
        "data": data,
        "initial": root / "initial",
        "vector": root / "vector",
        "merged": root / "merged",
    }


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return build_setup(tmp_path_factory.mktemp("capability"))


def random_vector(preset: str, data: Path, root: Path) -> Path:
    """A capability vector for ``preset`` on ``data``: small random deltas on its capability
    parameters. Only its keys and shapes must fit; no donor fit needed."""
    dm = RobotDataModule(train_files=[str(data)], augment=False)
    module = VLAModule(backbone=preset, data_spec=dm.spec)
    module.export(root / "sft")
    with torch.no_grad():
        for p in module.parameters():
            p.add_(1e-3 * torch.randn_like(p))
    module.export(root / "aux")
    extract(aux=root / "aux", sft=root / "sft", out=root / "vector")
    return root / "vector"


def fit(
    module: VLAModule, dm: RobotDataModule, callbacks: list, steps: int, root: Path
) -> L.Trainer:
    trainer = cpu_trainer(steps, root, callbacks=callbacks)
    trainer.fit(module, dm)
    return trainer


def test_a_bad_vector_stops_the_run_before_anything_changes(setup: dict, tmp_path: Path) -> None:
    dm = RobotDataModule(train_files=[str(setup["data"])], batch_size=4)
    module = VLAModule(pretrained=str(setup["initial"]), data_spec=dm.spec)
    before = {k: v.clone() for k, v in module.state_dict().items()}
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in setup["vector"].iterdir():
        (broken / f.name).write_bytes(f.read_bytes())
    tensors = load_file(broken / "capability_vector.safetensors")
    key = next(k for k in tensors if k.endswith("fc1.weight"))
    tensors[key] = tensors[key][:, :3].contiguous()  # wrong shape
    save_file(tensors, str(broken / "capability_vector.safetensors"))
    with pytest.raises(CapVectorError, match="fc1.weight"):
        fit(module, dm, [MergeCapabilityVector(str(broken))], 2, tmp_path)
    after = module.state_dict()
    assert all(torch.equal(v, after[k]) for k, v in before.items())


def test_orthogonality_is_anchored_at_the_merged_weights(setup: dict, tmp_path: Path) -> None:
    """Merge at fit start, then penalise: the penalty is exactly 0 at θ_meta and grows after."""
    from lightning.pytorch.loggers import CSVLogger

    dm = RobotDataModule(train_files=[str(setup["data"])], batch_size=4, augment=False)
    module = VLAModule(pretrained=str(setup["initial"]), data_spec=dm.spec)
    callbacks = [
        MergeCapabilityVector(str(setup["vector"]), scale=0.5),
        OrthogonalRegularization(str(setup["vector"]), weight=10.0),
    ]
    trainer = cpu_trainer(4, logger=CSVLogger(tmp_path), log_every_n_steps=1, callbacks=callbacks)
    trainer.fit(module, dm)
    rows = list(csv.DictReader((Path(trainer.log_dir) / "metrics.csv").open()))
    penalty = [
        float(r["train/loss_orthogonality"]) for r in rows if r.get("train/loss_orthogonality")
    ]
    assert penalty[0] == 0.0 and penalty[-1] > 0.0
    for r in rows:
        if r.get("train/loss"):
            total = float(r["train/loss_action"]) + 10.0 * float(r["train/loss_orthogonality"])
            assert float(r["train/loss"]) == pytest.approx(total, rel=1e-5)
    assert any(r.get("orth/mean_abs_projection") for r in rows)


def projection_on_vector(weights: dict[str, torch.Tensor], base: Path, vector: Path) -> float:
    """⟨θ − θ_base, c⟩ / ‖c‖² over the vector's tensors: how many times c the weights hold."""
    theta0 = load_file(base / "model.safetensors")
    c = load_file(vector / "capability_vector.safetensors")
    dot = sum(((weights[k] - theta0[k]).double() * c[k].double()).sum() for k in c)
    return float(dot / sum(c[k].double().square().sum() for k in c))


def merge_fit(
    pretrained: Path, vector: str, data: Path, steps: int, root: Path, ckpt: Path | None = None,
    scale: float = 0.7,
) -> VLAModule:  # fmt: skip
    """SFT from ``pretrained`` with the vector merged at fit start and orthogonal regularization,
    as the downstream recipe runs; saves ``root / "last.ckpt"``."""
    dm = RobotDataModule(train_files=[str(data)], batch_size=4, augment=False)
    module = VLAModule(pretrained=str(pretrained), data_spec=dm.spec)
    callbacks = [
        MergeCapabilityVector(vector, scale=scale),
        OrthogonalRegularization(vector, weight=100.0),
    ]
    trainer = cpu_trainer(steps, root, callbacks=callbacks)
    trainer.fit(module, dm, ckpt_path=ckpt)
    trainer.save_checkpoint(root / "last.ckpt")
    return module


def spell(vector: Path, how: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """The same vector folder, written another way (the ways the issue found merging twice)."""
    if how == "trailing slash":
        return f"{vector}/"
    if how == "relative":
        monkeypatch.chdir(vector.parent)
        return f"./{vector.name}"
    if how == "symlink":
        link = tmp_path / "link-to-vector"
        link.symlink_to(vector, target_is_directory=True)
        return str(link)
    if how == "moved":
        moved = tmp_path / "elsewhere" / "vector"
        moved.parent.mkdir()
        shutil.copytree(vector, moved)
        return str(moved)
    return str(vector)


@pytest.fixture(scope="module")
def uninterrupted_projection(setup: dict, tmp_path_factory: pytest.TempPathFactory) -> float:
    """How many times c the weights hold after the 3-step fit run without a stop."""
    module = merge_fit(
        setup["initial"], str(setup["vector"]), setup["data"], 3, tmp_path_factory.mktemp("whole")
    )
    weights = {k: v.detach() for k, v in module.backbone.state_dict().items()}
    return projection_on_vector(weights, setup["initial"], setup["vector"])


@pytest.fixture(scope="module")
def stopped_checkpoint(setup: dict, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The checkpoint of the fit below stopped after 2 steps (λ = 0.7 merged at fit start): the
    same for every spelling of the resume, so it is fitted once."""
    root = tmp_path_factory.mktemp("stopped")
    first = merge_fit(setup["initial"], str(setup["vector"]), setup["data"], 2, root)
    assert len(first.merged_vectors) == 1
    return root / "last.ckpt"


@pytest.mark.parametrize("how", ["same path", "trailing slash", "relative", "symlink", "moved"])
def test_a_resume_never_merges_again_however_the_vector_is_spelled(
    how: str,
    setup: dict,
    uninterrupted_projection: float,
    stopped_checkpoint: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Fit 2 steps (λ = 0.7 merged at fit start), stop, resume 1 more step with the vector folder
    spelled another way: the weights hold c as many times as the fit run without a stop (about
    0.7: SFT steps move along c a little too, c being 2 steps of SFT), not 1.4."""
    vector = spell(setup["vector"], how, tmp_path, monkeypatch)
    resumed = merge_fit(
        setup["initial"], vector, setup["data"], 3, tmp_path / "b", ckpt=stopped_checkpoint
    )
    weights = {k: v.detach() for k, v in resumed.backbone.state_dict().items()}
    projection = projection_on_vector(weights, setup["initial"], setup["vector"])
    assert projection == pytest.approx(uninterrupted_projection, abs=1e-6)
    assert projection == pytest.approx(0.7, abs=0.1)
    assert [r.scale for r in resumed.merged_vectors] == [0.7]


def test_a_resume_with_another_scale_or_vector_names_both(
    setup: dict, stopped_checkpoint: Path, tmp_path: Path
) -> None:
    ckpt = stopped_checkpoint  # λ = 0.7 of setup's vector merged at its fit start
    with pytest.raises(CapVectorError, match=r"merged .*x 0\.7.*asks for .*x 0\.5"):
        merge_fit(
            setup["initial"], str(setup["vector"]), setup["data"], 3, tmp_path / "b", ckpt, 0.5
        )
    other = random_vector("openvla-oft-tiny", setup["data"], tmp_path / "other")
    with pytest.raises(CapVectorError, match=r"records .*vector x 0\.7.*asks for .*other"):
        merge_fit(setup["initial"], str(other), setup["data"], 3, tmp_path / "c", ckpt)


def test_the_record_travels_into_exports_and_merge_refuses_a_repeat(
    setup: dict, tmp_path: Path
) -> None:
    """θ_meta written by `capvector merge` (or exported after a merge at fit start) records the
    vector: merging it again, offline or at fit start, is refused unless allowed explicitly."""
    config = json.loads((setup["merged"] / "config.json").read_text())
    (entry,) = config["merged_vectors"]
    assert entry["scale"] == 0.5 and entry["by"] == "capvector merge"
    with pytest.raises(CapVectorError, match="already holds vector"):
        merge(setup["merged"], [(setup["vector"], 0.5)], tmp_path / "twice")
    assert not (tmp_path / "twice").exists()
    twice = merge(setup["merged"], [(setup["vector"], 0.5)], tmp_path / "twice", allow_repeat=True)
    assert len(twice["vectors"]) == 1
    assert len(json.loads((tmp_path / "twice" / "config.json").read_text())["merged_vectors"]) == 2
    with pytest.raises(CapVectorError, match="pretrained model already holds"):
        merge_fit(setup["merged"], str(setup["vector"]), setup["data"], 1, tmp_path / "fit")
    module = merge_fit(setup["initial"], str(setup["vector"]), setup["data"], 1, tmp_path / "ok")
    module.export(tmp_path / "export")
    exported = json.loads((tmp_path / "export" / "config.json").read_text())["merged_vectors"]
    assert [e["by"] for e in exported] == ["MergeCapabilityVector"]


def test_bf16_frozen_export_is_in_the_base_dtype_unless_asked(setup: dict, tmp_path: Path) -> None:
    """LoRA with frozen bf16 weights: the export is bf16 throughout (the base's dtype, as
    OpenVLA-OFT's merge script writes), ``dtype="float32"`` writes every tensor in float32 with
    the LoRA-merged and trained ones unrounded; both load back."""
    from capvector.backbones import from_pretrained
    from capvector.io.lora_layers import constant_scaling, merge_lora
    from capvector.training.lora import LoraSettings

    dm = RobotDataModule(train_files=[str(setup["data"])], batch_size=4)
    module = VLAModule(
        pretrained=str(setup["initial"]), data_spec=dm.spec, lora=LoraSettings(r=4, alpha=8),
        frozen_dtype="bfloat16",
    )  # fmt: skip
    trainer = cpu_trainer(2, precision="bf16-mixed")
    trainer.fit(module, dm)
    module.export(tmp_path / "base")
    module.export(tmp_path / "full", dtype="float32")
    base = load_file(tmp_path / "base" / "model.safetensors")
    full = load_file(tmp_path / "full" / "model.safetensors")
    assert {t.dtype for t in base.values() if t.is_floating_point()} == {torch.bfloat16}
    assert {t.dtype for t in full.values() if t.is_floating_point()} == {torch.float32}
    for folder, dtype in (("base", "bfloat16"), ("full", "float32")):
        config = json.loads((tmp_path / folder / "config.json").read_text())
        assert (config["frozen_dtype"], config["torch_dtype"]) == ("bfloat16", dtype)
        assert from_pretrained(tmp_path / folder) is not None
    # The float32 export holds the merge of the trained float32 weights exactly; the bf16 export
    # is that rounded once (round-to-nearest: within half a bf16 step of it).
    trained = merge_lora(
        module.backbone.state_dict(), constant_scaling(module.lora_settings.scaling)
    )
    lora_targets = {n.removesuffix(".base_layer.weight") + ".weight" for n, _ in module.backbone.named_parameters() if n.endswith(".base_layer.weight")}  # fmt: skip
    assert lora_targets
    for key in lora_targets:
        assert trained[key].dtype == torch.float32
        torch.testing.assert_close(full[key], trained[key], rtol=0, atol=0)
        assert torch.equal(base[key], trained[key].bfloat16())


def test_export_dtype_is_checked_before_the_fit() -> None:
    from capvector.callbacks import ExportOnFitEnd

    with pytest.raises(CapVectorError, match="unknown floating dtype 'bf16'; use float32"):
        ExportOnFitEnd(dtype="bf16")


def test_frozen_bf16_needs_autocast(setup: dict, tmp_path: Path) -> None:
    dm = RobotDataModule(train_files=[str(setup["data"])], batch_size=4)
    module = VLAModule(pretrained=str(setup["initial"]), data_spec=dm.spec, frozen_dtype="bfloat16")
    with pytest.raises(Exception, match="needs trainer.precision: bf16-mixed"):
        fit(module, dm, [], 1, tmp_path)


def test_bf16_frozen_weights_with_full_fine_tuning_of_a_subset(setup: dict, tmp_path: Path) -> None:
    """Full fine-tuning with the vision backbone frozen (any subset with requires_grad off when the
    fit starts): that subset is stored in bf16, the rest trains in float32."""
    dm = RobotDataModule(train_files=[str(setup["data"])], batch_size=4)
    module = VLAModule(pretrained=str(setup["initial"]), data_spec=dm.spec, frozen_dtype="bfloat16")
    for name, param in module.backbone.named_parameters():
        if name.startswith("vision_backbone."):
            param.requires_grad_(False)
    before = {n: p.detach().clone() for n, p in module.backbone.named_parameters()}
    frozen = {n for n, p in module.backbone.named_parameters() if not p.requires_grad}
    assert any(n.startswith("vision_backbone.") for n in frozen)  # and the unused LM head
    trainer = cpu_trainer(2, precision="bf16-mixed")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer.fit(module, dm)
    emulated = [w for w in caught if "CPU without bf16 hardware" in str(w.message)]
    assert len(emulated) == (0 if native_bf16_cpu() else 1)  # said once, where it is emulated
    for name, param in module.backbone.named_parameters():
        assert param.dtype == (torch.bfloat16 if name in frozen else torch.float32), name
        if name in frozen:  # stored in bf16, otherwise untouched
            torch.testing.assert_close(param.float(), before[name].bfloat16().float())
    assert any(
        not torch.equal(p, before[n])
        for n, p in module.backbone.named_parameters()
        if n.startswith("action_head.")
    )


@pytest.mark.parametrize("float32_weights", [True, False])
def test_a_lora_fit_keeps_in_float32_only_the_frozen_weights_the_vector_changes(
    setup: dict, tmp_path: Path, float32_weights: bool
) -> None:
    """A vector between two LoRA fits names every tensor but changes only the LoRA targets: only
    those stay float32 beside bf16 frozen weights (or none, ``float32_weights=False``), and the
    planner's vector term is what the fit holds beyond a fit without the vector."""
    from capvector.profiling.memory import keep_in_float32, vector_copy_bytes
    from capvector.training.lora import LoraSettings
    from capvector.vectors import load_vector

    dm = RobotDataModule(train_files=[str(setup["data"])], batch_size=4)

    def lora_module() -> VLAModule:
        return VLAModule(
            pretrained=str(setup["initial"]), data_spec=dm.spec, frozen_dtype="bfloat16",
            lora=LoraSettings(r=4, alpha=8),
        )  # fmt: skip

    sft = lora_module()
    sft.export(tmp_path / "sft")
    targets = [n for n, m in sft.backbone.named_modules() if hasattr(m, "lora_A")][:3]
    with torch.no_grad():  # θ_aux: three LoRA targets' base weights moved, nothing else
        for name in targets:
            weight = sft.backbone.get_submodule(name).base_layer.weight
            weight.add_(0.05 * torch.randn_like(weight))
    sft.export(tmp_path / "aux")
    extract(aux=tmp_path / "aux", sft=tmp_path / "sft", out=tmp_path / "vector")
    vector = str(tmp_path / "vector")
    changed = {f"{name}.weight" for name in targets}

    plain, merged = lora_module(), lora_module()
    cpu_trainer(1, tmp_path / "plain", precision="bf16-mixed").fit(plain, dm)
    callbacks = [
        MergeCapabilityVector(vector, float32_weights=float32_weights),
        OrthogonalRegularization(vector, mode="lora"),
    ]
    trainer = cpu_trainer(1, tmp_path / "merged", callbacks=callbacks, precision="bf16-mixed")
    trainer.fit(merged, dm)

    def canonical(name: str) -> str:
        return name.replace("base_model.model.", "").replace(".base_layer", "")

    in_float32 = {
        canonical(n) for n, p in merged.backbone.named_parameters()
        if not p.requires_grad and p.dtype == torch.float32
    }  # fmt: skip
    assert in_float32 == (changed if float32_weights else set())

    def stored(module: VLAModule) -> int:
        return sum(p.numel() * p.element_size() for p in module.backbone.parameters())

    held = stored(merged) - stored(plain) + sum(
        b.numel() * b.element_size() for b in callbacks[1].loss.buffers()
        if b.dtype == torch.float32
    )  # fmt: skip
    # The planner's term, from the backbone as training stores it without the vector (`plain`'s),
    # which it then holds as the merged fit does.
    loaded = load_vector(vector)
    kept = keep_in_float32(plain.backbone, loaded.changed_keys()) if float32_weights else 0
    assert kept + vector_copy_bytes(loaded) == held
    assert stored(plain) == stored(merged)
