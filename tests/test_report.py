"""`capvector report`: the arms of a recipe run, read back from real CSVLogger files; and the
committed reports, rebuilt from their results.json."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest
from lightning.pytorch.loggers import CSVLogger

from capvector.errors import CapVectorError
from capvector.workflows.report import main, report, report_from_results

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def write_fit(run_dir: Path, stage: str, success: dict[int, float], l1: dict[int, float]) -> None:
    """A fit stage's log as the recipe lays it out; steps are optimizer steps done."""
    logger = CSVLogger(run_dir / stage, name="fit", version="version_0")
    for step in range(1, max(success) + 1):
        metrics = {"train/loss": 1.0 / step, "perf/step_seconds": 0.1 + step / 1000,
                   "perf/peak_memory_mib": 500.0 + step}  # fmt: skip
        if step in success:
            metrics |= {"val/success_rate": success[step], "val/action_l1": l1[step],
                        "val/episodes": 10.0}  # fmt: skip
        logger.log_metrics(metrics, step=step - 1)  # Lightning's 0-based row index
    logger.save()


def write_evaluation(run_dir: Path, stage: str, successes: int, episodes: int) -> None:
    (run_dir / stage).mkdir(parents=True)
    row = {"task": "Lift", "robot": "Sawyer", "episodes": episodes, "successes": successes}
    (run_dir / stage / "results.json").write_text(json.dumps([row]))


def test_report_reads_every_seed_and_summarizes_the_arms(tmp_path: Path) -> None:
    run = tmp_path / "run"
    write_evaluation(run, "eval_pre", 3, 30)
    write_evaluation(run, "eval_meta", 6, 30)
    write_fit(run, "down_sft_s0", {2: 0.2, 4: 0.6}, {2: 0.30, 4: 0.20})
    write_fit(run, "down_sft_s1", {2: 0.4, 4: 0.4}, {2: 0.34, 4: 0.24})
    write_fit(run, "down_cv_s0", {2: 0.7, 4: 0.9}, {2: 0.20, 4: 0.10})
    arms = [("plain SFT", "down_sft_s*", "eval_pre"), ("CapVector", "down_cv_s*", "eval_meta")]
    out = tmp_path / "report"
    table = report(run, arms, [("out of the box", "eval_meta")], out, threshold=0.5)

    result = json.loads((out / "results.json").read_text())
    sft, cv = result["arms"]
    assert sft["seeds"] == ["down_sft_s0", "down_sft_s1"]
    assert sft["success"]["0"]["values"] == [0.1, 0.1]  # step 0: the starting weights' evaluation
    assert sft["success"]["2"]["mean"] == pytest.approx(0.3)
    assert sft["success"]["4"]["values"] == [0.6, 0.4]
    # counts a reader can recompute intervals from: [successes, episodes] per seed and step
    assert sft["counts"]["0"] == [[3, 30], [3, 30]] and sft["counts"]["4"] == [[6, 10], [4, 10]]
    assert result["reference_counts"] == {"out of the box": [6, 30]}
    assert sft["held_out_l1"]["4"]["mean"] == pytest.approx(0.22)
    assert sft["steps_to_threshold"] == [4, None] and cv["steps_to_threshold"] == [2]
    assert sft["peak_memory_mib"] == 504.0
    assert sft["step_seconds"]["mean"] == pytest.approx(0.1025)  # median of each seed's steps
    assert result["references"] == {"out of the box": pytest.approx(0.2)}
    assert "| plain SFT | 10% ± 0% | 30% ± 14% | 50% ± 14% | 4 (1/2) | 0.220 ± 0.028 |" in table
    assert "| CapVector | 20% ± 0% | 70% ± 0% | 90% ± 0% | 2 (1/1) | 0.100 ± 0.000 |" in table
    assert (out / "results.md").read_text().strip() == table
    assert (out / "success_vs_steps.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_errors_name_the_missing_stage(tmp_path: Path) -> None:
    run = tmp_path / "run"
    write_evaluation(run, "eval_pre", 3, 30)
    with pytest.raises(CapVectorError, match="no stage folder in .* matches 'down_x_s\\*'"):
        report(run, [("x", "down_x_s*", "eval_pre")], [], tmp_path / "out", 0.5)
    (run / "down_x_s0").mkdir()
    with pytest.raises(CapVectorError, match="has the fit stage 'down_x_s0' run"):
        main(["--run-dir", str(run), "--arm", "x", "down_x_s*", "eval_pre", "--out", "o"])
    assert not (tmp_path / "out").exists()


def write_episodes(run_dir: Path, stage: str, outcomes: dict[int, list[int]]) -> None:
    """The fit's episodes.csv as the validation loop writes it (evaluation seeds from 1e6)."""
    lines = ["step,task,seed,success"]
    for step, successes in outcomes.items():
        lines += [f"{step},Lift_Sawyer,{1_000_000 + i},{ok}" for i, ok in enumerate(successes)]
    (run_dir / stage / "fit" / "version_0" / "episodes.csv").write_text("\n".join(lines) + "\n")


def write_outcomes(run_dir: Path, stage: str, by_variant: dict[str | None, list[int]]) -> None:
    """An evaluate stage's results.json with each episode's outcome."""
    (run_dir / stage).mkdir(parents=True)
    rows = [
        {"task": "Lift", "robot": "Sawyer", "variant": variant, "episodes": len(successes),
         "successes": sum(successes),
         "outcomes": [[1_000_000 + i, bool(ok)] for i, ok in enumerate(successes)]}
        for variant, successes in by_variant.items()
    ]  # fmt: skip
    (run_dir / stage / "results.json").write_text(json.dumps(rows))


def test_report_compares_arms_paired_by_evaluation_seed(tmp_path: Path) -> None:
    run = tmp_path / "run"
    write_outcomes(run, "eval_pre", {None: [0, 0, 0, 0]})
    for seed, (sft, aux) in enumerate([([1, 0, 0, 0], [1, 1, 1, 0]), ([0, 1, 0, 0], [1, 1, 0, 1])]):
        write_fit(run, f"sft_s{seed}", {2: sum(sft) / 4}, {2: 0.3})
        write_episodes(run, f"sft_s{seed}", {2: sft})
        write_fit(run, f"aux_s{seed}", {2: sum(aux) / 4}, {2: 0.3})
        write_episodes(run, f"aux_s{seed}", {2: aux})
        write_outcomes(run, f"zs_sft_s{seed}", {"camera": sft, "lighting": [0, 0, 0, 0]})
        write_outcomes(run, f"zs_aux_s{seed}", {"camera": aux, "lighting": [0, 0, 0, 1]})
    arms = [("plain SFT", "sft_s*", "eval_pre"), ("aux-SFT", "aux_s*", "eval_pre")]
    zero_shot = [("plain SFT", "zs_sft_s*"), ("aux-SFT", "zs_aux_s*")]
    out = tmp_path / "report"
    text = report(run, arms, [], out, 0.5, ["plain SFT"], zero_shot, resamples=500)

    result = json.loads((out / "results.json").read_text())
    sft, aux = result["comparison"]["arms"]
    assert sft["points"] == [0, 2] and sft["success"] == [0.0, 0.25] and aux["success"][1] == 0.75
    assert sft["outcomes"][1] == [[0, 0, 0, 0], [0, 1, 0, 0]]  # per seed, point, evaluation seed
    assert sft["eval_seeds"][0] == ["Lift_Sawyer", 1_000_000]
    (difference,) = result["comparison"]["differences"]
    assert difference["arm"] == "aux-SFT" and difference["against"] == "plain SFT"
    assert difference["points"]["2"]["difference"] == pytest.approx(0.5)
    assert difference["auc"]["difference"] == pytest.approx(0.25)
    (zs,) = result["zero_shot"]["differences"]
    assert zs["points"]["lighting"]["difference"] == pytest.approx(0.25)
    assert "| aux-SFT | 2 × 4 | 0.0% | 75.0% | 0.375 | 2 |" in text  # reaches SFT's 25% at step 2
    assert "| aux-SFT − plain SFT | +0 pts" in text
    assert "| plain SFT | 2 × 4 | 25.0% | 0.0% |" in text  # zero-shot: camera, lighting


def test_comparison_needs_the_per_episode_log(tmp_path: Path) -> None:
    run = tmp_path / "run"
    write_outcomes(run, "eval_pre", {None: [0, 0]})
    write_fit(run, "sft_s0", {2: 0.5}, {2: 0.3})
    with pytest.raises(CapVectorError, match="no fit/version_0/episodes.csv"):
        report(run, [("x", "sft_s*", "eval_pre")], [], tmp_path / "o", 0.5, ["x"])


# Each committed report and the arms its command compared with (docs/results.md).
COMMITTED = [
    ("powered", ["plain SFT", "aux-SFT"]),
    ("pilot_few_demos/demos_10", ["plain SFT", "aux-SFT"]),
    ("pilot_few_demos/demos_5", ["plain SFT"]),
    ("libero_pilot", ["plain SFT"]),
    ("libero_demos50", ["plain SFT"]),
    ("libero_steps16k", ["plain SFT"]),
    ("libero_layer2", ["plain SFT"]),
    ("libero_objectives", ["plain SFT", "aux-SFT"]),
]


@pytest.mark.parametrize(("name", "compare_to"), COMMITTED, ids=[n for n, _ in COMMITTED])
def test_the_committed_reports_rebuild_from_their_results_json(
    name: str, compare_to: list[str], tmp_path: Path
) -> None:
    """The run folders are not committed; their results.json is, and gives back every table."""
    committed = RESULTS / name
    out = tmp_path / "rebuilt"
    main(["--from-results", str(committed / "results.json"), "--compare-to", *compare_to,
          "--out", str(out)])  # fmt: skip
    assert (out / "results.md").read_bytes() == (committed / "results.md").read_bytes()
    assert (out / "results.json").read_bytes() == (committed / "results.json").read_bytes()
    # The file's two records of the same episodes agree: each seed's success count (metrics.csv)
    # and its per-episode outcomes (episodes.csv).
    result = json.loads((committed / "results.json").read_text())
    for arm, episodes in zip(result["arms"], result["comparison"]["arms"], strict=True):
        for p, point in enumerate(episodes["points"]):
            successes = [sum(seed[p]) for seed in episodes["outcomes"]]
            assert successes == [k for k, _ in arm["counts"][str(point)]], (arm["arm"], point)


def test_a_rebuild_computes_again_what_is_derived(tmp_path: Path) -> None:
    """Stale derived numbers in the file change nothing; a changed measurement changes the
    tables and intervals."""
    committed = (RESULTS / "powered" / "results.md").read_text()
    result = json.loads((RESULTS / "powered" / "results.json").read_text())
    sft = result["arms"][0]
    sft["success"]["600"]["mean"], sft["steps_to_threshold"] = 0.99, [600] * 5
    result["references"] = dict.fromkeys(result["references"], 1.0)
    for section in ("comparison", "zero_shot"):
        for arm in result[section]["arms"]:
            arm["success"] = [1.0] * len(arm["success"])
        result[section]["differences"] = []
    stale = tmp_path / "stale.json"
    stale.write_text(json.dumps(result))
    report_from_results(stale, tmp_path / "stale", 0.5, ["plain SFT", "aux-SFT"])
    assert (tmp_path / "stale" / "results.md").read_text() == committed

    sft["success"]["600"]["values"][0] = 0.82  # seed 0 at step 600: 0.32 measured
    aux = result["comparison"]["arms"][1]
    assert aux["arm"] == "aux-SFT" and aux["points"][2] == 600
    aux["outcomes"][0][2][0] = flipped = 1 - aux["outcomes"][0][2][0]  # one episode at step 600
    tampered = tmp_path / "tampered.json"
    tampered.write_text(json.dumps(result))
    text = report_from_results(tampered, tmp_path / "tampered", 0.5, ["plain SFT", "aux-SFT"])
    assert "| plain SFT | 0% ± 0% | 25% ± 5% | 45% ± 21% |" in text  # mean 35% ± 4% before
    shift = 1 / 250 if flipped else -1 / 250  # one of 5 seeds × 50 episodes
    assert f"| aux-SFT | 5 × 50 | 0.0% | 32.0% | {0.388 + shift:.1%} |" in text
    rebuilt = json.loads((tmp_path / "tampered" / "results.json").read_text())
    difference = rebuilt["comparison"]["differences"][0]
    assert difference["arm"] == "aux-SFT" and difference["against"] == "plain SFT"
    assert difference["points"]["600"]["difference"] == pytest.approx(0.036 + shift)


def test_from_results_takes_the_place_of_the_run_folder(tmp_path: Path) -> None:
    powered = str(RESULTS / "powered" / "results.json")
    with pytest.raises(CapVectorError, match="reads the arms from its file: drop --run-dir"):
        main(["--from-results", powered, "--run-dir", "R", "--out", str(tmp_path / "o")])
    with pytest.raises(CapVectorError, match="give --run-dir and --arm .* or --from-results"):
        main(["--out", str(tmp_path / "o")])
    with pytest.raises(CapVectorError, match="holds the input"):
        main(["--from-results", powered, "--out", str(RESULTS / "powered")])
    (tmp_path / "notes.json").write_text('{"threshold": 0.5}')
    with pytest.raises(CapVectorError, match="not a results.json written by capvector report"):
        main(["--from-results", str(tmp_path / "notes.json"), "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_libero_episodes_pair_by_task_and_initial_state(tmp_path: Path) -> None:
    """LIBERO's evaluation units are (task, official initial state): the validation loop's
    episodes.csv names them `libero_spatial/<task>` and trial (tests/test_libero_eval.py), the
    evaluate stage's results.json the same, so trial 0 of task 5 pairs with trial 0 of task 5 only."""
    run, tasks, trials = tmp_path / "run", (5, 6), (0, 1)
    rows = [
        {"task": f"libero_spatial/{t}", "robot": "Panda", "variant": None, "episodes": 2,
         "successes": 0, "outcomes": [[i, False] for i in trials]}
        for t in tasks
    ]  # fmt: skip
    (run / "eval_pre").mkdir(parents=True)
    (run / "eval_pre" / "results.json").write_text(json.dumps(rows))
    # task 5 is solved from state 0 by both arms, task 6 from state 1 by aux only
    arms = {"sft": {(5, 0): 1, (6, 1): 0}, "aux": {(5, 0): 1, (6, 1): 1}}
    for arm, solved in arms.items():
        write_fit(run, f"{arm}_s0", {4: sum(solved.values()) / 4}, {4: 0.3})
        lines = ["step,task,seed,success"] + [
            f"4,libero_spatial/{t},{i},{solved.get((t, i), 0)}" for t in tasks for i in trials
        ]
        (run / f"{arm}_s0" / "fit" / "version_0" / "episodes.csv").write_text("\n".join(lines))
    out = tmp_path / "report"
    stages = [("plain SFT", "sft_s*", "eval_pre"), ("aux-SFT", "aux_s*", "eval_pre")]
    text = report(run, stages, [], out, 0.5, ["plain SFT"], [], resamples=200)
    # where each arm's successes come from, per task at the final step (seeds pooled)
    assert "| arm (step 4) | libero_spatial/5 | libero_spatial/6 |" in text
    assert "| plain SFT | 1/2 | 0/2 |" in text and "| aux-SFT | 1/2 | 1/2 |" in text
    result = json.loads((out / "results.json").read_text())
    sft, aux = result["comparison"]["arms"]
    units = [[f"libero_spatial/{t}", i] for t in tasks for i in trials]
    assert sft["eval_seeds"] == aux["eval_seeds"] == units
    assert sft["outcomes"][0][1] == [1, 0, 0, 0] and aux["outcomes"][0][1] == [1, 0, 0, 1]
    (difference,) = result["comparison"]["differences"]
    assert difference["points"]["4"]["difference"] == pytest.approx(0.25)


def test_the_libero_recipe_table_is_its_committed_evaluation() -> None:
    """docs/evaluation.md's per-task table of the LIBERO-Spatial recipe run counts what the run's
    committed `capvector evaluate --json` holds, episode by episode."""
    rows = json.loads((RESULTS / "libero_spatial_recipe" / "evaluate.json").read_text())
    text = (RESULTS.parent / "evaluation.md").read_text()
    table = text[text.index("### A policy trained on LIBERO-Spatial") :]
    total = 0
    for row in rows:
        task = int(row["task"].split("/")[1])
        successes = sum(ok for _, ok in row["outcomes"])
        assert successes == row["successes"] and len(row["outcomes"]) == 20
        assert re.search(rf"^\| {task} [^|]*\| {successes}/20 ", table, re.M), task
        total += successes
    assert f"| all | {total}/200 " in table


def test_the_libero_recipe_fails_the_same_with_twice_the_step_limit() -> None:
    """docs/evaluation.md's step-limit check: at 440 steps the recipe's policy solves exactly the
    episodes it solved at 220 (tasks 0-4, states 0-9), as the committed evaluations say."""

    def episodes(name: str) -> list[dict]:
        rows = json.loads((RESULTS / "libero_spatial_recipe" / name).read_text())
        return [e for row in rows for e in row["per_episode"]]

    def solved(episodes: list[dict]) -> set[tuple[int, int]]:
        return {(e["task"], e["trial"]) for e in episodes if e["success"]}

    doubled = episodes("evaluate_440_steps.json")
    assert {(e["task"], e["trial"]) for e in doubled} == {
        (t, i) for t in range(5) for i in range(10)
    }
    assert all(e["steps"] == 440 for e in doubled if not e["success"])
    at_220 = {(t, i) for t, i in solved(episodes("evaluate.json")) if t < 5 and i < 10}
    assert solved(doubled) == at_220
    text = (RESULTS.parent / "evaluation.md").read_text()
    assert f"succeeds in **{len(at_220)} of 50 episodes at 440 steps**" in text


def test_the_libero_recipe_fails_its_own_training_placements_too() -> None:
    """docs/evaluation.md's training-placement check: from its demos' start states (tasks 0-3,
    demos 0-9) the recipe's policy succeeds as rarely as the committed evaluation says."""
    rows = json.loads((RESULTS / "libero_spatial_recipe" / "evaluate_from_demos.json").read_text())
    episodes = [e for row in rows for e in row["per_episode"]]
    assert {(e["task"], e["trial"]) for e in episodes} == {
        (t, i) for t in range(4) for i in range(10)
    }
    assert all(e["from_demos"].endswith("runs/libero_spatial/demos_0_3/demos") for e in episodes)
    solved = sum(e["success"] for e in episodes)
    text = (RESULTS.parent / "evaluation.md").read_text()
    assert f"it succeeds in **{solved} of 40 episodes" in text
    official = json.loads((RESULTS / "libero_spatial_recipe" / "evaluate.json").read_text())
    same_tasks = sum(row["successes"] for row in official if int(row["task"].split("/")[1]) < 4)
    assert re.search(rf"against {same_tasks} of 80 from the\s+official states", text)


def test_the_libero_recipe_had_not_converged() -> None:
    """docs/evaluation.md's loss means per 1,000 steps and pass count, from the committed fit log."""
    with (RESULTS / "libero_spatial_recipe" / "fit_metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["train/loss"]]

    def mean_loss(start: int) -> str:
        losses = [float(r["train/loss"]) for r in rows if start <= int(r["step"]) < start + 1000]
        return f"{sum(losses) / len(losses):.3f}"

    text = " ".join((RESULTS.parent / "evaluation.md").read_text().split())
    means = [mean_loss(s) for s in (3000, 4000, 5000)]
    assert f"(mean {means[0]} over steps 3,000–4,000, {means[1]}, then {means[2]} over" in text
    passes = int(rows[-1]["epoch"]) + 1
    assert (
        f"the run made {['', 'one', 'two', 'three', 'four', 'five', 'six'][passes]} passes" in text
    )
