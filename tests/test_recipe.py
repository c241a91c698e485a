"""`capvector recipe`: stages in order, outputs in one run folder, resume after an interruption."""

from __future__ import annotations

import collections
import csv
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

import capvector.workflows.recipe as recipe_module
from capvector.cli import main
from capvector.errors import CapVectorError
from capvector.workflows.launchers import record_run, write_done
from capvector.workflows.recipe import (
    Stage,
    command_line,
    dependencies,
    expand_seeds,
    load_recipe,
    required_stages,
    resolve_stage,
    run,
    stage_status,
)

REPO = Path(__file__).resolve().parents[1]


def recipe_file(tmp_path: Path, data: Path) -> Path:
    fit = [
        "--config",
        str(REPO / "configs/debug.yaml"),
        f"--data.train_files=[{data}]",
        "--data.batch_size=4",
        "--data.eval_tasks=null",  # no rollouts: the stages and their resume are what is tested
        "--trainer.log_every_n_steps=1",
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


@pytest.mark.slow
def test_recipe_runs_resumes_and_never_redoes_a_stage(tmp_path: Path, demo_file: Path) -> None:
    recipe = recipe_file(tmp_path, demo_file)
    run_dir, stages = load_recipe(recipe)
    # An interrupted run: the downstream fit died after 2 of its 4 steps (its checkpoint exists,
    # its .done marker does not). Run the earlier stages and half of downstream by hand, in this
    # process (`capvector`'s main, with the arguments the recipe gives a stage; every path in them
    # is absolute): they only set the scene, and 4 processes would import torch 4 times more. The
    # recipe below starts its stage as a process, as always.
    launcher = [sys.executable, "-m", "capvector.cli"]
    for stage in stages[:3]:
        line = command_line(stage)
        assert line[:3] == launcher and main(line[3:]) == 0, line
        (stage.directory / ".done").write_text("{}")
    downstream = stages[3]
    half = command_line(downstream)[3:]
    half = [a if a != "--trainer.max_steps=4" else "--trainer.max_steps=2" for a in half]
    half += ["--trainer.callbacks.every_n_train_steps=2"]
    assert main(half) == 0
    markers = {s.name: (s.directory / ".done").stat().st_mtime_ns for s in stages[:3]}
    status = capvector("recipe", "--config", str(recipe), "--status")
    assert status.returncode == 0, status.stderr[-3000:]
    assert f"{tmp_path / 'run'}: 3 of 4 stages done" in status.stdout
    assert "  extract     done\n" in status.stdout
    assert (
        "  downstream  started, not done: step 1 of 2 logged; resumes from its last checkpoint"
        in status.stdout
    )

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
    # The metrics logged before the interruption are still there, followed by the resumed steps.
    with (downstream.directory / "fit" / "version_0" / "metrics.csv").open() as f:
        steps = {int(row["step"]) for row in csv.DictReader(f)}
    assert steps == {0, 1, 2, 3}
    status = capvector("recipe", "--config", str(recipe), "--status").stdout
    assert "4 of 4 stages done" in status
    assert re.search(r"  downstream  done in \d+ s\n", status)


def fit_stage_folder(tmp_path: Path) -> tuple[Stage, Path]:
    """A recipe's one fit stage, and its fit's folder with the config Lightning saved there
    (8,000 steps)."""
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(f"run_dir: {tmp_path}\nstages:\n  - {{name: sft, command: fit, args: []}}\n")
    (stage,) = load_recipe(recipe)[1]
    fit_dir = stage.directory / "fit" / "version_0"
    fit_dir.mkdir(parents=True)
    (fit_dir / "config.yaml").write_text("trainer:\n  max_steps: 8000\n")
    return stage, fit_dir


def test_status_gives_a_fits_step_of_its_max_steps_and_its_recent_step_time(tmp_path: Path) -> None:
    """What `--status` says of a stopped fit, from the files Lightning and StepCost wrote."""
    stage, fit_dir = fit_stage_folder(tmp_path)
    rows = ["epoch,perf/step_seconds,step,train/loss"]
    rows += [f"0,{seconds},{step},0.5" for step, seconds in ((49, 2.0), (99, 0.9), (149, 0.8))]
    rows += ["0,,149,"]  # a validation row: no step time
    (fit_dir / "metrics.csv").write_text("\n".join(rows) + "\n")
    assert stage_status(stage) == (
        "started, not done: step 149 of 8000 logged (0.90 s per step lately: 2.0 h of steps "
        "left); no checkpoint yet: starts again"
    )
    (fit_dir / "config.yaml").write_text("trainer:\n  max_steps: 1000\n")
    assert "(0.90 s per step lately: 13 min of steps left)" in stage_status(stage)
    (fit_dir / "config.yaml").write_text("trainer:\n  max_steps: -1\n")  # no limit: no total
    assert stage_status(stage).startswith(
        "started, not done: step 149 logged (0.90 s per step lately)"
    )


def test_status_gives_a_running_fits_rollout_validation_under_way(tmp_path: Path) -> None:
    """The metrics stop at a validation's step for all of it: `--status` adds the last progress
    line of a validation under way from the running fit's log, and nothing once it is done or
    when the fit is not running (it validates again when resumed)."""
    from capvector.workflows.launchers import LOG, lock_stage

    stage, fit_dir = fit_stage_folder(tmp_path)
    (fit_dir / "metrics.csv").write_text("epoch,step,train/loss\n0,3999,0.5\n")
    under_way = (
        "rollout validation at step 4000: 36/100 episodes, 9 succeeded, 44 min, about 78 min left"
    )
    log = stage.directory / LOG
    log.write_text(
        f"Epoch 0 \r\n[info] using task orders\n{under_way.replace('36/', '12/')}\n{under_way}\n"
    )
    assert under_way not in stage_status(stage)  # stopped: the validation starts again
    lock = lock_stage(stage.directory)  # as the fit's process holds it
    try:
        assert stage_status(stage) == (
            f"running: step 3999 of 8000 logged; {under_way}; no checkpoint yet: starts again"
        )
        with log.open("a") as f:
            f.write("rollout validation at step 4000: 100/100 episodes, 25 succeeded, 2.0 h\n")
        assert "rollout validation" not in stage_status(stage)
    finally:
        os.close(lock)


def test_status_gives_a_running_evaluations_progress(tmp_path: Path) -> None:
    """A `capvector evaluate` stage logs nothing else until its table: `--status` adds its last
    progress line while it runs, and nothing when it is stopped or its episodes are all done."""
    from capvector.workflows.launchers import LOG, lock_stage

    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(f"run_dir: {tmp_path}\nstages:\n  - {{name: eval, command: evaluate}}\n")
    (stage,) = load_recipe(recipe)[1]
    stage.directory.mkdir()
    under_way = "evaluating: 36/100 episodes, 9 succeeded, 44 min, about 78 min left"
    log = stage.directory / LOG
    log.write_text(f"libero_spatial/5/0: failure after 220 steps\n{under_way}\n[info] evaluating\n")
    assert stage_status(stage) == "started, not done"
    lock = lock_stage(stage.directory)  # as the evaluation's process holds it
    try:
        assert stage_status(stage) == f"running: {under_way}"
        with log.open("a") as f:
            f.write("evaluating: 100/100 episodes, 25 succeeded, 2.0 h\n")
        assert stage_status(stage) == "running"
    finally:
        os.close(lock)


def test_a_stage_stopped_and_resumed_is_done_in_the_time_of_all_its_runs(tmp_path: Path) -> None:
    """A fit stopped once and resumed: `--status` gives its two runs' time, not its last run's."""
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(f"run_dir: {tmp_path}\nstages:\n  - {{name: sft, command: fit, args: []}}\n")
    (stage,) = load_recipe(recipe)[1]
    stage.directory.mkdir(parents=True)
    now = time.time()
    record_run(stage.directory, began=now - 100)  # stopped after 100 s
    write_done(stage.directory, ["python", "-m", "capvector.cli", "fit"], began=now - 30)
    marker = json.loads(stage.done_marker.read_text())
    assert marker["runs"] == 2 and marker["seconds"] == pytest.approx(30, abs=1)
    assert marker["seconds_all_runs"] == pytest.approx(130, abs=1)
    assert re.fullmatch(r"done in 1[23]\d s over 2 runs \(the last [23]\d s\)", stage_status(stage))
    del marker["runs"], marker["seconds_all_runs"]  # a marker from before runs were counted
    stage.done_marker.write_text(json.dumps(marker))
    legacy = r"done in [23]\d s \(its last run; earlier runs were not counted\)"
    assert re.fullmatch(legacy, stage_status(stage))


def test_recipe_errors_are_clear(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("stages: []\n")
    completed = capvector("recipe", "--config", str(bad))
    assert completed.returncode == 2 and "needs `run_dir`" in completed.stderr


# Every recipe shipped (a config with stages; the others are fit configs its stages add).
RECIPES = sorted(
    p.name for p in (REPO / "configs/recipes").glob("*.yaml") if "\nstages:" in p.read_text()
)


@pytest.mark.parametrize("name", RECIPES)
def test_shipped_recipes_resolve(name: str) -> None:
    run_dir, stages = load_recipe(REPO / "configs/recipes" / name, ["run_dir=/tmp/x"])
    assert str(run_dir) == "/tmp/x" and all("${" not in a for s in stages for a in s.args)


def test_seeds_make_one_fit_stage_per_seed_and_after_waits_for_all_of_them(
    tmp_path: Path,
) -> None:
    stages = [
        {"name": "pre", "command": "fit", "args": ["--trainer.max_steps=2"]},
        {"name": "down", "command": "fit", "seeds": [0, 2], "after": ["pre"],
         "args": ["--model.pretrained=${out.pre.export}"]},
        {"name": "report", "command": "report", "after": ["down"], "args": ["${out.down_s2.dir}"]},
        {"name": "eval", "command": "evaluate", "seeds": [2],
         "args": ["--ckpt", "${out.down.export}", "--json", "${out.eval.dir}/r.json"]},
    ]  # fmt: skip
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    run_dir, resolved = load_recipe(path)
    assert [s.name for s in resolved] == ["pre", "down_s0", "down_s2", "report", "eval_s2"]
    pretrained = f"--model.pretrained={run_dir}/pre/fit/version_0/export"
    assert resolved[1].args == [pretrained, "--seed_everything=0"]
    assert resolved[2].args == [pretrained, "--seed_everything=2"]
    assert resolved[3].args == [str(run_dir / "down_s2")]
    # A seeded non-fit stage reads its own seed's outputs of seeded stages, with no --seed_everything.
    export_s2 = f"{run_dir}/down_s2/fit/version_0/export"
    assert resolved[4].args == ["--ckpt", export_s2, "--json", f"{run_dir}/eval_s2/r.json"]
    from omegaconf import OmegaConf

    raw = OmegaConf.create({"stages": expand_seeds(OmegaConf.create(stages), path)})
    assert dependencies(raw, 3) == {"down_s0", "down_s2"}
    assert dependencies(raw, 2) == {"pre"}
    assert dependencies(raw, 4) == {"report", "down_s2"}

    stages[2]["seeds"] = [0]  # a seeded report that reads no seeded stage
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    with pytest.raises(CapVectorError, match="`seeds` needs .* name an earlier seeded stage"):
        load_recipe(path)


def test_a_stage_waits_for_the_one_before_its_after_list_and_the_outputs_it_names() -> None:
    from omegaconf import OmegaConf

    raw = OmegaConf.create({"stages": [
        {"name": "a", "command": "demos"},
        {"name": "b", "command": "demos", "after": []},
        {"name": "c", "command": "fit", "after": ["b"], "args": ["--x=${out.a.export}"]},
        {"name": "d", "command": "fit"},
    ]})  # fmt: skip
    assert [dependencies(raw, i) for i in range(4)] == [set(), set(), {"a", "b"}, {"c"}]
    raw.stages[3].after = ["e"]
    with pytest.raises(CapVectorError, match=r"`after` names \['e'\], which are not earlier"):
        dependencies(raw, 3)


def test_a_stage_waits_for_a_later_stage_it_names_and_a_cycle_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stages = [
        {"name": "a", "command": "backbone-info", "args": ["${out.c.dir}"]},
        {"name": "b", "command": "backbone-info", "after": []},
        {"name": "c", "command": "backbone-info", "after": ["b"]},
    ]
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    run(path, dry_run=True)
    started = [line.split("] ")[1].split(" ")[0] for line in capsys.readouterr().out.splitlines()
               if line.startswith("[recipe") and " started; " in line]  # fmt: skip
    assert started == ["b", "c", "a"]
    stages[2]["after"] = ["a"]  # a waits for c, which waits for a
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run2"), "stages": stages}))
    with pytest.raises(CapVectorError, match="in a cycle: a waits for c waits for a"):
        run(path, dry_run=True)
    assert not (tmp_path / "run2").exists()


def test_jobs_run_independent_stages_together_and_stop_at_a_failure(tmp_path: Path) -> None:
    info = ["openvla-oft-tiny"]
    stages = [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "backbone-info", "after": [], "args": info},
        {"name": "c", "command": "backbone-info", "after": ["a", "b"], "args": ["no-such-preset"]},
        {"name": "d", "command": "backbone-info", "args": info},
    ]
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "jobs": 2, "stages": stages}))
    completed = capvector("recipe", "--config", str(path))
    assert completed.returncode == 2 and "stage(s) ['c'] failed" in completed.stderr
    run = tmp_path / "run"
    # a and b ran at once (each logging to its own file), c only after both, d never.
    assert (run / "a/.done").is_file() and (run / "b/.done").is_file()
    assert not (run / "c/.done").exists() and not (run / "d").exists()
    assert "openvla-oft-tiny" in (run / "a/log.txt").read_text()
    assert "no-such-preset" in (run / "c/log.txt").read_text()  # the error, shown as well:
    assert "no-such-preset" in completed.stdout
    started = [line.split("] ")[1].split(" ")[0] for line in completed.stdout.splitlines()
               if line.startswith("[recipe") and " started; " in line]  # fmt: skip
    assert started == ["a", "b", "c"]
    a_done = (run / "a/.done").stat().st_mtime
    assert (run / "c/log.txt").stat().st_ctime >= a_done


def test_a_stage_without_room_is_resolved_again_only_when_a_stage_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stage ready to start but without room is resolved once per stage that ends (what it
    reads may change then), not at every poll: beside two fits that ran for hours, the mini
    study's recipe spent ~10 % of a core resolving its seven waiting stages 5 times a second."""
    info = ["openvla-oft-tiny"]
    stages = [{"name": n, "command": "backbone-info", "after": [], "args": info} for n in "ab"]
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "jobs": 1, "stages": stages}))
    resolved: collections.Counter[str] = collections.Counter()

    def counted(raw, index, run_dir, recipe):  # the real resolution, counted
        resolved[str(raw.stages[index].name)] += 1
        return resolve_stage(raw, index, run_dir, recipe)

    monkeypatch.setattr(recipe_module, "resolve_stage", counted)
    run(path)  # a runs for seconds (a process that imports torch) while b waits for room
    assert (tmp_path / "run/b/.done").is_file()
    # The recipe's check, b's first try (no room) and its start once a ended.
    assert resolved["b"] == 3, resolved


def test_only_runs_the_named_stages_and_what_they_wait_for(tmp_path: Path) -> None:
    stages = [
        {"name": "a", "command": "backbone-info", "args": ["openvla-oft-tiny"]},
        {"name": "b", "command": "backbone-info", "after": [], "args": ["openvla-oft-tiny"]},
        {"name": "c", "command": "fit", "after": ["b"], "args": ["--x=${out.a.export}"]},
        {"name": "d", "command": "fit", "seeds": [0, 1], "after": ["a"]},
        {"name": "e", "command": "report", "after": ["d"]},
    ]
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    from omegaconf import OmegaConf

    raw = OmegaConf.create({"stages": expand_seeds(OmegaConf.create(stages), path)})
    waits_for = {str(s.name): dependencies(raw, i) for i, s in enumerate(raw.stages)}
    assert required_stages(waits_for, ["e"]) == {"a", "d_s0", "d_s1", "e"}
    assert required_stages(waits_for, ["d"]) == {"a", "d_s0", "d_s1"}  # a seeded stage: all seeds
    assert required_stages(waits_for, ["c", "d_s1"]) == {"a", "b", "c", "d_s1"}
    with pytest.raises(CapVectorError, match="--only names 'f', which is no stage"):
        required_stages(waits_for, ["f"])
    # What only finished stages wait for is not needed (a study moved without its demos).
    assert required_stages(waits_for, ["e"], done={"d_s0", "d_s1"}) == {"d_s0", "d_s1", "e"}
    assert required_stages(waits_for, ["e"], done={"d_s0"}) == {"a", "d_s0", "d_s1", "e"}

    (tmp_path / "run" / "b").mkdir(parents=True)
    (tmp_path / "run" / "b" / ".done").write_text("{}")  # finished in an earlier run
    completed = capvector("recipe", "--config", str(path), "--dry-run", "--only", "c")
    assert completed.returncode == 0, completed.stderr[-3000:]
    started = [line.split("] ")[1].split(" ")[0] for line in completed.stdout.splitlines()
               if line.startswith("[recipe") and " started; " in line]  # fmt: skip
    assert started == ["a", "c"]
    # What is left counts neither stages outside --only nor finished ones.
    assert "[recipe 1/3] a (backbone-info) started; 1 more to run: c" in completed.stdout
    assert "[recipe 3/3] c (fit)" in completed.stdout

    # --status runs nothing: what each stage (of --only's) waits for.
    status = capvector("recipe", "--config", str(path), "--status", "--only", "c", "e")
    assert status.returncode == 0, status.stderr[-3000:]
    assert status.stdout.splitlines() == [
        f"{tmp_path / 'run'}: 1 of 6 stages done",
        "  a     not started",
        "  b     done",
        "  c     not started; waits for a",
        "  d_s0  not started; waits for a",
        "  d_s1  not started; waits for a",
        "  e     not started; waits for d_s0, d_s1",
    ]
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["b"]

    for seed in "01":  # d's fits finished, their input a gone: e runs, a does not
        (tmp_path / "run" / f"d_s{seed}").mkdir()
        (tmp_path / "run" / f"d_s{seed}" / ".done").write_text("{}")
    completed = capvector("recipe", "--config", str(path), "--dry-run", "--only", "e")
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert "[recipe 1/3] d_s0 (fit): done earlier, skipped" in completed.stdout
    assert "[recipe 3/3] e (report) started; 0 more to run" in completed.stdout
    assert " a (" not in completed.stdout


def test_a_finished_stage_whose_output_a_stage_to_run_reads_is_gone_runs_again(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A study carried to a new machine without its demos: the demo stage's marker says done, but
    a fit still to run reads its folder, so it records them again rather than the fit failing."""
    stages = [
        {"name": "a", "command": "backbone-info", "args": ["openvla-oft-tiny"]},
        {"name": "b", "command": "backbone-info", "args": ["openvla-oft-tiny", "${out.a.dir}/demos"]},
    ]  # fmt: skip
    path = tmp_path / "recipe.yaml"
    path.write_text(json.dumps({"run_dir": str(tmp_path / "run"), "stages": stages}))
    (tmp_path / "run" / "a").mkdir(parents=True)
    write_done(tmp_path / "run" / "a", ["python", "-m", "capvector.cli", "backbone-info",
               "openvla-oft-tiny"], began=time.time() - 60)  # finished on another machine  # fmt: skip
    done = tmp_path / "run" / "a" / ".done"

    run(path, status=True)
    gone = f"{tmp_path / 'run' / 'a' / 'demos'}, which b reads, is gone: runs again"
    assert capsys.readouterr().out.splitlines() == [
        f"{tmp_path / 'run'}: 0 of 2 stages done",
        f"  a  done in 60 s, but {gone}",
        "  b  not started; waits for a",
    ]
    run(path, dry_run=True)
    assert f"[recipe 1/2] a (backbone-info): done earlier, but {gone}" in capsys.readouterr().out
    assert done.is_file()  # a dry run changes nothing
    run(path, only=["a"], dry_run=True)  # no stage to run reads it: nothing to record again
    assert "a (backbone-info): done earlier, skipped" in capsys.readouterr().out

    with pytest.raises(CapVectorError, match=r"stage\(s\) \['b'\] failed"):  # its extra argument
        run(path)
    assert f"a (backbone-info): done earlier, but {gone}" in capsys.readouterr().out
    assert json.loads(done.read_text())["runs"] == 2  # a ran again before b started

    (tmp_path / "run" / "a" / "demos").mkdir()  # its output there: a is done again
    run(path, dry_run=True)
    assert "a (backbone-info): done earlier, skipped" in capsys.readouterr().out


def test_a_finished_stage_that_ran_with_other_arguments_is_skipped_and_says_what_changed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """An edited recipe never runs a finished stage again on its own, but says what changed since
    it ran. What the recipe adds to a fit (its folder, loggers, the checkpoint it resumed from) and
    the run folder spelled another way (relative then, absolute now) are not changes."""
    monkeypatch.chdir(tmp_path)

    def recipe(run_dir: str, steps: int) -> Path:
        args = [f"--trainer.max_steps={steps}", "--data.train_files=[${run_dir}/demos, x.hdf5]"]
        stages = [{"name": "sft", "command": "fit", "args": args}]
        path = tmp_path / "recipe.yaml"
        path.write_text(json.dumps({"run_dir": run_dir, "stages": stages}))
        return path

    (ran,) = load_recipe(recipe("run", steps=100))[1]
    ran.directory.mkdir(parents=True)
    resumed = [*command_line(ran), f"--ckpt_path={ran.directory}/fit/last.ckpt"]
    write_done(ran.directory, resumed, began=time.time() - 60)

    path = recipe(str(tmp_path / "run"), steps=200)
    changed = "it ran with other arguments than the recipe's now (then --trainer.max_steps=100, "
    changed += "now --trainer.max_steps=200)"
    run(path, status=True)
    assert capsys.readouterr().out.splitlines()[1] == f"  sft  done in 60 s; {changed}"
    run(path, dry_run=True)
    delete = f"delete {tmp_path / 'run' / 'sft'} to run it with these"
    assert f"sft (fit): done earlier, skipped; {changed}: {delete}\n" in capsys.readouterr().out
    assert ran.done_marker.is_file()

    run(recipe(str(tmp_path / "run"), steps=100), dry_run=True)  # as it ran: nothing to say
    assert capsys.readouterr().out.endswith("sft (fit): done earlier, skipped\n")
