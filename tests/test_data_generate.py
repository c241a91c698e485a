"""The first command on a fresh checkout: ``capvector fit --config configs/debug.yaml`` records the
demos it names (``data.generate``), then trains and saves a checkpoint, with nothing else present."""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import pytest

from capvector.cli import main

DEBUG = Path(__file__).parents[1] / "configs" / "debug.yaml"


@pytest.mark.sim
def test_debug_config_on_a_fresh_checkout_records_its_demos_trains_and_checkpoints(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # the config's relative data/ and runs/, as in a fresh checkout
    # Only smaller: 2 episodes, 2 steps, no rollout validation.
    code = main(
        [
            "fit", "--config", str(DEBUG), "--data.generate.episodes=2", "--data.eval_tasks=null",
            "--trainer.max_steps=2", "--trainer.enable_progress_bar=false",
        ]
    )  # fmt: skip
    assert code == 0
    with h5py.File(tmp_path / "data" / "demos" / "lift.hdf5", "r") as f:
        assert sorted(f["data"]) == ["demo_0", "demo_1"]
        assert f["data"].attrs["env_args"]  # as `capvector demos` writes it
    run = tmp_path / "runs" / "debug" / "fit" / "version_0"
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert (run / "export" / "model.safetensors").is_file()


@pytest.mark.parametrize(
    ("arg", "message"),
    [
        ("--model.backbone=openvla-oft-tinyy", r"unknown backbone preset 'openvla-oft-tinyy'"),
        ("--trainer.logger.init_args.save_dir=a_file/logs", r"cannot write into the logger's"),
        ("--trainer.default_root_dir=a_file/runs", r"cannot write into trainer.default_root_dir"),
        ("--data.generate.episodes=0", r"data.generate could not record .*at least 1, got 0"),
    ],
)
def test_bad_input_is_refused_before_the_recording(
    arg: str,
    message: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.chdir(tmp_path)
    Path("a_file").write_text("not a folder")
    code = main(["fit", "--config", str(DEBUG), "--data.generate.episodes=1", arg])
    assert code == 2
    assert re.search(message, capfd.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]  # nothing recorded, no run
