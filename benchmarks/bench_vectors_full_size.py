"""Capability vectors between two full-size exports: extract, inspect and merge, with peak memory.

Takes two exports of one full-size preset (θ_aux and θ_sft, e.g. ``bench_full_size.py --export``'s
``aux`` and ``sft`` runs) and a base export of the same preset to merge into. Each step runs as
``capvector`` in a process of its own, its peak RSS read from the kernel when it exits
(``os.wait4``'s ``ru_maxrss``); the bytes it wrote and its seconds are recorded:

- ``extract`` full form (every capability parameter, in the exports' dtype);
- ``extract`` LoRA form (``--rank``) of the language model, where the auxiliary objectives act
  (``--lowrank-include``), by ``--svd`` (default ``randomized``: an exact SVD of every 2-D weight
  of a 7 B language model takes hours on two cores, one 4,096 × 11,008 weight about 90 s);
- ``inspect`` of both;
- ``merge`` of the full vector into the base (``λ = 1``).

The goal for ``merge`` (issue 58): peak RSS ≤ 2 GiB above the largest single tensor, by streaming.
A numpy referee then checks a sample of tensors without capvector or torch arithmetic:
c = aux − sft in float64, and the merge = base + c rounded to the base's dtype (bf16 rounded to
nearest-even on the float32 bit pattern, as torch's cast does).

Outputs go under ``--work`` and are deleted at the end unless ``--keep``. At 7 B, θ_aux, θ_sft,
the full vector and the merge are 15 GB each: ``--drop-aux`` deletes θ_aux once the vector is
checked against it, before the merge writes, so three of them are on disk at once, not four.

    python benchmarks/bench_vectors_full_size.py --aux A --sft S --base B --work DIR [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

GIB = 1024**3
ROOT = Path(__file__).resolve().parents[1]
CAPVECTOR = [sys.executable, "-m", "capvector.cli"]


def run(name: str, args: list[str], output: Path | None) -> dict[str, Any]:
    """``capvector args`` in a child process: seconds, peak RSS, bytes written to ``output``."""
    start = time.perf_counter()
    child = subprocess.Popen([*CAPVECTOR, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    assert child.stdout is not None
    text = child.stdout.read().decode()
    _, status, usage = os.wait4(child.pid, 0)
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise SystemExit(f"{name} failed (exit {child.returncode}):\n{text[-3000:]}")
    written = sum(f.stat().st_size for f in output.rglob("*") if f.is_file()) if output else 0
    return {
        "step": name,
        "command": " ".join(["capvector", *args]),
        "seconds": time.perf_counter() - start,
        "peak_rss_gib": usage.ru_maxrss * 1024 / GIB,
        "written_gib": written / GIB,
        "output_tail": text.strip().splitlines()[-4:],
    }


def float32_of(folder: Path, key: str) -> np.ndarray:
    """A tensor of a safetensors folder as float32 numpy, read from the file's bytes by its own
    header (bf16 widened by shifting its 16 bits into a float32's high half: exact)."""
    for shard in sorted(folder.glob("*.safetensors")):
        with shard.open("rb") as f:
            size = int.from_bytes(f.read(8), "little")
            header = json.loads(f.read(size))
        if key not in header:
            continue
        entry = header[key]
        begin, end = entry["data_offsets"]
        raw = np.fromfile(shard, dtype=np.uint8, count=end - begin, offset=8 + size + begin)
        if entry["dtype"] == "BF16":
            wide = raw.view(np.uint16).astype(np.uint32) << 16
            return wide.view(np.float32).reshape(entry["shape"])
        if entry["dtype"] == "F32":
            return raw.view(np.float32).reshape(entry["shape"])
        raise SystemExit(f"{key} in {shard} is {entry['dtype']}; the referee reads BF16 and F32")
    raise KeyError(f"{key} is in no safetensors file of {folder}")


def round_to(x: np.ndarray, like: str) -> np.ndarray:
    """float32 → ``like`` (``BF16``: nearest, ties to even, as torch's cast) → float32."""
    if like == "F32":
        return x
    bits = x.view(np.uint32)
    rounded = (bits + np.uint32(0x7FFF) + ((bits >> 16) & np.uint32(1))) & np.uint32(0xFFFF0000)
    return rounded.view(np.float32)


def dtype_in(folder: Path, key: str) -> str:
    for shard in sorted(folder.glob("*.safetensors")):
        with shard.open("rb") as f:
            header = json.loads(f.read(int.from_bytes(f.read(8), "little")))
        if key in header:
            return header[key]["dtype"]
    raise KeyError(key)


def vector_referee(aux: Path, sft: Path, vector: Path, keys: list[str]) -> list[dict[str, Any]]:
    """Over ``keys``: how many elements of the vector differ from numpy's own c = round(aux −
    sft), in float32 arithmetic as IEEE defines it."""
    rows = []
    for key in keys:
        c32 = float32_of(aux, key) - float32_of(sft, key)  # exact for two bf16 inputs
        c = round_to(c32, dtype_in(vector, key))
        rows.append({
            "tensor": key,
            "elements": int(c.size),
            "vector_mismatches": int((float32_of(vector, key) != c).sum()),
            "vector_nonzero": int((c != 0).sum()),
        })  # fmt: skip
    return rows


def merge_referee(base: Path, vector: Path, meta: Path, keys: list[str]) -> list[dict[str, Any]]:
    """Over ``keys``: how many elements of the merge differ from numpy's round(base + c)."""
    rows = []
    for key in keys:
        merged = round_to(float32_of(base, key) + float32_of(vector, key), dtype_in(meta, key))
        rows.append({
            "tensor": key,
            "merge_mismatches": int((float32_of(meta, key) != merged).sum()),
        })  # fmt: skip
    return rows


def largest_tensor_bytes(folder: Path) -> tuple[str, int]:
    best = ("", 0)
    for shard in sorted(folder.glob("*.safetensors")):
        with shard.open("rb") as f:
            header = json.loads(f.read(int.from_bytes(f.read(8), "little")))
        for key, entry in header.items():
            if (
                key != "__metadata__"
                and entry["data_offsets"][1] - entry["data_offsets"][0] > best[1]
            ):
                best = (key, entry["data_offsets"][1] - entry["data_offsets"][0])
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--aux", type=Path, required=True)
    parser.add_argument("--sft", type=Path, required=True)
    parser.add_argument("--base", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True, help="where the outputs go")
    parser.add_argument("--rank", type=int, default=32)
    parser.add_argument("--lowrank-include", nargs="+", default=["language_model.*"])
    parser.add_argument("--sample", type=int, default=12, help="tensors the referee checks")
    parser.add_argument("--out", type=Path, default=ROOT / "docs/results/full_size_vectors.json")
    parser.add_argument("--keep", action="store_true", help="keep the outputs under --work")
    parser.add_argument("--svd", choices=["exact", "randomized"], default="randomized")
    parser.add_argument(
        "--drop-aux", action="store_true", help="delete --aux once the vector is checked"
    )
    args = parser.parse_args()
    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    full, lowrank, meta = work / "vector_full", work / "vector_lora", work / "theta_meta"
    pair = ["--aux", str(args.aux), "--sft", str(args.sft), "--overwrite"]
    steps = [
        run("extract full", ["extract", *pair, "--out", str(full)], full),
        run(
            "extract lora",
            [
                "extract",
                *pair,
                "--out",
                str(lowrank),
                "--rank",
                str(args.rank),
                "--svd",
                args.svd,
                "--include",
                *args.lowrank_include,
            ],
            lowrank,
        ),  # fmt: skip
        run("inspect full", ["inspect", str(full)], None),
        run("inspect lora", ["inspect", str(lowrank), "--against", str(full)], None),
    ]
    # Spread over the tensors c changes (by name), and one it leaves at zero if there is one.
    norms = json.loads((full / "capability_vector.json").read_text())["tensors"]
    changed = sorted(k for k, t in norms.items() if t["norm"] > 0)
    sample = changed[:: max(1, len(changed) // args.sample)][: args.sample]
    sample += sorted(k for k, t in norms.items() if t["norm"] == 0)[:1]
    checked = vector_referee(args.aux, args.sft, full, sample)
    if args.drop_aux:
        shutil.rmtree(args.aux)
    merge = ["merge", "--base", str(args.base), "--vector", str(full), "--out", str(meta)]
    steps.append(run("merge", [*merge, "--overwrite"], meta))
    for row, merged in zip(checked, merge_referee(args.base, full, meta, sample), strict=True):
        row.update(merged)
    name, largest = largest_tensor_bytes(args.base)
    result = {
        "aux": str(args.aux), "sft": str(args.sft), "base": str(args.base),
        "aux_deleted_before_merge": args.drop_aux,
        "steps": steps,
        "largest_tensor": name,
        "largest_tensor_gib": largest / GIB,
        "merge_peak_above_largest_gib": steps[-1]["peak_rss_gib"] - largest / GIB,
        "referee": {"tensors": checked},
        "command": "python benchmarks/bench_vectors_full_size.py " + " ".join(sys.argv[1:]),
    }  # fmt: skip
    tmp = args.out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(args.out)
    print(json.dumps(result, indent=2))
    if not args.keep:
        for folder in (full, lowrank, meta):
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
