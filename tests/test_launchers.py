"""Where recipe stages run: local processes sharing GPUs and the CPUs this process may use, and
jobs through submitit (its LocalExecutor here; real SLURM in tests/test_slurm.py)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from capvector.errors import CapVectorError
from capvector.io.cpus import cgroup_cpu_quota, usable_cpus
from capvector.workflows.launchers import LocalLauncher, Resources, running_pid
from capvector.workflows.recipe import run

REPO = Path(__file__).resolve().parents[1]


def write_recipe(path: Path, stages: list[dict], **settings: object) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"run_dir": str(path.parent / "run"), **settings, "stages": stages}))
    return path


def fit_stage(data: Path, name: str = "fit", steps: int = 2) -> dict:
    """A short fit of the tiny preset, no rollouts."""
    args = [
        "--config", str(REPO / "configs/debug.yaml"), f"--data.train_files=[{data}]",
        "--data.batch_size=4", "--data.eval_tasks=null", f"--trainer.max_steps={steps}",
        "--trainer.log_every_n_steps=1", "--trainer.enable_progress_bar=false",
    ]  # fmt: skip
    return {"name": name, "command": "fit", "args": args}


def two_stage_recipe(tmp_path: Path, data: Path, launcher: str) -> Path:
    """backbone-info, then a 2-step fit, each a job of ``launcher``."""
    stages = [
        {"name": "info", "command": "backbone-info", "args": ["openvla-oft-tiny"]},
        fit_stage(data),
    ]
    return write_recipe(
        tmp_path / "recipe.yaml", stages, launcher=launcher, resources={"time_min": 10}
    )


def check_two_stage_run(recipe: Path, launcher: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Both stages ran as jobs, left logs and markers, and a rerun skips them."""
    run(recipe)
    out = capsys.readouterr().out
    runs = recipe.parent / "run"
    for stage in ("info", "fit"):
        marker = json.loads((runs / stage / ".done").read_text())
        assert marker["launcher"] == launcher and marker["job"]
        assert f"[recipe {1 + (stage == 'fit')}/2] {stage} " in out
        assert (runs / stage / "submitit").is_dir()
    assert "openvla-oft-tiny" in (runs / "info/log.txt").read_text()
    assert "`Trainer.fit` stopped: `max_steps=2` reached" in (runs / "fit/log.txt").read_text()
    assert (runs / "fit/fit/version_0/export/model.safetensors").is_file()
    assert (runs / "fit/fit/version_0/checkpoints/last.ckpt").is_file()
    run(recipe)
    assert capsys.readouterr().out.count("done earlier, skipped") == 2


def test_a_recipe_runs_through_submitits_local_executor(
    tmp_path: Path, demo_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recipe = two_stage_recipe(tmp_path, demo_file, "submitit-local")
    check_two_stage_run(recipe, "submitit-local", capsys)

    # A failing stage: its log's tail is printed, and no marker is written.
    stages = [{"name": "bad", "command": "backbone-info", "args": ["no-such-preset"]}]
    bad = write_recipe(tmp_path / "bad" / "recipe.yaml", stages, launcher="submitit-local",
                       resources={"time_min": 5})  # fmt: skip
    with pytest.raises(CapVectorError, match=r"stage\(s\) \['bad'\] failed"):
        run(bad)
    assert "unknown backbone preset 'no-such-preset'" in capsys.readouterr().out
    assert not (tmp_path / "bad/run/bad/.done").exists()


def test_jobs_2_on_two_gpus_gives_each_stage_its_own(tmp_path: Path) -> None:
    """``jobs: 2`` on a machine showing two (fake) GPUs: each stage gets one of them and half of
    the CPUs this process may use; the markers record what each stage was given."""
    info = ["openvla-oft-tiny"]
    stages = [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "backbone-info", "after": [], "args": info},
    ]
    recipe = write_recipe(tmp_path / "recipe.yaml", stages, jobs=2)
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": "0,1"}
    done = subprocess.run([sys.executable, "-m", "capvector.cli", "recipe", "--config", str(recipe)],
                          env=env, capture_output=True, text=True, cwd=REPO)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    markers = [json.loads((tmp_path / f"run/{s}/.done").read_text()) for s in "ab"]
    assert sorted(m["gpus"][0] for m in markers) == ["0", "1"]
    assert all(len(m["gpus"]) == 1 and m["cores"] == max(1, usable_cpus() // 2) for m in markers)


def test_local_stages_see_their_gpus_and_wait_for_free_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)  # a user's own choice would be kept
    launcher = LocalLauncher(jobs=2, threads=1, gpus=["GPU-a", "GPU-b", "GPU-c"])
    show = "import os, time; time.sleep(0.5); print(os.environ['CUDA_VISIBLE_DEVICES'], os.environ['CAPVECTOR_CORES'], os.environ['OMP_NUM_THREADS'], os.environ['LP_NUM_THREADS'])"  # noqa: E501
    command = [sys.executable, "-c", show]
    one, two = Resources(gpus=1), Resources(gpus=2)
    first = launcher.start("a", tmp_path / "a", lambda: command, two, fit=False)
    assert not launcher.has_room(two)  # one GPU left
    second = launcher.start("b", tmp_path / "b", lambda: command, one, fit=False)
    assert not launcher.has_room(Resources(gpus=0))  # jobs: 2 are running
    assert first.wait() == 0 and second.wait() == 0
    cores = max(1, usable_cpus() // 2)
    shown = {stage: (tmp_path / stage / "log.txt").read_text().split() for stage in "ab"}
    assert shown == {"a": ["GPU-a,GPU-b", str(cores), "1", str(cores)],
                     "b": ["GPU-c", str(cores), "1", str(cores)]}  # fmt: skip
    assert launcher.has_room(Resources(gpus=3))  # all returned
    with pytest.raises(CapVectorError, match="asks for 4 GPUs; this machine shows 3"):
        launcher.check("big", Resources(gpus=4))


def test_usable_cpus_follow_the_affinity_and_the_cgroup_quota(tmp_path: Path) -> None:
    code = (
        "from capvector.io.cpus import usable_cpus; import os; print(usable_cpus(), os.cpu_count())"
    )
    done = subprocess.run(["taskset", "-c", "0", sys.executable, "-c", code],
                          capture_output=True, text=True, check=True)  # fmt: skip
    assert done.stdout.split()[0] == "1"  # os.cpu_count() says every core of the machine

    # A SLURM job's cgroup (v2) capped at 1.5 CPUs under a parent without a cap; and v1.
    proc = tmp_path / "v2/proc/self"
    proc.mkdir(parents=True)
    (proc / "cgroup").write_text("0::/slurm/job_7\n")
    (proc / "mountinfo").write_text("30 23 0:26 / /sys/fs/cgroup rw,nosuid - cgroup2 cgroup2 rw\n")
    job = tmp_path / "v2/sys/fs/cgroup/slurm/job_7"
    job.mkdir(parents=True)
    (job / "cpu.max").write_text("150000 100000\n")
    (job.parent / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_quota(tmp_path / "v2") == 1.5
    assert usable_cpus(tmp_path / "v2") == min(2, len(os.sched_getaffinity(0)))
    (job.parent / "cpu.max").write_text("50000 100000\n")  # a parent's smaller cap counts
    assert usable_cpus(tmp_path / "v2") == 1

    proc = tmp_path / "v1/proc/self"
    proc.mkdir(parents=True)
    (proc / "cgroup").write_text("5:memory:/docker/x\n4:cpu,cpuacct:/docker/x\n")
    (proc / "mountinfo").write_text(
        "32 31 0:29 / /sys/fs/cgroup/cpu,cpuacct rw - cgroup cgroup rw,cpu,cpuacct\n"
    )
    group = tmp_path / "v1/sys/fs/cgroup/cpu,cpuacct/docker/x"
    group.mkdir(parents=True)
    (group / "cpu.cfs_quota_us").write_text("100000\n")
    (group / "cpu.cfs_period_us").write_text("100000\n")
    assert usable_cpus(tmp_path / "v1") == 1
    assert cgroup_cpu_quota(tmp_path / "none") is None


def test_resources_and_launcher_errors_are_clear(tmp_path: Path) -> None:
    stages = [{"name": "a", "command": "backbone-info", "resources": {"gpu": 1}}]
    with pytest.raises(
        CapVectorError, match=r"unknown `resources` key\(s\) \['gpu'\]; known: gpus"
    ):
        run(write_recipe(tmp_path / "r1.yaml", stages), dry_run=True)
    stages[0]["resources"] = {"gpus": "two"}
    with pytest.raises(CapVectorError, match="`resources.gpus` must be a whole number, got 'two'"):
        run(write_recipe(tmp_path / "r1.yaml", stages), dry_run=True)
    stages = [{"name": "a", "command": "backbone-info"}]
    with pytest.raises(CapVectorError, match="a SLURM job needs a time limit"):
        run(write_recipe(tmp_path / "r2.yaml", stages, launcher="slurm"), dry_run=True)
    with pytest.raises(CapVectorError, match="launcher must be one of .*did you mean slurm"):
        run(write_recipe(tmp_path / "r3.yaml", stages, launcher="slrum"), dry_run=True)
    assert not (tmp_path / "run").exists()


def test_a_sigtermed_fit_does_not_exit_as_finished(tmp_path: Path, demo_file: Path) -> None:
    """Lightning ends a fit stopped by SIGTERM (a kill, a preemption) with exit status 0, as if
    it had finished, which a recipe took for done; `capvector fit` exits 143 instead."""
    args = fit_stage(demo_file, steps=10_000)["args"]
    log = tmp_path / "fit" / "version_0" / "metrics.csv"
    fit = subprocess.Popen(
        [sys.executable, "-m", "capvector.cli", "fit", *args, f"--trainer.default_root_dir={tmp_path}",
         f"--trainer.logger.init_args.save_dir={tmp_path}", "--trainer.log_every_n_steps=1",
         "--trainer.logger.init_args.flush_logs_every_n_steps=1"],
        stderr=subprocess.PIPE, text=True, cwd=REPO,
    )  # fmt: skip
    deadline = time.time() + 300
    while not (log.is_file() and len(log.read_text().splitlines()) > 2):
        assert fit.poll() is None and time.time() < deadline
        time.sleep(0.5)
    fit.send_signal(signal.SIGTERM)
    _, stderr = fit.communicate(timeout=120)
    assert fit.returncode == 128 + signal.SIGTERM
    assert "capvector fit: stopped by SIGTERM before its end" in stderr


@pytest.mark.slow
def test_a_stopped_recipe_stops_its_fit_and_a_rerun_names_one_still_running(
    tmp_path: Path, demo_file: Path
) -> None:
    """`kill` (SIGTERM) to the recipe alone stops its local fit with it, also while the recipe
    waits for the fit to end after another stage failed, and so does `kill -INT` when the recipe
    was started as a shell starts a background job (SIGINT ignored, which its children inherit); a
    recipe killed outright leaves its fit running, and a rerun names that fit instead of starting
    a second process that would write into the same folder."""
    fit_only = write_recipe(tmp_path / "recipe.yaml", [fit_stage(demo_file, steps=100_000)])
    command = [sys.executable, "-m", "capvector.cli", "recipe", "--config", str(fit_only)]
    # The same fit (the same run folder) beside a stage that fails at once, two at a time.
    broken = {"name": "broken", "command": "backbone-info", "after": [], "args": ["no-such-preset"]}
    with_failure = write_recipe(
        tmp_path / "with_failure.yaml", [fit_stage(demo_file, steps=100_000), broken], jobs=2
    )
    after_a_failure = [*command[:-1], str(with_failure)]
    # `capvector recipe ... &` in a script: the recipe's own process, with SIGINT ignored.
    in_background = [
        sys.executable, "-c", "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
        "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])", *command[1:],
    ]  # fmt: skip
    stage = tmp_path / "run" / "fit"
    checkpoint = stage / "fit" / "version_0" / "checkpoints" / "last.ckpt"
    log = tmp_path / "recipe.log"

    def start_recipe(how: list[str] = command, until: str = "") -> tuple[subprocess.Popen, int]:
        """The recipe, once its fit runs and has a checkpoint (and its output says ``until``);
        the fit's pid (from its lock)."""
        with log.open("w") as out:  # a file, not a pipe: a fit left running never blocks on it
            recipe_run = subprocess.Popen(how, stdout=out, stderr=subprocess.STDOUT, cwd=REPO)
        before = checkpoint.stat().st_mtime_ns if checkpoint.is_file() else None
        deadline = time.time() + 300
        while not (
            checkpoint.is_file() and checkpoint.stat().st_mtime_ns != before
            and until in log.read_text()
        ):  # fmt: skip
            assert recipe_run.poll() is None, log.read_text()[-3000:]
            assert time.time() < deadline
            time.sleep(0.5)
        pid = running_pid(stage)
        assert pid and pid != recipe_run.pid
        return recipe_run, pid

    first, fit = start_recipe(after_a_failure, until="broken (backbone-info) failed")
    try:
        first.terminate()
        assert first.wait(timeout=120) == 128 + signal.SIGTERM
        assert (
            "capvector recipe: stopping fit; run the same command again to resume"
            in log.read_text()
        )
        assert running_pid(stage) is None  # the fit ended with the recipe: nothing holds its lock
        with pytest.raises(ProcessLookupError):
            os.kill(fit, 0)

        background, fit = start_recipe(in_background)  # resumes the fit from its checkpoint
        background.send_signal(signal.SIGINT)
        assert background.wait(timeout=120) == 130  # `capvector recipe: interrupted`
        assert running_pid(stage) is None
        with pytest.raises(ProcessLookupError):
            os.kill(fit, 0)

        second, fit = start_recipe()
        second.kill()  # nothing runs in a SIGKILLed recipe: its fit goes on without it
        second.wait()
        assert running_pid(stage) == fit
        status = subprocess.run([*command, "--status"], capture_output=True, text=True, cwd=REPO)
        assert re.search(
            rf"  fit  running \(pid {fit}\): step \d+ of \d+ logged.*; resumes", status.stdout
        )
        again = subprocess.run(command, capture_output=True, text=True, cwd=REPO, timeout=300)
        assert again.returncode == 2
        assert (
            "stage(s) still running from an earlier `capvector recipe` run: fit "
            f"(pid {fit}). Wait for them to end, or stop them (`kill -INT <pid>`"
        ) in again.stderr
        assert running_pid(stage) == fit  # the rerun started nothing and left the fit alone
        os.kill(fit, signal.SIGINT)
        deadline = time.time() + 120
        while running_pid(stage) is not None and time.time() < deadline:
            time.sleep(0.5)
        assert running_pid(stage) is None and not (stage / ".done").exists()
        # The runs their recipe stopped count towards the stage's time; the killed one's cannot.
        assert json.loads((stage / ".runs.json").read_text())["runs"] == 2
    finally:  # a failed check leaves no fit running on (SIGTERM: heard where SIGINT is ignored)
        if (left := running_pid(stage)) is not None:
            os.kill(left, signal.SIGTERM)


def test_a_stage_a_signal_ended_names_the_signal(tmp_path: Path) -> None:
    """A stage the kernel killed (SIGKILL, as the out-of-memory killer does) fails with the signal
    by name and where to look, not a bare negative exit code; its log is shown after it."""
    launcher = LocalLauncher(jobs=2, threads=1, gpus=[])

    def ended_by(sig: signal.Signals) -> str:
        """The failure of a stage that prints a line, then gets ``sig``."""
        script = f"import os; print('training', flush=True); os.kill(os.getpid(), {int(sig)})"
        stage = launcher.start(sig.name, tmp_path / sig.name,
                               lambda: [sys.executable, "-c", script], Resources(), fit=False)  # fmt: skip
        assert stage.wait() == -sig
        return stage.failure()

    reason, log = ended_by(signal.SIGKILL).split("\n", 1)
    assert reason == (
        "killed by SIGKILL (most often the out-of-memory killer: `dmesg | grep -i oom`)"
    )
    assert "training" in log
    assert ended_by(signal.SIGSEGV).split("\n")[0] == "killed by SIGSEGV"


@pytest.mark.sim
def test_a_stage_without_gpus_can_open_robosuites_egl_renderer(tmp_path: Path) -> None:
    """A stage given no GPU sees ``CUDA_VISIBLE_DEVICES=""``, which robosuite's EGL context (what
    LIBERO's official renderer opens) parses as device ids and fails on; the stage's environment
    points it at the first EGL device, where robosuite opens a display."""
    launcher = LocalLauncher(jobs=2, threads=1, gpus=[])  # jobs > 1: the stage writes log.txt
    opened = (
        "import os; os.environ.setdefault('MUJOCO_GL', 'egl');"
        "from robosuite.renderers.context.egl_context import create_initialized_egl_device_display;"
        "from mujoco.egl import egl_ext as EGL;"
        "print(create_initialized_egl_device_display(-1) != EGL.EGL_NO_DISPLAY)"
    )
    stage = launcher.start("r", tmp_path / "r", lambda: [sys.executable, "-c", opened],
                           Resources(), fit=False)  # fmt: skip
    assert stage.wait() == 0, (tmp_path / "r/log.txt").read_text()[-2000:]
    assert (tmp_path / "r/log.txt").read_text().split()[-1] == "True"
