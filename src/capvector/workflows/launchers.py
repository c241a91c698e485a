"""Where ``capvector recipe`` runs its stages: child processes of the recipe, or SLURM jobs.

``local``: each stage is a child process; with ``jobs: N`` up to N at once, each with its own GPUs
(``CUDA_VISIBLE_DEVICES``, from those this process sees) and its share of the CPUs this process may
use (``capvector.io.cpus``: affinity and cgroup quota, not the machine's core count).

``slurm``: each stage is a SLURM job, submitted by submitit (https://github.com/facebookincubator/
submitit) with the stage's ``resources``; the recipe waits on the jobs as it waits on processes.
The job itself runs the stage's command, appends its output to ``<stage>/log.txt`` and writes the
``.done`` marker, so a stage that finished is skipped on rerun even when the recipe stopped
waiting. Preemption and time limits: SLURM signals the job (submitit asks for ``USR2`` 90 s
ahead); a ``fit`` stage (``RequeueAtStepEnd``, at the end of the step that signal lands in)
saves a checkpoint and requeues the job, which resumes from it; any other stage is requeued by
submitit and runs again.

A recipe run again while a stage's SLURM job is still queued or running (the recipe on a login
node was stopped, its jobs were not) waits for that job instead of submitting a second one.

A local stage runs in its own process group and holds ``<stage>/.lock`` while it runs: a recipe
that stops (Ctrl-C, ``kill``, an error) stops its stages as Ctrl-C in their terminal would, and a
recipe run again while an earlier run's stage is still running (its recipe was killed with
``SIGKILL``, its terminal closed) names that stage instead of starting a second process that writes
into the same folder.

``submitit-local``: the ``slurm`` path with each job a local process (submitit's
``LocalExecutor``), to try a cluster recipe, resources, pickling and all, without a cluster.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Protocol

from capvector.errors import CapVectorError
from capvector.io.cpus import usable_cpus
from capvector.io.names import STAGE_CORES
from capvector.io.outputs import atomic_write_bytes

LAUNCHERS = ("local", "slurm", "submitit-local")
DONE = ".done"
RUNS = ".runs.json"
LOG = "log.txt"
LOCK = ".lock"
REQUEUE_SIGNAL = signal.SIGUSR2
"""What submitit has SLURM send a job before its time limit (``--signal=USR2@90``) and, where the
cluster sends it on preemption, before that."""


@dataclass(frozen=True)
class Resources:
    """What a stage asks for: the recipe's ``resources:``, with a stage's own ``resources:`` over
    it. Locally only ``gpus`` and ``cpus`` count."""

    gpus: int | None = None
    """GPUs of the stage (local default: an equal share of the GPUs among ``jobs``; SLURM: 0)."""
    cpus: int | None = None
    """CPUs (SLURM ``--cpus-per-task``; locally the stage's simulator workers; default: a share
    of the CPUs this process may use, or SLURM's default)."""
    mem_gb: float | None = None
    time_min: int | None = None
    """The job's time limit in minutes; SLURM jobs need one."""
    partition: str | None = None
    tasks: int | None = None
    """Processes the job starts (default: a ``fit`` stage one per GPU, as Lightning runs under
    SLURM, whose ``trainer.devices`` must match; other stages 1)."""
    slurm: Mapping[str, Any] = field(default_factory=dict)
    """Further sbatch options, e.g. ``{account: a, qos: high, constraint: a100}``."""

    @classmethod
    def merged(cls, where: str, *entries: Mapping[str, Any] | None) -> Resources:
        """Resources from ``entries`` (later ones over earlier ones); unknown keys fail."""
        known = [f.name for f in fields(cls)]
        values: dict[str, Any] = {}
        for entry in entries:
            unknown = sorted(set(entry or {}) - set(known))
            if unknown:
                raise CapVectorError(
                    f"{where}: unknown `resources` key(s) {unknown}; known: {', '.join(known)}"
                )
            values.update({k: v for k, v in (entry or {}).items() if v is not None})
        kinds = {"mem_gb": ((int, float), "a number"), "partition": (str, "a name"),
                 "slurm": (Mapping, "a mapping of sbatch options")}  # fmt: skip
        for name, value in values.items():
            kind, what = kinds.get(name, (int, "a whole number"))
            if not isinstance(value, kind) or isinstance(value, bool):
                raise CapVectorError(f"{where}: `resources.{name}` must be {what}, got {value!r}")
        return cls(**values)


class Started(Protocol):
    """A stage that was started."""

    def poll(self) -> int | None:
        """None while it runs, then 0 (done, its marker written) or a failure code."""

    def wait(self) -> int:
        """Wait for it to end; ``poll``'s code."""

    def where(self) -> str:
        """Where to follow it: its log (and job)."""

    def failure(self) -> str:
        """What went wrong, for the recipe to print."""

    def stop(self) -> bool:
        """The recipe stops: ask the stage to stop with it. True if it will (then ``wait``), False
        if it goes on without the recipe (a SLURM job)."""


def stage_environment(threads: int, cores: int, gpus: list[str] | None = None) -> dict[str, str]:
    """A stage process's environment: ``threads`` torch (OpenMP, MKL) threads, fixed so results do
    not depend on how many stages run at once; ``cores`` for simulator workers, whose number does
    not change outcomes (``capvector.eval.rollout.default_workers``); ``gpus`` (ids as this process
    sees them) as its ``CUDA_VISIBLE_DEVICES`` when given."""
    fixed = {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    env = {**os.environ, **fixed, STAGE_CORES: str(cores)}
    # Mesa's software renderer (llvmpipe: EGL on a machine without GPUs) starts one rasterizer
    # thread per CPU of the machine in every stage unless told; a stage renders on its own cores
    env.setdefault("LP_NUM_THREADS", str(cores))
    if gpus is not None:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(gpus)
        if not gpus:  # robosuite's EGL context parses an empty CUDA_VISIBLE_DEVICES as device ids
            # and fails (int('')), so LIBERO's official renderer could not start: it draws on the
            # first EGL device instead (Mesa's software one on a machine without GPUs)
            env.setdefault("MUJOCO_EGL_DEVICE_ID", "0")
    return env


def record_run(directory: Path, began: float) -> dict[str, float]:
    """Add the stage's run that began at ``began`` and ended now to its ``.runs.json``; the
    totals (``runs``, ``seconds``). A fit stopped and resumed runs several times, and its time is
    theirs together. A run whose recipe was killed outright (SIGKILL) is not counted: no process
    was left to see it end."""
    path = directory / RUNS
    earlier = json.loads(path.read_text()) if path.is_file() else {"runs": 0, "seconds": 0.0}
    totals = {"runs": earlier["runs"] + 1, "seconds": earlier["seconds"] + time.time() - began}
    atomic_write_bytes(path, json.dumps(totals).encode())
    return totals


def write_done(directory: Path, command: list[str], began: float, **facts: Any) -> None:
    """The ``.done`` marker: what ran, in which run folder (``recipe.arguments_changed`` reads
    both), how long (this run, and all its runs), where. Records the run first (``record_run``)."""
    totals = record_run(directory, began)
    marker = {"command": command[2:], "run_dir": str(directory.parent), **facts,
              "seconds": round(time.time() - began, 1),
              "runs": totals["runs"], "seconds_all_runs": round(totals["seconds"], 1),
              "finished": time.ctime()}  # fmt: skip
    atomic_write_bytes(directory / DONE, json.dumps(marker, indent=2).encode())


def running_pid(directory: Path) -> int | None:
    """The process id of a local stage still running in ``directory`` (0 if it has not written
    it yet), or None when none is: the stage's process holds ``.lock`` until it ends."""
    path = directory / LOCK
    if not path.is_file():
        return None
    with path.open() as f:
        try:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            text = f.read().strip()
            return int(text) if text.isdigit() else 0
    return None  # the lock was free; closing the file released it


def lock_stage(directory: Path) -> int:
    """The open file descriptor of ``directory/.lock``, locked for the stage about to start (the
    stage of that folder's name), or a clear error when a process of an earlier run holds it."""
    fd = os.open(directory / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise CapVectorError(still_running({directory.name: running_pid(directory) or 0})) from None
    return fd


def still_running(pids: Mapping[str, int]) -> str:
    """The error for stages whose process from an earlier recipe run has not ended."""
    stages = ", ".join(f"{name} (pid {pid})" if pid else name for name, pid in pids.items())
    return (
        f"stage(s) still running from an earlier `capvector recipe` run: {stages}. Wait for them "
        "to end, or stop them (`kill -INT <pid>`; a fit resumes from its last checkpoint), then run "
        "this again: a second process would write into the same folder"
    )


def log_tail(path: Path, size: int = 3000) -> str:
    return path.read_bytes()[-size:].decode(errors="replace") if path.is_file() else ""


GPU_DEVICE_FILES = ("/dev/nvidiactl", "/dev/nvhost-ctrl-gpu", "/dev/kfd", "/dev/dxg")
"""What a GPU torch could use shows in /dev: NVIDIA's driver, a Jetson's, ROCm's, WSL 2's (its
CUDA)."""


def visible_gpus() -> list[str]:
    """The GPUs this process may hand out: ``CUDA_VISIBLE_DEVICES`` (ids, UUIDs or MIG names) when
    set, else every GPU CUDA finds; none without a GPU driver's device file, without importing
    torch (~300 MB resident in a recipe that waits for days, and seconds of every start)."""
    if "CUDA_VISIBLE_DEVICES" in os.environ:
        return [g.strip() for g in os.environ["CUDA_VISIBLE_DEVICES"].split(",") if g.strip()]
    if not any(os.path.exists(path) for path in GPU_DEVICE_FILES):
        return []
    import torch

    return [str(i) for i in range(torch.cuda.device_count())]


def make_launcher(
    launcher: str, jobs: int | None, threads: int
) -> LocalLauncher | SubmititLauncher:
    """The runner of ``launcher`` (one of ``LAUNCHERS``), starting at most ``jobs`` stages at once
    (default: locally 1; through submitit no limit, SLURM queues them)."""
    if launcher == "local":
        return LocalLauncher(jobs or 1, threads)
    return SubmititLauncher("slurm" if launcher == "slurm" else "local", threads, jobs)


def hear_interrupts() -> None:
    """Handle SIGINT (Ctrl-C) in this process if it was ignored. A shell without job control (a
    script) starts a background job (`cmd &`) with SIGINT ignored, and a child inherits an ignored
    signal: the stages would not hear ``LocalStage.stop``, and the recipe, stopped, would wait for
    them forever. A handled signal is reset to its default at exec, so the stages hear it again."""
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    ):
        signal.signal(signal.SIGINT, signal.default_int_handler)


class LocalLauncher:
    """Stages as child processes, up to ``jobs`` at once, sharing the GPUs and CPUs."""

    poll_seconds = 0.2

    def __init__(self, jobs: int, threads: int, gpus: list[str] | None = None) -> None:
        self.jobs, self.threads = jobs, threads
        self.free_gpus = visible_gpus() if gpus is None else list(gpus)
        self.total_gpus = len(self.free_gpus)
        self.running = 0
        hear_interrupts()

    def gpus_of(self, resources: Resources) -> int:
        """A stage's GPUs; unless it says, an equal share among ``jobs`` (at least one)."""
        if resources.gpus is not None:
            return resources.gpus
        return max(1, self.total_gpus // self.jobs) if self.total_gpus else 0

    def has_room(self, resources: Resources) -> bool:
        return self.running < self.jobs and self.gpus_of(resources) <= len(self.free_gpus)

    def check(self, name: str, resources: Resources) -> None:
        if self.gpus_of(resources) > self.total_gpus:
            raise CapVectorError(
                f"stage {name!r} asks for {resources.gpus} GPUs; this machine shows "
                f"{self.total_gpus} (CUDA_VISIBLE_DEVICES, else CUDA's count)"
            )

    def start(
        self, name: str, directory: Path, command: Callable[[], list[str]], resources: Resources,
        fit: bool,
    ) -> LocalStage:  # fmt: skip
        count = self.gpus_of(resources)
        gpus, self.free_gpus = self.free_gpus[:count], self.free_gpus[count:]
        cores = resources.cpus or max(1, usable_cpus() // self.jobs)
        # Without GPUs to hand out, CUDA_VISIBLE_DEVICES stays as it was (unset: every GPU).
        env = stage_environment(self.threads, cores, gpus if gpus or count == 0 else None)
        directory.mkdir(parents=True, exist_ok=True)
        log = None if self.jobs == 1 else directory / LOG
        stage = LocalStage(self, directory, command(), env, log, gpus, cores)
        self.running += 1
        return stage


class LocalStage:
    def __init__(
        self, launcher: LocalLauncher, directory: Path, command: list[str], env: dict[str, str],
        log: Path | None, gpus: list[str], cores: int,
    ) -> None:  # fmt: skip
        self.launcher, self.directory, self.command, self.log = launcher, directory, command, log
        self.gpus, self.cores, self.began = gpus, cores, time.time()
        lock = lock_stage(directory)
        out = None if log is None else log.open("ab")
        try:
            # Its own process group: Ctrl-C reaches the recipe alone, which then stops its stages
            # (``stop``), so a stage never outlives a recipe that was stopped unless it is killed.
            # The child inherits the locked descriptor and holds the lock until it ends.
            self.process = subprocess.Popen(
                command, env=env, stdout=out, stderr=None if out is None else subprocess.STDOUT,
                start_new_session=True, pass_fds=(lock,),
            )  # fmt: skip
            os.ftruncate(lock, 0)
            os.pwrite(lock, f"{self.process.pid}\n".encode(), 0)
        finally:
            os.close(lock)
            if out is not None:
                out.close()  # the child holds its own copy
        self.code: int | None = None

    def poll(self) -> int | None:
        if self.code is None and (code := self.process.poll()) is not None:
            self.code = code
            self.launcher.running -= 1
            self.launcher.free_gpus += self.gpus
            if code == 0:
                write_done(self.directory, self.command, self.began, launcher="local",
                           threads=self.launcher.threads, gpus=self.gpus, cores=self.cores)  # fmt: skip
            else:
                record_run(self.directory, self.began)
        return self.code

    def wait(self) -> int:
        self.process.wait()
        return self.poll()  # type: ignore[return-value]

    def where(self) -> str:
        return f"log: {self.log}"

    def stop(self) -> bool:
        """SIGINT to the stage's process group, as Ctrl-C in its terminal: a fit ends cleanly
        (Lightning's graceful shutdown; it resumes from its last checkpoint), another command
        removes its half-written outputs."""
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):  # it ended since
                os.killpg(self.process.pid, signal.SIGINT)
        return True

    def failure(self) -> str:
        assert self.code is not None
        return exit_reason(self.code) + ("" if self.log is None else "\n" + log_tail(self.log))


def exit_reason(code: int) -> str:
    """``exit 2``, or the signal that ended the process (Popen's negative code), by name. Nobody
    SIGKILLs a stage on purpose but the kernel when memory runs out, and the stage's log then ends
    mid-line without a word: say where that shows."""
    if code >= 0:
        return f"exit {code}"
    try:
        name = signal.Signals(-code).name
    except ValueError:
        return f"killed by signal {-code}"
    if -code == signal.SIGKILL:
        return f"killed by {name} (most often the out-of-memory killer: `dmesg | grep -i oom`)"
    return f"killed by {name}"


LIVE_STATES = frozenset({
    "PENDING", "CONFIGURING", "RUNNING", "COMPLETING", "SUSPENDED", "STOPPED", "SIGNALING",
    "STAGE_OUT", "RESIZING", "REQUEUED", "REQUEUE_FED", "REQUEUE_HOLD", "PREEMPTED",
})  # fmt: skip
"""squeue's job states (``squeue(1)``, JOB STATE CODES) of a job that may still run or be
requeued. PREEMPTED is among them: with ``PreemptMode=REQUEUE`` it passes to PENDING."""
FORGOTTEN = "no longer known to SLURM"


def slurm_state(job_id: str) -> str | None:
    """A SLURM job's state from ``squeue`` (``RUNNING``, ``CANCELLED``, ...), or ``FORGOTTEN``
    once slurmctld has dropped it (``MinJobAge`` after it ended, 300 s by default); None when
    squeue cannot answer (slurmctld unreachable): then nothing is known.

    squeue, not sacct (what submitit asks): small clusters often run without accounting, and
    then submitit never learns that a cancelled job ended. ``--states=all`` also lists jobs
    that ended while slurmctld remembers them."""
    try:
        queue = subprocess.run(
            ["squeue", "--noheader", "--states=all", "--jobs", str(job_id), "--format", "%T"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        return None
    states = queue.stdout.split()
    if queue.returncode == 0:
        return states[0] if states else FORGOTTEN
    return FORGOTTEN if "Invalid job id" in queue.stderr else None


class SubmititLauncher:
    """Stages as jobs through submitit: SLURM's (``cluster="slurm"``) or local processes."""

    poll_seconds = 1.0
    squeue_seconds = 5.0
    """How often a waiting stage asks squeue whether its SLURM job still exists; a job seen
    ended with no result this long apart twice fails the stage."""

    def __init__(self, cluster: str, threads: int, jobs: int | None) -> None:
        self.cluster, self.threads, self.jobs = cluster, threads, jobs
        self.running = 0
        hear_interrupts()  # a backgrounded recipe (`cmd &` in a script) stops on SIGINT too

    def has_room(self, resources: Resources) -> bool:
        return self.jobs is None or self.running < self.jobs

    def check(self, name: str, resources: Resources) -> None:
        if resources.time_min is None:
            raise CapVectorError(
                f"stage {name!r}: a SLURM job needs a time limit: set `resources: {{time_min: M}}` "
                "in the recipe (every stage) or the stage (a fit requeues itself at the limit "
                "and goes on)"
            )

    def start(
        self, name: str, directory: Path, command: Callable[[], list[str]], resources: Resources,
        fit: bool,
    ) -> SubmititStage:  # fmt: skip
        import submitit

        directory.mkdir(parents=True, exist_ok=True)
        executor = submitit.AutoExecutor(folder=directory / "submitit", cluster=self.cluster)
        gpus = resources.gpus or 0
        tasks = resources.tasks or (max(gpus, 1) if fit else 1)
        executor.update_parameters(
            name=name, timeout_min=resources.time_min, gpus_per_node=gpus or None,
            tasks_per_node=tasks, cpus_per_task=resources.cpus, mem_gb=resources.mem_gb,
            slurm_partition=resources.partition,
            slurm_additional_parameters=dict(resources.slurm) or None,
        )  # fmt: skip
        launcher = "slurm" if self.cluster == "slurm" else "submitit-local"
        job = self._running_job(directory / "submitit", tasks) if self.cluster == "slurm" else None
        if job is not None:
            print(
                f"stage {name!r}: SLURM job {job.job_id} from an earlier run is still queued or "
                "running: waiting for it, not submitting another",
                flush=True,
            )
        else:
            job = executor.submit(StageJob(directory, command, self.threads, launcher, fit))
        self.running += 1
        return SubmititStage(self, directory, job)

    @staticmethod
    def _running_job(folder: Path, tasks: int) -> Any:
        """The stage's newest SLURM job if SLURM still queues or runs it: the recipe (on a login
        node) may have stopped while its jobs went on, and a second job would write into the
        same stage folder."""
        import submitit

        submitted = sorted(folder.glob("*_submitted.pkl"), key=lambda p: p.stat().st_mtime)
        if not submitted:
            return None
        job_id = submitted[-1].name.removesuffix("_submitted.pkl")
        if slurm_state(job_id) not in LIVE_STATES:  # ended, SLURM forgot it, or cannot tell
            return None
        return submitit.SlurmJob(folder=folder, job_id=job_id, tasks=tuple(range(tasks)))


class SubmititStage:
    def __init__(self, launcher: SubmititLauncher, directory: Path, job: Any) -> None:
        self.launcher, self.directory, self.job = launcher, directory, job
        self.code: int | None = None
        self.error = ""
        self._next_check = time.monotonic() + launcher.squeue_seconds
        self._ended: str | None = None  # a state squeue gave as ended, awaiting a second look

    def poll(self) -> int | None:
        if self.code is None and self.job.done():
            self.launcher.running -= 1
            error = self.job.exception()
            self.error = "" if error is None else str(error)
            self.code = 0 if error is None and (self.directory / DONE).is_file() else 1
        elif self.code is None and self.launcher.cluster == "slurm":
            self._check_queue()
        return self.code

    def _check_queue(self) -> None:
        """Fail the stage when SLURM says its job ended and submitit has no result for it
        (``scancel``, a node failure): submitit learns that from sacct only, so without
        accounting the recipe would wait forever. Seen twice, ``squeue_seconds`` apart, so a
        result written as the job ends, or a requeue passing through an ended state, is not
        taken for one."""
        now = time.monotonic()
        if now < self._next_check:
            return
        self._next_check = now + self.launcher.squeue_seconds
        state = slurm_state(self.job.job_id)
        if state is None or state in LIVE_STATES:
            self._ended = None
            return
        if self._ended is None:
            self._ended = state
            return
        state = self._ended if state == FORGOTTEN else state  # the state it ended in
        self.launcher.running -= 1
        self.code = 1
        self.error = (
            f"SLURM job {self.job.job_id} ended ({state}) without a result: it was cancelled "
            "(scancel) or its node failed; rerun the same command to run the stage again"
        )

    def wait(self) -> int:
        while self.poll() is None:
            time.sleep(self.launcher.poll_seconds)
        return self.code  # type: ignore[return-value]

    def where(self) -> str:
        state = slurm_state(self.job.job_id) if self.launcher.cluster == "slurm" else None
        return f"job {self.job.job_id}{f', {state}' if state else ''}; log: {self.directory / LOG}"

    def failure(self) -> str:
        tail = "\n".join(t for t in (self.error, log_tail(self.directory / LOG)) if t)
        return f"job {self.job.job_id}; submitit's logs in {self.directory / 'submitit'}\n{tail}"

    def stop(self) -> bool:
        """A job goes on without the recipe (stopped on a login node); run again, the recipe
        waits for it."""
        return False


class StageJob:
    """What a submitit job runs: the stage's command, built when the job starts (a requeued fit
    resumes from the checkpoint its first run left), its output appended to ``<stage>/log.txt``,
    and the ``.done`` marker when it succeeds.

    submitit calls ``checkpoint`` on its requeue signal: the job is requeued as it is, and the
    stage runs again. A ``fit`` stage on SLURM leaves that signal to the fit: it saves a
    checkpoint and requeues the job itself (``RequeueAtStepEnd``). A job ended
    from outside (that signal, or SIGTERM: a requeue, a preemption, a cancel) leaves no result, so
    the recipe waits for a requeued job and takes a cancelled one as failed."""

    def __init__(
        self, directory: Path, command: Callable[[], list[str]], threads: int, launcher: str,
        fit: bool,
    ) -> None:  # fmt: skip
        self.directory, self.command, self.threads = directory, command, threads
        self.launcher, self.fit = launcher, fit

    def __call__(self) -> None:
        import submitit

        if (self.directory / DONE).is_file():  # requeued after its stage had finished
            return
        rank = submitit.JobEnvironment().global_rank
        log = self.directory / (LOG if rank == 0 else f"log_rank{rank}.txt")
        command = self.command()
        cores = usable_cpus()
        env = stage_environment(self.threads, cores)
        stopped: list[int] = []  # signals that end this job from outside; the stage gets them too

        def note(signum: int, _frame: object) -> None:
            stopped.append(signum)

        signal.signal(signal.SIGTERM, note)  # a cancel, a preemption, a requeue
        if self.fit and self.launcher == "slurm":
            signal.signal(REQUEUE_SIGNAL, note)  # the fit's Lightning saves and requeues
        began = time.time()
        with log.open("ab") as out:
            process = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)
            try:
                code = process.wait()
            finally:  # submitit's requeue ends this process by an exception: stop the stage too
                if process.poll() is None:
                    process.terminate()
                    process.wait()
                if process.returncode != 0 and rank == 0:
                    record_run(self.directory, began)
        if code == 0:
            if rank == 0:
                job = submitit.JobEnvironment().job_id
                write_done(self.directory, command, began, launcher=self.launcher, job=job,
                           threads=self.threads, cores=cores)  # fmt: skip
            return
        if stopped:  # no result: a requeued job writes its own, a cancelled one has none
            sys.exit(f"stopped by signal {stopped[0]} (the stage exited with {code})")
        raise CapVectorError(f"capvector {command[3]} exited with {code}\n{log_tail(log)}")

    def checkpoint(self) -> Any:
        """submitit's hook on the requeue signal: requeue the stage as it is."""
        import submitit

        return submitit.helpers.DelayedSubmission(self)
