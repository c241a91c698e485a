"""The LIBERO study's final policies on upstream LIBERO against the port, episode by episode
(docs/results.md, "Lever 6's final policies on upstream LIBERO")::

    # collect: the evaluate JSONs of each stack (RESULTS/<stack>/<policy>.json, or one task's
    # chunk <policy>.task<k>.json) and the study's own outcomes at step 16,000 (its fits'
    # episodes.csv) into one CSV
    python tools/libero/upstream_study_table.py --collect RUNS/results RUNS/libero_study \\
        --out docs/results/libero_upstream/episodes.csv
    # tables (and paired bootstrap intervals) from the committed CSV; --tasks: those tasks only
    PYTHONPATH=src python tools/libero/upstream_study_table.py docs/results/libero_upstream/episodes.csv
    # and a figure: success per task on each stack, one panel per arm (Wilson 95% intervals)
    PYTHONPATH=src python tools/libero/upstream_study_table.py EPISODES.csv --plot success_by_stack.png

An episode (task, initial state) enters the CSV only when every policy ran it on both stacks (the
plans' pairing). An episode run twice on a stack (the chunks start again at initial state 0) keeps
its first run, from the file that sorts first; --collect prints how many re-runs came out otherwise.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

import numpy as np

ARMS = {"steps16k_sft": "plain SFT", "spatial_only": "spatial alignment only"}
STEP = 16_000  # the study's final exports
STACKS = {  # column -> what it is (the labels `capvector evaluate` writes, and the study's)
    "study": "the study's evaluation (port before the MuJoCo 2.3.7 corrections, fast renderer)",
    "port": "port now (robosuite 1.5.2, MuJoCo 3.9.0, corrected; fast renderer)",
    "upstream": "upstream LIBERO (robosuite 1.4.0, MuJoCo 2.3.7; official renderer)",
}
COLUMNS = ["policy", "arm", "task", "trial", "study", "port", "upstream", "port_steps",
           "upstream_steps", "port_stack", "port_renderer", "upstream_stack", "upstream_renderer"]  # fmt: skip


def policy_of(path: Path) -> str:
    """``<policy>.json`` holds a policy's episodes, ``<policy>.task<k>.json`` one task's."""
    return path.name.split(".")[0]


def plan_order(policy: str) -> tuple[str, bool]:
    return policy[-1], "spatial" in policy  # seed by seed, plain SFT first (the plans' order)


def collect(results: Path, study: Path) -> tuple[list[dict], str]:
    """The CSV's rows and a line saying what went in (and how many re-runs differed)."""
    ran: dict[str, dict[tuple[int, int], dict[str, tuple[dict, dict]]]] = {}
    reruns = differing = 0
    for stack in ("port", "upstream"):
        for path in sorted((results / stack).glob("*.json")):  # <policy>.json before its chunks
            for row in json.loads(path.read_text()):
                for e in row["per_episode"]:
                    by_stack = ran.setdefault(policy_of(path), {}).setdefault(
                        (e["task"], e["trial"]), {}
                    )
                    if stack in by_stack:
                        reruns += 1
                        differing += by_stack[stack][0]["success"] != e["success"]
                    else:
                        by_stack[stack] = (e, row)
    both_stacks = {p: {k for k, by_stack in ran[p].items() if len(by_stack) == 2} for p in ran}
    policies = sorted((p for p in ran if both_stacks[p]), key=plan_order)  # not run on both: out
    both = [both_stacks[p] for p in policies]
    episodes = sorted(set.intersection(*both)) if both else []
    rows = []
    for policy in policies:
        with (study / policy / "fit" / "version_0" / "episodes.csv").open() as f:
            studied = {
                (int(r["task"].split("/")[1]), int(r["seed"])): r["success"]
                for r in csv.DictReader(f)
                if int(r["step"]) == STEP
            }  # the last row of an episode counts, as capvector report reads it
        for task, trial in episodes:
            (p, prow), (u, urow) = (
                ran[policy][task, trial]["port"],
                ran[policy][task, trial]["upstream"],
            )
            rows.append({
                "policy": policy, "arm": ARMS[policy.rsplit("_s", 1)[0]], "task": task,
                "trial": trial, "study": studied[task, trial], "port": int(p["success"]),
                "upstream": int(u["success"]), "port_steps": p["steps"],
                "upstream_steps": u["steps"], "port_stack": prow["stack"],
                "port_renderer": prow["renderer"], "upstream_stack": urow["stack"],
                "upstream_renderer": urow["renderer"],
            })  # fmt: skip
    left_out = sum(len(k) for k in both) - len(episodes) * len(policies)
    said = (f"{len(episodes)} episodes of each of {len(policies)} policies; {left_out} run on both "
            f"stacks by only some policies left out; {reruns} re-runs, {differing} with another outcome")  # fmt: skip
    return rows, said


def tables(rows: list[dict]) -> str:
    from capvector.eval.comparison import ArmOutcomes, compare, format_difference
    from capvector.eval.results import success_cell

    out = ["| policy | task | trial | " + " | ".join(STACKS) + " |", "|---|---|---|---|---|---|"]
    for r in rows:
        cells = [r["policy"], r["task"], r["trial"], *("✓" if int(r[s]) else "✗" for s in STACKS)]
        out.append("| " + " | ".join(map(str, cells)) + " |")
    out += ["", "| arm | policies × episodes | " + " | ".join(STACKS) + " | upstream − port now "
            "| upstream − study | outcomes agree, upstream/port now |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    by_arm: dict[str, dict[str, np.ndarray]] = {}
    for arm in [a for a in ARMS.values() if any(r["arm"] == a for r in rows)]:
        mine = [r for r in rows if r["arm"] == arm]
        policies = list(dict.fromkeys(r["policy"] for r in mine))
        seeds = sorted({(r["task"], r["trial"]) for r in mine})
        outcomes = {
            s: np.array([[[next(int(r[s]) for r in mine if r["policy"] == p
                                and (r["task"], r["trial"]) == e) for e in seeds]] for p in policies])
            for s in STACKS
        }  # fmt: skip
        arms = [ArmOutcomes(s, [STEP], seeds, outcomes[s].astype(float)) for s in STACKS]
        diffs = {(d["arm"], d["against"]): d for d in compare(arms, ["port", "study"])}
        by_arm[arm] = outcomes
        cells = [arm, f"{len(policies)} × {len(seeds)}"]
        cells += [success_cell(int(outcomes[s].sum()), outcomes[s].size) for s in STACKS]
        cells += [format_difference(diffs["upstream", against]["points"][STEP])
                  for against in ("port", "study")]  # fmt: skip
        agree = int((outcomes["upstream"] == outcomes["port"]).sum())
        cells.append(f"{agree}/{outcomes['port'].size}")
        out.append("| " + " | ".join(cells) + " |")
    if len(by_arm) == 2:  # the study's question on each stack: the objective's difference
        (sft, sft_arm), (spatial, spatial_arm) = by_arm.items()
        out += ["", f"| stack | {spatial} − {sft} (paired bootstrap 95% interval) |", "|---|---|"]
        seeds = sorted({(r["task"], r["trial"]) for r in rows})
        for s in STACKS:
            arms = [ArmOutcomes(name, [STEP], seeds, outcomes[s].astype(float))
                    for name, outcomes in ((sft, sft_arm), (spatial, spatial_arm))]  # fmt: skip
            (d,) = compare(arms, [sft])
            out.append(f"| {STACKS[s]} | {format_difference(d['points'][STEP])} |")
    return "\n".join(out)


def plot(rows: list[dict], out: Path) -> None:
    """Success per task (and over them) on each stack, one panel per arm, with Wilson 95%
    intervals: where the stacks part is easier seen than read from the tables."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from capvector.eval.results import wilson_interval

    arms = [a for a in ARMS.values() if any(r["arm"] == a for r in rows)]
    tasks = sorted({int(r["task"]) for r in rows})
    groups = [(f"task {t}", [r for r in rows if int(r["task"]) == t]) for t in tasks]
    groups.append(("all", rows))
    width = 0.8 / len(STACKS)
    fig, axes = plt.subplots(1, len(arms), figsize=(5 * len(arms), 3.6), sharey=True, squeeze=False)
    for ax, arm in zip(axes[0], arms, strict=True):
        for i, stack in enumerate(STACKS):
            rates, low, high = [], [], []
            for _, group in groups:
                outcomes = [int(r[stack]) for r in group if r["arm"] == arm]
                rate = sum(outcomes) / len(outcomes)
                lo, hi = wilson_interval(sum(outcomes), len(outcomes))
                rates.append(100 * rate)
                low.append(100 * (rate - lo))
                high.append(100 * (hi - rate))
            x = np.arange(len(groups)) + (i - (len(STACKS) - 1) / 2) * width
            ax.bar(x, rates, width, yerr=[low, high], capsize=2, label=STACKS[stack].split(" (")[0])
        n = sum(r["arm"] == arm for r in rows) // len(tasks)
        ax.set_title(f"{arm} ({n} episodes per task and stack)", fontsize=10)
        ax.set_xticks(np.arange(len(groups)), [name for name, _ in groups])
        ax.set_ylim(0, 100)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].set_ylabel("success (%), Wilson 95%")
    axes[0][-1].legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    tmp = out.with_name(out.name + ".tmp")
    fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    tmp.replace(out)  # atomically


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("csv", nargs="?", type=Path, help="the collected CSV to tabulate")
    parser.add_argument("--collect", nargs=2, type=Path, metavar=("RESULTS", "STUDY"))
    parser.add_argument("--out", type=Path, help="where --collect writes the CSV")
    parser.add_argument("--tasks", nargs="+", type=int, help="tabulate these tasks' episodes only")
    parser.add_argument("--plot", type=Path, help="also draw success per task and stack (PNG)")
    args = parser.parse_args()
    if args.collect:
        rows, said = collect(*args.collect)
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(buffer.getvalue())
        tmp.replace(args.out)  # atomically
        print(f"{said}: {args.out}")
        return
    with args.csv.open() as f:
        rows = [r for r in csv.DictReader(f) if args.tasks is None or int(r["task"]) in args.tasks]
    if not rows:
        parser.error(f"{args.csv} has no episode of tasks {args.tasks}")
    print(tables(rows))
    if args.plot:
        plot(rows, args.plot)
        print(f"figure: {args.plot}")


if __name__ == "__main__":
    main()
