"""``capvector recipe``: the whole CapVector recipe as a list of ordinary ``capvector`` commands.

A recipe YAML names a run folder and stages; each stage is one command (``demos``, ``fit``,
``extract``, ``merge``, ``evaluate``, ...) with its arguments, exactly as typed on a shell. Stages
run in order, each in its own process, with their outputs under ``<run_dir>/<stage>/``. A finished
stage leaves a ``.done`` marker and is skipped when the recipe is rerun (saying what changed when
the recipe's arguments for it are no longer those it ran with); a ``fit`` stage that was
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
import difflib
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

from capvector.errors import CapVectorError, config_error, did_you_mean, unknown_name
from capvector.eval.results import SuccessRow, best_scale, format_success_table
from capvector.io.names import EVALUATE_PROGRESS, VALIDATION_PROGRESS
from capvector.tool_cli import run_tool
from capvector.workflows.launchers import (
    DONE,
    LAUNCHERS,
    LOG,
    REQUEUE_SIGNAL,
    LocalLauncher,
    Resources,
    Started,
    SubmititLauncher,
    log_tail,
    make_launcher,
    running_pid,
    still_running,
)

OUT_REFERENCE = re.compile(r"\$\{out\.([A-Za-z0-9_]+)\.([A-Za-z0-9_]*)")
"""``${out.<stage>.<output>`` (groups: the stage, the output)."""
OUT_PATH = re.compile(r"\$\{out\.([A-Za-z0-9_]+)\.([A-Za-z0-9_]+)\}([^\s,\[\]{}\"'$]*)")
"""``${out.<stage>.<output>}`` and the path it continues into (``/demos``): what a stage reads."""
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
    if not Path(path).is_file():
        raise CapVectorError(
            f"--config {path} does not exist; recipes ship in configs/recipes/ "
            "(e.g. configs/recipes/quick.yaml)"
        )
    raw = OmegaConf.load(path)
    if overrides:
        raw = OmegaConf.merge(raw, OmegaConf.from_dotlist(overrides))
    if "run_dir" not in raw or "stages" not in raw or not OmegaConf.is_list(raw.stages):
        raise CapVectorError(f"{path} needs `run_dir` and a list of `stages` (name, command, args)")
    for entry in raw.stages:
        check_entry(entry, path)
    raw.stages = expand_seeds(raw.stages, path)
    run_dir = Path(str(raw.run_dir))
    names = [str(s.name) for s in raw.stages]
    if len(set(names)) != len(names):
        raise CapVectorError(f"{path}: stage names must be unique, got {names}")
    raw.out = {name: stage_outputs(run_dir, name) for name in names}
    return run_dir, raw


def check_entry(entry: Any, path: str | Path) -> None:
    """A stage as the recipe wrote it: a mapping with a `name`, a `command`, and `args` as a list
    of words (a string would be split into characters, a nested list passed as its repr)."""
    from omegaconf import OmegaConf

    if not OmegaConf.is_dict(entry) or "name" not in entry or "command" not in entry:
        raise CapVectorError(
            f"{path}: every stage needs a `name` and a `command` (and `args`), got {entry!r}"
        )
    where = f"stage {str(entry.name)!r} in {path}"
    args = OmegaConf.to_container(entry, resolve=False).get("args", [])  # type: ignore[union-attr]
    if not isinstance(args, list):
        raise CapVectorError(
            f"{where}: `args` must be a list of strings (one per word, as typed on a shell), got "
            f"{args!r} ({type(args).__name__}); write args: [{args}]"
        )
    nested = [i for i, a in enumerate(args) if isinstance(a, list | dict)]
    if nested:
        raise CapVectorError(
            f"{where}: args[{nested[0]}] is {args[nested[0]]!r}, not a word; quote it "
            '(e.g. "--data.train_files=[a.hdf5, b.hdf5]")'
        )


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
        if stage == names[index] and output != "dir":
            raise CapVectorError(
                f"stage {stage!r} names its own output {reference}: a stage can read only other "
                f"stages' outputs (its own ${{out.{stage}.dir}} is where it writes)"
            )
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


def inputs(raw: Any, index: int, run_dir: Path) -> list[tuple[str, Path]]:
    """The other stages' outputs that stage ``index`` reads, as (stage, path in ``run_dir``)."""
    from omegaconf import OmegaConf

    entry = raw.stages[index]
    text = " ".join(map(str, OmegaConf.to_container(entry, resolve=False).get("args", [])))
    return [
        (stage, Path(stage_outputs(run_dir, stage)[output] + rest))
        for stage, output, rest in OUT_PATH.findall(text)
        if stage != str(entry.name)
    ]


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
    commands: Collection[str] = (),
) -> list[dict]:
    """Run the stages, up to ``jobs`` at a time once their dependencies have finished, each with
    ``threads`` torch threads, through ``launcher`` (default: the recipe's, ``local``); with
    ``only``, just those stages and what they wait for; with ``status``, print where they stand
    instead (``print_status``). ``commands``: the commands a stage may run (``capvector``'s; not
    checked when empty).

    The whole recipe is checked before any stage runs: its settings, every stage's command and
    arguments, what the stages wait for (no cycle) and every interpolation.
    Locally with ``jobs > 1``, and always through submitit, each stage's output goes to
    ``<stage>/log.txt``.
    """
    run_dir, raw = _load_raw(recipe, overrides)
    threads = _count_setting(raw, "threads", threads, DEFAULT_THREADS, recipe)
    jobs = _count_setting(raw, "jobs", jobs, None, recipe)  # submitit: no limit unless given
    launcher = _launcher_setting(raw, launcher)
    if commands:
        check_commands(raw, commands, recipe)
    names = [str(s.name) for s in raw.stages]
    waits_for = {names[i]: dependencies(raw, i) for i in range(len(names))}
    check_order(waits_for, recipe)
    scheduler = Scheduler(
        recipe, run_dir, raw, names, waits_for, make_launcher(launcher, jobs, threads), launcher,
        dry_run, quiet=launcher == "local" and (jobs or 1) == 1,
    )  # fmt: skip
    scheduler.check()
    if only:
        scheduler.keep_only(only)
    if status:
        stages = [scheduler.resolve(n) for n in scheduler.names]
        print_status(run_dir, stages, waits_for, scheduler.stale)
        return []
    return scheduler.run()


def _count_setting(
    raw: Any, key: str, given: int | None, default: int | None, path: str | Path
) -> int | None:
    """``jobs`` or ``threads``: the option given, else the recipe's, else ``default``; a whole
    number of at least 1."""
    value = raw.get(key, default) if given is None else given
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        raise CapVectorError(
            f"{path}: `{key}` must be an integer ({SETTINGS[key]}), got {value!r} "
            f"({type(value).__name__}); write e.g. {key}: 2"
        )
    if value < 1:
        raise CapVectorError(f"{key} ({SETTINGS[key]}) must be at least 1, got {value}")
    return value


SETTINGS = {"jobs": "stages run at once", "threads": "torch threads per stage"}


def _launcher_setting(raw: Any, given: str | None) -> str:
    launcher = str(given or raw.get("launcher", "local"))
    if launcher not in LAUNCHERS:
        raise CapVectorError(
            f"launcher must be one of {', '.join(LAUNCHERS)}, got {launcher!r}"
            f"{did_you_mean(launcher, LAUNCHERS)}"
        )
    return launcher


def check_commands(raw: Any, commands: Collection[str], path: str | Path) -> None:
    """Every stage runs one of ``commands``: a misspelt one is found before any stage runs."""
    for entry in raw.stages:
        if str(entry.command) not in commands:
            raise CapVectorError(
                f"stage {str(entry.name)!r} in {path}: "
                f"{unknown_name('command', str(entry.command), commands)}"
            )


@dataclass
class Scheduler:
    """Runs a checked recipe's stages: each once the stages it waits for have finished, up to the
    runner's room at once; stops the running ones when the recipe stops (Ctrl-C, SIGTERM, an
    error) and lets them finish when one fails. Its state is these fields."""

    recipe: str | Path
    run_dir: Path
    raw: Any
    names: list[str]
    """The stages to run, in the recipe's order."""
    waits_for: dict[str, set[str]]
    runner: LocalLauncher | SubmititLauncher
    launcher: str
    dry_run: bool
    quiet: bool
    """The stages' output is this process's (locally, one job at a time): no ``where`` lines."""
    stages: dict[str, Stage] = field(default_factory=dict)
    """Resolved, each right before it runs (it may use what earlier stages produced)."""
    stale: dict[str, str] = field(default_factory=dict)
    """Finished stages that run again, each with why: a stage still to run reads an output of
    theirs that is gone (a study carried to a new machine without its demos)."""
    finished: set[str] = field(default_factory=set)
    running: dict[str, Started] = field(default_factory=dict)
    failed: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.index = {str(s.name): i for i, s in enumerate(self.raw.stages)}
        self.find_stale()

    def resolve(self, name: str) -> Stage:
        return resolve_stage(self.raw, self.index[name], self.run_dir, self.recipe)

    def done_earlier(self, name: str) -> bool:
        return (self.run_dir / name / DONE).is_file() and name not in self.stale

    def find_stale(self) -> bool:
        """Add to ``stale`` every finished stage whose output a stage still to run reads and is
        gone, then what those read in turn; whether any was added."""
        pending = [n for n in self.names if not self.done_earlier(n)]
        found = False
        while pending:
            reader = pending.pop(0)  # the first in the recipe's order is the one named
            for stage, path in inputs(self.raw, self.index[reader], self.run_dir):
                if self.done_earlier(stage) and not path.exists():
                    self.stale[stage] = f"{path}, which {reader} reads, is gone"
                    pending.append(stage)
                    found = True
        return found

    def check(self) -> None:
        """Every stage's interpolations resolve and the runner can give it what it asks for: a typo
        fails now, not hours in."""
        for name in self.names:
            self.runner.check(name, self.resolve(name).resources)

    def keep_only(self, targets: list[str]) -> None:
        """Only ``targets`` and what they wait for (``required_stages``), found again while a
        stage to run makes a finished one stale (then what it waits for is needed again)."""
        every = self.names
        self.stale.clear()  # what only stages outside ``targets`` read is not needed
        while True:
            done = {n for n in every if self.done_earlier(n)}
            required = required_stages(self.waits_for, targets, done)
            self.names = [n for n in every if n in required]
            if not self.find_stale():
                return

    def run(self) -> list[dict]:
        if not self.dry_run:  # before anything starts: an earlier run's stage may still be running
            pids = {
                n: running_pid(self.run_dir / n) for n in self.names if not self.done_earlier(n)
            }
            busy = {n: pid for n, pid in pids.items() if pid is not None}
            if busy:
                raise CapVectorError(still_running(busy))
        self.run_dir.mkdir(parents=True, exist_ok=True)
        try:
            while len(self.finished) < len(self.names) and not self.failed:
                self.start_ready()
                # Nothing more can start until a stage ends (room, waits): resolving the stages
                # that wait at every poll cost a study's recipe ~10 % of a core beside its fits.
                while self.running and not self.reap_ended():
                    time.sleep(self.runner.poll_seconds)
            for name in list(self.running):  # a stage failed: let the others finish, then stop
                self.reap(name, self.running[name].wait())
        except BaseException:  # Ctrl-C, SIGTERM, an error: the local stages stop with the recipe
            self.stop()  # also while it waits for the others after a failure
            raise
        if self.failed:
            raise CapVectorError(
                f"stage(s) {self.failed} failed; fix and rerun the same command: finished stages "
                "are skipped and an interrupted fit resumes"
            )
        return collect_results([self.stages[n] for n in self.names])

    def start_ready(self) -> None:
        """Start (or skip, when done earlier) every stage whose waits are over, while there is
        room."""
        for name in self.names:
            if name in self.finished or name in self.running:
                continue
            done_earlier = self.done_earlier(name)
            if not (done_earlier or self.waits_for[name] <= self.finished):
                continue  # a finished stage waits for nothing: its inputs may be gone
            # Resolved only now, so the arguments can use what earlier stages produced.
            self.stages[name] = self.resolve(name)
            if done_earlier:
                stage = self.stages[name]
                changed = arguments_changed(stage, json.loads(stage.done_marker.read_text()))
                if changed:
                    changed = f"; {changed}: delete {stage.directory} to run it with these"
                print(f"{self.label(name)}: done earlier, skipped{changed}", flush=True)
                self.finished.add(name)
            elif self.runner.has_room(self.stages[name].resources):
                if name in self.stale:
                    print(f"{self.label(name)}: done earlier, but {self.stale[name]}: runs again",
                          flush=True)  # fmt: skip
                    if not self.dry_run:  # a rerun stopped halfway must not count as done
                        self.stages[name].done_marker.unlink()
                self.start(name)

    def label(self, name: str) -> str:
        number = self.names.index(name) + 1
        return f"[recipe {number}/{len(self.names)}] {name} ({self.stages[name].command})"

    def start(self, name: str) -> None:
        stage = self.stages[name]
        left = [n for n in self.names if n not in self.finished and n not in self.running
                and n != name and not self.done_earlier(n)]  # fmt: skip
        more = f": {', '.join(left[:3])}{', ...' if len(left) > 3 else ''}" if left else ""
        print(f"{self.label(name)} started; {len(left)} more to run{more}", flush=True)
        if self.dry_run:
            print("  " + " ".join(command_line(stage, self.launcher)[2:]))
            self.finished.add(name)
            return
        command = functools.partial(command_line, stage, self.launcher)
        self.running[name] = self.runner.start(
            name, stage.directory, command, stage.resources, stage.command == "fit"
        )
        if not self.quiet:
            print(f"  {self.running[name].where()}", flush=True)

    def reap_ended(self) -> bool:
        """Reap the stages that have ended; whether any had."""
        ended = False
        for name in list(self.running):
            code = self.running[name].poll()
            if code is not None:
                self.reap(name, code)
                ended = True
        return ended

    def reap(self, name: str, code: int) -> None:
        started = self.running.pop(name)
        if code != 0:
            self.failed.append(name)
            print(f"{self.label(name)} failed: {started.failure()}", flush=True)
            return
        self.finished.add(name)
        if not self.quiet:
            marker = json.loads(self.stages[name].done_marker.read_text())
            print(f"{self.label(name)} finished{took(marker)}", flush=True)

    def stop(self) -> None:
        """The running local stages stop and are waited for; SLURM jobs outlive the recipe, and
        the user is told which."""
        stopping = [name for name, started in self.running.items() if started.stop()]
        if stopping:
            print(f"capvector recipe: stopping {', '.join(stopping)}; run the same command "
                  "again to resume", flush=True)  # fmt: skip
            for name in stopping:
                self.running[name].wait()
        left = ", ".join(f"{n} ({s.where()})" for n, s in self.running.items() if n not in stopping)
        if left:  # SLURM jobs outlive the recipe: say which, in the state SLURM gives now
            print(f"capvector recipe: stopped waiting for {left}")


def print_status(
    run_dir: Path, stages: list[Stage], waits_for: dict[str, set[str]], stale: dict[str, str]
) -> None:
    """One line per stage: what its folder says (``stage_status``), and for a stage not started,
    the stages it still waits for; a finished stage in ``stale`` says why it runs again."""
    done = {s.name for s in stages if s.done_marker.is_file() and s.name not in stale}
    print(f"{run_dir}: {len(done)} of {len(stages)} stages done")
    width = max((len(s.name) for s in stages), default=0)
    for stage in stages:
        line = stage_status(stage)
        if stage.name in stale:
            line += f", but {stale[stage.name]}: runs again"
        waiting = sorted(n for n in waits_for[stage.name] if n not in done)
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
    its recent step time (validation not counted), its rollout validation or a running
    evaluation's progress and whether it would resume from a checkpoint, or not started."""
    if stage.done_marker.is_file():
        marker = json.loads(stage.done_marker.read_text() or "{}")
        changed = arguments_changed(stage, marker)
        return "done" + took(marker) + (f"; {changed}" if changed else "")
    if not stage.directory.exists():
        return "not started"
    pid = running_pid(stage.directory)
    state = "started, not done" if pid is None else f"running (pid {pid})" if pid else "running"
    label = PROGRESS_LABELS.get(stage.command)
    under_way = (
        progress_under_way(stage.directory / LOG, label) if pid is not None and label else ""
    )
    if stage.command != "fit":
        return f"{state}: {under_way}" if under_way else state
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
    if under_way:
        logged += f"; {under_way}"
    resumes = (
        "resumes from its last checkpoint" if checkpoint.is_file()
        else "no checkpoint yet: starts again"
    )  # fmt: skip
    return f"{state}: {logged}; {resumes}"


PROGRESS_LABELS = {"fit": VALIDATION_PROGRESS, "evaluate": EVALUATE_PROGRESS}
"""How the progress lines of a command's stage begin (``ProgressLines``), for ``--status``."""


def progress_under_way(log: Path, label: str) -> str:
    """The last progress line (``capvector.eval.rollout.ProgressLines``) beginning with ``label``
    in a running stage's log while its episodes are under way, or "": a fit's metrics stop at a
    rollout validation's step for all of it (two hours of LIBERO episodes here), which would look
    like a fit that hangs, and `capvector evaluate` logs nothing else until its table."""
    pattern = re.compile(rf"{re.escape(label)}[^:]*: (\d+)/(\d+) episodes.*")
    found = [m for line in log_tail(log, 20_000).splitlines() if (m := pattern.search(line))]
    return found[-1][0] if found and found[-1][1] != found[-1][2] else ""


def arguments_changed(stage: Stage, marker: dict) -> str:
    """How the arguments a finished stage ran with (its ``.done`` marker) differ from the recipe's
    now, e.g. "it ran with other arguments than the recipe's now (then --trainer.max_steps=100,
    now --trainer.max_steps=200)"; "" when they do not. A finished stage is never run again on its
    own, and an edited recipe would otherwise skip it in silence. Paths are compared within the run
    folder, however it was spelled then and now; a marker written before it recorded its run
    folder (``run_dir``) is not compared."""
    if "run_dir" not in marker or "command" not in marker:
        return ""
    then = marker["command"][1:]  # after "capvector.cli"
    if stage.command == "fit":  # what ``command_line`` adds after the stage's own arguments
        added = [i for i, a in enumerate(then) if a.startswith("--trainer.default_root_dir=")]
        then = then[: added[-1]] if added else then
    then = [_moved(a, marker["run_dir"], str(stage.directory.parent)) for a in then]
    now = [stage.command, *stage.args]
    changes = [
        f"then {' '.join(then[i1:i2]) or 'nothing'}, now {' '.join(now[j1:j2]) or 'nothing'}"
        for tag, i1, i2, j1, j2 in difflib.SequenceMatcher(a=then, b=now).get_opcodes()
        if tag != "equal"
    ]
    return (
        f"it ran with other arguments than the recipe's now ({'; '.join(changes)})"
        if changes
        else ""
    )


def _moved(argument: str, old: str, new: str) -> str:
    """``argument`` with every path inside folder ``old`` (alone, after ``=``, or in a ``[a, b]``
    list) moved into ``new``."""
    inside = rf"(?<![\w.~/-]){re.escape(old)}(?=/|$|[\],])"
    return re.sub(inside, lambda _: new, argument)


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


def main(argv: list[str] | None = None, commands: Collection[str] = ()) -> int:
    """``capvector recipe``; ``commands``: those its stages may run (``capvector.cli``'s)."""
    return run_tool(recipe_cli, argv, "recipe", commands=list(commands))


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
    commands: Collection[str] = (),
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
        commands: the commands a stage may run (given by ``capvector.cli``, not an option)
    """
    rows = run(config, list(overrides), dry_run, jobs, only, threads, launcher, status, commands)
    if rows:
        print("\nResults\n" + format_success_table(rows))
