"""Content hashes of `capvector demos` HDF5 files, to check that demos recorded again from their
seeds (a study moved to another machine without them: docs/recipe.md) are the demos it trained on.

    python tools/libero/demo_hashes.py runs/libero_study/demos_down50/demos ... > hashes.json
    python tools/libero/demo_hashes.py --check hashes.json   # exits 1 naming any file that differs

A file's hash covers its datasets' values and its demos' seeds, not the file's bytes (HDF5 keeps
its own metadata) nor the attributes that hold the recording machine's paths.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import h5py
import numpy as np


def file_hash(path: Path) -> str:
    digest = hashlib.sha256()

    def visit(name: str, obj: Any) -> None:
        digest.update(name.encode())
        for key in ("seed", "seeds"):
            if key in obj.attrs:
                digest.update(repr(np.asarray(obj.attrs[key]).tolist()).encode())
        if isinstance(obj, h5py.Dataset):
            data = np.asarray(obj[()])
            # strings (the annotations) come back as objects, whose bytes are pointers
            digest.update(
                repr(data.tolist()).encode() if data.dtype.kind == "O" else data.tobytes()
            )

    with h5py.File(path, "r") as f:
        visit("/", f)
        f.visititems(visit)
    return digest.hexdigest()


def folder_hashes(folders: list[str]) -> dict[str, str]:
    return {
        str(path): file_hash(path)
        for folder in folders
        for path in sorted(Path(folder).glob("*.hdf5"))
        if not path.name.startswith(".")  # a file still being written
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*", help="demo folders to hash")
    parser.add_argument(
        "--check", metavar="JSON", help="hashes to compare the files they name with"
    )
    args = parser.parse_args()
    if not args.check:
        print(json.dumps(folder_hashes(args.folders), indent=1))
        return 0
    expected: dict[str, str] = json.loads(Path(args.check).read_text())
    differ = [p for p, h in expected.items() if not Path(p).is_file() or file_hash(Path(p)) != h]
    for path in differ:
        print(f"differs or is missing: {path}", file=sys.stderr)
    print(f"{len(expected) - len(differ)} of {len(expected)} demo files as recorded before")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
