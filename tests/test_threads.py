"""Fits started by hand share the CPUs: the registry of running fits and `ShareCores`."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L
import pytest
import torch

from capvector.cli import main
from capvector.io.cpus import usable_cpus
from capvector.training import threads
from capvector.training.threads import fair_threads, running_fits
from conftest import write_demo_file

HOLD = (
    "import sys; from pathlib import Path; from capvector.training.threads import RunningFit;"
    "fit = RunningFit(Path(sys.argv[1])).open(); print('ready', flush=True); sys.stdin.read();"
    "fit.close()"
)


def other_fit(registry: Path) -> subprocess.Popen:
    """Another process registered as a running fit until its stdin closes."""
    process = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(registry)], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )
    assert process.stdout is not None and process.stdout.readline() == b"ready\n"
    return process


def test_running_fits_are_the_live_entries(tmp_path: Path) -> None:
    assert running_fits(tmp_path / "none") == 0
    first, second = other_fit(tmp_path), other_fit(tmp_path)
    assert running_fits(tmp_path) == 2
    assert fair_threads(tmp_path) == max(1, usable_cpus() // 2)
    os.kill(second.pid, signal.SIGKILL)  # its entry stays behind, unlocked
    second.wait()
    assert running_fits(tmp_path) == 1
    assert [p.name for p in tmp_path.iterdir()] == [f"{first.pid}.lock"]  # the dead one removed
    first.communicate(b"")  # ends normally, removing its entry
    assert running_fits(tmp_path) == 0 and not list(tmp_path.iterdir())


threads_seen: list[int] = []


class ThreadProbe(L.Callback):
    def on_train_batch_start(self, *args: object) -> None:
        threads_seen.append(torch.get_num_threads())


def test_a_fit_started_by_hand_takes_its_share_of_the_cores(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`capvector fit` without OMP_NUM_THREADS: all usable CPUs alone, half beside another fit,
    never more than the process had; torch's threads restored after it."""
    for variable in ("OMP_NUM_THREADS", "CAPVECTOR_CORES"):
        monkeypatch.delenv(variable, raising=False)
    monkeypatch.setattr(threads, "REGISTRY", tmp_path / "registry")
    data = write_demo_file(tmp_path / "demos.hdf5")
    args = [
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=2", "--trainer.logger=false",
        "--trainer.enable_progress_bar=false", "--trainer.enable_checkpointing=false",
        f"--trainer.default_root_dir={tmp_path}", "--model.backbone=openvla-oft-tiny",
        f"--data.train_files=[{data}]", "--data.batch_size=2",
        f"--trainer.callbacks+={__name__}.ThreadProbe",
    ]  # fmt: skip
    before = torch.get_num_threads()
    torch.set_num_threads(usable_cpus())  # a fresh process's torch default: one thread per core
    threads_seen.clear()
    assert main(args) == 0
    assert threads_seen == [usable_cpus()] * 2
    assert torch.get_num_threads() == usable_cpus()  # restored
    other = other_fit(tmp_path / "registry")
    threads_seen.clear()
    assert main(args) == 0
    assert threads_seen == [max(1, usable_cpus() // 2)] * 2
    torch.set_num_threads(1)
    threads_seen.clear()
    assert main(args) == 0  # a process that chose fewer threads keeps them
    other.communicate(b"")
    assert threads_seen == [1, 1]
    torch.set_num_threads(before)
