"""The first command on a fresh checkout: ``capvector fit --config configs/debug.yaml`` records the
demos it names (``data.generate``), then trains and saves a checkpoint, with nothing else present."""

from __future__ import annotations

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
