"""The CSV logger keeps a resumed fit's earlier metrics (Lightning's deletes them); videos and
figures reach the loggers people watch, read back with TensorBoard's and W&B's own readers."""

from __future__ import annotations

import csv
import json
import os
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger

from capvector.training.loggers import CSVLogger

REPO = Path(__file__).resolve().parents[1]


def rows(logger: LightningCSVLogger) -> list[dict[str, str]]:
    with open(Path(logger.log_dir) / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_second_run_in_the_same_folder_appends_with_the_earlier_columns(tmp_path: Path) -> None:
    first = CSVLogger(tmp_path, name="fit", version="version_0")
    first.log_metrics({"train/loss": 1.0}, step=0)
    first.log_metrics({"val/success_rate": 0.5}, step=1)
    first.save()
    resumed = CSVLogger(tmp_path, name="fit", version="version_0")  # a resumed fit, same folder
    resumed.log_metrics({"train/loss": 0.5, "perf/step_seconds": 0.1}, step=1)
    resumed.save()
    got = rows(resumed)
    assert [r["step"] for r in got] == ["0", "1", "1"]
    assert got[0]["train/loss"] == "1.0" and got[1]["val/success_rate"] == "0.5"
    assert got[2]["train/loss"] == "0.5" and got[2]["perf/step_seconds"] == "0.1"

    # Lightning's own logger, for contrast: the earlier rows are gone.
    lightning = LightningCSVLogger(tmp_path, name="fit", version="version_0")
    lightning.log_metrics({"train/loss": 0.25}, step=2)
    lightning.save()
    assert [r["step"] for r in rows(lightning)] == ["2"]


def wandb_records(run_dir: Path) -> list:
    """The records of an offline W&B run (its ``run-<id>.wandb`` file: a LevelDB-style log of
    ``wandb_internal_pb2.Record`` protobufs, parsed with wandb's own schema)."""
    from wandb.proto import wandb_internal_pb2

    block, header = 32768, 7
    data = next(run_dir.glob("run-*.wandb")).read_bytes()
    assert data[:4] == b":W&B", data[:7]
    records, pos, pieces = [], header, b""
    while pos + header <= len(data):
        if block - pos % block < header:  # a block's tail too short for a record: padding
            pos += block - pos % block
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos : pos + header])
        pieces += data[pos + header : pos + header + length]
        pos += header + length
        if kind in (1, 4):  # a whole record, or the last piece of one
            records.append(wandb_internal_pb2.Record.FromString(pieces))
            pieces = b""
    return records


def wandb_history(run_dir: Path) -> dict[str, list[str]]:
    """Every logged key of an offline W&B run, with its values (JSON) in logging order."""
    history: dict[str, list[str]] = {}
    for record in wandb_records(run_dir):
        if record.WhichOneof("record_type") == "history":
            for item in record.history.item:
                history.setdefault(item.key or "/".join(item.nested_key), []).append(
                    item.value_json
                )
    return history


def tensorboard_events(log_dir: Path) -> Any:
    """TensorBoard's own reader over every event file of a run folder."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(log_dir), size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    return events


def test_videos_and_figures_reach_tensorboard_and_wandb(tmp_path: Path) -> None:
    import imageio.v2 as imageio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from lightning.pytorch.loggers import TensorBoardLogger, WandbLogger

    from capvector.eval.video import write_video
    from capvector.training.loggers import log_figure, log_video

    frames = [np.full((32, 48, 3), 40 * i, np.uint8) for i in range(6)]
    video = write_video(frames, tmp_path / "Lift_Panda_seed7.mp4")
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1], [0, 1])
    fig.savefig(tmp_path / "figure.png")
    plt.close(fig)
    tensorboard = TensorBoardLogger(tmp_path, name="tb")
    wandb = WandbLogger(save_dir=tmp_path, offline=True, project="capvector-test")
    loggers = [CSVLogger(tmp_path, name="csv"), tensorboard, wandb]
    log_video(loggers, "val/video/Lift_Panda_seed7", frames, video, step=3)
    log_figure(loggers, "report/figure", tmp_path / "figure.png", step=3)
    tensorboard.finalize("success")
    wandb.experiment.finish()
    import wandb as wandb_sdk

    wandb_sdk.teardown()  # its service, which later processes would otherwise share

    events = tensorboard_events(Path(tensorboard.log_dir))
    (gif,) = events.Images("val/video/Lift_Panda_seed7")
    played = imageio.mimread(gif.encoded_image_string, format="GIF")
    assert gif.step == 3 and len(played) == 6 and played[0].shape[:2] == (32, 48)
    (png,) = events.Images("report/figure")
    assert imageio.imread(png.encoded_image_string).shape[:2] == (200, 300)

    (run,) = (tmp_path / "wandb").glob("offline-run-*")
    history = wandb_history(run)
    (videos,) = history["val/video/Lift_Panda_seed7/videos"]
    stored = run / "files" / json.loads(videos)[0]["path"]
    assert stored.read_bytes() == video.read_bytes()  # the mp4 itself
    (images,) = history["report/figure/filenames"]
    assert imageio.imread(run / "files" / json.loads(images)[0]).shape[:2] == (200, 300)
    assert history["trainer/global_step"] == ["3", "3"]


@pytest.mark.sim
@pytest.mark.slow
def test_a_recipe_fit_keeps_the_configs_loggers_and_they_show_videos_and_the_report(
    tmp_path: Path, demo_file: Path
) -> None:
    """A fit stage whose config logs to TensorBoard and (offline) W&B: the recipe's CSV logger
    joins them instead of replacing them; the rollout video and the report's figure reach both
    runs; metrics.csv, checkpoints and episodes stay where the recipe and the report read them."""
    loggers = tmp_path / "loggers.yaml"
    tensorboard = {"save_dir": str(tmp_path / "tb"), "name": "fit", "version": "run"}
    wandb = {"save_dir": str(tmp_path), "offline": True, "project": "capvector-test", "id": "fit0"}
    loggers.write_text(json.dumps({"trainer": {"logger": [
        {"class_path": "lightning.pytorch.loggers.TensorBoardLogger", "init_args": tensorboard},
        {"class_path": "lightning.pytorch.loggers.WandbLogger", "init_args": wandb},
    ]}}))  # fmt: skip
    fit = [
        "--config", str(REPO / "configs/debug.yaml"), "--config", str(loggers),
        f"--data.train_files=[{demo_file}]", "--data.batch_size=4", "--trainer.max_steps=2",
        "--trainer.val_check_interval=2", "--trainer.num_sanity_val_steps=0",
        "--trainer.log_every_n_steps=1", "--trainer.enable_progress_bar=false",
        "--data.eval_tasks=[{task: Lift, episodes: 1, max_steps: 16}]", "--model.rollout.videos=1",
    ]  # fmt: skip
    report = ["--run-dir", "${run_dir}", "--arm", "sft", "fit", "start", "--out"]
    to_wandb = [f"--logger.{k}={v}" for k, v in wandb.items()]
    stages = [
        {"name": "fit", "command": "fit", "args": fit},
        {"name": "start", "command": "evaluate", "args": [
            "--ckpt", "${out.fit.export}", "--episodes", "1", "--videos", "0",
            "--json", "${out.start.dir}/results.json"]},
        {"name": "report_tb", "command": "report", "args": [
            *report, "${out.report_tb.dir}", "--logger", "TensorBoardLogger",
            *[f"--logger.{k}={v}" for k, v in tensorboard.items()]]},
        {"name": "report_wandb", "command": "report", "args": [
            *report, "${out.report_wandb.dir}", "--logger", "WandbLogger", *to_wandb]},
    ]  # fmt: skip
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    # The stages' W&B runs, not a W&B service this test process may run (WANDB_SERVICE).
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    done = subprocess.run([sys.executable, "-m", "capvector.cli", "recipe", "--config", str(recipe)],
                          capture_output=True, text=True, cwd=REPO, env=env)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]

    # The recipe's own record, where it reads it: metrics, episodes, checkpoint, the mp4.
    version = tmp_path / "run/fit/fit/version_0"
    assert "val/success_rate" in (version / "metrics.csv").read_text().splitlines()[0]
    assert (version / "episodes.csv").is_file() and (version / "checkpoints/last.ckpt").is_file()
    (video,) = (version / "videos").rglob("*.mp4")
    key = f"val/video/{video.stem}"

    events = tensorboard_events(tmp_path / "tb/fit/run")
    assert {"train/loss", "val/success_rate"} <= set(events.Tags()["scalars"])
    assert {key, "report/success_vs_steps"} <= set(events.Tags()["images"])

    history: dict[str, list[str]] = {}
    for run in (tmp_path / "wandb").glob("offline-run-*-fit0"):  # the fit, then the report
        for name, values in wandb_history(run).items():
            history.setdefault(name, []).extend(values)
    assert {"train/loss", "val/success_rate", f"{key}/videos"} <= history.keys()
    assert "report/success_vs_steps/filenames" in history


def test_report_sweep_and_inspect_show_their_plot_in_the_given_logger(tmp_path: Path) -> None:
    from capvector.cli import main
    from capvector.data.datamodule import RobotDataModule
    from capvector.module import VLAModule
    from capvector.vectors import extract
    from conftest import write_demo_file
    from test_report import write_evaluation, write_fit

    def logger(name: str) -> list[str]:
        return ["--logger", "TensorBoardLogger", f"--logger.save_dir={tmp_path / 'tb'}",
                f"--logger.name={name}"]  # fmt: skip

    run = tmp_path / "run"
    write_evaluation(run, "start", 3, 30)
    write_fit(run, "fit_s0", {2: 0.2, 4: 0.6}, {2: 0.30, 4: 0.20})
    report = ["report", "--run-dir", str(run), "--arm", "sft", "fit_s*", "start"]
    assert main([*report, "--out", str(tmp_path / "report"), *logger("report")]) == 0

    data = write_demo_file(tmp_path / "demos.hdf5")
    module = VLAModule(data_spec=RobotDataModule(train_files=[str(data)], batch_size=4).spec)
    module.export(tmp_path / "pre")
    with torch.no_grad():
        for parameter in module.backbone.parameters():
            parameter.add_(0.01)
    module.export(tmp_path / "moved")
    extract(aux=tmp_path / "moved", sft=tmp_path / "pre", out=tmp_path / "vector", include=["*"])
    sweep = ["sweep-scale", "--base", str(tmp_path / "pre"), "--vector", str(tmp_path / "vector"),
             "--scales", "0,1", "--demos", str(data), "--out", str(tmp_path / "sweep")]  # fmt: skip
    assert main([*sweep, *logger("sweep")]) == 0
    inspect = ["inspect", str(tmp_path / "vector"), "--plot", str(tmp_path / "norms.png")]
    assert main([*inspect, *logger("inspect")]) == 0

    for name, tag in [("report", "report/success_vs_steps"), ("sweep", "sweep/scale"),
                      ("inspect", "inspect/norms_by_layer")]:  # fmt: skip
        assert tensorboard_events(tmp_path / "tb" / name / "version_0").Tags()["images"] == [tag]


def mlflow_store_ok(root: Path) -> None:
    """The store root holds only what MLflow's file store makes (experiment folders and its
    trash): anything else makes MLflow report a malformed experiment."""
    for entry in root.iterdir():
        assert entry.name == ".trash" or (entry / "meta.yaml").is_file(), entry


@pytest.mark.sim
def test_a_fit_with_rollouts_logs_to_mlflow_tensorboard_and_wandb_at_one_step(
    tmp_path: Path, demo_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fit whose first logger is MLflow on a file store (MLflow >= 3 refuses it unless
    MLFLOW_ALLOW_FILE_STORE=true, which the user sets, not capvector), with TensorBoard and W&B
    beside it: the metrics are stored, the rollout video and episodes.csv are MLflow artifacts
    and nothing lands in the store root; each logger shows the video at the step of the
    validation's success rate."""
    from mlflow.tracking import MlflowClient

    store = tmp_path / "mlruns"
    loggers = tmp_path / "loggers.yaml"
    mlflow = {"experiment_name": "capvector-test", "tracking_uri": f"file://{store}"}
    tensorboard = {"save_dir": str(tmp_path / "tb"), "name": "fit", "version": "run"}
    wandb = {"save_dir": str(tmp_path), "offline": True, "project": "capvector-test", "id": "fit0"}
    loggers.write_text(json.dumps({"trainer": {"logger": [
        {"class_path": "lightning.pytorch.loggers.MLFlowLogger", "init_args": mlflow},
        {"class_path": "lightning.pytorch.loggers.TensorBoardLogger", "init_args": tensorboard},
        {"class_path": "lightning.pytorch.loggers.WandbLogger", "init_args": wandb},
    ]}}))  # fmt: skip
    fit = [
        "fit", "--config", str(REPO / "configs/debug.yaml"), "--config", str(loggers),
        f"--data.train_files=[{demo_file}]", "--data.batch_size=4", "--trainer.max_steps=2",
        "--trainer.val_check_interval=2", "--trainer.num_sanity_val_steps=0",
        "--trainer.log_every_n_steps=1", "--trainer.enable_progress_bar=false",
        f"--trainer.default_root_dir={tmp_path / 'root'}",
        "--data.eval_tasks=[{task: Lift, episodes: 1, max_steps: 16}]", "--model.rollout.videos=1",
    ]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith(("WANDB_", "MLFLOW_"))}
    env["MLFLOW_ALLOW_FILE_STORE"] = "true"
    done = subprocess.run([sys.executable, "-m", "capvector.cli", *fit], capture_output=True,
                          text=True, cwd=tmp_path, env=env)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]

    mlflow_store_ok(store)
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # for this process's reader too
    client = MlflowClient(tracking_uri=f"file://{store}")
    (experiment,) = [
        e for e in client.search_experiments() if e.name == "capvector-test"
    ]  # fmt: skip
    (run,) = client.search_runs([experiment.experiment_id])
    history = client.get_metric_history(run.info.run_id, "val/success_rate")
    by_task = client.get_metric_history(run.info.run_id, "val/success_rate_by_task/Lift")
    assert [m.step for m in history] == [m.step for m in by_task] == [1]  # 2 optimizer steps done
    assert "train/loss" in run.data.metrics
    artifacts = Path(run.info.artifact_uri.removeprefix("file://"))
    (video,) = artifacts.rglob("*.mp4")
    assert video.parent.name == "step000001"
    episodes = (artifacts / "episodes.csv").read_text().splitlines()
    assert episodes[0] == "step,task,seed,success,stack,renderer" and len(episodes) == 2
    # The run's own files beside Lightning's checkpoints, inside the run's folder.
    folder = store / experiment.experiment_id / run.info.run_id
    assert {"checkpoints", "export", "videos", "episodes.csv"} <= {p.name for p in folder.iterdir()}
    key = f"val/video/{video.stem}"

    events = tensorboard_events(tmp_path / "tb/fit/run")
    (success,) = events.Scalars("val/success_rate")
    (gif,) = events.Images(key)
    assert gif.step == success.step == 1

    steps: dict[str, str] = {}
    (wandb_run,) = (tmp_path / "wandb").glob("offline-run-*-fit0")
    for record in wandb_records(wandb_run):
        if record.WhichOneof("record_type") == "history":
            items = {
                item.key or "/".join(item.nested_key): item.value_json
                for item in record.history.item
            }
            for name in ("val/success_rate", f"{key}/videos"):
                if name in items:
                    steps[name] = items["trainer/global_step"]
    assert steps == {"val/success_rate": "1", f"{key}/videos": "1"}
