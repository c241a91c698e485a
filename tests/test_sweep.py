"""`capvector sweep-scale`: a vector whose right scale is known is ranked right; sweeps resume."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import torch

from capvector.cli import main
from capvector.data.datamodule import RobotDataModule
from capvector.errors import CapVectorError
from capvector.eval.results import best_scale
from capvector.module import VLAModule
from capvector.vectors import extract
from capvector.workflows.fit import run_lightning_cli
from capvector.workflows.sweep import sweep
from conftest import cpu_trainer, write_demo_file


def export_pre_and_vector(tmp_path: Path, dm: RobotDataModule) -> None:
    """θ_pre (``tmp_path/pre``) and a vector (``tmp_path/vector``) between two random models."""
    torch.manual_seed(0)
    VLAModule(data_spec=dm.spec).export(tmp_path / "pre")
    torch.manual_seed(1)
    VLAModule(data_spec=dm.spec).export(tmp_path / "other")
    extract(aux=tmp_path / "other", sft=tmp_path / "pre", out=tmp_path / "vector")


def test_exact_difference_vector_is_best_at_scale_one(tmp_path: Path) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(16, 16))
    dm = RobotDataModule(train_files=[str(data)], batch_size=8, augment=False)
    torch.manual_seed(0)
    module = VLAModule(data_spec=dm.spec)
    module.export(tmp_path / "pre")
    cpu_trainer(40).fit(module, dm)  # fits the demos: the model that "solves" them
    module.export(tmp_path / "solved")
    # c = θ_solved − θ_pre over every parameter: θ_pre + 1·c is exactly the solved model.
    extract(aux=tmp_path / "solved", sft=tmp_path / "pre", out=tmp_path / "vector", include=["*"])
    rows = sweep(
        str(tmp_path / "pre"),
        str(tmp_path / "vector"),
        [0.0, 0.5, 1.0, 1.5],
        str(tmp_path / "sweep"),
        demos=str(data),
    )
    assert [r["scale"] for r in rows] == [0.0, 0.5, 1.0, 1.5]
    assert best_scale(rows) == 1.0
    assert all(r["merge_relative_error"] < 1e-5 for r in rows)  # float32 weights keep all of λc
    # Resume: finished scales are read back, only the new one is computed.
    saved = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    assert main([
        "sweep-scale", "--base", str(tmp_path / "pre"), "--vector", str(tmp_path / "vector"),
        "--scales", "0,0.5,0.75,1,1.5", "--demos", str(data), "--out", str(tmp_path / "sweep"),
    ]) == 0  # fmt: skip
    resumed = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    assert [r for r in resumed if r["scale"] != 0.75] == saved
    assert (tmp_path / "sweep" / "sweep.png").is_file()


@pytest.mark.sim
def test_sweep_with_downstream_finetuning_and_rollouts(tmp_path: Path) -> None:
    """Each λ: merge in memory, 2 steps of SFT + orthogonal regularization, 1 validation episode."""
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    dm = RobotDataModule(train_files=[str(data)], batch_size=4)
    export_pre_and_vector(tmp_path, dm)
    rows = sweep(
        str(tmp_path / "pre"), str(tmp_path / "vector"), [0.0, 1.0], str(tmp_path / "sweep"),
        task="Lift", episodes=1, demos=str(data), finetune_steps=2,
    )  # fmt: skip
    assert [r["episodes"] for r in rows] == [1, 1]
    assert all(
        0 <= r["success_rate"] <= 1 and len(r["ci95"]) == 2 and r["held_out_l1"] > 0 for r in rows
    )


@pytest.mark.sim
def test_the_sweep_scores_what_the_validation_loop_logs_on_the_configured_trainer(
    tmp_path: Path,
) -> None:
    """A fit config's trainer and data; the row equals `capvector validate` of θ_pre + λc."""
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    dm = RobotDataModule(train_files=[str(data)], augment=False)
    export_pre_and_vector(tmp_path, dm)
    config = tmp_path / "fit.yaml"  # evaluation seeds in the config: the sweep validates on others
    config.write_text(f"""
trainer: {{accelerator: cpu, limit_val_batches: 1, enable_progress_bar: false}}
model: {{rollout: {{videos: 0, workers: 0}}}}
data:
  train_files: [{data}]
  batch_size: 4
  augment: false
  eval_tasks: [{{task: Lift, episodes: 2, max_steps: 8}}]
""")
    (row,) = sweep(
        str(tmp_path / "pre"), str(tmp_path / "vector"), [1.0], str(tmp_path / "sweep"),
        demos=str(data), fit_configs=[str(config)],
    )  # fmt: skip
    with (tmp_path / "sweep" / "scale_1" / "version_0" / "episodes.csv").open() as f:
        assert [r["seed"] for r in csv.DictReader(f)] == ["2000000", "2000001"]
    merged = tmp_path / "merged"
    assert main(["merge", "--base", str(tmp_path / "pre"), "--vector", f"{tmp_path / 'vector'}:1",
                 "--out", str(merged)]) == 0  # fmt: skip

    def validate(*args: str) -> dict[str, float]:
        cli = run_lightning_cli([
            "validate", "--config", str(config), f"--model.pretrained={merged}",
            f"--data.val_files=[{data}]", "--trainer.logger=false",
            f"--trainer.default_root_dir={tmp_path / 'validate'}", *args,
        ])  # fmt: skip
        metrics = cli.trainer.callback_metrics  # type: ignore[attr-defined]
        return {k: float(v) for k, v in metrics.items()}

    logged = validate(
        "--data.eval_tasks=[{task: Lift, episodes: 2, max_steps: 8, start_seed: 2000000}]"
    )
    assert row["held_out_l1"] == pytest.approx(logged["val/action_l1"], rel=1e-6)
    assert (row["episodes"], row["success_rate"]) == (2, logged["val/success_rate"])
    # trainer.limit_val_batches of the config took effect: over every held-out batch, L1 differs.
    every_batch = validate("--data.eval_tasks=null", "--trainer.limit_val_batches=1.0")
    assert abs(every_batch["val/action_l1"] - row["held_out_l1"]) > 1e-4


@pytest.mark.sim
def test_a_sweep_by_rollouts_alone_keeps_the_models_own_preprocessing(tmp_path: Path) -> None:
    """No demos: a data module of validation episodes only; θ_pre's data spec drives the policy."""
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    dm = RobotDataModule(train_files=[str(data)], cameras=["agentview"])  # not the default two
    export_pre_and_vector(tmp_path, dm)
    (row,) = sweep(
        str(tmp_path / "pre"), str(tmp_path / "vector"), [0.5], str(tmp_path / "sweep"),
        task="Lift", episodes=1,
    )  # fmt: skip
    # The policy fed θ_pre's one camera (the default data spec's two would not fit the model).
    assert row["episodes"] == 1 and "held_out_l1" not in row
    with (tmp_path / "sweep" / "scale_0.5" / "version_0" / "episodes.csv").open() as f:
        assert [r["seed"] for r in csv.DictReader(f)] == ["2000000"]


def test_a_fit_config_that_merges_a_vector_itself_is_refused(tmp_path: Path) -> None:
    """sweep-scale merges θ_pre + λc itself: a merge callback in --fit-config would merge a vector a
    second time into every λ it fine-tunes, so the sweep stops before any work, naming it."""
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    dm = RobotDataModule(train_files=[str(data)], augment=False)
    export_pre_and_vector(tmp_path, dm)
    config = tmp_path / "fit.yaml"
    config.write_text(f"""
trainer:
  accelerator: cpu
  callbacks:
    - class_path: capvector.callbacks.MergeCapabilityVector
      init_args: {{vector: {tmp_path / "vector"}, scale: 1.0}}
data: {{train_files: [{data}], val_files: [{data}]}}
""")
    with pytest.raises(CapVectorError, match="MergeCapabilityVector: sweep-scale merges"):
        sweep(
            str(tmp_path / "pre"), str(tmp_path / "vector"), [1.0], str(tmp_path / "sweep"),
            fit_configs=[str(config)], finetune_steps=2,
        )  # fmt: skip
    assert not (tmp_path / "sweep").exists()
