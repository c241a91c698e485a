"""The tools' parsers, built from their functions' signatures (``capvector.tool_cli``): every
spelling that recipes, docs and scripts use parses to the values it always meant, every tool reads
its options from ``--config`` and prints them with ``--print_config``, and a bad argument is one
line with exit code 2."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from capvector import cli
from capvector.tool_cli import Tool
from capvector.workflows.recipe import load_recipe, recipe_cli

ROOT = Path(__file__).resolve().parents[1]


def options(command: str, argv: list[str], capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    """The options ``capvector COMMAND ARGV`` runs with, as ``--print_config`` prints them (the
    recipe has none: its ``--config`` is the recipe; they are what its parser returns)."""
    if command == "recipe":
        return Tool(recipe_cli, "recipe").parse(argv)
    capsys.readouterr()
    with pytest.raises(SystemExit) as done:
        cli.main([command, *argv, "--print_config"])
    assert done.value.code == 0
    return yaml.safe_load(capsys.readouterr().out)


# (command, argv, some of the options it means), in the spellings the tools had under argparse
CASES: list[tuple[str, list[str], dict[str, Any]]] = [
    ("merge", ["--base", "B", "--vector", "A:0.5", "--vector", "C", "--out", "O", "--allow-repeat"],
     {"vector": ["A:0.5", "C"], "allow_repeat": True, "dtype": None}),
    ("compose", ["--vectors", "A", "B", "--weights", "1", "-0.5", "--method", "ties", "--out", "O"],
     {"vectors": ["A", "B"], "weights": [1.0, -0.5], "method": "ties", "overwrite": False}),
    ("inspect", ["V", "--against", "W"], {"path": "V", "against": "W", "plot": None}),
    ("extract", ["--aux", "A", "--sft", "S", "--out", "O", "--max-shard-size", "1.5GiB",
                 "--exclude", "*.norm.*", "--full-rank", "*embed*", "--rank", "4"],
     {"max_shard_size": "1.5GiB", "exclude": ["*.norm.*"], "full_rank": ["*embed*"], "rank": 4}),
    ("backbone-info", ["openvla-oft-tiny", "--memory", "--lora-rank", "8", "--gpu-tflops", "312"],
     {"preset": "openvla-oft-tiny", "memory": True, "lora_rank": 8, "gpu_tflops": 312.0}),
    ("backbone-info", ["--list", "--batch", "2"], {"list": True, "batch": 2}),
    ("demos", ["--task", "Lift", "--episodes", "2", "--out", "d.hdf5", "--cameras", "--no-progress",
               "--fovy", "agentview=40", "--image-size", "32"],
     {"cameras": [], "progress": False, "fovy": ["agentview=40"], "image_size": 32}),
    ("evaluate", ["--ckpt", "C", "--task", "Lift", "Stack", "--variant", "lighting", "--start-seed",
                  "5", "--json", "r.json", "--device", "cpu", "--precision", "bf16-mixed"],
     {"task": ["Lift", "Stack"], "variant": ["lighting"], "start_seed": 5, "json": "r.json",
      "device": "cpu", "precision": "bf16-mixed"}),
    ("evaluate", ["--ckpt", "C", "--suite", "libero_spatial", "--tasks", "0", "3", "--trials", "5",
                  "--rendering", "official"],
     {"suite": "libero_spatial", "tasks": [0, 3], "trials": 5, "rendering": "official"}),
    ("recipe", ["--config", "R.yaml", "--dry-run", "run_dir=x", "--only", "a", "b", "--jobs", "2",
                "--threads", "3"],
     {"overrides": ["run_dir=x"], "dry_run": True, "only": ["a", "b"], "jobs": 2, "threads": 3}),
    ("report", ["--run-dir", "R", "--arm", "plain SFT", "sft_s*", "eval_pre", "--reference", "θ_pre",
                "eval_pre", "--arm", "aux", "aux_s*", "eval_pre", "--compare-to", "plain SFT",
                "--out", "O"],
     {"arm": [["plain SFT", "sft_s*", "eval_pre"], ["aux", "aux_s*", "eval_pre"]],
      "reference": [["θ_pre", "eval_pre"]], "compare_to": ["plain SFT"]}),
    ("report", ["--from-results", "R.json", "--compare-to", "plain SFT", "aux-SFT", "--out", "O"],
     {"from_results": "R.json", "run_dir": None, "arm": None,
      "compare_to": ["plain SFT", "aux-SFT"]}),
    ("sweep-scale", ["--base", "B", "--vector", "V", "--out", "O", "--scales", "0,0.5,1",
                     "--finetune-steps", "2", "--allow-large-scale"],
     {"scales": "0,0.5,1", "finetune_steps": 2, "allow_large_scale": True}),
    ("export", ["--ckpt", "C", "--out", "O", "--overwrite"], {"overwrite": True}),
    ("serve", ["--ckpt", "C", "--port", "0", "--precision", "bf16-mixed", "--max-batch", "4"],
     {"port": 0, "precision": "bf16-mixed", "max_batch": 4, "device": None}),
    ("import-original", ["--preset", "openvla-oft-tiny", "--folder", "F", "--out", "O",
                         "--apply-lora-adapter"], {"apply_lora_adapter": True, "override": "{}"}),
    ("push", ["F", "org/name", "--dry-run", "--revision", "dev"],
     {"folder": "F", "repo_id": "org/name", "dry_run": True, "revision": "dev", "private": False}),
]  # fmt: skip
IDS = [f"{command} {' '.join(argv)}"[:60] for command, argv, _ in CASES]


def test_every_tool_is_covered() -> None:
    assert {command for command, _, _ in CASES} == set(cli.TOOLS)


@pytest.mark.parametrize(("command", "argv", "expected"), CASES, ids=IDS)
def test_argparse_spellings_keep_their_meaning(
    command: str, argv: list[str], expected: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    values = options(command, argv, capsys)
    assert {key: values[key] for key in expected} == expected


def test_records_reach_the_function_as_records() -> None:
    from capvector.workflows.report import Arm, report_cli
    from capvector.workflows.vectors import ScaledVector, merge_cli

    argv = ["--run-dir", "R", "--arm", "a", "a_s*", "eval_pre", "--out", "O"]
    assert Tool(report_cli, "report").parse(argv)["arm"] == [Arm("a", "a_s*", "eval_pre")]
    argv = ["--base", "B", "--vector", "A:0.5", "--vector", "C", "--out", "O"]
    vectors = Tool(merge_cli, "merge", skip=["command"]).parse(argv)["vector"]
    assert vectors == [ScaledVector("A", 0.5), ScaledVector("C", 1.0)]


@pytest.mark.parametrize(("command", "argv", "expected"), CASES, ids=IDS)
def test_print_config_reads_back_with_config(
    command: str,
    argv: list[str],
    expected: dict[str, Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if command == "recipe":  # its --config is the recipe itself
        assert cli.main(["recipe", *argv, "--print_config"]) == 2
        assert "unrecognized arguments: --print_config" in capsys.readouterr().err
        return
    config = tmp_path / "options.yaml"
    config.write_text(yaml.safe_dump(options(command, argv, capsys)))
    assert options(command, ["--config", str(config)], capsys) == options(command, argv, capsys)


def test_the_command_line_overrides_a_config_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "merge.yaml"
    config.write_text("base: B\nvector: [A:0.5]\nout: O\ndtype: float32\n")
    values = options(
        "merge", ["--config", str(config), "--dtype", "bfloat16", "--vector", "C:2"], capsys
    )
    assert values["dtype"] == "bfloat16"
    assert values["vector"] == ["A:0.5", "C:2"]  # a repeatable option adds to the file's list


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["report", "--run-dir", "R", "--arm", "a", "b", "--out", "O"],
         r"argument --arm: expected 3 arguments"),
        (["merge", "--base", "B", "--vector", "V:x", "--out", "O"],
         r"argument --vector: .*λ after the colon must be a number \(DIR:0.7\), got 'x'"),
        (["compose", "--vectors", "A", "--density", "most", "--out", "O"],
         r"argument --density: expected float, got most"),
        (["evaluate", "--ckpt", "C", "--workers", "many"],
         r"argument --workers: expected int \| None, got many"),
        (["merge", "--base", "B", "--vector", "V", "--out", "O", "--dtype", "float64"],
         r"argument --dtype: expected .*'float32', 'bfloat16', 'float16'.*, got float64"),
        (["demos", "--task", "Lift", "--out", "d.hdf5"], r"give --episodes N"),
        (["inspect"], r"required: path"),
        (["export", "--ckpt", "C", "--out", "O", "--overwrite=yes"], r"--overwrite"),
        (["extract", "--aux", "A", "--sft", "S", "--out", "O", "--rnak", "4"],
         r"unrecognized arguments: --rnak 4"),
    ],
)  # fmt: skip
def test_a_bad_argument_is_one_line_naming_help(
    argv: list[str], message: str, capfd: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(argv) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"capvector {argv[0]}: error: "), err
    assert re.search(message, err), err
    assert err.rstrip().endswith(f"(see capvector {argv[0]} --help)"), err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--max-shard-size", "2XB"], "not a size: '2XB' (try 2GB or 500MB)"),
        (["--rank", "2", "--energy", "0.9"], "pass either --rank or --energy, not both"),
    ],
)
def test_what_the_library_checks_is_one_line_before_any_work(
    argv: list[str], message: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """``extract``'s own checks: a size is text until the library reads it, as in transformers;
    --rank and --energy exclude each other."""
    out = tmp_path / "vector"
    assert cli.main(["extract", "--aux", "A", "--sft", "S", "--out", str(out), *argv]) == 2
    assert capfd.readouterr().err == f"capvector extract: error: {message}\n"
    assert not out.exists()


@pytest.mark.parametrize(
    ("command", "config", "message"),
    [
        ("export", "ckpt: C\nout: O\noverwirte: true\n", "overwirte"),
        ("report", "run_dir: R\narm: [[a, a_s*]]\nout: O\n",
         "argument --arm: expected LABEL GLOB START, got ['a', 'a_s*']"),
    ],
)  # fmt: skip
def test_a_bad_config_file_is_one_line(
    command: str, config: str, message: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """An unknown key; a record whose values do not fit it (checked as the command line's)."""
    path = tmp_path / "options.yaml"
    path.write_text(config)
    assert cli.main([command, "--config", str(path)]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and message in err, err


RECIPES = [
    p for p in sorted((ROOT / "configs/recipes").rglob("*.yaml")) if "\nstages:" in p.read_text()
]


@pytest.mark.parametrize("recipe", RECIPES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_stage_of_the_shipped_recipes_parses(
    recipe: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, stages = load_recipe(recipe)
    tools = [stage for stage in stages if stage.command in cli.TOOLS]
    assert tools
    for stage in tools:  # a merge by the sweep's best λ, before the sweep ran: a λ of 1
        options(stage.command, [re.sub(r"<best λ of [^>]*>", "1", a) for a in stage.args], capsys)


@pytest.mark.parametrize("command", sorted(cli.TOOLS))
def test_the_cli_reference_names_only_real_options(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every ``--option`` in docs/cli.md's synopsis of a tool is in the tool's ``--help``."""
    text = (ROOT / "docs" / "cli.md").read_text()
    (synopsis,) = re.findall(rf"^\| `capvector {command} (.*?)` \|", text, re.M)
    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    shown = set(re.findall(r"--[a-z][\w-]*", capsys.readouterr().out))
    assert set(re.findall(r"--[a-z][\w-]*", synopsis)) <= shown


def fit_shape(args: list[str]) -> tuple[str, ...]:
    """A fit stage's ``--config`` files and the names of the options it sets."""
    configs = [b for a, b in zip(args, args[1:], strict=False) if a == "--config"]
    names = sorted({a.split("=")[0] for a in args if a.startswith("--") and a != "--config"})
    return (*configs, *names)


@pytest.mark.parametrize("recipe", RECIPES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_fit_stage_of_the_shipped_recipes_parses(
    recipe: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fit stage's configs and overrides make one valid `capvector fit` configuration (its
    typos would otherwise surface hours into a study, when the stage starts)."""
    monkeypatch.chdir(ROOT)  # the stages name their configs relative to the repository
    _, stages = load_recipe(recipe)
    # one stage of each shape (its configs and the options it sets): the others differ only in
    # values a parse accepts alike (seeds, paths)
    fits = {fit_shape(s.args): s for s in stages if s.command == "fit"}
    for stage in fits.values():
        config = options("fit", stage.args, capsys)
        assert config["trainer"]["max_steps"] > 0 and config["data"]["train_files"]
