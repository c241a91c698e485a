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
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capvector.errors import CapVectorError
from capvector.fileio import atomic_write_bytes

DONE = ".done"
FIT_VERSION = "version_0"


@dataclass
class Stage:
    name: str
    command: str
    args: list[str]
    directory: Path

    @property
    def done_marker(self) -> Path:
        return self.directory / DONE


def stage_outputs(run_dir: Path, name: str) -> dict[str, str]:
    directory = run_dir / name
    fit_dir = directory / "fit" / FIT_VERSION
    return {
        "dir": str(directory),
        "export": str(fit_dir / "export"),
        "ckpt": str(fit_dir / "checkpoints" / "last.ckpt"),
    }


def _best_scale(sweep_dir: str) -> str:
    """Resolver ``${best_scale:DIR}``: the best λ of a finished ``sweep-scale`` stage."""
    from capvector.sweep import best_scale

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
        OmegaConf.register_new_resolver("best_scale", _best_scale)
    raw = OmegaConf.load(path)
    if overrides:
        raw = OmegaConf.merge(raw, OmegaConf.from_dotlist(overrides))
    if "run_dir" not in raw or "stages" not in raw:
        raise CapVectorError(f"{path} needs `run_dir` and a list of `stages` (name, command, args)")
    run_dir = Path(str(raw.run_dir))
    names = [str(s.name) for s in raw.stages]
    if len(set(names)) != len(names):
        raise CapVectorError(f"{path}: stage names must be unique, got {names}")
    raw.out = {name: stage_outputs(run_dir, name) for name in names}
    return run_dir, raw


def resolve_stage(raw: Any, index: int, run_dir: Path, path: str | Path) -> Stage:
    """One stage with its interpolations resolved. Done right before the stage runs, so a stage
    can use what an earlier one produced (``${best_scale:${out.sweep.dir}}``)."""
    from omegaconf import OmegaConf

    entry: Any = OmegaConf.to_container(raw.stages[index], resolve=True)
    if "command" not in entry:
        raise CapVectorError(f"stage {entry.get('name')!r} in {path} has no `command`")
    args = [str(a) for a in entry.get("args", [])]
    return Stage(entry["name"], entry["command"], args, run_dir / entry["name"])


def command_line(stage: Stage) -> list[str]:
    """The ``capvector`` command of a stage; fit stages get their folder, logger and resume point."""
    args = [stage.command, *stage.args]
    if stage.command == "fit":
        outputs = stage_outputs(stage.directory.parent, stage.name)
        args += [
            f"--trainer.default_root_dir={stage.directory}",
            "--trainer.logger=lightning.pytorch.loggers.CSVLogger",
            f"--trainer.logger.init_args.save_dir={stage.directory}",
            "--trainer.logger.init_args.name=fit",
            f"--trainer.logger.init_args.version={FIT_VERSION}",
            "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
            "--trainer.callbacks.save_last=true",
            "--trainer.callbacks.every_n_train_steps=50",
        ]
        if Path(outputs["ckpt"]).is_file():
            args.append(f"--ckpt_path={outputs['ckpt']}")  # resume the interrupted stage
    return [sys.executable, "-m", "capvector.cli", *args]


def run(
    recipe: str | Path, overrides: list[str] | None = None, dry_run: bool = False
) -> list[dict]:
    run_dir, raw = _load_raw(recipe, overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    names = [str(s.name) for s in raw.stages]
    stages = []
    for index in range(len(names)):
        stage = resolve_stage(raw, index, run_dir, recipe)
        stages.append(stage)
        status = f"[recipe {index + 1}/{len(names)}] {stage.name} ({stage.command})"
        if stage.done_marker.is_file():
            print(f"{status}: done earlier, skipped", flush=True)
            continue
        print(f"{status}; then: {', '.join(names[index + 1 :]) or 'nothing'}", flush=True)
        cmd = command_line(stage)
        if dry_run:
            print("  " + " ".join(cmd[2:]))
            continue
        stage.directory.mkdir(parents=True, exist_ok=True)
        start = time.time()
        completed = subprocess.run(cmd)
        if completed.returncode != 0:
            raise CapVectorError(
                f"stage {stage.name!r} failed (exit {completed.returncode}); fix it and rerun the same "
                "command: finished stages are skipped and an interrupted fit resumes"
            )
        marker = {
            "command": cmd[2:],
            "seconds": round(time.time() - start, 1),
            "finished": time.ctime(),
        }
        atomic_write_bytes(stage.done_marker, json.dumps(marker, indent=2).encode())
    return collect_results(stages)


def collect_results(stages: list[Stage]) -> list[dict]:
    """Rows of every evaluate stage's ``--json`` output, tagged with the stage name."""
    rows = []
    for stage in stages:
        if stage.command != "evaluate" or "--json" not in stage.args:
            continue
        path = Path(stage.args[stage.args.index("--json") + 1])
        if path.is_file():
            rows += [{"stage": stage.name, **row} for row in json.loads(path.read_text())]
    return rows


def format_results(rows: list[dict]) -> str:
    lines = ["| stage | task | robot | episodes | success | 95% CI |", "|---|---|---|---|---|---|"]
    for r in rows:
        low, high = r["ci95"]
        lines.append(
            f"| {r['stage']} | {r['task']} | {r['robot']} | {r['episodes']} | "
            f"{r['success_rate']:.0%} | {low:.0%}–{high:.0%} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="capvector recipe", description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="recipe YAML (configs/recipes/*.yaml)")
    parser.add_argument("--dry-run", action="store_true", help="print the stage commands only")
    parser.add_argument("overrides", nargs="*", help="dotlist overrides, e.g. run_dir=runs/x")
    args = parser.parse_args(argv)
    rows = run(args.config, args.overrides, args.dry_run)
    if rows:
        print("\nResults\n" + format_results(rows))
    return 0
