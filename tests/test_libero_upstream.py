"""`capvector evaluate --backend upstream`: LIBERO's protocol on upstream LIBERO (robosuite 1.4,
MuJoCo 2.3.7) through the served policy, and every result saying which stack made it.

The upstream environment (`tools/libero/install_libero14.sh`) is not part of CI: the episode test
skips without it, and runs under `-m referee` (about a minute on the shared machine: LIBERO's env
built in both stacks, the policy loaded twice).
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from capvector.cli import main
from capvector.eval.results import SuccessRow, format_success_table, pooled_row
from capvector.workflows.evaluate_upstream import (
    DEFAULT_UPSTREAM_ENV,
    INSTALL_SCRIPT,
    UPSTREAM_ENV_VAR,
)
from conftest import write_untrained_libero_export

SUITE = "libero_spatial"
EEF_MM = 3.0  # tests/test_libero_served.py: the closed loop before contact, 0.2-1.1 mm measured


def upstream_env() -> Path | None:
    """The upstream environment where the install script (or $CAPVECTOR_LIBERO14) put it."""
    folder = Path(os.environ.get(UPSTREAM_ENV_VAR) or DEFAULT_UPSTREAM_ENV).expanduser()
    return folder if (folder / "bin" / "python").is_file() else None


def test_without_the_upstream_environment_one_line_names_its_install(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Refused before the checkpoint is read (there is none here), from the flag, the variable
    and the default folder alike, each naming the command that installs it there."""
    missing = tmp_path / "nowhere"
    monkeypatch.setenv("HOME", str(tmp_path))  # the default folder is under ~
    for flags, env in (
        (["--upstream-env", str(missing)], None),
        ([], str(missing)),
        ([], None),
    ):
        if env is None:
            monkeypatch.delenv(UPSTREAM_ENV_VAR, raising=False)
        else:
            monkeypatch.setenv(UPSTREAM_ENV_VAR, env)
        code = main([
            "evaluate", "--ckpt", str(tmp_path / "no_export"), "--suite", SUITE, "--tasks", "0",
            "--trials", "1", "--backend", "upstream", *flags,
        ])  # fmt: skip
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1, err
        folder = missing if flags or env else tmp_path / ".cache" / "capvector" / "libero14"
        assert f"no upstream LIBERO environment at {folder}" in err
        assert f"install_libero14.sh {folder}`" in err and INSTALL_SCRIPT.is_file()


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--task", "Lift"], "--task"),
        (["--suite", SUITE, "--video", "v"], "--video"),
        (["--suite", SUITE, "--rendering", "fast"], "--rendering"),
        (["--suite", SUITE, "--variant", "camera"], "--variant"),
        (["--suite", "metaworld_mt10"], "a LIBERO suite"),
    ],
)
def test_the_upstream_backend_refuses_what_it_cannot_honour(
    flags: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["evaluate", "--ckpt", str(tmp_path), "--backend", "upstream", *flags])
    err = capsys.readouterr().err
    assert code == 2 and named in err, err


def test_upstream_env_without_the_upstream_backend_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["evaluate", "--ckpt", str(tmp_path), "--suite", SUITE, "--upstream-env", "x"])
    assert code == 2 and "add --backend upstream" in capsys.readouterr().err


PORT = "port (robosuite 1.5.2, MuJoCo 3.9.0)"
UPSTREAM = "upstream LIBERO (robosuite 1.4.0, MuJoCo 2.3.7)"


def test_a_table_says_which_stack_and_renderer_made_its_rows() -> None:
    """One line under the table when every row shares them, a column when they differ, and
    rows from before results said: not recorded. The JSON form keeps them."""
    port = SuccessRow("libero_spatial/5", "Panda", 2, 1, 100.0, stack=PORT, renderer="fast")
    upstream = SuccessRow("libero_spatial/5", "Panda", 2, 0, 220.0, stack=UPSTREAM,
                          renderer="official")  # fmt: skip
    table = format_success_table([port, pooled_row([port], "libero_spatial (all)")])
    assert table.endswith(f"\n\nStack: {PORT}, fast renderer.")
    mixed = format_success_table([port, upstream]).splitlines()
    assert mixed[0].endswith("| mean steps | stack |")
    assert mixed[2].endswith(f"| {PORT}, fast renderer |")
    assert mixed[3].endswith(f"| {UPSTREAM}, official renderer |")
    old = SuccessRow("Lift", "Panda", 2, 1, 50.0)
    assert "stack" not in format_success_table([old])
    assert format_success_table([old, port]).splitlines()[2].endswith("| not recorded |")
    assert SuccessRow.from_dict(upstream.to_dict()) == upstream
    assert pooled_row([port, upstream], "all").stack is None  # pooled across stacks: no one stack


RESULTS = Path(__file__).parents[1] / "docs" / "results"


@pytest.mark.parametrize(
    ("folder", "policies", "trials"),
    [("libero_upstream", 3, {"0"}), ("libero_upstream_all", 6, None)],  # the subset; every state
)
def test_the_committed_upstream_tables_are_their_evaluations(
    folder: str, policies: int, trials: set[str] | None
) -> None:
    """docs/results.md's port-vs-upstream tables are computed from each folder's episodes.csv;
    every outcome and step count there is the one the committed `capvector evaluate --json` of
    its stack wrote (a policy's file, or one task's chunk; the first run of an episode, as
    --collect keeps it), and those name their stacks (upstream_study_table.py --collect)."""
    committed = RESULTS / folder
    with (committed / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len({r["policy"] for r in rows}) == policies
    assert trials is None or {r["trial"] for r in rows} == trials
    for stack in ("port", "upstream"):
        ran: dict[tuple[str, int, int], tuple[dict, dict]] = {}
        labels = set()
        for path in sorted((committed / stack).glob("*.json")):
            for row in json.loads(path.read_text()):
                labels.add((row["stack"], row["renderer"]))
                for e in row["per_episode"]:
                    ran.setdefault((path.name.split(".")[0], e["task"], e["trial"]), (e, row))
        assert {policy for policy, _, _ in ran} == {r["policy"] for r in rows}
        for r in rows:
            episode, row = ran[r["policy"], int(r["task"]), int(r["trial"])]
            assert (int(episode["success"]), episode["steps"]) == (
                int(r[stack]),
                int(r[f"{stack}_steps"]),
            )
            assert (row["stack"], row["renderer"]) == (r[f"{stack}_stack"], r[f"{stack}_renderer"])
        assert labels == ({(UPSTREAM, "official")} if stack == "upstream" else {(PORT, "fast")})


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_untrained_libero_export(tmp_path_factory.mktemp("libero") / "export")


@pytest.mark.sim
@pytest.mark.referee
def test_one_upstream_episode_is_laid_out_and_moves_as_the_ports(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """One real episode on robosuite 1.4 through the served policy, cut to two chunks, and the
    same trial on the port with LIBERO's official renderer: the same JSON layout (so `capvector
    report` and `recipe` read either), each row naming its stack, the same steps, and the end
    effector where the port leaves it, before any contact, within the served test's EEF_MM. A
    policy trained at other fields of view is refused there as on the port."""
    env = upstream_env()
    if env is None:  # an opt-in referee run installs the stack from the registry, one command
        subprocess.run(["bash", str(INSTALL_SCRIPT)], check=True, timeout=3600)
        env = upstream_env()
        assert env is not None, f"{INSTALL_SCRIPT} ran but left no environment"
    monkeypatch.setenv(UPSTREAM_ENV_VAR, str(env))
    runs = {}
    port_only = ["--rendering", "official", "--workers", "0", "--batch-size", "1", "--videos", "0"]
    for backend, extra in (("upstream", []), ("port", port_only)):
        out = tmp_path / f"{backend}.json"
        code = main([
            "evaluate", "--ckpt", str(export), "--suite", SUITE, "--tasks", "0", "--trials", "1",
            "--max-steps", "16", "--backend", backend, "--json", str(out), *extra,
        ])  # fmt: skip
        assert code == 0
        printed = capsys.readouterr()
        table = printed.out
        # Where no bar shows (a recipe stage's log), the progress lines --status reads.
        assert "evaluating: 1/1 episodes, 0 succeeded" in printed.err, printed.err[-2000:]
        (runs[backend],) = json.loads(out.read_text())
        stack = runs[backend]["stack"]
        assert f"Stack: {stack}, {runs[backend]['renderer']} renderer." in table
    upstream, port = runs["upstream"], runs["port"]
    assert upstream["stack"] == UPSTREAM and upstream["renderer"] == "official"
    assert port["stack"].startswith("port (robosuite 1.5") and port["renderer"] == "official"
    (u,), (p,) = upstream.pop("per_episode"), port.pop("per_episode")
    assert set(u) >= set(p) and set(upstream) == set(port)  # the client adds states, chunk
    same = ("suite", "task", "trial", "success", "steps", "reason")
    assert {k: u[k] for k in same} == {k: p[k] for k in same}
    assert u["steps"] == 16 and upstream["outcomes"] == port["outcomes"] == [[0, False]]
    eef = 1e3 * np.linalg.norm(np.subtract(u["final_proprio"][:3], p["final_proprio"][:3]))
    assert eef < EEF_MM, eef
    # θ_pre trained on robosuite's Lift cameras (agentview at 35°): LIBERO's is 45°
    theta_pre = Path(__file__).parents[1] / "assets" / "theta_pre"
    code = main([
        "evaluate", "--ckpt", str(theta_pre), "--suite", SUITE, "--tasks", "0", "--trials", "1",
        "--backend", "upstream",
    ])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "vertical field of view of 35.0°, LIBERO's scene has 45.0°" in err, err


def test_collect_pairs_the_episodes_every_policy_ran_on_both_stacks(tmp_path: Path) -> None:
    """upstream_study_table.py --collect reads per-policy files and one task's chunks alike: an
    episode enters only when every policy ran it on both stacks (the plans' pairing), a re-run
    keeps the first run, and the count of re-runs with another outcome is said."""

    def evaluated(stack: str, name: str, task: int, outcomes: list[bool]) -> None:
        episodes = [{"task": task, "trial": i, "success": ok, "steps": 100 + i}
                    for i, ok in enumerate(outcomes)]  # fmt: skip
        row = {"task": f"{SUITE}/{task}", "stack": stack, "renderer": "r", "per_episode": episodes}
        (tmp_path / "results" / stack).mkdir(parents=True, exist_ok=True)
        (tmp_path / "results" / stack / f"{name}.json").write_text(json.dumps([row]))

    for policy in ("steps16k_sft_s0", "spatial_only_s0"):
        fit = tmp_path / "study" / policy / "fit" / "version_0"
        fit.mkdir(parents=True)
        fit.joinpath("episodes.csv").write_text(
            "step,task,seed,success\n" + "".join(f"16000,{SUITE}/{t},{i},1\n" for t in (5, 6) for i in range(3))
        )  # fmt: skip
        for stack in ("port", "upstream"):
            evaluated(stack, policy, 5, [True])  # the subset: state 0
            evaluated(stack, f"{policy}.task5", 5, [stack == "port", False, True])  # chunk
    evaluated("port", "steps16k_sft_s0.task6", 6, [True, True, True])  # one stack, one policy
    evaluated("upstream", "steps16k_sft_s0.task6", 6, [True, True, True])
    out = tmp_path / "episodes.csv"
    tool = Path(__file__).parents[1] / "tools" / "libero" / "upstream_study_table.py"
    said = subprocess.run(
        [sys.executable, str(tool), "--collect", str(tmp_path / "results"), str(tmp_path / "study"),
         "--out", str(out)], capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert [(r["policy"], r["task"], r["trial"]) for r in rows] == [
        (p, "5", str(i)) for p in ("steps16k_sft_s0", "spatial_only_s0") for i in range(3)
    ]  # task 6 ran for one policy only: out
    assert {r["upstream"] for r in rows if r["trial"] == "0"} == {"1"}  # the first run kept
    assert "3 episodes of each of 2 policies; 3 run on both stacks by only some" in said
    assert "4 re-runs, 2 with another outcome" in said  # state 0 of task 5 upstream, each policy

    figure = tmp_path / "success_by_stack.png"
    table = subprocess.run([sys.executable, str(tool), str(out), "--plot", str(figure)],
                           capture_output=True, text=True, check=True).stdout  # fmt: skip
    assert "| plain SFT | 1 × 3 | 100% (3/3" in table  # the study's episodes.csv: all succeeded
    assert figure.read_bytes().startswith(b"\x89PNG") and not list(tmp_path.glob("*.tmp"))
