"""Entry points of ``capvector extract|merge|compose|inspect`` (wired in ``capvector.cli``).

Each ``*_main(argv)`` parses its own arguments, runs the library function with a progress bar and
prints a short summary. Bad input raises ``CapVectorError``, which ``capvector.cli.main`` prints as
one line (exit code 2), as for every command.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path

from capvector.errors import ToolParser
from capvector.io.weights import DEFAULT_MAX_SHARD_SIZE

_OUT_HELP = "output folder; written atomically, an existing one is an error unless --overwrite"


def command_line(command: str, argv: list[str] | None) -> str:
    """The shell command that ran this tool, for the metadata and model card it writes."""
    return shlex.join(["capvector", command, *(sys.argv[1:] if argv is None else argv)])


def parse_size(text: str) -> int:
    """``2GB`` (10^9 bytes, as in transformers), ``2GiB`` (2^30), ``500MB`` or a number of bytes."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(?:([KMGT])(i?)B)?\s*", text, re.IGNORECASE)
    if not match:
        raise argparse.ArgumentTypeError(f"not a size: {text!r} (try 2GB or 500MB)")
    number, unit, binary = match.groups()
    power = "KMGT".index(unit.upper()) + 1 if unit else 0
    return int(float(number) * (1024 if binary else 1000) ** power)


def _add_common(parser: argparse.ArgumentParser, dtype: bool = True, shards: bool = True) -> None:
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    if dtype:
        parser.add_argument(
            "--dtype",
            choices=("float32", "bfloat16", "float16"),
            help="storage dtype of the vector (default: the inputs')",
        )
    if shards:
        parser.add_argument(
            "--max-shard-size",
            type=parse_size,
            default=DEFAULT_MAX_SHARD_SIZE,
            help="bytes per safetensors shard, e.g. 2GB (default)",
        )


def extract_main(argv: list[str] | None = None) -> int:
    parser = ToolParser(
        prog="capvector extract",
        description="Capability vector c = θ_aux − θ_sft from two export folders or checkpoints.",
    )
    parser.add_argument(
        "--aux", required=True, help="θ_aux: export folder or .ckpt (SFT + auxiliary objectives)"
    )
    parser.add_argument("--sft", required=True, help="θ_sft: export folder or .ckpt (plain SFT)")
    parser.add_argument("--out", required=True, help=_OUT_HELP)
    parser.add_argument(
        "--base", help="θ_pre: also write the task vectors aux−base and sft−base into subfolders"
    )
    parser.add_argument(
        "--include",
        nargs="+",
        metavar="GLOB",
        help="parameters to cover (default: capability_parameters)",
    )
    parser.add_argument(
        "--exclude", nargs="+", metavar="GLOB", default=[], help="parameters to leave out"
    )
    lowrank = parser.add_mutually_exclusive_group()
    lowrank.add_argument("--rank", type=int, help="store 2-D weights as a rank-R PEFT LoRA adapter")
    lowrank.add_argument(
        "--energy", type=float, help="per-layer rank keeping this fraction of ‖c‖² (e.g. 0.9)"
    )
    parser.add_argument(
        "--full-rank",
        nargs="+",
        metavar="GLOB",
        default=[],
        help="2-D weights kept in full with --rank/--energy (e.g. embeddings, for PeftModel loading)",
    )
    parser.add_argument(
        "--objectives", nargs="+", help="names of the auxiliary objectives of θ_aux"
    )
    _add_common(parser)
    args = parser.parse_args(argv)

    from capvector.vectors.extract import TASK_VECTOR_AUX, TASK_VECTOR_SFT, extract

    meta = extract(
        args.aux,
        args.sft,
        args.out,
        base=args.base,
        include=args.include,
        exclude=args.exclude,
        rank=args.rank,
        energy=args.energy,
        objectives=args.objectives,
        full_rank=args.full_rank,
        dtype=args.dtype,
        max_shard_size=args.max_shard_size,
        overwrite=args.overwrite,
        progress=True,
        command=command_line("extract", argv),
    )
    tensors = meta["tensors"].values()
    lora = [t for t in tensors if t["storage"] == "lora"]
    print(
        f"wrote {args.out}: {meta['num_tensors']} tensors, {meta['num_parameters']:,} parameters, "
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
    if args.base:
        print(f"  task vectors: {args.out}/{TASK_VECTOR_AUX}, {args.out}/{TASK_VECTOR_SFT}")
    return 0


def _vector_arg(text: str) -> tuple[str, float]:
    """``DIR`` or ``DIR:λ``. A colon followed by something that is not a number is part of the
    path only when that path exists; otherwise it is a mistyped λ and says so."""
    path, sep, scale = text.rpartition(":")
    if not (sep and path):
        return text, 1.0
    try:
        return path, float(scale)
    except ValueError:
        if Path(text).exists():
            return text, 1.0
        raise argparse.ArgumentTypeError(
            f"{text!r}: λ after the colon must be a number (DIR:0.7), got {scale!r}"
        ) from None


def merge_main(argv: list[str] | None = None) -> int:
    parser = ToolParser(
        prog="capvector merge",
        description="θ_meta = θ_pre + Σ λ_i c_i, written as an export folder sharded like the base.",
    )
    parser.add_argument("--base", required=True, help="θ_pre: an export folder")
    parser.add_argument(
        "--vector",
        action="append",
        required=True,
        type=_vector_arg,
        metavar="DIR[:λ]",
        help="a vector folder (full, low-rank or PEFT LoRA) and its scale λ (default 1); repeatable",
    )
    parser.add_argument("--out", required=True, help=_OUT_HELP)
    parser.add_argument(
        "--allow-repeat",
        action="store_true",
        help="merge a vector the base already holds (its config.json records merged vectors)",
    )
    parser.add_argument(
        "--allow-large-scale",
        action="store_true",
        help="accept |λ| > 100 (refused by default: it is almost always a typo)",
    )
    parser.add_argument(
        "--dtype",
        choices=("float32", "bfloat16", "float16"),
        help="dtype of the merged weights (default: the base's); float32 keeps all of Σλc",
    )
    _add_common(parser, dtype=False, shards=False)
    args = parser.parse_args(argv)

    from capvector.vectors.merge import merge
    from capvector.vectors.precision import precision_warning

    record = merge(
        args.base,
        args.vector,
        args.out,
        overwrite=args.overwrite,
        progress=True,
        allow_repeat=args.allow_repeat,
        allow_large_scale=args.allow_large_scale,
        command=command_line("merge", argv),
        dtype=args.dtype,
    )
    terms = " + ".join(f"{s:g}·{p}" for p, s in args.vector)
    print(f"wrote {args.out} = {args.base} + {terms}")
    print("  non-weight files of the base copied")
    kept = record["precision"]
    print(f"  {kept['dtype']} output keeps Σλc up to a {kept['relative_error']:.2%} relative error")
    if warning := precision_warning(kept):
        print(f"capvector merge: warning: {warning}", file=sys.stderr)
    return 0


def compose_main(argv: list[str] | None = None) -> int:
    parser = ToolParser(
        prog="capvector compose", description="Combine vectors by a weighted sum or TIES-merging."
    )
    parser.add_argument("--vectors", nargs="+", required=True, metavar="DIR", help="vector folders")
    parser.add_argument("--method", choices=("sum", "ties"), default="sum")
    parser.add_argument(
        "--weights", nargs="+", type=float, help="one weight per vector (default 1)"
    )
    parser.add_argument(
        "--density", type=float, default=0.2, help="TIES: fraction of entries kept per vector (0.2)"
    )
    parser.add_argument(
        "--consensus", choices=("sum", "count"), default="sum", help="TIES sign election (sum)"
    )
    parser.add_argument("--out", required=True, help=_OUT_HELP)
    _add_common(parser)
    args = parser.parse_args(argv)

    from capvector.vectors.compose import compose

    meta = compose(
        args.vectors,
        args.out,
        args.method,
        weights=args.weights,
        density=args.density,
        consensus=args.consensus,
        dtype=args.dtype,
        max_shard_size=args.max_shard_size,
        overwrite=args.overwrite,
        progress=True,
        command=command_line("compose", argv),
    )
    how = (
        f"TIES (density {args.density}, {args.consensus} consensus)"
        if args.method == "ties"
        else "sum"
    )
    print(
        f"wrote {args.out}: {how} of {len(args.vectors)} vectors, {meta['num_tensors']} tensors, "
        f"‖c‖ = {meta['norm']:.4g}"
    )
    return 0


def inspect_main(argv: list[str] | None = None) -> int:
    parser = ToolParser(
        prog="capvector inspect",
        description="Per-layer norms of a vector, cosines against another.",
    )
    parser.add_argument("vector", metavar="DIR", help="a vector folder")
    parser.add_argument("--against", metavar="DIR2", help="a second vector to compare with")
    parser.add_argument(
        "--plot", metavar="PNG", help="write norms (and cosines) by layer to this PNG"
    )
    args = parser.parse_args(argv)

    from capvector.vectors.inspect import inspect_vector

    report = inspect_vector(args.vector, against=args.against, plot=args.plot, progress=True)
    print(report.table())
    print(
        f"\n{report.num_tensors} tensors ({report.lowrank_tensors} low-rank), ‖c‖ = {report.norm:.4g}"
    )
    if args.against:
        cosine = "undefined (a zero vector)" if report.cosine is None else f"{report.cosine:.4f}"
        print(
            f"cosine with {args.against}: {cosine} over {report.shared_tensors} shared "
            f"tensors ({len(report.only_here)} only here, {len(report.only_against)} only there)"
        )
    if args.plot:
        print(f"plot: {args.plot}")
    return 0
