"""A fit refused after Lightning's ``setup`` hooks (here in ``configure_model``) is one line, exit
code 2, and leaves no run folder: the config is saved once every check has passed."""

from __future__ import annotations

from pathlib import Path

import pytest

from capvector.cli import main
from conftest import write_demo_file


def test_a_fit_refused_in_configure_model_leaves_no_run_folder(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(10, 8))
    out = tmp_path / "out"
    code = main(
        [
            "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=1",
            f"--trainer.default_root_dir={out}", "--model.backbone=openvla-oft-tiny",
            f"--data.train_files=[{data}]", "--data.batch_size=4",
            "--model.frozen_dtype=bfloat16",  # refused: trainer.precision is 32-true
        ]
    )  # fmt: skip
    errors = [line for line in capfd.readouterr().err.splitlines() if "error" in line]
    assert code == 2
    assert len(errors) == 1 and "needs trainer.precision: bf16-mixed" in errors[0], errors
    assert not out.exists(), sorted(out.rglob("*"))
