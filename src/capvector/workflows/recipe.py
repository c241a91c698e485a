"""``capvector recipe``: the whole CapVector recipe as a list of ordinary ``capvector`` commands.

A recipe YAML names a run folder and stages; each stage is one command (``demos``, ``fit``,
``extract``, ``merge``, ``evaluate``, ...) with its arguments, exactly as typed on a shell. Stages
run in order, each in its own process, with their outputs under ``<run_dir>/<stage>/``. A finished
stage leaves a ``.done`` marker and is skipped when the recipe is rerun; a ``fit`` stage that was
interrupted resumes from its last checkpoint (the merge callback's state in that checkpoint keeps a
capability vector from being merged twice).

Arguments may refer to other stages' outputs with omegaconf interpolation::

    ${out.<stage>.dir}      the stage's folder
    ${out.<stage>.export}   a fit stage's export folder (weights + config + statistics)
    ${out.<stage>.ckpt}     a fit stage's last checkpoint
    ${run_dir}              the run folder
    ${best_scale:${out.<sweep stage>.dir}}   the λ a ``sweep-scale`` stage found best

A stage waits for the stage before it, or for the stages in its ``after:`` list, and always for
the stages whose outputs it names. With ``jobs: N`` (or ``--jobs N``) up to N stages whose waits
are over run at once, e.g. the seeds of a downstream comparison.

``launcher: local`` (the default) runs each stage as a child process, each of ``jobs`` stages with
its own GPUs; ``launcher: slurm`` submits each stage as a SLURM job through submitit, with the
recipe's and the stage's ``resources:`` (``capvector.workflows.launchers``). A fit stage's loggers
are its config's, and the recipe's CSV logger beside them (``metrics.csv``, read by ``report``).

Every stage's process gets ``threads: T`` (or ``--threads T``, default 1) torch threads, whatever
``jobs``, the machine's core count or its load: a float reduction split over another number of
threads rounds differently, so weights and rollout outcomes would follow them. A seeded recipe
gives the same results on one kind of machine (the CPU's instruction set picks torch's kernels).

A stage with ``seeds: [0, 1, 2]`` stands for one stage per seed, ``<name>_s<seed>``; a ``fit``
stage gets ``--seed_everything=<seed>``, and seed k of a stage reads seed k of any seeded stage it
names (``--ckpt ${out.down.export}`` in a seeded ``evaluate`` stage evaluates each seed's fit of
``down``). An ``after:`` list that names ``<name>`` waits for all of its seeds.

``--only STAGE ...`` runs those stages and what they wait for, nothing else (a seeded stage's
name stands for all of its seeds), e.g. one report of a large recipe; what only finished stages
waited for is not needed again. ``--status`` runs nothing and says where each of them stands:
done (in how long), a fit's last logged step and whether it resumes from a checkpoint, or what it
waits for.
"""

from __future__ import annotations

import csv
import functools
import json
import re
import statistics
import sys
import time
from collections.abc import Collection, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from capvector.errors import CapVectorError, config_error, did_you_mean
from capvector.eval.results import SuccessRow, format_success_table
from capvector.tool_cli import run_tool
from capvector.workflows.launchers import (
    DONE,
    LAUNCHERS,
    REQUEUE_SIGNAL,
    Resources,
    Started,
    make_launcher,
    running_pid,
    still_running,
)

OUT_REFERENCE = re.compile(r"\$\{out\.([A-Za-z0-9_]+)\.([A-Za-z0-9_]*)")
"""``${out.<stage>.<output>`` (groups: the stage, the output)."""
FIT_VERSION = "version_0"
DEFAULT_THREADS = 1
"""Torch threads per stage: two 1-thread trainings of a tiny preset outrun one 2-thread training
(torch's intra-op parallelism scales poorly at these sizes), and threads beyond the free cores
wait on each other (the demo's fits, 2 threads each beside other work on 2 cores: 15 s a step
against 1 s with 1 thread)."""


@dataclass
class Stage:
    name: str
    command: str
    args: list[str]
    directory: Path
    resources: Resources = field(default_factory=Resources)

    @property
    def done_marker(self) -> Path:
        return self.directory / DONE


def stage_outputs(run_dir: Path, name: str) -> dict[str, str]:
    """What ``${out.<name>.<output>}`` stands for, by output."""
    directory = run_dir / name
    fit_dir = directory / "fit" / FIT_VERSION
    return {
        "dir": str(directory),
        "export": str(fit_dir / "export"),
        "ckpt": str(fit_dir / "checkpoints" / "last.ckpt"),
    }


def _best_scale(sweep_dir: str) -> str:
    """Resolver ``${best_scale:DIR}``: the best λ of a finished ``sweep-scale`` stage."""
    from capvector.workflows.sweep import best_scale

    path = Path(sweep_dir) / "sweep.json"
    if not path.is_file():
        return "<best λ of " + sweep_dir + ">"  # a dry run before the sweep has run
    return f"{best_scale(json.loads(path.read_text())):g}"


def load_recipe(path: str | Path, overrides: list[str] | None = None) -> tuple[Path, list[Stage]]:
    """The run folder and the stages, their arguments resolved now (see ``resolve_stage``)."""
    run_dir, raw = _load_raw(path, overrides)
    return run_dir, [resolve_stage(raw, i, run_dir, path) for i in range(len(raw.stages))]


def _load_raw(path: str | Path, overrides: list[str] | None) -> tuple[Path, Any]:
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("best_scale"):
        OmegaConf.register_resolver("best_scale", _best_scale)
    raw = OmegaConf.load(path)
    if overrides:
        raw = OmegaConf.merge(raw, OmegaConf.from_dotlist(overrides))
    if "run_dir" not in raw or "stages" not in raw:
        raise CapVectorError(f"{path} needs `run_dir` and a list of `stages` (name, command, args)")
    raw.stages = expand_seeds(raw.stages, path)
    run_dir = Path(str(raw.run_dir))
    names = [str(s.name) for s in raw.stages]
    if len(set(names)) != len(names):
        raise CapVectorError(f"{path}: stage names must be unique, got {names}")
    raw.out = {name: stage_outputs(run_dir, name) for name in names}
    return run_dir, raw


def expand_seeds(stages: Any, path: str | Path) -> Any:
    """Stages with ``seeds: [...]`` become one stage per seed (``<name>_s<seed>``), as an
    omegaconf list. Seed k of a stage reads seed k of the seeded stages it names
    (``${out.<seeded>.*}`` means ``${out.<seeded>_s<k>.*}``); a ``fit`` stage also gets
    ``--seed_everything=<seed>``. ``after:`` entries naming a seeded stage name all its seeds."""
    from omegaconf import OmegaConf

    expanded: list[Any] = []
    seeded: dict[str, list[str]] = {}
    for entry in stages:
        entry = OmegaConf.to_container(entry, resolve=False)
        if "after" in entry:
            entry["after"] = [n for a in entry["after"] for n in seeded.get(str(a), [str(a)])]
        seeds = entry.pop("seeds", None)
        if seeds is None:
            expanded.append(entry)
            continue
        args = [str(a) for a in entry.get("args", [])]
        is_fit = entry.get("command") == "fit"
        reads_seeded = any(_output_references(seeded).search(a) for a in args)
        if not seeds or not (is_fit or reads_seeded):
            raise CapVectorError(
                f"stage {entry.get('name')!r} in {path}: `seeds` needs a non-empty list of seeds "
                f"and a `fit` stage, or arguments that name an earlier seeded stage's outputs "
                f"(got command {entry.get('command')!r}, seeds {seeds})"
            )
        name = str(entry["name"])
        seeded[name] = [f"{name}_s{seed}" for seed in seeds]
        references = _output_references(seeded)  # its own outputs included
        for seed, seed_name in zip(seeds, seeded[name], strict=True):
            to_seed = f"${{out.\\g<1>_s{int(seed)}."
            seed_args = [references.sub(to_seed, a) for a in args]
            if is_fit:
                seed_args.append(f"--seed_everything={int(seed)}")
            expanded.append({**entry, "name": seed_name, "args": seed_args})
    return OmegaConf.create(expanded)


def _output_references(stages: Iterable[str]) -> re.Pattern[str]:
    """Matches ``${out.<stage>.`` for any of ``stages`` (group 1: the stage's name)."""
    names = "|".join(map(re.escape, stages)) or r"(?!)"
    return re.compile(r"\$\{out\.(" + names + r")\.")


def resolve_stage(raw: Any, index: int, run_dir: Path, path: str | Path) -> Stage:
    """One stage with its interpolations resolved. Done right before the stage runs, so a stage
    can use what an earlier one produced (``${best_scale:${out.sweep.dir}}``)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        entry: Any = OmegaConf.to_container(raw.stages[index], resolve=True)
    except OmegaConfBaseException as err:
        raise config_error(f"stage {raw.stages[index].get('name')!r} in {path}", err) from err
    if "command" not in entry:
        raise CapVectorError(f"stage {entry.get('name')!r} in {path} has no `command`")
    args = [str(a) for a in entry.get("args", [])]
    resources = Resources.merged(
        f"stage {entry['name']!r} in {path}", raw.get("resources"), entry.get("resources")
    )
    return Stage(entry["name"], entry["command"], args, run_dir / entry["name"], resources)


def command_line(stage: Stage, launcher: str = "local") -> list[str]:
    """The ``capvector`` command of a stage; fit stages get their folder, their CSV logger (beside
    the config's loggers) and the checkpoint to resume from, if any; on SLURM, Lightning's
    auto-requeue on the signal submitit asks SLURM for, acted on at a step's end."""
    args = [stage.command, *stage.args]
    if stage.command == "fit":
        args += [
            f"--trainer.default_root_dir={stage.directory}",
            # Appended to the config's loggers (`capvector fit` puts this one first: Lightning
            # writes checkpoints, the export and rollout videos into the first logger's folder).
            "--trainer.logger+=capvector.training.loggers.CSVLogger",
            f"--trainer.logger.init_args.save_dir={stage.directory}",
            "--trainer.logger.init_args.name=fit",
            f"--trainer.logger.init_args.version={FIT_VERSION}",
            "--trainer.callbacks+=capvector.callbacks.CheckpointAfterValidation",
            "--trainer.callbacks.save_last=true",
            "--trainer.callbacks.every_n_train_steps=50",
        ]
        if launcher == "slurm":
            args += [
                "--trainer.plugins+=lightning.pytorch.plugins.environments.SLURMEnvironment",
                f"--trainer.plugins.init_args.requeue_signal={REQUEUE_SIGNAL.name}",
                # Lightning's requeue, at the end of the step the signal lands in (not mid-step).
                "--trainer.callbacks+=capvector.callbacks.RequeueAtStepEnd",
                f"--trainer.callbacks.requeue_signal={REQUEUE_SIGNAL.name}",
            ]
        resume = resume_point(stage)
        if resume is not None:
            args.append(f"--ckpt_path={resume}")  # resume the interrupted stage
    return [sys.executable, "-m", "capvector.cli", *args]


def resume_point(stage: Stage) -> Path | None:
    """The newest checkpoint of an interrupted fit stage: its ``last.ckpt``, or one Lightning's
    SLURM auto-requeue saved into the stage folder (``hpc_ckpt_<n>.ckpt``)."""
    last = Path(stage_outputs(stage.directory.parent, stage.name)["ckpt"])
    found = [p for p in [last, *stage.directory.glob("hpc_ckpt_*.ckpt")] if p.is_file()]
    return max(found, key=lambda p: p.stat().st_mtime) if found else None


def dependencies(raw: Any, index: int) -> set[str]:
    """The stages stage ``index`` waits for: its ``after:`` list (default: the stage before it)
    plus every other stage whose outputs its arguments name (``${out.<stage>.<output>}``), which
    must be a stage and one of its outputs."""
    from omegaconf import OmegaConf

    entry = raw.stages[index]
    names = [str(s.name) for s in raw.stages]
    text = json.dumps(OmegaConf.to_container(entry, resolve=False).get("args", []))
    named: set[str] = set()
    for stage, output in OUT_REFERENCE.findall(text):
        reference = f"${{out.{stage}.{output}}}"
        if stage not in names:
            raise CapVectorError(
                f"stage {names[index]!r} names {reference}, but no stage is called {stage!r}"
                f"{did_you_mean(stage, names)}; stages: {names}"
            )
        outputs = list(stage_outputs(Path(), stage))
        if output not in outputs:
            raise CapVectorError(
                f"stage {names[index]!r} names {reference}: a stage's outputs are "
                f"{', '.join(outputs)}{did_you_mean(output, outputs)}"
            )
        named.add(stage)
    if "after" in entry:
        after = [str(a) for a in entry.after]
        unknown = sorted(set(after) - set(names[:index]))
        if unknown:
            raise CapVectorError(
                f"stage {names[index]!r}: `after` names {unknown}, which are not earlier stages "
                f"(earlier: {names[:index]})"
            )
    else:
        after = names[index - 1 : index]
    return set(after) | (named - {names[index]})


def check_order(waits_for: dict[str, set[str]], path: str | Path) -> None:
    """Fail when stages wait for each other in a cycle (a stage naming a later stage's outputs,
    which waits for it in turn), naming the cycle, before any stage runs."""
    finished: set[str] = set()

    def visit(name: str, trail: list[str]) -> None:
        if name in finished:
            return
        if name in trail:
            cycle = " waits for ".join([*trail[trail.index(name) :], name])
            raise CapVectorError(
                f"{path}: stages wait for each other in a cycle: {cycle} (a stage waits for the "
                "one before it or its `after:` list, and for every stage whose ${out.*} it names); "
                "name only earlier stages' outputs"
            )
        trail.append(name)
        for other in sorted(waits_for[name]):
            visit(other, trail)
        trail.pop()
        finished.add(name)

    for name in waits_for:
        visit(name, [])


def required_stages(
    waits_for: dict[str, set[str]], targets: list[str], done: Collection[str] = ()
) -> set[str]:
    """The ``targets`` and every stage they wait for, directly or not, but not through a stage in
    ``done``: a finished stage needs its inputs no more (a study carried to another machine
    without its demos does not record again the demos only finished fits used). A target that
    names a seeded stage (``<name>`` of ``<name>_s0``, ``<name>_s1``, ...) stands for all of its
    seeds."""
    wanted: list[str] = []
    for target in targets:
        seeded = [n for n in waits_for if re.fullmatch(rf"{re.escape(target)}_s\d+", n)]
        if target not in waits_for and not seeded:
            raise CapVectorError(
                f"--only names {target!r}, which is no stage; stages: {list(waits_for)}"
            )
        wanted += [target] if target in waits_for else seeded
    required: set[str] = set()
    while wanted:
        name = wanted.pop()
        if name not in required:
            required.add(name)
            if name not in done:
                wanted += waits_for[name]
    return required


def run(
    recipe: str | Path,
    overrides: list[str] | None = None,
    dry_run: bool = False,
    jobs: int | None = None,
    only: list[str] | None = None,
    threads: int | None = None,
    launcher: str | None = None,
    status: bool = False,
) -> list[dict]:
    """Run the stages, up to ``jobs`` at a time once their dependencies have finished, each with
    ``threads`` torch threads, through ``launcher`` (default: the recipe's, ``local``); with
    ``only``, just those stages and what they wait for; with ``status``, print where they stand
    instead (``print_status``).

    Locally with ``jobs > 1``, and always through submitit, each stage's output goes to
    ``<stage>/log.txt``.
    """
    run_dir, raw = _load_raw(recipe, overrides)
    threads = int(raw.get("threads", DEFAULT_THREADS) if threads is None else threads)
    if threads < 1:
        raise CapVectorError(f"threads (torch threads per stage) must be at least 1, got {threads}")
    launcher = str(launcher or raw.get("launcher", "local"))
    if launcher not in LAUNCHERS:
        raise CapVectorError(
            f"launcher must be one of {', '.join(LAUNCHERS)}, got {launcher!r}"
            f"{did_you_mean(launcher, LAUNCHERS)}"
        )
    jobs = jobs or raw.get("jobs")  # submitit: no limit unless given; SLURM queues the jobs
    if jobs is not None and int(jobs) < 1:
        raise CapVectorError(f"jobs must be at least 1, got {jobs}")
    names = [str(s.name) for s in raw.stages]
    waits_for = {names[i]: dependencies(raw, i) for i in range(len(names))}
    check_order(waits_for, recipe)
    runner = make_launcher(launcher, None if jobs is None else int(jobs), threads)
    for i in range(len(names)):  # every interpolation resolves: a typo fails now, not hours in
        runner.check(names[i], resolve_stage(raw, i, run_dir, recipe).resources)
    if only:
        done = {n for n in names if (run_dir / n / DONE).is_file()}
        required = required_stages(waits_for, only, done)
        names = [n for n in names if n in required]
    index = {str(s.name): i for i, s in enumerate(raw.stages)}
    if status:
        print_status(
            run_dir, [resolve_stage(raw, index[n], run_dir, recipe) for n in names], waits_for
        )
        return []
    if not dry_run:  # before anything starts: an earlier run's stage may still be running
        pids = {n: running_pid(run_dir / n) for n in names if not (run_dir / n / DONE).is_file()}
        busy = {n: pid for n, pid in pids.items() if pid is not None}
        if busy:
            raise CapVectorError(still_running(busy))
    run_dir.mkdir(parents=True, exist_ok=True)
    stages: dict[str, Stage] = {}
    finished: set[str] = set()
    running: dict[str, Started] = {}
    failed: list[str] = []
    quiet = launcher == "local" and (jobs or 1) == 1  # the stage's output is this one's

    def label(name: str) -> str:
        return f"[recipe {names.index(name) + 1}/{len(names)}] {name} ({stages[name].command})"

    def start(name: str) -> None:
        stage = stages[name]
        left = [n for n in names if n not in finished and n not in running and n != name
                and not (run_dir / n / DONE).is_file()]  # fmt: skip
        more = f": {', '.join(left[:3])}{', ...' if len(left) > 3 else ''}" if left else ""
        print(f"{label(name)} started; {len(left)} more to run{more}", flush=True)
        if dry_run:
            print("  " + " ".join(command_line(stage, launcher)[2:]))
            finished.add(name)
            return
        command = functools.partial(command_line, stage, launcher)
        running[name] = runner.start(name, stage.directory, command, stage.resources,
                                     stage.command == "fit")  # fmt: skip
        if not quiet:
            print(f"  {running[name].where()}", flush=True)

    def reap(name: str, code: int) -> None:
        started = running.pop(name)
        if code != 0:
            failed.append(name)
            print(f"{label(name)} failed: {started.failure()}", flush=True)
            return
        finished.add(name)
        if not quiet:
            marker = json.loads(stages[name].done_marker.read_text())
            print(f"{label(name)} finished{took(marker)}", flush=True)

    try:
        while len(finished) < len(names) and not failed:
            for name in names:
                if name in finished or name in running:
                    continue
                done_earlier = (run_dir / name / DONE).is_file()
                if not (done_earlier or waits_for[name] <= finished):
                    continue  # a finished stage waits for nothing: its inputs may be gone
                # Resolved only now, so the arguments can use what earlier stages produced.
                stages[name] = resolve_stage(raw, index[name], run_dir, recipe)
                if done_earlier:
                    print(f"{label(name)}: done earlier, skipped", flush=True)
                    finished.add(name)
                elif runner.has_room(stages[name].resources):
                    start(name)
            if not running:
                continue
            time.sleep(runner.poll_seconds)
            for name in list(running):
                code = running[name].poll()
                if code is not None:
                    reap(name, code)
    except BaseException:  # Ctrl-C, SIGTERM, an error: the local stages stop with the recipe
        stopping = [name for name, started in running.items() if started.stop()]
        if stopping:
            print(f"capvector recipe: stopping {', '.join(stopping)}; run the same command "
                  "again to resume", flush=True)  # fmt: skip
            for name in stopping:
                running[name].wait()
        left = ", ".join(f"{n} ({s.where()})" for n, s in running.items() if n not in stopping)
        if left:  # SLURM jobs outlive the recipe: say which, in the state SLURM gives now
            print(f"capvector recipe: stopped waiting for {left}")
        raise
    for name in list(running):  # a stage failed: let the others finish their work, then stop
        reap(name, running[name].wait())
    if failed:
        raise CapVectorError(
            f"stage(s) {failed} failed; fix and rerun the same command: finished stages are "
            "skipped and an interrupted fit resumes"
        )
    return collect_results([stages[n] for n in names])


def print_status(run_dir: Path, stages: list[Stage], waits_for: dict[str, set[str]]) -> None:
    """One line per stage: what its folder says (``stage_status``), and for a stage not started,
    the stages it still waits for."""
    done = {s.name for s in stages if s.done_marker.is_file()}
    print(f"{run_dir}: {len(done)} of {len(stages)} stages done")
    width = max((len(s.name) for s in stages), default=0)
    for stage in stages:
        line = stage_status(stage)
        waiting = sorted(n for n in waits_for[stage.name] if not (run_dir / n / DONE).is_file())
        if line == "not started" and waiting:
            line += f"; waits for {', '.join(waiting)}"
        print(f"  {stage.name:<{width}}  {line}")


def took(marker: dict) -> str:
    """How long a finished stage took, from its ``.done`` marker: " in T s", and over how many
    runs when it was stopped and resumed ("" for a marker without times). A marker written before
    runs were counted (no ``runs``) knows only its last run's time, and says so."""
    if "seconds" not in marker:
        return ""
    if "runs" not in marker:
        return f" in {marker['seconds']:.0f} s (its last run; earlier runs were not counted)"
    if marker["runs"] == 1:
        return f" in {marker['seconds']:.0f} s"
    total, runs, last = marker["seconds_all_runs"], marker["runs"], marker["seconds"]
    return f" in {total:.0f} s over {runs} runs (the last {last:.0f} s)"


def stage_status(stage: Stage) -> str:
    """Where a stage stands, from its folder: done (in how long), running (a local process holds
    its lock) or started and stopped, a fit's last logged step, what its remaining steps cost at
    its recent step time (validation not counted) and whether it would resume from a checkpoint,
    or not started."""
    if stage.done_marker.is_file():
        return "done" + took(json.loads(stage.done_marker.read_text() or "{}"))
    if not stage.directory.exists():
        return "not started"
    pid = running_pid(stage.directory)
    state = "started, not done" if pid is None else f"running (pid {pid})" if pid else "running"
    if stage.command != "fit":
        return state
    outputs = stage_outputs(stage.directory.parent, stage.name)
    checkpoint = Path(outputs["ckpt"])
    metrics = (
        Path(outputs["export"]).parent / "metrics.csv"
    )  # beside the export, in the fit's folder
    steps, seconds = [], []
    if metrics.is_file():
        with metrics.open(newline="") as f:
            for row in csv.DictReader(f):
                if row.get("step"):
                    steps.append(int(row["step"]))
                if row.get("perf/step_seconds"):
                    seconds.append(float(row["perf/step_seconds"]))
    total = _max_steps(metrics.with_name("config.yaml"))
    logged = (
        f"step {max(steps)}{f' of {total}' if total else ''} logged" if steps else "no step logged"
    )
    if seconds:  # the StepCost callback's, over the last few logs: what the rest will cost
        lately = statistics.median(seconds[-5:])
        left = ""
        if total:  # past the last step (its final validation), nothing is left to train
            left = f": {_hours_or_minutes(max(0, total - max(steps)) * lately)} of steps left"
        logged += f" ({lately:.2f} s per step lately{left})"
    resumes = (
        "resumes from its last checkpoint" if checkpoint.is_file()
        else "no checkpoint yet: starts again"
    )  # fmt: skip
    return f"{state}: {logged}; {resumes}"


def _hours_or_minutes(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"


def _max_steps(config: Path) -> int | None:
    """``trainer.max_steps`` of the config a fit saved in its folder (None if unknown or -1)."""
    try:
        steps = (yaml.safe_load(config.read_text()) or {}).get("trainer", {}).get("max_steps")
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    return steps if isinstance(steps, int) and steps > 0 else None


def collect_results(stages: list[Stage]) -> list[SuccessRow]:
    """Rows of every evaluate stage's ``--json`` output, labelled with the stage name."""
    rows = []
    for stage in stages:
        if stage.command != "evaluate" or "--json" not in stage.args:
            continue
        path = Path(stage.args[stage.args.index("--json") + 1])
        if path.is_file():
            rows += [SuccessRow.from_dict(r, stage.name) for r in json.loads(path.read_text())]
    return rows


def main(argv: list[str] | None = None) -> int:
    return run_tool(recipe_cli, argv, "recipe")


def recipe_cli(
    overrides: Sequence[str] = (),
    /,
    *,
    config: str,
    dry_run: bool = False,
    jobs: int | None = None,
    threads: int | None = None,
    only: list[str] | None = None,
    launcher: str | None = None,
    status: bool = False,
) -> None:
    """Run the whole recipe, or the stages some need, as resumable stages.

    Args:
        overrides: dotlist overrides, e.g. run_dir=runs/x
        config: recipe YAML (configs/recipes/*.yaml)
        dry_run: print the stage commands only
        jobs: stages run at once when their `after` stages are done (default: the recipe's
            `jobs`, 1)
        threads: torch threads of every stage (default: the recipe's `threads`, 1); results
            depend on it, not on --jobs
        only: run only these stages and the stages they wait for (not those that only
            finished stages wait for)
        launcher: local (child processes), slurm (a SLURM job per stage, through submitit) or
            submitit-local (the slurm path, jobs as local processes); default: the recipe's
            `launcher`, local
        status: run nothing; print where each stage (of --only's) stands
    """
    rows = run(config, list(overrides), dry_run, jobs, only, threads, launcher, status)
    if rows:
        print("\nResults\n" + format_success_table(rows))
