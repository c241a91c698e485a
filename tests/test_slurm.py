"""`launcher: slurm` on a real one-node SLURM cluster (slurmctld, slurmd, munge) that
tools/slurm/single_node.sh starts in a temporary folder. Skipped, with the reason, where SLURM is
not installed or cannot run (it needs root); `make test` installs it where apt-get can."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from test_launchers import REPO, check_two_stage_run, fit_stage, two_stage_recipe, write_recipe

SCRIPT = REPO / "tools/slurm/single_node.sh"


@pytest.fixture(scope="module")
def slurm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The cluster's folder; ``SLURM_CONF`` points the SLURM commands (and submitit) at it."""
    folder = tmp_path_factory.mktemp("slurm")
    started = subprocess.run([SCRIPT, "start", folder], capture_output=True, text=True)
    if started.returncode == 3:  # not installed, or not root
        pytest.skip(started.stderr.strip())
    assert started.returncode == 0, started.stderr
    try:
        with pytest.MonkeyPatch.context() as env:
            env.setenv("SLURM_CONF", str(folder / "slurm.conf"))
            yield folder
    finally:
        subprocess.run([SCRIPT, "stop", folder], check=True)


def test_a_recipe_runs_on_a_slurm_cluster(
    slurm: Path, tmp_path: Path, demo_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = two_stage_recipe(tmp_path, demo_file, "slurm")
    check_two_stage_run(recipe, "slurm", capsys)
    # The jobs were SLURM's: submitit's batch script asked for the stage's time limit.
    script = next((tmp_path / "run/fit/submitit").glob("*_submission.sh")).read_text()
    assert "#SBATCH --time=10" in script and "#SBATCH --signal=USR2@90" in script


def slurm_command(*args: str) -> str:
    return subprocess.run(args, capture_output=True, text=True, check=True).stdout


@pytest.mark.slow
def test_a_preempted_fit_requeues_and_resumes_from_its_checkpoint(
    slurm: Path, tmp_path: Path, demo_file: Path
) -> None:
    """SLURM's warning signal (time limit, or preemption) reaches the fit: at the end of that
    step it saves a checkpoint and requeues the job, whose second run resumes from it and
    finishes the stage."""
    steps = 150
    recipe = write_recipe(tmp_path / "recipe.yaml", [fit_stage(demo_file, steps=steps)],
                          launcher="slurm", resources={"time_min": 10})  # fmt: skip
    driver = subprocess.Popen(
        [sys.executable, "-m", "capvector.cli", "recipe", "--config", str(recipe)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
    )  # fmt: skip
    stage = tmp_path / "run/fit"
    metrics = stage / "fit/version_0/metrics.csv"
    deadline = time.time() + 600
    while not (metrics.is_file() and len(metrics.read_text().splitlines()) > 5):
        assert driver.poll() is None and time.time() < deadline, driver.stdout.read()  # type: ignore[union-attr]
        time.sleep(0.5)
    job = slurm_command("squeue", "-h", "-o", "%i").split()[0]
    slurm_command("scancel", "--signal=USR2", job)
    while not (stage / "hpc_ckpt_1.ckpt").is_file() or "PD" not in slurm_command(
        "squeue", "-h", "-j", job, "-o", "%t"
    ):
        assert time.time() < deadline
        time.sleep(0.5)
    slurm_command("scontrol", "update", f"JobId={job}", "StartTime=now")  # SLURM holds it 2 min
    out, _ = driver.communicate(timeout=600)
    assert driver.returncode == 0, out[-3000:]
    assert "[recipe 1/1] fit (fit) finished" in out
    log = (stage / "log.txt").read_text()
    # Saved at the end of the step the signal landed in (RequeueAtStepEnd), not mid-step.
    assert f"saved {stage / 'hpc_ckpt_1.ckpt'}; requeued SLURM job {job}" in log
    assert "capvector fit: stopped by SIGTERM" in log
    assert f"Restored all states from the checkpoint at {stage / 'hpc_ckpt_1.ckpt'}" in log
    with metrics.open() as f:
        trained = {int(row["step"]) for row in csv.DictReader(f)}
    assert trained == set(range(steps))  # both runs' steps, in one metrics.csv, none shifted
    marker = json.loads((stage / ".done").read_text())
    assert marker["job"] == job and (stage / "fit/version_0/export/model.safetensors").is_file()


@pytest.mark.slow
def test_a_recipe_run_again_waits_for_its_job_still_running(
    slurm: Path, tmp_path: Path, demo_file: Path
) -> None:
    """The recipe (on a login node) can stop while its jobs go on; run again, it waits for a
    stage's job that is still running instead of submitting a second into the same folder."""
    recipe = write_recipe(tmp_path / "recipe.yaml", [fit_stage(demo_file, steps=150)],
                          launcher="slurm", resources={"time_min": 10})  # fmt: skip
    command = [sys.executable, "-m", "capvector.cli", "recipe", "--config", str(recipe)]
    first = subprocess.Popen(command, stdout=subprocess.DEVNULL, cwd=REPO)
    stage = tmp_path / "run/fit"
    metrics = stage / "fit/version_0/metrics.csv"
    deadline = time.time() + 600
    while not (metrics.is_file() and len(metrics.read_text().splitlines()) > 5):
        assert first.poll() is None and time.time() < deadline
        time.sleep(0.5)
    first.kill()  # the recipe stops; its job does not
    first.wait()
    (job,) = slurm_command("squeue", "-h", "-o", "%i").split()
    again = subprocess.run(command, capture_output=True, text=True, cwd=REPO, timeout=600)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert f"SLURM job {job} from an earlier run is still queued or running" in again.stdout
    assert [p.name for p in (stage / "submitit").glob("*_submitted.pkl")] == [
        f"{job}_submitted.pkl"
    ]
    assert json.loads((stage / ".done").read_text())["job"] == job


def start_fit_recipe(tmp_path: Path, demo_file: Path, **popen: Any) -> tuple[Any, str]:
    """A recipe of one 300-step fit on SLURM, started; returns it once the fit is training, and
    the fit's job id."""
    recipe = write_recipe(tmp_path / "recipe.yaml", [fit_stage(demo_file, steps=300)],
                          launcher="slurm", resources={"time_min": 10})  # fmt: skip
    driver = subprocess.Popen(
        [sys.executable, "-m", "capvector.cli", "recipe", "--config", str(recipe)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO, **popen,
    )  # fmt: skip
    metrics = tmp_path / "run/fit/fit/version_0/metrics.csv"
    deadline = time.time() + 600
    while not (metrics.is_file() and len(metrics.read_text().splitlines()) > 5):
        assert driver.poll() is None and time.time() < deadline, driver.stdout.read()  # type: ignore[union-attr]
        time.sleep(0.5)
    (job,) = slurm_command("squeue", "-h", "-o", "%i").split()
    return driver, job


@pytest.mark.slow
def test_a_cancelled_job_fails_its_stage_with_its_state(
    slurm: Path, tmp_path: Path, demo_file: Path
) -> None:
    """The one-node cluster has no accounting (no sacct), as many small ones: submitit would
    never learn that the job ended; the recipe asks squeue and fails the stage."""
    from capvector.workflows.launchers import FORGOTTEN, slurm_state

    assert subprocess.run(["sacct"], capture_output=True).returncode != 0  # no accounting here
    driver, job = start_fit_recipe(tmp_path, demo_file)
    assert slurm_state(job) == "RUNNING"
    slurm_command("scancel", job)
    out, _ = driver.communicate(timeout=120)  # noticed in seconds, not never
    assert driver.returncode == 2, out[-3000:]
    assert f"SLURM job {job} ended (CANCELLED) without a result" in out
    assert "stage(s) ['fit'] failed" in out
    assert slurm_state("999999") == FORGOTTEN


@pytest.mark.slow
def test_a_backgrounded_recipe_stops_on_sigint_and_names_its_running_job(
    slurm: Path, tmp_path: Path, demo_file: Path
) -> None:
    """Started as a script's `cmd &` starts it (SIGINT ignored), the recipe still stops on
    SIGINT; its job goes on, named with the state SLURM gives it."""
    driver, job = start_fit_recipe(
        tmp_path, demo_file, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)
    )
    try:
        driver.send_signal(signal.SIGINT)
        out, _ = driver.communicate(timeout=60)
        assert driver.returncode != 0, out[-3000:]
        assert f"capvector recipe: stopped waiting for fit (job {job}, RUNNING; log: " in out
    finally:
        subprocess.run(["scancel", job], check=False)
