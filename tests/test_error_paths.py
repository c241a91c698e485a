"""One error path for every command: bad input raised anywhere (a tool, LightningCLI's parser, a
library reading a cut-short file) is one line from ``capvector.cli.main`` with exit code 2, before
anything is written and with the inputs byte for byte as they were; a bug keeps its traceback."""

from __future__ import annotations

import errno
import json
import re
import shlex
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from safetensors.torch import load_file, save_file

from capvector import cli
from capvector.cli import main
from conftest import UPSTREAM_FIXTURES
from test_cli_errors import fit_args, inputs, tree_digest  # noqa: F401 (inputs: a fixture)
from test_lerobot import CAMERAS, write_lerobot_v3


def _cut(path: Path) -> None:
    """What an interrupted copy or save leaves: the first half of the file."""
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _sharded_original(folder: Path) -> Path:
    """The OpenVLA-OFT fixture with its VLM weights in two shards + index, as save_pretrained
    writes a large model."""
    shutil.copytree(UPSTREAM_FIXTURES / "openvla_oft" / "libero", folder)
    state = load_file(str(folder / "model.safetensors"))
    (folder / "model.safetensors").unlink()
    names = sorted(state)
    weight_map = {}
    for i, keys in enumerate((names[::2], names[1::2]), start=1):
        shard = f"model-0000{i}-of-00002.safetensors"
        save_file({k: state[k] for k in keys}, str(folder / shard))
        weight_map.update(dict.fromkeys(keys, shard))
    (folder / "model.safetensors.index.json").write_text(json.dumps({"weight_map": weight_map}))
    return folder


def _recipe(path: Path, run_dir: Path, stages: list[dict], **settings: object) -> Path:
    path.write_text(json.dumps({"run_dir": str(run_dir), "stages": stages, **settings}))
    return path


@pytest.fixture(scope="module")
def bad(tmp_path_factory: pytest.TempPathFactory, inputs: Path) -> Path:  # noqa: F811
    """Inputs cut short or naming what is not there, each as a user would meet it."""
    root = tmp_path_factory.mktemp("bad")
    missing = _sharded_original(root / "missing_shard")
    (missing / "model-00002-of-00002.safetensors").unlink()
    _cut(_sharded_original(root / "cut_shard") / "model-00002-of-00002.safetensors")
    shutil.copytree(UPSTREAM_FIXTURES / "openvla_oft" / "libero", root / "cut_component")
    _cut(next((root / "cut_component").glob("action_head--*checkpoint.pt")))
    info = ["openvla-oft-tiny"]
    _recipe(root / "nosuch.yaml", root / "never" / "run", [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "backbone-info", "args": ["${out.nosuch.export}"]},
    ])  # fmt: skip
    _recipe(root / "cycle.yaml", root / "never" / "run", [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "backbone-info", "args": ["${out.c.dir}"]},
        {"name": "c", "command": "backbone-info", "args": info},  # after b, the stage before it
    ])  # fmt: skip
    (root / "typo.yaml").write_text("trainer:\n  max_stesp: 1\n")
    write_lerobot_v3(root / "lerobot")
    (root / "libero.yaml").write_text("data:\n  eval_tasks:\n    - {suite: libero_spatial}\n")
    _recipe(root / "jobs_word.yaml", root / "never" / "run", [
        {"name": "a", "command": "backbone-info", "args": info},
    ], jobs="two")  # fmt: skip
    _recipe(root / "own_output.yaml", root / "never" / "run", [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "fit", "args": ["--model.pretrained=${out.b.export}"]},
    ])  # fmt: skip
    _recipe(root / "unknown_command.yaml", root / "never" / "run", [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "exportt", "args": info},
    ])  # fmt: skip
    _recipe(root / "string_args.yaml", root / "never" / "run", [
        {"name": "a", "command": "backbone-info", "args": info},
        {"name": "b", "command": "backbone-info", "args": "openvla-oft-tiny"},
    ])  # fmt: skip
    (root / "loop").mkdir()  # a log folder whose path goes round in symlinks
    (root / "loop" / "a").symlink_to(root / "loop" / "b")
    (root / "loop" / "b").symlink_to(root / "loop" / "a")
    # A real one-step fit's checkpoint, then cut as a run killed while saving it leaves it; its
    # export with a cut tokenizer.json.
    runs = root / "runs"
    assert main(fit_args(inputs, runs, "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint",
                         "--trainer.callbacks.save_last=true",
                         "--trainer.callbacks+=capvector.callbacks.ExportOnFitEnd",
                         f"--trainer.callbacks.dirpath={root / 'cut_tokenizer'}")) == 0  # fmt: skip
    _cut(runs / "lightning_logs" / "version_0" / "checkpoints" / "last.ckpt")
    _cut(root / "cut_tokenizer" / "tokenizer.json")
    # LIBERO start states from a folder whose task-0 file was cut short while copying.
    from capvector.envs.libero.demos import demo_file_name

    (root / "cut_demos").mkdir()
    shutil.copy(inputs / "demos.hdf5", root / "cut_demos" / demo_file_name("libero_spatial", 0))
    _cut(root / "cut_demos" / demo_file_name("libero_spatial", 0))
    # A vector written before metadata digests, whose JSON claims Pi0.5 (edited, or mixed up).
    shutil.copytree(inputs / "oft_vector", root / "old_vector")
    meta = json.loads((root / "old_vector" / "capability_vector.json").read_text())
    del meta["metadata_sha256"]
    for source in meta["sources"].values():
        source.update(family="pi05", preset="pi05-tiny")
    (root / "old_vector" / "capability_vector.json").write_text(json.dumps(meta))
    return root


Case = Callable[[Path, Path, Path], list[str]]  # (inputs, bad inputs, out) -> argv

CASES: dict[str, tuple[Case, str]] = {
    "import-original: an index naming a missing shard": (
        lambda i, b, o: ["import-original", "--preset", "openvla-oft-tiny", "--folder", str(b / "missing_shard"), "--out", str(o / "x")],
        r"model\.safetensors\.index\.json names 1 shard\(s\) missing from .*missing_shard, e\.g\. `model-00002-of-00002\.safetensors`: the folder is incomplete",
    ),
    "import-original: a truncated shard": (
        lambda i, b, o: ["import-original", "--preset", "openvla-oft-tiny", "--folder", str(b / "cut_shard"), "--out", str(o / "x")],
        r"cannot read .*cut_shard/model-00002-of-00002\.safetensors \(.*\): it is incomplete, corrupt or not a safetensors file; copy or download it again",
    ),
    "import-original: a truncated component checkpoint": (
        lambda i, b, o: ["import-original", "--preset", "openvla-oft-tiny", "--folder", str(b / "cut_component"), "--out", str(o / "x")],
        r"cannot read .*cut_component/action_head--5_checkpoint\.pt .*not a torch file; copy or download it again",
    ),
    "evaluate: a misspelt task, before the checkpoint is read": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--task", "Liftt", "--json", str(o / "r.json")],
        r"unknown task or task set 'Liftt' \(did you mean Lift\?\); known: .*Lift, Stack, PickPlaceCan",
    ),
    "evaluate: a misspelt scene variant": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--variant", "lightning", "--json", str(o / "r.json")],
        r"unknown scene variant 'lightning' \(did you mean lighting\?\)",
    ),
    "evaluate: a misspelt LIBERO suite": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_spatail", "--json", str(o / "r.json")],
        r"unknown task or task set 'libero_spatail' \(did you mean libero_spatial or .*\); known: .*libero_spatial, libero_object",
    ),
    "evaluate: a LIBERO task the suite lacks": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_goal", "--tasks", "0", "10", "--json", str(o / "r.json")],
        r"libero_goal has tasks 0\.\.9, not 10",
    ),
    "evaluate: more LIBERO trials than official initial states": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_10", "--trials", "60", "--json", str(o / "r.json")],
        r"LIBERO tasks have 50 official initial states, one per trial: trials must be 1\.\.50, not 60",
    ),
    "evaluate: LIBERO task ids for a robosuite task, named by their flag": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--tasks", "3", "--json", str(o / "r.json")],
        r"--tasks does not apply to Lift \(robosuite\); its options: --robot, --start-seed, ",
    ),
    "evaluate: LIBERO start states from a folder that is not there": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_spatial", "--from-demos", str(i / "nosuch"), "--json", str(o / "r.json")],
        r"from_demos: .*nosuch is not a folder of demos",
    ),
    "evaluate: a robosuite task and a LIBERO suite at once": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_spatial", "--task", "Lift", "--variant", "lighting", "--json", str(o / "r.json")],
        r"--task names a task, --suite libero_spatial a task set: give one or the other",
    ),
    "evaluate: a robosuite variant for a LIBERO suite, named by its flag": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_spatial", "--variant", "lighting", "--json", str(o / "r.json")],
        r"--variant does not apply to libero_spatial \(libero\); its options: --tasks, --max-steps, --rendering, --from-demos",
    ),
    "recipe: ${out.X} naming no stage, and no run folder made": (
        lambda i, b, o: ["recipe", "--config", str(b / "nosuch.yaml"), f"run_dir={o / 'run'}"],
        r"stage 'b' names \$\{out\.nosuch\.export\}, but no stage is called 'nosuch'; stages: \['a', 'b'\]",
    ),
    "recipe: a cycle through ${out.X}, found before any stage runs": (
        lambda i, b, o: ["recipe", "--config", str(b / "cycle.yaml"), f"run_dir={o / 'run'}"],
        r"stages wait for each other in a cycle: b waits for c waits for b",
    ),
    "fit: a typo'd key on the command line, without the usage block": (
        lambda i, b, o: fit_args(i, o, "--trainer.max_stesp=1"),
        r"unrecognized arguments: --trainer\.max_stesp=1 \(see capvector fit --help\)",
    ),
    "fit: a typo'd key in a config file": (
        lambda i, b, o: fit_args(i, o, "--config", str(b / "typo.yaml")),
        r"does not accept option 'trainer\.max_stesp' \(see capvector fit --help\)",
    ),
    "fit: --ckpt_path last finds a truncated last.ckpt": (
        lambda i, b, o: fit_args(i, b / "runs", "--ckpt_path=last"),
        r"--ckpt_path .*version_0/checkpoints/last\.ckpt is incomplete or corrupt .*delete it \(--ckpt_path last then takes the newest checkpoint left\) or pass another --ckpt_path",
    ),
    "fit: --ckpt_path names a truncated checkpoint": (
        lambda i, b, o: fit_args(i, o, f"--ckpt_path={b / 'runs/lightning_logs/version_0/checkpoints/last.ckpt'}"),
        r"last\.ckpt is incomplete or corrupt",
    ),
    "fit: --ckpt_path names no file": (
        lambda i, b, o: fit_args(i, o, f"--ckpt_path={i / 'missing.ckpt'}"),
        r"--ckpt_path .*missing\.ckpt does not exist",
    ),
    "fit: the log folder inside the pretrained export, before step 0": (
        lambda i, b, o: fit_args(i, i / "oft_sft" / "runs", f"--model.pretrained={i / 'oft_sft'}"),
        r"trainer\.default_root_dir .*oft_sft/runs lies inside the input .*oft_sft; an output must be outside every input",
    ),
    "fit: the log folder inside the demos' LeRobot folder, before step 0": (
        lambda i, b, o: [*(a for a in fit_args(i, b / "lerobot" / "runs") if not a.startswith("--data.train_files")),
                         f"--data.lerobot_root={b / 'lerobot'}", f"--data.cameras=[{','.join(CAMERAS)}]",
                         "--data.proprio_keys=[observation.state]", "--data.chunk_size=3"],
        r"lies inside the input .*lerobot; an output must be outside every input",
    ),
    "sweep-scale: neither rollouts nor held-out demos": (
        lambda i, b, o: ["sweep-scale", "--base", str(i / "oft_sft"), "--vector", str(i / "oft_vector"), "--out", str(o)],
        r"give --task/--episodes \(rollouts\) and/or --demos",
    ),
    "sweep-scale: LIBERO's official initial states, which evaluation reports": (
        lambda i, b, o: ["sweep-scale", "--base", str(i / "oft_sft"), "--vector", str(i / "oft_vector"), "--fit-config", str(b / "libero.yaml"), "--out", str(o)],
        r"data\.eval_tasks has libero_spatial \(libero\), whose episodes start from the fixed initial states that evaluation reports",
    ),
    # Round 3 (issue 62, items 7 and 8): the tracebacks left, and the validation gaps.
    "fit: a log folder through a symlink loop": (
        lambda i, b, o: fit_args(i, b / "loop" / "a" / "logs"),
        r"loop/a/logs goes through a symbolic link that loops \(.*loop/a\); remove that link or choose another trainer\.default_root_dir",
    ),
    "evaluate: LIBERO start states from a truncated demo file": (
        lambda i, b, o: ["evaluate", "--ckpt", str(i / "missing.ckpt"), "--suite", "libero_spatial", "--tasks", "0", "--trials", "1", "--from-demos", str(b / "cut_demos"), "--json", str(o / "r.json")],
        r"cut_demos/pick_up_the_black_bowl.*_demo\.hdf5 is not a readable HDF5 file \(h5py: .*truncated file.*\); re-record or re-download it",
    ),
    "evaluate: an export whose tokenizer.json is truncated": (
        lambda i, b, o: ["evaluate", "--ckpt", str(b / "cut_tokenizer"), "--task", "Lift", "--episodes", "1", "--json", str(o / "r.json")],
        r"cannot read the tokenizer in .*cut_tokenizer \(.*\): its tokenizer\.json or tokenizer_config\.json is incomplete or corrupt; copy or export it again",
    ),
    "recipe: `jobs: two`": (
        lambda i, b, o: ["recipe", "--config", str(b / "jobs_word.yaml"), f"run_dir={o / 'run'}"],
        r"jobs_word\.yaml: `jobs` must be an integer \(stages run at once\), got 'two' \(str\); write e\.g\. jobs: 2",
    ),
    "recipe: a config file that is not there": (
        lambda i, b, o: ["recipe", "--config", str(b / "nosuch_recipe.yaml"), f"run_dir={o / 'run'}"],
        r"--config .*nosuch_recipe\.yaml does not exist; recipes ship in configs/recipes/",
    ),
    "recipe: a stage naming its own output, found before any stage runs": (
        lambda i, b, o: ["recipe", "--config", str(b / "own_output.yaml"), f"run_dir={o / 'run'}"],
        r"stage 'b' names its own output \$\{out\.b\.export\}: a stage can read only other stages' outputs \(its own \$\{out\.b\.dir\} is where it writes\)",
    ),
    "recipe: an unknown command, found before any stage runs": (
        lambda i, b, o: ["recipe", "--config", str(b / "unknown_command.yaml"), f"run_dir={o / 'run'}"],
        r"stage 'b' in .*unknown_command\.yaml: unknown command 'exportt' \(did you mean export.*\?\); known: fit, validate, backbone-info",
    ),
    "recipe: `args` as a string, found before any stage runs": (
        lambda i, b, o: ["recipe", "--config", str(b / "string_args.yaml"), f"run_dir={o / 'run'}"],
        r"stage 'b' in .*string_args\.yaml: `args` must be a list of strings \(one per word, as typed on a shell\), got 'openvla-oft-tiny' \(str\); write args: \[openvla-oft-tiny\]",
    ),
    **{f"merge: λ = {scale}, a zero scale": (
        lambda i, b, o, scale=scale: ["merge", "--base", str(i / "oft_sft"), "--vector", f"{i / 'oft_vector'}:{scale}", "--out", str(o / "m")],
        rf"λ = {re.escape(scale)} for .*oft_vector is zero \(in float32, in which it is added\): the merge would change nothing yet record the vector as merged; drop --vector .* or give a non-zero λ",
    ) for scale in ("0", "-0", "1e-310")},
    "fit: λ = 0 for the merge callback": (
        lambda i, b, o: fit_args(i, o, "--trainer.callbacks+=capvector.callbacks.MergeCapabilityVector", f"--trainer.callbacks.vector={i / 'oft_vector'}", "--trainer.callbacks.scale=0"),
        r"λ = 0 for .*oft_vector is zero",
    ),
    "merge: a digest-less vector JSON claiming another family": (
        lambda i, b, o: ["merge", "--base", str(i / "oft_sft"), "--vector", str(b / "old_vector"), "--out", str(o / "m")],
        r"vector .*old_vector was extracted from pi05 models \(its capability_vector\.json says; written before metadata digests, so unchecked\), but the base .*oft_sft is openvla-oft: merge a vector of openvla-oft models, or extract this one again",
    ),
    "fit: a digest-less vector JSON claiming another family": (
        lambda i, b, o: fit_args(i, o, "--trainer.callbacks+=capvector.callbacks.MergeCapabilityVector", f"--trainer.callbacks.vector={b / 'old_vector'}"),
        r"vector .*old_vector was extracted from pi05 models .* but the model being fit is openvla-oft",
    ),
    "merge: --vector naming a file in the vector folder": (
        lambda i, b, o: ["merge", "--base", str(i / "oft_sft"), "--vector", str(i / "oft_vector" / "capability_vector.json"), "--out", str(o / "m")],
        r"vector folder .*capability_vector\.json is a file: pass the folder that holds it, .*oft_vector",
    ),
    "fit: scale=nan for the merge callback": (
        lambda i, b, o: fit_args(i, o, "--trainer.callbacks+=capvector.callbacks.MergeCapabilityVector", f"--trainer.callbacks.vector={i / 'oft_vector'}", "--trainer.callbacks.scale=nan"),
        r"trainer\.callbacks\.scale \(MergeCapabilityVector\) is nan, which is not finite; expected a finite float \(see capvector fit --help\)",
    ),
    "fit: a word where an integer goes": (
        lambda i, b, o: fit_args(i, o, "--data.batch_size=four"),
        r"data\.batch_size is 'four'; expected int \(see capvector fit --help\)",
    ),
    "fit: a word where an optional integer goes": (
        lambda i, b, o: fit_args(i, o, "--trainer.max_epochs=abc"),
        r"trainer\.max_epochs is 'abc'; expected int or None \(see capvector fit --help\)",
    ),
    "fit: a word where a callback's integer goes": (
        lambda i, b, o: fit_args(i, o, "--trainer.callbacks+=lightning.pytorch.callbacks.ModelCheckpoint", "--trainer.callbacks.save_top_k=many"),
        r"trainer\.callbacks\.save_top_k \(ModelCheckpoint\) is 'many'; expected int \(see capvector fit --help\)",
    ),
    "demos: a misspelt robot, before simulating": (
        lambda i, b, o: ["demos", "--task", "Lift", "--episodes", "1", "--robot", "Sawyr", "--out", str(o / "d.hdf5")],
        r"unknown one-arm robot 'Sawyr' \(did you mean Sawyer\?\)",
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_from_the_entry_point(
    case: str,
    inputs: Path,  # noqa: F811 (the fixture)
    bad: Path,
    tmp_path: Path,
    capfd: pytest.CaptureFixture[str],
) -> None:
    build_args, message = CASES[case]
    out = tmp_path / "out"
    before = tree_digest(inputs), tree_digest(bad)
    capfd.readouterr()
    code = main(build_args(inputs, bad, out))
    err = capfd.readouterr().err
    # Lightning's and robosuite's info lines may come first; ours is the one error line.
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert code == 2, err
    assert len(errors) == 1 and errors[0].startswith(
        f"capvector {build_args(inputs, bad, out)[0]}: error: "
    ), err
    assert re.search(message, errors[0]), errors[0]
    assert "Traceback" not in err and "usage:" not in err, err
    assert not out.exists(), sorted(out.rglob("*"))
    assert (tree_digest(inputs), tree_digest(bad)) == before


def _failing_tool(error: BaseException) -> Callable[[list[str]], int]:
    def tool(argv: list[str]) -> int:
        raise error

    return tool


@pytest.mark.parametrize(
    "bug", [RuntimeError("a bug"), TypeError("a bug"), KeyError("a bug"), ValueError("a bug")]
)
def test_a_bug_keeps_its_traceback(
    bug: Exception, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """Only bad input is shortened to one line: an error of another type propagates as it is."""
    monkeypatch.setattr(cli, "broken_main", _failing_tool(bug), raising=False)
    monkeypatch.setitem(cli.TOOLS, "broken", ("capvector.cli:broken_main", "raises"))
    with pytest.raises(type(bug)) as raised:
        main(["broken"])
    assert raised.value is bug
    assert "error" not in capfd.readouterr().err


def test_the_machine_refusing_is_one_line_exit_1(
    monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    read_only = OSError(errno.EROFS, "Read-only file system", "/data/out/model.safetensors")
    monkeypatch.setattr(cli, "broken_main", _failing_tool(read_only), raising=False)
    monkeypatch.setitem(cli.TOOLS, "broken", ("capvector.cli:broken_main", "raises"))
    assert main(["broken"]) == 1
    assert capfd.readouterr().err == (
        "capvector broken: error: [Errno 30] Read-only file system: '/data/out/model.safetensors'\n"
    )
    # A full disk met outside io.outputs (Lightning's checkpoint, a logger) is the output's place
    # to change, as bad input is (issue 62): exit 2, the path and what to do.
    full = OSError(errno.ENOSPC, "No space left on device", "/nonexistent/out/model.safetensors")
    monkeypatch.setattr(cli, "broken_main", _failing_tool(full))
    assert main(["broken"]) == 2
    assert re.fullmatch(
        r"capvector broken: error: cannot write output /nonexistent/out/model\.safetensors: its "
        r"disk filled up while writing it \(.* free once the partial output was removed\); free "
        r"space there or choose another output\n", capfd.readouterr().err)  # fmt: skip
    missing = FileNotFoundError(errno.ENOENT, "No such file or directory", "x")  # a bug's, maybe
    monkeypatch.setattr(cli, "broken_main", _failing_tool(missing))
    with pytest.raises(FileNotFoundError):
        main(["broken"])


def test_help_into_a_closed_pipe_is_quiet() -> None:
    """``capvector --help | head -1``: the reader leaves after a line; the rest is not an error."""
    import subprocess
    import sys

    shell = f"{shlex.quote(sys.executable)} -m capvector.cli --help | head -1"
    done = subprocess.run(["bash", "-o", "pipefail", "-c", shell], capture_output=True, text=True)
    assert done.stdout == "usage: capvector COMMAND [...]\n"
    assert done.stderr == "" and done.returncode in (0, 141), done.stderr


def test_fit_help_still_prints_the_usage(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["fit", "--help"])
    assert done.value.code == 0
    assert "--trainer.max_steps" in capsys.readouterr().out


# Round 3 (issue 62): no NaN reaches a robot.

REPO = Path(__file__).resolve().parents[1]


def _one_error_line(err: str, command: str) -> str:
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith(f"capvector {command}: error: "), err
    assert "Traceback" not in err, err
    return errors[0]


def test_nan_and_zero_depth_are_missing_and_the_fit_exports_finite_weights(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """The issue's reproduction: a 10 x 10 NaN patch in demo_0's agentview depth (and a 0 patch,
    the other spelling of a missing pixel) under configs/recipes/aux_sft.yaml trained to NaN
    from step 0 and exported 124 of 168 tensors non-finite. Masked out of the spatial loss, every
    loss term stays finite and so does every exported tensor."""
    import csv

    import h5py
    import numpy as np
    import torch

    from conftest import write_demo_file

    demos = write_demo_file(tmp_path / "demos.hdf5")
    with h5py.File(demos, "a") as f:
        depth = f["data/demo_0/obs/agentview_depth"]
        patched = depth[()]
        patched[:, 20:30, 20:30] = np.nan
        patched[:, 40:50, 5:15] = 0.0
        depth[...] = patched
    out = tmp_path / "run"
    code = main([
        "fit", "--config", str(REPO / "configs/recipes/aux_sft.yaml"),
        f"--data.train_files=[{demos}]", "--data.batch_size=4", "--trainer.max_steps=2",
        "--trainer.log_every_n_steps=1", f"--trainer.default_root_dir={out}",
        f"--trainer.logger.init_args.save_dir={out}", "--trainer.enable_progress_bar=false",
    ])  # fmt: skip
    assert code == 0, capfd.readouterr().err[-3000:]
    with (out / "fit" / "version_0" / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    for column in ("train/loss", "train/loss_spatial_alignment"):
        values = [float(r[column]) for r in rows if r.get(column)]
        assert len(values) == 2 and all(np.isfinite(values)), (column, values)
    tensors = load_file(str(out / "fit" / "version_0" / "export" / "model.safetensors"))
    bad = [name for name, t in tensors.items() if not torch.isfinite(t.float()).all()]
    assert not bad, f"{len(bad)} of {len(tensors)} exported tensors are not finite"


def test_a_non_finite_loss_stops_the_fit_in_one_line_and_nothing_is_exported(
    inputs: Path,  # noqa: F811 (the fixture)
    tmp_path: Path,
    capfd: pytest.CaptureFixture[str],
) -> None:
    """A learning rate of 1e30 blows the weights up after the first step: the fit stops at the
    first non-finite loss, naming the step and the term, exits 2 and exports nothing."""
    out = tmp_path / "run"
    args = fit_args(
        inputs, out, "--trainer.max_steps=5", "--model.optimizer.lr=1e30",
        "--trainer.callbacks+=capvector.callbacks.ExportOnFitEnd",
    )  # fmt: skip
    capfd.readouterr()
    assert main(args) == 2
    line = _one_error_line(capfd.readouterr().err, "fit")
    assert re.search(r"step [1-4]: loss term action = (nan|inf|-inf) is not finite", line), line
    assert not list(out.rglob("export")), sorted(out.rglob("*"))


def test_non_finite_weights_are_never_exported(tmp_path: Path) -> None:
    import torch

    from capvector.errors import CapVectorError
    from capvector.module import VLAModule

    module = VLAModule(backbone="openvla-oft-tiny")
    with torch.no_grad():
        module.backbone.language_model.model.embed_tokens.weight[4] = float("nan")
    with pytest.raises(
        CapVectorError, match=r"not exporting to .*: `.*embed_tokens.weight` holds NaN"
    ):
        module.export(tmp_path / "export")
    assert not (tmp_path / "export").exists()
    assert not list(tmp_path.iterdir()), "the export's temporary folder was left behind"


def test_evaluate_of_a_policy_that_answers_nan_exits_2(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """The issue's NaN export, evaluated: every episode ends on its first action; after the
    table the command says why, in one line, and exits 2 instead of 0."""
    import torch

    from capvector.module import VLAModule

    export = VLAModule(backbone="openvla-oft-tiny").export(tmp_path / "export")
    weights = export / "model.safetensors"
    save_file(
        {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v
         for k, v in load_file(str(weights)).items()},
        str(weights), metadata={"format": "pt"},
    )  # fmt: skip
    capfd.readouterr()
    code = main([
        "evaluate", "--ckpt", str(export), "--task", "Lift", "--episodes", "2", "--workers", "0",
        "--max-steps", "20", "--json", str(tmp_path / "r.json"),
    ])  # fmt: skip
    captured = capfd.readouterr()
    assert code == 2, captured.err[-3000:]
    line = _one_error_line(captured.err, "evaluate")
    assert "2 of 2 episodes ended on a non-finite action from the policy" in line, line
    assert (tmp_path / "r.json").is_file()  # the table and rows are still written
