"""``capvector report``: the downstream comparison of a recipe run as a table and a plot.

Each arm is a set of seeds, i.e. ``fit`` stages of one recipe run whose names match a glob, plus
the ``evaluate`` stage of their starting weights (step 0). From the fits' CSV logs it reads the
rollout success and held-out action L1 at every validation, the step time and peak memory
(``StepCost``); references are evaluate-only arms (e.g. θ_pre + λc with no training). Writes
``results.json``, ``results.md`` and ``success_vs_steps.png`` to ``--out`` and prints the table.
``--from-results`` writes them again from a ``results.json`` alone (run folders are not committed),
recomputing everything derived from the measurements it keeps.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import statistics
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from lightning.pytorch.loggers import Logger

from capvector.errors import CapVectorError
from capvector.eval.comparison import (
    ArmOutcomes,
    area_under_curve,
    arm_from_episodes,
    compare,
    format_difference,
)
from capvector.eval.results import metric_key, provenance_label
from capvector.io.outputs import atomic_write_bytes, check_output
from capvector.tool_cli import run_tool
from capvector.training.loggers import log_figure

SUCCESS = "val/success_rate"
EPISODES = "val/episodes"
HELD_OUT_L1 = "val/action_l1"
STEP_SECONDS = "perf/step_seconds"
PEAK_MEMORY = "perf/peak_memory_mib"


@dataclass
class SeedRun:
    """One fit stage: metrics by training step (steps trained, not the logger's 0-based index)."""

    stage: str
    success: dict[int, float] = field(default_factory=dict)
    episodes: dict[int, int] = field(default_factory=dict)
    """Episodes behind each success rate (``val/episodes``), so counts can be recomputed."""
    held_out_l1: dict[int, float] = field(default_factory=dict)
    step_seconds: list[float] = field(default_factory=list)
    peak_memory_mib: float | None = None
    stacks: set[str] = field(default_factory=set)
    """Which simulator stack and renderer its rollouts ran on (``episodes.csv``)."""


def read_fit(stage_dir: Path) -> SeedRun:
    """Metrics of a recipe fit stage from ``<stage>/fit/version_0/metrics.csv`` (CSVLogger)."""
    path = stage_dir / "fit" / "version_0" / "metrics.csv"
    if not path.is_file():
        raise CapVectorError(f"{path} does not exist: has the fit stage {stage_dir.name!r} run?")
    run = SeedRun(stage_dir.name)
    with path.open() as f:
        for row in csv.DictReader(f):
            # Lightning logs the metrics of step k (k optimizer steps done) at row "step" k - 1.
            step = int(row["step"]) + 1
            if row.get(SUCCESS):
                run.success[step] = float(row[SUCCESS])
            if row.get(EPISODES):
                run.episodes[step] = round(float(row[EPISODES]))
            if row.get(HELD_OUT_L1):
                run.held_out_l1[step] = float(row[HELD_OUT_L1])
            if row.get(STEP_SECONDS):
                run.step_seconds.append(float(row[STEP_SECONDS]))
            if row.get(PEAK_MEMORY):
                run.peak_memory_mib = max(run.peak_memory_mib or 0.0, float(row[PEAK_MEMORY]))
    if not run.success:
        raise CapVectorError(f"{path} has no {SUCCESS}: the fit ran without rollout validation")
    run.stacks = episode_log_stacks(stage_dir)
    return run


def episode_log_stacks(stage_dir: Path) -> set[str]:
    """The stacks (and renderers) a fit's ``episodes.csv`` says its rollouts ran on; a log from
    before it said, or none: ``not recorded``."""
    stacks = set()
    for path in sorted((stage_dir / "fit" / "version_0").glob("episodes*.csv")):
        with path.open() as f:
            stacks |= {
                provenance_label(r.get("stack"), r.get("renderer")) for r in csv.DictReader(f)
            }
    return stacks or {provenance_label(None, None)}


def evaluation_stacks(stage_dir: Path) -> set[str]:
    """The stacks (and renderers) the rows of an ``evaluate`` stage's ``results.json`` name."""
    rows = json.loads((stage_dir / "results.json").read_text())
    return {provenance_label(r.get("stack"), r.get("renderer")) for r in rows}


def read_evaluation(stage_dir: Path) -> tuple[int, int]:
    """(successes, episodes) over every row of an ``evaluate`` stage's ``results.json``."""
    path = stage_dir / "results.json"
    if not path.is_file():
        raise CapVectorError(f"{path} does not exist: run the evaluate stage with --json {path}")
    rows = json.loads(path.read_text())
    return sum(r["successes"] for r in rows), sum(r["episodes"] for r in rows)


def read_episode_log(stage_dir: Path) -> dict[int, dict[tuple[str, int], bool]]:
    """``{step: {(task key, evaluation seed): success}}`` from a fit stage's ``episodes.csv``
    (every rank's file; an evaluation repeated after a resume: the last one counts)."""
    files = sorted((stage_dir / "fit" / "version_0").glob("episodes*.csv"))
    if not files:
        raise CapVectorError(
            f"{stage_dir} has no fit/version_0/episodes.csv: per-episode outcomes are logged "
            "since the validation loop batches episodes; rerun the fit to compare arms"
        )
    by_step: dict[int, dict[tuple[str, int], bool]] = {}
    for path in files:
        with path.open() as f:
            for row in csv.DictReader(f):
                episode = (row["task"], int(row["seed"]))
                by_step.setdefault(int(row["step"]), {})[episode] = row["success"] == "1"
    return by_step


def read_evaluation_outcomes(stage_dir: Path) -> dict[str | None, dict[tuple[str, int], bool]]:
    """``{variant: {(task key, evaluation seed): success}}`` of an ``evaluate`` stage."""
    rows = json.loads((stage_dir / "results.json").read_text())
    out: dict[str | None, dict[tuple[str, int], bool]] = {}
    for row in rows:
        key = metric_key(row["task"], row["robot"])
        variant = out.setdefault(row.get("variant"), {})
        variant.update({(key, int(seed)): bool(ok) for seed, ok in row["outcomes"]})
    return out


def steps_to(success: dict[int, float], threshold: float) -> int | None:
    """The first evaluated step whose success rate reaches ``threshold`` (None: never)."""
    return next((s for s in sorted(success) if success[s] >= threshold), None)


def summarize_arm(
    label: str,
    runs: list[SeedRun],
    start_counts: tuple[int, int],
    threshold: float,
    start_stacks: Iterable[str] = (),
) -> dict[str, Any]:
    start = start_counts[0] / start_counts[1]
    steps = sorted(set.intersection(*(set(r.success) for r in runs)))
    curve = {0: [start] * len(runs)} | {s: [r.success[s] for r in runs] for s in steps}
    reached = [steps_to({0: start} | r.success, threshold) for r in runs]
    l1_steps = sorted(set.intersection(*(set(r.held_out_l1) for r in runs)))
    seconds = [statistics.median(r.step_seconds) for r in runs if r.step_seconds]
    memory = [r.peak_memory_mib for r in runs if r.peak_memory_mib is not None]
    return {
        "arm": label,
        "seeds": [r.stage for r in runs],
        "success": {s: _spread(v) for s, v in curve.items()},
        # Per seed and step: successes and episodes, so intervals can be recomputed from the file
        # (step 0 is the one evaluation of the starting weights every seed shares).
        "counts": {0: [list(start_counts)] * len(runs)}
        | {s: [_counts(r, s) for r in runs] for s in steps},
        "held_out_l1": {s: _spread([r.held_out_l1[s] for r in runs]) for s in l1_steps},
        "steps_to_threshold": reached,
        "step_seconds": _spread(seconds) if seconds else None,
        "peak_memory_mib": max(memory) if memory else None,
        # Which stack produced its numbers (step 0's evaluation and every fit's rollouts).
        "stacks": sorted(set(start_stacks).union(*(r.stacks for r in runs))),
    }


def _counts(run: SeedRun, step: int) -> list[int] | None:
    """[successes, episodes] of one validation (None when the log has no episode count)."""
    episodes = run.episodes.get(step)
    return None if episodes is None else [round(run.success[step] * episodes), episodes]


def _spread(values: list[float]) -> dict[str, Any]:
    return {
        "mean": statistics.fmean(values),
        "std": statistics.stdev(values) if len(values) > 1 else 0.0,
        "min": min(values),
        "max": max(values),
        "values": values,
    }


def format_table(
    arms: list[dict],
    references: dict[str, float],
    threshold: float,
    reference_stacks: dict[str, list[str]] | None = None,
) -> str:
    steps = sorted({int(s) for a in arms for s in a["success"]})
    head = ["arm", *(f"step {s}" for s in steps), f"steps to {threshold:.0%}",
            "held-out L1 (last)", "s/step", "peak MiB"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for a in arms:
        cells = [a["arm"]]
        for s in steps:
            v = a["success"].get(s)
            cells.append(f"{v['mean']:.0%} ± {v['std']:.0%}" if v else "–")
        reached = [r for r in a["steps_to_threshold"] if r is not None]
        n = len(a["steps_to_threshold"])
        cells.append(
            f"{statistics.median(reached):.0f} ({len(reached)}/{n})" if reached else f"– (0/{n})"
        )
        # The action L1 on held-out demos at the last validation: it still ranks arms whose
        # policies do not succeed yet (training L1 does not track closed-loop success).
        l1 = a["held_out_l1"][max(a["held_out_l1"], key=int)] if a["held_out_l1"] else None
        cells.append(f"{l1['mean']:.3f} ± {l1['std']:.3f}" if l1 else "–")
        cells.append(f"{a['step_seconds']['mean']:.3f}" if a["step_seconds"] else "–")
        cells.append(f"{a['peak_memory_mib']:.0f}" if a["peak_memory_mib"] else "–")
        lines.append("| " + " | ".join(cells) + " |")
    for label, rate in references.items():
        lines.append("| " + " | ".join([label, f"{rate:.0%}", *["" for _ in head[2:]]]) + " |")
    return "\n".join(lines) + "\n\n" + format_stacks(arms, reference_stacks or {})


def format_stacks(arms: list[dict], reference_stacks: dict[str, list[str]]) -> str:
    """Which simulator stack and renderer produced the numbers: one line when every arm shares
    them, else one line per arm (a LIBERO port's numbers are never read as upstream's)."""
    per_arm = {a["arm"]: a.get("stacks") or [provenance_label(None, None)] for a in arms}
    per_arm |= reference_stacks
    distinct = {tuple(v) for v in per_arm.values()}
    if len(distinct) == 1:
        return f"Stack: {'; '.join(distinct.pop())}."
    return "\n".join(f"Stack of {label}: {'; '.join(v)}." for label, v in per_arm.items())


def plot(arms: list[dict], references: dict[str, float], path: Path) -> None:
    """Success (mean, band = min..max over seeds) and held-out L1 against training steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for a in arms:
        steps = sorted(int(s) for s in a["success"])
        mean = [a["success"][s]["mean"] for s in steps]
        line = left.plot(steps, mean, marker="o", label=f"{a['arm']} ({len(a['seeds'])} seeds)")[0]
        low = [a["success"][s]["min"] for s in steps]
        high = [a["success"][s]["max"] for s in steps]
        left.fill_between(steps, low, high, color=line.get_color(), alpha=0.15)
        if a["held_out_l1"]:
            l1_steps = sorted(int(s) for s in a["held_out_l1"])
            l1 = [a["held_out_l1"][s]["mean"] for s in l1_steps]
            right.plot(l1_steps, l1, marker="o", color=line.get_color(), label=a["arm"])
    for (label, rate), style in zip(references.items(), itertools.cycle(["--", ":", "-."])):
        left.axhline(rate, linestyle=style, color="gray", label=f"{label} (no training)")
    left.set(xlabel="training steps", ylabel="success rate", ylim=(-0.02, 1.02))
    left.set_title("MuJoCo success (mean; band: min–max over seeds)")
    left.legend(fontsize=7)
    right.set(xlabel="training steps", ylabel="held-out action L1")
    right.set_title("held-out action L1 (mean over seeds)")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())


def training_arm(
    label: str, stages: list[Path], start_stage: Path, steps: list[int]
) -> ArmOutcomes:
    """An arm's outcomes at step 0 (its starting weights' evaluation, shared by every seed) and
    at each evaluated step of its fits."""
    start = read_evaluation_outcomes(start_stage).get(None, {})
    per_seed = [{0: start} | read_episode_log(stage) for stage in stages]
    return arm_from_episodes(label, per_seed, [0, *steps])


def zero_shot_arm(label: str, stages: list[Path]) -> ArmOutcomes:
    """An arm's outcomes per scene variant, from the ``evaluate`` stage of each seed's policy."""
    per_seed = [read_evaluation_outcomes(stage) for stage in stages]
    variants = [v for v in per_seed[0] if v is not None]
    return arm_from_episodes(label, per_seed, variants)


def steps_to_reach(arm: ArmOutcomes, target: float) -> int | None:
    """The first evaluated step at which the arm's success over all seeds reaches ``target``."""
    return next((p for p, r in zip(arm.points, arm.rates(), strict=True) if r >= target), None)


def format_comparison(
    arms: list[ArmOutcomes], differences: list[dict], reference: str, zero_shot: bool
) -> str:
    """Success per arm at every point and, per compared pair, the differences with intervals."""
    points = arms[0].points
    name = (lambda p: str(p)) if zero_shot else (lambda p: f"step {p}")
    head = ["arm", "seeds × episodes", *(name(p) for p in points)]
    if not zero_shot:
        ref = next(a for a in arms if a.label == reference)
        target = ref.rates()[-1]
        head += ["area under curve", f"steps to {reference}'s final {target:.0%}"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm in arms:
        seeds, _, episodes = arm.outcomes.shape
        cells = [arm.label, f"{seeds} × {episodes}", *(f"{r:.1%}" for r in arm.rates())]
        if not zero_shot:
            cells.append(f"{area_under_curve(points, arm.rates()):.3f}")
            reached = steps_to_reach(arm, target)
            cells.append("–" if reached is None else str(reached))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "| difference | " + " | ".join(name(p) for p in points)
              + (" |" if zero_shot else " | area under curve |"),
              "|" + "---|" * (len(points) + 1 + (not zero_shot))]  # fmt: skip
    for d in differences:
        cells = [f"{d['arm']} − {d['against']}"]
        cells += [format_difference(d["points"][p]) for p in points]
        if "auc" in d:
            cells.append(format_difference(d["auc"]))
        lines.append("| " + " | ".join(cells) + " |")
    if not zero_shot:  # the family-wise reading is of the final step (zero-shot variants: none)
        lines += format_holm(differences, points[-1], name(points[-1]))
    return "\n".join(lines)


def format_holm(differences: list[dict], point: Any, name: str) -> list[str]:
    """At the last point, Holm's adjustment over the arms compared with each reference (rows
    only where a reference has two or more): the family-wise reading beside the 95% intervals."""
    adjusted = [d for d in differences if "holm" in d["points"][point]]
    if not adjusted:
        return []
    lines = ["", f"Holm's adjustment at {name}, over the arms compared with each reference "
             "(family-wise 5%; detected where the adjusted p is below 0.05):", "",
             "| difference | adjusted p | interval at the Holm level |", "|---|---|---|"]  # fmt: skip
    for d in adjusted:
        h = d["points"][point]["holm"]
        low, high = (100 * x for x in h["ci"])
        lines.append(f"| {d['arm']} − {d['against']} | {h['p']:.3f} | "
                     f"({low:+.0f}, {high:+.0f}) at {h['level']:.1%} |")  # fmt: skip
    return lines


def format_per_task(arms: list[ArmOutcomes]) -> str | None:
    """Successes per task at the final step, pooled over training seeds, when the episodes span
    more than one task (a LIBERO suite): where an arm's success comes from. None for one task."""
    tasks = list(dict.fromkeys(seed[0] for seed in arms[0].eval_seeds))
    if len(tasks) < 2:
        return None
    head = [f"arm (step {arms[0].points[-1]})", *map(str, tasks)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm in arms:
        final = arm.outcomes[:, -1]  # (training seeds, evaluation seeds)
        cells = [arm.label]
        for task in tasks:
            columns = [i for i, seed in enumerate(arm.eval_seeds) if seed[0] == task]
            cells.append(f"{int(final[:, columns].sum())}/{final[:, columns].size}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def report(
    run_dir: Path,
    arms: list[tuple[str, str, str]],
    references: list[tuple[str, str]],
    out: Path,
    threshold: float,
    compare_to: list[str] | None = None,
    zero_shot: list[tuple[str, str]] | None = None,
    resamples: int = 10_000,
) -> str:
    """The table and plot; with ``compare_to``, differences against those arms with paired
    bootstrap intervals from the fits' per-episode outcomes (and for ``zero_shot`` arms: label,
    glob of each seed's ``evaluate`` stage with variants)."""
    globs = [(label, pattern) for label, pattern, _ in arms] + list(zero_shot or [])
    stages = [run_dir / stage for *_, stage in [*arms, *references]]
    stages += [d for label, pattern in globs for d in _stage_dirs(run_dir, label, pattern)]
    check_output(out, overwrite=True, inputs=stages)  # the results are rewritten on each run
    summaries, stage_dirs = [], {}
    for label, pattern, start_stage in arms:
        dirs = _stage_dirs(run_dir, label, pattern)
        runs = [read_fit(d) for d in dirs]
        start = read_evaluation(run_dir / start_stage)
        start_stacks = evaluation_stacks(run_dir / start_stage)
        summaries.append(summarize_arm(label, runs, start, threshold, start_stacks))
        stage_dirs[label] = (dirs, run_dir / start_stage)
    ref_counts = {label: read_evaluation(run_dir / stage) for label, stage in references}
    ref_stacks = {label: sorted(evaluation_stacks(run_dir / stage)) for label, stage in references}
    training = zero_shot_arms = None
    if compare_to:
        steps = sorted(set.intersection(*(set(map(int, a["success"])) for a in summaries)) - {0})
        training = [training_arm(label, *stage_dirs[label], steps) for label, _, _ in arms]
    if zero_shot:
        zero_shot_arms = [
            zero_shot_arm(label, _stage_dirs(run_dir, label, g)) for label, g in zero_shot
        ]
    return write_report(
        out, summaries, ref_counts, threshold, compare_to, training, zero_shot_arms, resamples,
        ref_stacks,
    )  # fmt: skip


def report_from_results(
    path: Path,
    out: Path,
    threshold: float,
    compare_to: list[str] | None = None,
    resamples: int = 10_000,
) -> str:
    """``report`` again from the ``results.json`` it wrote, e.g. a committed one whose run folder
    is gone: what was measured (each seed's success, episode counts, held-out L1 and step time,
    every episode's outcome) is read back, everything derived from it (spreads, steps to the
    threshold, success over seeds, differences and their bootstrap intervals, tables, plot) is
    computed again, with ``threshold``, ``compare_to`` and ``resamples`` as given."""
    check_output(out, overwrite=True, inputs=[path])
    try:
        result = json.loads(path.read_text())
        summaries = [_summary_from_json(arm, threshold) for arm in result["arms"]]
        ref_counts = {label: tuple(c) for label, c in result["reference_counts"].items()}
        ref_stacks = result.get("reference_stacks", {})  # absent: written before stacks were
        training = _outcomes_from_json(result["comparison"]) if "comparison" in result else None
        zero_shot = _outcomes_from_json(result["zero_shot"]) if "zero_shot" in result else None
    except FileNotFoundError as err:
        raise CapVectorError(f"{path} does not exist: give the results.json of a report") from err
    except (ValueError, KeyError, IndexError, TypeError) as err:  # JSONDecodeError is one
        raise CapVectorError(
            f"{path} is not a results.json written by capvector report ({type(err).__name__}: "
            f"{err}); give the results.json of a report"
        ) from err
    if compare_to and training is None:
        raise CapVectorError(
            f"{path} has no per-episode outcomes (it was written without --compare-to): drop "
            "--compare-to"
        )
    return write_report(
        out, summaries, ref_counts, threshold, compare_to, training, zero_shot, resamples,
        ref_stacks,
    )  # fmt: skip


def _summary_from_json(arm: dict[str, Any], threshold: float) -> dict[str, Any]:
    """An arm's summary made again by ``summarize_arm`` from the per-seed values it stored."""
    success, counts, l1 = arm["success"], arm["counts"], arm["held_out_l1"]
    seconds = arm["step_seconds"]["values"] if arm["step_seconds"] else []
    runs = []
    for i, stage in enumerate(arm["seeds"]):
        run = SeedRun(stage, peak_memory_mib=arm["peak_memory_mib"])  # the file keeps the max
        for step in (s for s in success if s != "0"):
            run.success[int(step)] = success[step]["values"][i]
            if counts[step][i] is not None:
                run.episodes[int(step)] = counts[step][i][1]
        run.held_out_l1 = {int(s): v["values"][i] for s, v in l1.items()}
        # Each seed's median step time is stored, in the order of the seeds that logged one;
        # only their spread is used, so the first seeds carry them.
        run.step_seconds = seconds[i : i + 1]
        runs.append(run)
    stacks = set(arm.get("stacks", ()))  # absent: written before reports said which stack
    return summarize_arm(arm["arm"], runs, tuple(counts["0"][0]), threshold, stacks)


def _outcomes_from_json(section: dict[str, Any]) -> list[ArmOutcomes]:
    """The arms of a ``comparison`` or ``zero_shot`` section, from their per-episode outcomes."""
    return [
        ArmOutcomes(
            a["arm"],
            a["points"],
            [tuple(seed) for seed in a["eval_seeds"]],
            np.asarray(a["outcomes"], dtype=float),
        )
        for a in section["arms"]
    ]


def write_report(
    out: Path,
    summaries: list[dict[str, Any]],
    ref_counts: dict[str, tuple[int, int]],
    threshold: float,
    compare_to: list[str] | None,
    training: list[ArmOutcomes] | None,
    zero_shot: list[ArmOutcomes] | None,
    resamples: int,
    ref_stacks: dict[str, list[str]] | None = None,
) -> str:
    """Tables, comparisons, ``results.json`` and plot from the arms' summaries and outcomes."""
    refs = {label: k / n for label, (k, n) in ref_counts.items()}
    table = format_table(summaries, refs, threshold, ref_stacks)
    result: dict[str, Any] = {
        "threshold": threshold,
        "arms": summaries,
        "references": refs,
        "reference_counts": {label: list(c) for label, c in ref_counts.items()},
        "reference_stacks": ref_stacks or {},
    }
    sections = [table]
    if compare_to and training is not None:
        differences = compare(training, compare_to, resamples)
        result["comparison"] = _comparison_json(training, differences, resamples)
        sections.append(format_comparison(training, differences, compare_to[0], False))
        per_task = format_per_task(training)
        if per_task is not None:
            sections.append(per_task)
    if zero_shot:
        labels = {a.label for a in zero_shot}
        against = [label for label in compare_to or [] if label in labels]
        differences = compare(zero_shot, against or [zero_shot[0].label], resamples)
        result["zero_shot"] = _comparison_json(zero_shot, differences, resamples)
        sections.append(format_comparison(zero_shot, differences, "", True))
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "results.json", json.dumps(result, indent=2).encode())
    text = "\n\n".join(sections)
    atomic_write_bytes(out / "results.md", (text + "\n").encode())
    plot(summaries, refs, out / "success_vs_steps.png")
    return text


def _stage_dirs(run_dir: Path, label: str, pattern: str) -> list[Path]:
    dirs = sorted(d for d in run_dir.glob(pattern) if d.is_dir())
    if not dirs:
        raise CapVectorError(f"arm {label!r}: no stage folder in {run_dir} matches {pattern!r}")
    return dirs


def _comparison_json(arms: list[ArmOutcomes], differences: list[dict], resamples: int) -> dict:
    """Per-episode outcomes (so anyone can recompute) and the differences with intervals."""
    return {
        "method": f"95% percentile bootstrap, {resamples} resamples: evaluation seeds drawn with "
        "replacement, the same draw for both arms (paired); training seeds drawn with "
        "replacement per arm",
        "arms": [
            {
                "arm": a.label,
                "points": a.points,
                "eval_seeds": [list(s) for s in a.eval_seeds],
                "success": a.rates().tolist(),
                # outcomes[training seed][point] = 0/1 per evaluation seed, in eval_seeds order
                "outcomes": a.outcomes.astype(int).tolist(),
            }
            for a in arms
        ],
        "differences": differences,
    }


class Arm(NamedTuple):
    """A training arm on the command line: ``--arm LABEL GLOB START``."""

    label: str
    glob: str
    start: str


class Reference(NamedTuple):
    """An evaluate-only arm: ``--reference LABEL STAGE``."""

    label: str
    stage: str


class ZeroShotArm(NamedTuple):
    """An arm's zero-shot evaluate stages: ``--zero-shot LABEL GLOB``."""

    label: str
    glob: str


def main(argv: list[str] | None = None) -> int:
    return run_tool(report_cli, argv, "report")


def report_cli(
    out: Path,
    run_dir: Path | None = None,
    arm: list[Arm] | None = None,
    from_results: Path | None = None,
    reference: list[Reference] | None = None,
    threshold: float = 0.5,
    compare_to: list[str] | None = None,
    zero_shot: list[ZeroShotArm] | None = None,
    resamples: int = 10_000,
    logger: Logger | None = None,
) -> None:
    """The downstream comparison of a recipe run as a table and a plot.

    Args:
        out: folder for the results
        run_dir: the recipe's run folder
        arm: an arm: its label, a glob of its fit stages (one per seed) and the evaluate stage of
            its starting weights (its step 0); repeatable
        from_results: a results.json this command wrote, instead of --run-dir and its arms: what
            it measured is read back and everything derived from it computed again
        reference: an evaluate-only arm (no training), drawn as a horizontal line; repeatable
        threshold: success rate to reach
        compare_to: arms to compare every other arm with: differences in success per step and
            in the area under the curve, paired bootstrap 95% intervals from the per-episode
            outcomes
        zero_shot: an arm's evaluate stages (one per seed, run with --variant ...): success per
            scene variant, compared like --compare-to; repeatable
        resamples: bootstrap resamples
        logger: a Lightning logger to show the plot in as well, given as in a fit config's
            trainer.logger, e.g. --logger lightning.pytorch.loggers.WandbLogger
            --logger.project P (TensorBoard, W&B and MLflow show it)
    """
    if from_results is not None:
        run_options = {"--run-dir": run_dir, "--arm": arm, "--reference": reference,
                       "--zero-shot": zero_shot}  # fmt: skip
        given = [flag for flag, value in run_options.items() if value]
        if given:
            raise CapVectorError(
                f"--from-results reads the arms from its file: drop {', '.join(given)}"
            )
        table = report_from_results(from_results, out, threshold, compare_to, resamples)
    elif run_dir is None or not arm:
        raise CapVectorError(
            "give --run-dir and --arm (a recipe run) or --from-results (a report's results.json)"
        )
    else:
        table = report(
            run_dir, arm, reference or [], out, threshold, compare_to, zero_shot, resamples
        )
    print(table)
    print(f"\nplot: {out / 'success_vs_steps.png'}")
    if logger is not None:
        log_figure([logger], "report/success_vs_steps", out / "success_vs_steps.png")
        logger.finalize("success")
