"""MuJoCo evaluation as Lightning's validation loop, and `capvector evaluate`."""

from __future__ import annotations

import csv
import json
import re
from importlib.metadata import version as installed
from pathlib import Path

import pytest

from capvector.cli import main
from capvector.data.datamodule import RobotDataModule
from capvector.data.episodes import EpisodeDataset, EpisodeSampler, EvalTask, eval_task
from capvector.data.hdf5 import DatasetError
from capvector.errors import CapVectorError
from capvector.eval.results import wilson_interval
from conftest import launch_fit_script

REPO = Path(__file__).resolve().parents[1]


def test_episode_sampler_evens_out_ranks_without_counting_twice() -> None:
    dataset = EpisodeDataset([EvalTask("Lift", episodes=3), EvalTask("Stack", episodes=2)])
    per_rank = [list(EpisodeSampler(dataset, num_replicas=2, rank=r)) for r in range(2)]
    assert [len(p) for p in per_rank] == [3, 3]  # equal step counts keep collectives in line
    items = [dataset[i] for p in per_rank for i in p]
    counted = sorted((item.spec.task, item.spec.seed) for item in items if item.counted)
    assert counted == sorted((s.task, s.seed) for s in dataset.specs)  # each episode exactly once
    assert sum(not item.counted for item in items) == 1
    assert all(s.seed >= 1_000_000 for s in dataset.specs)  # disjoint from demo seeds


def test_eval_tasks_entries_old_and_new_find_their_suite_by_name() -> None:
    """One entry type for every suite (``EvalTask``: task set, episodes, suite, options); the flat
    entries configs and checkpoints hold from before the registry give the same episodes."""
    robosuite = EvalTask("Lift", 3, "robosuite", {"robot": "Sawyer", "start_seed": 5})
    saved = {"task": "Lift", "episodes": 3, "robot": "Sawyer", "start_seed": 5, "max_steps": None,
             "gripper": None, "variant": None}  # fmt: skip  # an old checkpoint's hparams
    flat = {"task": "Lift", "episodes": 3, "robot": "Sawyer", "start_seed": 5}
    libero = EvalTask("libero_spatial", 2, "libero", {"tasks": [1, 4]})
    old_libero = {"suite": "libero_spatial", "tasks": [1, 4], "trials": 2}
    for new, *olds in [(robosuite, saved, flat), (libero, old_libero)]:
        for old in olds:
            entry = eval_task(old)
            assert entry.suite == new.suite and entry.task == new.task, old
            assert entry.specs() == new.specs(), old
    assert [s.task for s in libero.specs()] == ["libero_spatial/1"] * 2 + ["libero_spatial/4"] * 2
    # an option the suite does not take is one line naming it and the ones it does
    with pytest.raises(CapVectorError, match=r"tasks does not apply to eval task Lift .*robot"):
        eval_task({"task": "Lift", "tasks": [0]}).specs()
    with pytest.raises(
        CapVectorError, match=r"unknown task or task set 'Lfit' \(did you mean Lift"
    ):
        eval_task({"task": "Lfit"})


def test_a_data_module_of_rollouts_alone_validates_without_training_data(demo_file: Path) -> None:
    """What `capvector validate --model.pretrained P --data.eval_tasks ...` and a sweep by rollouts
    use: no training data, so no data spec (the model keeps the export's) and no training."""
    dm = RobotDataModule(eval_tasks=[EvalTask("Lift", episodes=2)])
    assert dm.spec is None
    (batch,) = list(dm.val_dataloader())
    assert [item.spec.seed for item in batch] == [1_000_000, 1_000_001]
    with pytest.raises(DatasetError, match="training needs data.train_files"):
        dm.train_dataloader()
    for held_out in ({}, {"val_files": [str(demo_file)]}):  # held-out L1 needs training statistics
        with pytest.raises(DatasetError, match="only rollouts .*validate without training data"):
            RobotDataModule(**held_out)


def test_wilson_interval() -> None:
    low, high = wilson_interval(0, 20)
    assert low == 0 and 0.1 < high < 0.2
    low, high = wilson_interval(10, 20)
    assert low < 0.5 < high


def test_progress_lines_come_once_a_while_and_at_the_end() -> None:
    """A line once ``every`` seconds have passed since the last one (0: after every episode),
    with the time left at the pace so far; always one at the end."""
    from capvector.eval.rollout import ProgressLines

    label = "rollout validation at step 8"
    written: dict[float, list[str]] = {}
    for every in (0.0, 3600.0):
        lines = written[every] = []
        progress = ProgressLines(3, label, lines.append, every=every)
        for success in (True, False, True):
            progress.update(success)
    assert len(written[0.0]) == 3 and len(written[3600.0]) == 1
    assert re.fullmatch(rf"{label}: 1/3 episodes, 1 succeeded, \d+ s, about \d+ s left",
                        written[0.0][0])  # fmt: skip
    for lines in written.values():
        assert re.fullmatch(rf"{label}: 3/3 episodes, 2 succeeded, \d+ s", lines[-1])


@pytest.mark.sim
def test_fit_runs_the_rollout_validation_loop(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    demos = tmp_path / "lift.hdf5"
    assert (
        main(
            [
                "demos",
                "--task",
                "Lift",
                "--episodes",
                "2",
                "--image-size",
                "64",
                "--seed",
                "10000",
                "--out",
                str(demos),
            ]
        )
        == 0
    )
    main([
        "fit", "--config", str(REPO / "configs/debug.yaml"), f"--data.train_files=[{demos}]",
        "--trainer.max_steps=2", "--trainer.val_check_interval=2", "--trainer.num_sanity_val_steps=0",
        "--data.eval_tasks=[{task: Lift, episodes: 2, max_steps: 16}]", "--model.rollout.videos=1",
        f"--trainer.default_root_dir={tmp_path}", f"--trainer.logger.init_args.save_dir={tmp_path}",
        "--trainer.enable_progress_bar=false", "--trainer.log_every_n_steps=1",
    ])  # fmt: skip
    version = tmp_path / "fit" / "version_0"
    header = (version / "metrics.csv").read_text().splitlines()[0]
    assert (
        "val/success_rate" in header
        and "val/success_rate_by_task/Lift" in header
        and "val/episodes" in header
    )
    assert len(list((version / "videos").rglob("*.mp4"))) == 1
    # Per-episode outcomes beside the metrics: the logged rate is their mean.
    with (version / "episodes.csv").open() as f:
        episodes = list(csv.DictReader(f))
    assert [(e["step"], e["task"], e["seed"]) for e in episodes] == [
        ("2", "Lift", "1000000"),
        ("2", "Lift", "1000001"),
    ]
    # and which simulator made them (capvector.envs.base.Suite.provenance)
    assert {(e["stack"], e["renderer"]) for e in episodes} == {
        (f"robosuite {installed('robosuite')}, MuJoCo {installed('mujoco')}", "MuJoCo")
    }
    with (version / "metrics.csv").open() as f:
        rate = next(
            float(r["val/success_rate"]) for r in csv.DictReader(f) if r["val/success_rate"]
        )
    assert rate == sum(int(e["success"]) for e in episodes) / 2
    # The whole validation is one step (Lightning's bar sits at 0/1): its progress is logged.
    succeeded = sum(int(e["success"]) for e in episodes)
    progress = [m for m in caplog.messages if m.startswith("rollout validation")]
    assert len(progress) == 1  # 2 episodes in seconds: only the final line
    assert re.fullmatch(rf"rollout validation at step 2: 2/2 episodes, {succeeded} succeeded, \d+ s",
                        progress[0])  # fmt: skip
    ckpt = next((version / "checkpoints").glob("*.ckpt"))
    table = tmp_path / "eval.json"
    assert main(["evaluate", "--ckpt", str(ckpt), "--episodes", "2", "--json", str(table)]) == 0
    (row,) = json.loads(table.read_text())
    assert row["task"] == "Lift" and row["episodes"] == 2 and 0 <= row["success_rate"] <= 1


@pytest.mark.sim
@pytest.mark.distributed
def test_ddp_validation_counts_each_episode_once(tmp_path: Path, demo_file: Path) -> None:
    """3 episodes over 2 ranks: the padded rank runs an uncounted episode; rates match 1 process."""
    results = []
    for devices in ("1", "2"):
        out = tmp_path / devices
        args = ["--devices", devices, "--strategy", "ddp" if devices == "2" else "auto"]
        launch_fit_script(out, demo_file, "--validate-episodes", "3", *args)
        results.append(json.loads((out / "validate.json").read_text()))
    single, ddp = results
    assert single["val/episodes"] == ddp["val/episodes"] == 3
    assert single["val/success_rate"] == ddp["val/success_rate"]

    # Each rank logs its own episodes: together, every episode once, as in one process.
    def outcomes(files: list[Path]) -> list[tuple[str, str]]:
        rows = [r for f in files for r in csv.DictReader(f.open())]
        return sorted((r["seed"], r["success"]) for r in rows)

    ddp_logs = sorted((tmp_path / "2").rglob("episodes*.csv"))
    assert [f.name for f in ddp_logs] == ["episodes.csv", "episodes_rank1.csv"]
    assert outcomes(ddp_logs) == outcomes(list((tmp_path / "1").rglob("episodes.csv")))
    assert len(outcomes(ddp_logs)) == 3
