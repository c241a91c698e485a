"""Fingerprints of `capvector demos` HDF5 files, to check that demos recorded again from their
seeds (a study moved to another machine without them: docs/recipe.md) are the demos it trained on.

    python tools/libero/demo_hashes.py runs/libero_study/demos_down50/demos ... > hashes.json
    python tools/libero/demo_hashes.py --check hashes.json   # exits 1 naming any file that differs

Per file: ``hash`` covers every dataset's values and the demos' seeds, not the file's bytes (HDF5
keeps its own metadata) nor the attributes that hold the recording machine's paths; ``shapes``
covers the seeds and each dataset's shape (so each demo's length); ``moments`` holds each dataset's
mean and standard deviation over the file's demos. Another CPU simulates with other float
rounding (compiled kernels chosen by CPU): the same seeds give demos of the same lengths whose
values differ in their last bits (this study's demos recorded on two machines: proprio within
7.2e-8, action statistics within 1e-15). So a file is *identical* when ``hash`` matches,
*recomputed* when ``shapes`` matches and every dataset's moments agree to 1e-5 (relative), and
differs otherwise. A mean is compared relative to its dataset's spread when that is larger: a
mean near 0 sums values of both signs, so its rounding scales with their spread, not with itself
(the gripper fingers' mean opening, ~1.7e-7 against a spread of 0.026, moved by 1e-3 of itself).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

import h5py
import numpy as np

MOMENTS_TOLERANCE = 1e-5


def _values(dataset: h5py.Dataset) -> tuple[np.ndarray, bytes]:
    data = np.asarray(dataset[()])
    # strings (the annotations) come back as objects, whose bytes are pointers
    return data, repr(data.tolist()).encode() if data.dtype.kind == "O" else data.tobytes()


def fingerprint(path: Path) -> dict[str, Any]:
    """``hash``, ``shapes`` and ``moments`` of one demo file (module docstring)."""
    everything, shapes = hashlib.sha256(), hashlib.sha256()
    sums: dict[str, list[float]] = {}  # dataset key without the demo -> [n, sum, sum of squares]

    def visit(name: str, obj: Any) -> None:
        everything.update(name.encode())
        for key in ("seed", "seeds"):
            if key in obj.attrs:
                seeds = repr(np.asarray(obj.attrs[key]).tolist()).encode()
                everything.update(seeds)
                shapes.update(seeds)
        if not isinstance(obj, h5py.Dataset):
            return
        data, raw = _values(obj)
        everything.update(raw)
        shapes.update(f"{name}{data.shape}".encode())
        if data.dtype.kind in "biuf":
            values = data.astype(np.float64)
            total = sums.setdefault(re.sub(r"demo_\d+/", "", name), [0.0, 0.0, 0.0])
            total[0] += values.size
            total[1] += float(values.sum())
            total[2] += float(np.square(values).sum())

    with h5py.File(path, "r") as f:
        visit("/", f)
        f.visititems(visit)
    moments = {
        key: [s / n, math.sqrt(max(squares / n - (s / n) ** 2, 0.0))]
        for key, (n, s, squares) in sorted(sums.items())
        if n
    }
    return {"hash": everything.hexdigest(), "shapes": shapes.hexdigest(), "moments": moments}


def folder_fingerprints(folders: list[str]) -> dict[str, dict[str, Any]]:
    return {
        str(path): fingerprint(path)
        for folder in folders
        for path in sorted(Path(folder).glob("*.hdf5"))
        if not path.name.startswith(".")  # a file still being written
    }


def moments_difference(recorded: dict[str, list[float]], now: dict[str, list[float]]) -> float:
    """The largest relative difference between two files' moments (inf if their keys differ):
    a standard deviation's relative to itself, a mean's relative to itself or to the dataset's
    standard deviation, whichever is larger (module docstring)."""
    if recorded.keys() != now.keys():
        return math.inf

    def difference(key: str) -> float:
        (mean, std), (mean_now, std_now) = recorded[key], now[key]
        spread = max(std, std_now)
        return max(
            abs(mean - mean_now) / max(abs(mean), abs(mean_now), spread, 1e-12),
            abs(std - std_now) / max(spread, 1e-12),
        )

    return max((difference(key) for key in recorded), default=0.0)


def compare(path: str, recorded: dict[str, Any]) -> tuple[str, float, bool]:
    """``identical``, ``recomputed`` or ``differs`` (or ``missing``), the moments' largest
    relative difference, and whether the seeds and lengths (``shapes``) are the recorded ones."""
    if not Path(path).is_file():
        return "missing", math.inf, False
    now = fingerprint(Path(path))
    difference = moments_difference(recorded["moments"], now["moments"])
    same_lengths = now["shapes"] == recorded["shapes"]
    if now["hash"] == recorded["hash"]:
        return "identical", difference, same_lengths
    if same_lengths and difference <= MOMENTS_TOLERANCE:
        return "recomputed", difference, same_lengths
    return "differs", difference, same_lengths


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*", help="demo folders to fingerprint")
    parser.add_argument(
        "--check", metavar="JSON", help="fingerprints to compare the files they name with"
    )
    args = parser.parse_args()
    if not args.check:
        print(json.dumps(folder_fingerprints(args.folders), indent=1))
        return 0
    expected: dict[str, dict[str, Any]] = json.loads(Path(args.check).read_text())
    verdicts = {path: compare(path, recorded) for path, recorded in expected.items()}
    for path, (verdict, difference, same_lengths) in verdicts.items():
        if verdict == "missing":
            print(f"missing: {path}", file=sys.stderr)
        elif verdict == "differs":
            # a demo whose length changed has diverged, not just been rounded differently
            lengths = "the same seeds and lengths" if same_lengths else "other lengths"
            print(
                f"differs: {path} ({lengths}; moments differ by up to {difference:.2g})",
                file=sys.stderr,
            )
    counts = {
        v: sum(verdict == v for verdict, *_ in verdicts.values())
        for v in ("identical", "recomputed")
    }
    largest = max(
        (d for verdict, d, _ in verdicts.values() if verdict == "recomputed"), default=0.0
    )
    print(
        f"{counts['identical'] + counts['recomputed']} of {len(expected)} demo files as recorded "
        f"before: {counts['identical']} identical, {counts['recomputed']} recomputed (the same "
        f"seeds and lengths; every dataset's moments within {largest:.2g}, relative)"
    )
    return 0 if counts["identical"] + counts["recomputed"] == len(expected) else 1


if __name__ == "__main__":
    sys.exit(main())
