"""Bad input, every command: one line that names the problem, exit code 2, no output written, and
the inputs byte for byte as they were."""

from __future__ import annotations

import hashlib
import re
from collections.abc import Callable
from pathlib import Path

# Lightning binds its log handler to the stderr of the moment it is imported: import it now, not
# inside a test whose captured stream closes after it.
import lightning.pytorch  # noqa: F401
import pytest

from capvector.backbones import build_backbone
from capvector.cli import main
from capvector.vectors import extract, merge
from conftest import write_demo_file


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Demos without depth, an OFT export, vectors for OFT and for Pi0.5, θ_meta with c merged."""
    root = tmp_path_factory.mktemp("inputs")
    path = write_demo_file(root / "demos.hdf5")
    import h5py

    with h5py.File(path, "a") as f:  # as `capvector demos` writes them without --depth
        for demo in f["data"].values():
            for key in [k for k in demo["obs"] if k.endswith("_depth")]:
                del demo["obs"][key]
    for preset, name in (("openvla-oft-tiny", "oft"), ("pi05-tiny", "pi05")):
        model = build_backbone(preset)
        model.save_pretrained(root / f"{name}_sft")
        build_backbone(preset).save_pretrained(root / f"{name}_aux")  # another init: a vector
        extract(aux=root / f"{name}_aux", sft=root / f"{name}_sft", out=root / f"{name}_vector")
    merge(root / "oft_sft", [(root / "oft_vector", 1.0)], root / "oft_meta")
    (root / "a_file").write_text("not a folder")
    return root


def fit_args(inputs: Path, out: Path, *extra: str) -> list[str]:
    return [
        "fit", "--trainer.accelerator=cpu", "--trainer.max_steps=1", f"--trainer.default_root_dir={out}",
        "--trainer.logger.class_path=capvector.training.loggers.CSVLogger",
        f"--trainer.logger.init_args.save_dir={out}", "--model.backbone=openvla-oft-tiny",
        f"--data.train_files=[{inputs / 'demos.hdf5'}]", "--data.batch_size=4", *extra,
    ]  # fmt: skip


CASES: dict[str, tuple[Callable[[Path, Path], list[str]], str]] = {
    "merge: λ that is not a number": (
        lambda i, o: ["merge", "--base", str(i / "oft_sft"), "--vector", f"{i / 'oft_vector'}:abc", "--out", str(o / "m")],
        r"λ after the colon must be a number .*got 'abc'",
    ),
    "merge: a vector the base already holds": (
        lambda i, o: ["merge", "--base", str(i / "oft_meta"), "--vector", str(i / "oft_vector"), "--out", str(o / "m")],
        r"already holds vector .*--allow-repeat",
    ),
    "merge: output inside a file": (
        lambda i, o: ["merge", "--base", str(i / "oft_sft"), "--vector", str(i / "oft_vector"), "--out", str(i / "a_file" / "m")],
        r"cannot write --out .*is a file, not a folder",
    ),
    "export: output inside a file, before reading the checkpoint": (
        lambda i, o: ["export", "--ckpt", str(i / "missing.ckpt"), "--out", str(i / "a_file" / "e")],
        r"cannot write --out .*is a file",
    ),
    "export: an existing output names --overwrite": (
        lambda i, o: ["export", "--ckpt", str(i / "missing.ckpt"), "--out", str(i / "oft_sft")],
        r"exists; choose another --out or pass --overwrite",
    ),
    "export: a dtype that is not one, before reading the checkpoint": (
        lambda i, o: ["export", "--ckpt", str(i / "missing.ckpt"), "--out", str(o / "e"), "--dtype", "bf16"],
        r"unknown floating dtype 'bf16'; use float32, bfloat16 or float16",
    ),
    "demos: output inside a file, before simulating": (
        lambda i, o: ["demos", "--task", "Lift", "--episodes", "50", "--out", str(i / "a_file" / "d.hdf5")],
        r"cannot write demo file .*is a file",
    ),
    "demos: output is a folder": (
        lambda i, o: ["demos", "--task", "Lift", "--episodes", "50", "--out", str(i / "oft_sft")],
        r"is a folder; give a file",
    ),
    "demos: an unknown LIBERO suite, before simulating": (
        lambda i, o: ["demos", "--suite", "libero_spatail", "--episodes-per-task", "2", "--out", str(o / "d")],
        r"unknown task or task set 'libero_spatail' \(did you mean libero_spatial",
    ),
    "demos: --suite without --episodes": (
        lambda i, o: ["demos", "--suite", "libero_spatial", "--out", str(o / "d")],
        r"give --episodes N: successful demos of libero_spatial to record",
    ),
    "demos: --workers for a robosuite task": (
        lambda i, o: ["demos", "--task", "Lift", "--episodes", "2", "--workers", "2", "--out", str(o / "d.hdf5")],
        r"--workers does not apply to robosuite demos; its options: --robot, --gripper, --noise, --extra-steps, --fovy",
    ),
    "demos: an unknown --rendering, before simulating": (
        lambda i, o: ["demos", "--suite", "libero_spatial", "--episodes-per-task", "2", "--rendering", "fastt", "--out", str(o / "d")],
        r"unknown rendering 'fastt'.*did you mean fast",
    ),
    "demos: negative --workers, before simulating": (
        lambda i, o: ["demos", "--suite", "libero_spatial", "--episodes-per-task", "2", "--workers", "-1", "--out", str(o / "d")],
        r"--workers must be 0 \(this process\) or more, got -1",
    ),
    "import-original: --override that is not JSON": (
        lambda i, o: ["import-original", "--preset", "openvla-oft-tiny", "--folder", str(i), "--override", "{depth: 2", "--out", str(o / "x")],
        r"--override is not JSON",
    ),
    "an unknown option": (
        lambda i, o: ["extract", "--aux", str(i / "oft_aux"), "--sft", str(i / "oft_sft"), "--out", str(o / "v"), "--rnak", "4"],
        r"unrecognized arguments: --rnak 4 \(see capvector extract --help\)",
    ),
    "fit: a vector of another preset": (
        lambda i, o: fit_args(i, o, "--trainer.callbacks+=capvector.callbacks.MergeCapabilityVector", f"--trainer.callbacks.vector={i / 'pi05_vector'}"),
        r"extracted from pi05 models \(its capability_vector.json says\), but the model being fit "
        r"is openvla-oft",
    ),
    "fit: logs inside a file": (
        lambda i, o: fit_args(i, o, f"--trainer.logger.init_args.save_dir={i / 'a_file' / 'logs'}"),
        r"cannot write into the CSVLogger's save_dir .*is a file",
    ),
    "fit: the export folder inside a file": (
        lambda i, o: fit_args(i, o, "--trainer.callbacks+=capvector.callbacks.ExportOnFitEnd", f"--trainer.callbacks.dirpath={i / 'a_file' / 'export'}"),
        r"cannot write into ExportOnFitEnd's dirpath .*is a file",
    ),
    "fit: --ckpt_path last with no earlier run": (
        lambda i, o: fit_args(i, o, "--ckpt_path=last"),
        r"--ckpt_path last: no checkpoint under .*drop --ckpt_path to start a new run",
    ),
    "fit: refused in configure_model, Lightning's default logger": (
        lambda i, o: [a for a in fit_args(i, o, "--model.frozen_dtype=bfloat16") if "logger" not in a],
        r"model.frozen_dtype=bfloat16 needs trainer.precision: bf16-mixed",
    ),
    "fit: demos without depth, a config that loads it": (
        lambda i, o: fit_args(i, o, "--data.load_depth=true"),
        r"recorded without depth.*capvector demos --depth.*data.load_depth=false",
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    case: str, inputs: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    build_args, message = CASES[case]
    out = tmp_path / "out"
    args = build_args(inputs, out)
    before = tree_digest(inputs)
    try:
        code = main(args)
    except SystemExit as exit_info:  # argparse errors exit from inside the tool
        code = exit_info.code
    # Lightning's own info lines (accelerator, TPU) may come first; ours is the one error line.
    errors = [line for line in capfd.readouterr().err.splitlines() if "error" in line]
    assert code == 2
    assert len(errors) == 1 and errors[0].startswith("capvector "), errors
    assert re.search(message, errors[0]), errors[0]
    assert not out.exists(), sorted(out.rglob("*"))
    assert tree_digest(inputs) == before


@pytest.mark.parametrize("command", ["test", "predict"])
def test_lightning_subcommands_the_module_cannot_run_are_unknown(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """VLAModule has no test or predict step, so `capvector test` would only fail inside Lightning:
    it is an unknown command, and the usage lists what trains and validates."""
    assert main([command]) == 2
    err = capsys.readouterr().err
    assert f"unknown command {command!r}" in err
    assert "  fit\n  validate\n" in err
