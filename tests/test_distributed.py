"""2 CPU processes (gloo) under DDP and FSDP2 (ModelParallelStrategy) against one process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from conftest import write_demo_file

SCRIPT = Path(__file__).with_name("distributed_fit.py")
pytestmark = pytest.mark.distributed


def run(out: Path, data: Path, *args: str) -> list[float]:
    result = subprocess.run(
        [sys.executable, str(SCRIPT), "--data", str(data), "--out", str(out), *args],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads((out / "losses.json").read_text())


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_demo_file(tmp_path_factory.mktemp("data") / "demos.hdf5", lengths=(20, 20))


@pytest.fixture(scope="module")
def single(tmp_path_factory: pytest.TempPathFactory, data: Path) -> tuple[list[float], Path]:
    out = tmp_path_factory.mktemp("single")
    return run(out, data, "--devices", "1"), out


@pytest.mark.parametrize("strategy", ["ddp", "fsdp2"])
def test_two_processes_match_one_on_the_same_global_batch(
    strategy: str, tmp_path: Path, data: Path, single: tuple[list[float], Path]
) -> None:
    losses, out = run(tmp_path, data, "--devices", "2", "--strategy", strategy), tmp_path
    reference, reference_out = single
    assert len(losses) == len(reference) == 4
    torch.testing.assert_close(torch.tensor(losses), torch.tensor(reference), rtol=1e-5, atol=1e-6)
    ours = load_file(out / "export" / "model.safetensors")
    theirs = load_file(reference_out / "export" / "model.safetensors")
    assert ours.keys() == theirs.keys()
    assert not any("lora_" in k or "base_layer" in k for k in ours)  # gathered and merged
    for key in theirs:
        torch.testing.assert_close(ours[key], theirs[key], rtol=1e-4, atol=1e-5, msg=key)


def test_activation_checkpointing_changes_nothing_but_memory(
    tmp_path: Path, data: Path, single: tuple[list[float], Path]
) -> None:
    losses = run(tmp_path, data, "--devices", "1", "--activation-checkpointing")
    torch.testing.assert_close(torch.tensor(losses), torch.tensor(single[0]), rtol=1e-6, atol=1e-7)
