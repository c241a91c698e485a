"""Entry points of ``capvector extract|merge|compose`` (wired in ``capvector.cli``; ``inspect``'s,
which may send its plot to a Lightning logger, is ``capvector.workflows.inspection``).

Each ``*_main(argv)`` takes its options from the signature of the function that does the work
(``capvector.tool_cli``: ``extract`` and ``compose`` themselves, ``merge_cli``
for merge's ``--vector DIR:λ``), runs it with a progress bar and prints a short summary. Bad input
raises ``CapVectorError``, which ``capvector.cli.main`` prints as one line (exit code 2), as for
every command.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import NamedTuple

from capvector.errors import CapVectorError
from capvector.io.weights import (
    StorageDtype,
    parse_size,  # noqa: F401 (re-exported: --max-shard-size's sizes)
)
from capvector.tool_cli import Tool, run_tool


def command_line(command: str, argv: list[str] | None) -> str:
    """The shell command that ran this tool, for the metadata and model card it writes."""
    return shlex.join(["capvector", command, *(sys.argv[1:] if argv is None else argv)])


def extract_main(argv: list[str] | None = None) -> int:
    """``capvector extract``: its options are ``extract``'s parameters."""
    from capvector.vectors.extract import TASK_VECTOR_AUX, TASK_VECTOR_SFT, extract

    fixed = {"progress": True, "command": command_line("extract", argv)}
    tool = Tool(extract, "extract", skip=fixed)
    options = tool.parse(argv)
    meta = tool.call(options, **fixed)
    out = options["out"]
    tensors = meta["tensors"].values()
    lora = [t for t in tensors if t["storage"] == "lora"]
    print(
        f"wrote {out}: {meta['num_tensors']} tensors, {meta['num_parameters']:,} parameters, "
        f"‖c‖ = {meta['norm']:.4g}, dtype {meta['dtype']}"
    )
    print(f"  include {meta['include']} ({meta['include_origin']}), exclude {meta['exclude']}")
    if lora:
        energies = [t["retained_energy"] for t in lora]
        ranks = [t["rank"] for t in lora]
        print(
            f"  low-rank: {len(lora)} tensors as a PEFT LoRA adapter, ranks {min(ranks)}–{max(ranks)}, "
            f"retained energy min {min(energies):.3f} mean {sum(energies) / len(energies):.3f}; "
            f"{len(tensors) - len(lora)} tensors in full"
        )
    skipped = {k: v for k, v in meta["skipped"].items() if v}
    for reason, keys in skipped.items():
        print(f"  skipped {len(keys)} tensor(s) {reason.replace('_', ' ')}, e.g. {keys[0]}")
    if options["base"]:
        print(f"  task vectors: {out}/{TASK_VECTOR_AUX}, {out}/{TASK_VECTOR_SFT}")
    return 0


class ScaledVector(NamedTuple):
    """A vector folder and its scale λ, written ``DIR:λ`` (or ``DIR``, λ = 1)."""

    path: str
    scale: float = 1.0

    @classmethod
    def parse(cls, text: str) -> ScaledVector:
        """A colon followed by something that is not a number is part of the path only when
        that path exists; otherwise it is a mistyped λ and says so."""
        text = str(text)  # a config file's value may be a number
        path, sep, scale = text.rpartition(":")
        if not (sep and path):
            return cls(text)
        try:
            return cls(path, float(scale))
        except ValueError:
            if Path(text).exists():
                return cls(text)
            raise CapVectorError(
                f"{text!r}: λ after the colon must be a number (DIR:0.7), got {scale!r}"
            ) from None


def merge_main(argv: list[str] | None = None) -> int:
    return run_tool(merge_cli, argv, "merge", command=command_line("merge", argv))


def merge_cli(
    base: str,
    vector: list[ScaledVector],
    out: str,
    allow_repeat: bool = False,
    allow_large_scale: bool = False,
    dtype: StorageDtype | None = None,
    overwrite: bool = False,
    *,
    command: str,
) -> None:
    """θ_meta = θ_pre + Σ λ_i c_i, written as an export folder sharded like the base.

    Args:
        base: θ_pre: an export folder
        vector: DIR[:λ], a vector folder (full, low-rank or PEFT LoRA) and its scale λ (default
            1); repeatable
        out: output folder; written atomically, an existing one is an error unless --overwrite
        allow_repeat: merge a vector the base already holds (its config.json records merged
            vectors)
        allow_large_scale: accept |λ| > 100 (refused by default: it is almost always a typo)
        dtype: dtype of the merged weights (default: the base's); float32 keeps all of Σλc
        overwrite: replace an existing --out
        command: the command line, for the model card
    """
    from capvector.vectors.merge import merge
    from capvector.vectors.precision import precision_warning

    record = merge(
        base, vector, out, overwrite=overwrite, progress=True, allow_repeat=allow_repeat,
        allow_large_scale=allow_large_scale, command=command, dtype=dtype,
    )  # fmt: skip
    terms = " + ".join(f"{s:g}·{p}" for p, s in vector)
    print(f"wrote {out} = {base} + {terms}")
    print("  non-weight files of the base copied")
    kept = record["precision"]
    print(f"  {kept['dtype']} output keeps Σλc up to a {kept['relative_error']:.2%} relative error")
    if warning := precision_warning(kept):
        print(f"capvector merge: warning: {warning}", file=sys.stderr)


def compose_main(argv: list[str] | None = None) -> int:
    """``capvector compose``: its options are ``compose``'s parameters."""
    from capvector.vectors.compose import compose

    fixed = {"progress": True, "command": command_line("compose", argv)}
    tool = Tool(compose, "compose", skip=fixed)
    options = tool.parse(argv)
    meta = tool.call(options, **fixed)
    method, density, consensus = options["method"], options["density"], options["consensus"]
    how = f"TIES (density {density}, {consensus} consensus)" if method == "ties" else "sum"
    print(
        f"wrote {options['out']}: {how} of {len(options['vectors'])} vectors, "
        f"{meta['num_tensors']} tensors, ‖c‖ = {meta['norm']:.4g}"
    )
    return 0
