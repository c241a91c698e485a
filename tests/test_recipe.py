"""`capvector recipe`: stages in order, outputs in one run folder, resume after an interruption."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from capvector.recipe import command_line, load_recipe

REPO = Path(__file__).resolve().parents[1]


def recipe_file(tmp_path: Path, data: Path) -> Path:
    fit = [
        "--config",
        str(REPO / "configs/debug.yaml"),
        f"--data.train_files=[{data}]",
        "--data.batch_size=4",
    ]
    stages = [
        {"name": "pretrain", "command": "fit", "args": [*fit, "--trainer.max_steps=2"]},
        {"name": "aux", "command": "fit", "args": [*fit, "--trainer.max_steps=2", "--model.pretrained=${out.pretrain.export}"]},
        {"name": "extract", "command": "extract",
         "args": ["--aux", "${out.aux.export}", "--sft", "${out.pretrain.export}", "--out", "${out.extract.dir}/vector"]},
        {"name": "downstream", "command": "fit",
         "args": [*fit, "--trainer.max_steps=4", "--model.pretrained=${out.pretrain.export}",
                  "--trainer.callbacks+=capvector.callbacks.MergeCapabilityVector",
                  "--trainer.callbacks.vector=${out.extract.dir}/vector"]},
    ]  # fmt: skip
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    return path


def capvector(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "capvector.cli", *args],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=REPO,
    )


def test_recipe_runs_resumes_and_never_redoes_a_stage(tmp_path: Path, demo_file: Path) -> None:
    recipe = recipe_file(tmp_path, demo_file)
    run_dir, stages = load_recipe(recipe)
    # An interrupted run: the downstream fit died after 2 of its 4 steps (its checkpoint exists,
    # its .done marker does not). Run the earlier stages and half of downstream by hand.
    for stage in stages[:3]:
        completed = subprocess.run(command_line(stage), capture_output=True, text=True, cwd=REPO)
        assert completed.returncode == 0, completed.stderr[-3000:]
        (stage.directory / ".done").write_text("{}")
    downstream = stages[3]
    half = command_line(downstream)
    half = [a if a != "--trainer.max_steps=4" else "--trainer.max_steps=2" for a in half]
    half += ["--trainer.callbacks.every_n_train_steps=2"]
    completed = subprocess.run(half, capture_output=True, text=True, cwd=REPO)
    assert completed.returncode == 0, completed.stderr[-3000:]
    markers = {s.name: (s.directory / ".done").stat().st_mtime_ns for s in stages[:3]}

    completed = capvector("recipe", "--config", str(recipe))
    assert completed.returncode == 0, completed.stderr[-3000:]
    out = completed.stdout
    for name in ("pretrain", "aux", "extract"):
        assert f"{name} " in out and "done earlier, skipped" in out
    assert {s.name: (s.directory / ".done").stat().st_mtime_ns for s in stages[:3]} == markers
    assert "[recipe 4/4] downstream (fit)" in out
    assert "merged before this resume; not again" in completed.stdout + completed.stderr
    assert (downstream.directory / ".done").is_file()
    assert "`Trainer.fit` stopped: `max_steps=4` reached" in completed.stdout + completed.stderr
    assert (downstream.directory / "fit" / "version_0" / "export" / "model.safetensors").is_file()


def test_recipe_errors_are_clear(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("stages: []\n")
    completed = capvector("recipe", "--config", str(bad))
    assert completed.returncode == 2 and "needs `run_dir`" in completed.stderr


@pytest.mark.parametrize("name", ["quick.yaml"])
def test_shipped_recipes_resolve(name: str) -> None:
    run_dir, stages = load_recipe(REPO / "configs/recipes" / name, ["run_dir=/tmp/x"])
    assert str(run_dir) == "/tmp/x" and all("${" not in a for s in stages for a in s.args)
