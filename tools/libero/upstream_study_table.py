"""The LIBERO study's final policies on upstream LIBERO against the port, episode by episode
(docs/results.md, "Lever 6's final policies on upstream LIBERO")::

    # collect: the evaluate JSONs of each stack (one file per policy, named by its stage) and the
    # study's own outcomes at step 16,000 (its fits' episodes.csv) into one CSV
    python tools/libero/upstream_study_table.py --collect RUNS/results RUNS/libero_study \\
        --out docs/results/libero_upstream/episodes.csv
    # tables (and paired bootstrap intervals) from the committed CSV
    PYTHONPATH=src python tools/libero/upstream_study_table.py docs/results/libero_upstream/episodes.csv

A policy enters the CSV only when its every episode ran on both stacks (the plan's pairing).
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


def collect(results: Path, study: Path) -> list[dict]:
    rows = []
    files = (results / "upstream").glob("*.json")
    for upstream_file in sorted(files, key=lambda f: (f.stem[-1], "spatial" in f.stem)):  # plan
        policy = upstream_file.stem
        port_file = results / "port" / upstream_file.name
        if not port_file.is_file():
            continue  # not run on both stacks
        ran = {}
        for stack, path in (("port", port_file), ("upstream", upstream_file)):
            for row in json.loads(path.read_text()):
                for e in row["per_episode"]:
                    ran.setdefault((e["task"], e["trial"]), {})[stack] = (e, row)
        with (study / policy / "fit" / "version_0" / "episodes.csv").open() as f:
            studied = {
                (int(r["task"].split("/")[1]), int(r["seed"])): r["success"]
                for r in csv.DictReader(f)
                if int(r["step"]) == STEP
            }  # the last row of an episode counts, as capvector report reads it
        for (task, trial), by_stack in sorted(ran.items()):
            (p, prow), (u, urow) = by_stack["port"], by_stack["upstream"]
            rows.append({
                "policy": policy, "arm": ARMS[policy.rsplit("_s", 1)[0]], "task": task,
                "trial": trial, "study": studied[task, trial], "port": int(p["success"]),
                "upstream": int(u["success"]), "port_steps": p["steps"],
                "upstream_steps": u["steps"], "port_stack": prow["stack"],
                "port_renderer": prow["renderer"], "upstream_stack": urow["stack"],
                "upstream_renderer": urow["renderer"],
            })  # fmt: skip
    return rows


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("csv", nargs="?", type=Path, help="the collected CSV to tabulate")
    parser.add_argument("--collect", nargs=2, type=Path, metavar=("RESULTS", "STUDY"))
    parser.add_argument("--out", type=Path, help="where --collect writes the CSV")
    args = parser.parse_args()
    if args.collect:
        rows = collect(*args.collect)
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(".tmp")
        tmp.write_text(buffer.getvalue())
        tmp.replace(args.out)  # atomically
        print(f"{len(rows)} episodes of {len({r['policy'] for r in rows})} policies: {args.out}")
        return
    with args.csv.open() as f:
        print(tables(list(csv.DictReader(f))))


if __name__ == "__main__":
    main()
