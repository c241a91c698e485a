"""Composition of several vectors into one: a weighted sum, or TIES-merging.

TIES (Yadav et al., "TIES-Merging: Resolving Interference When Merging Models", NeurIPS 2023),
following mergekit's ``ties`` method (``merge_methods/generalized_task_arithmetic.py``,
``sparsify.magnitude``):

1. trim: keep the top ``density`` fraction of each vector's entries by magnitude, zero the rest;
2. elect: per entry, the sign of Σ_i w_i·c_i over the trimmed vectors (ties go to +);
3. disjoint mean: average w_i·c_i over the vectors whose entry is non-zero and has the elected sign,
   dividing by the sum of their weights.

The result is a vector; λ is applied at merge time as for any vector.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm.auto import tqdm

from capvector.io.outputs import atomic_directory, check_output
from capvector.io.weights import (
    DEFAULT_MAX_SHARD_SIZE,
    CapVectorError,
    StorageDtype,
    TensorInfo,
    dtype_summary,
    examples,
    parse_dtype,
    parse_size,
    row_chunks,
)
from capvector.vectors.vector import VectorFolder, VectorFolderWriter

METHODS = ("sum", "ties")
CONSENSUS = ("sum", "count")


def compose(
    vectors: Sequence[str | Path],
    out: str | Path,
    method: str = "sum",
    *,
    weights: Sequence[float] | None = None,
    density: float = 0.2,
    consensus: str = "sum",
    dtype: StorageDtype | None = None,
    max_shard_size: int | str = DEFAULT_MAX_SHARD_SIZE,
    overwrite: bool = False,
    progress: bool = False,
    command: str | None = None,
) -> dict[str, Any]:
    """Write the composition of ``vectors`` (full, low-rank or PEFT folders) as a full vector folder.

    Args:
        vectors: the vector folders.
        out: the vector folder to create (atomically; an existing one needs ``overwrite``).
        method: ``"sum"`` (Σ w_i c_i) or ``"ties"`` (see the module docstring).
        weights: one per vector (default 1.0 each).
        density: TIES trim, the fraction of entries kept per vector and tensor.
        consensus: TIES sign election, ``"sum"`` (the paper's, mass-weighted) or ``"count"``.
        dtype: storage dtype (default: the inputs' common dtype).
        max_shard_size: bytes per ``capability_vector`` shard, or a size such as ``2GB``.
        overwrite: replace an existing ``out``.

    Returns:
        The metadata written to ``capability_vector.json``.
    """
    max_shard_size = parse_size(max_shard_size)
    if method not in METHODS:
        raise CapVectorError(f"unknown --method {method!r}; choose from {', '.join(METHODS)}")
    if consensus not in CONSENSUS:
        raise CapVectorError(f"unknown consensus {consensus!r}; choose from {', '.join(CONSENSUS)}")
    if not vectors:
        raise CapVectorError("no vectors to compose")
    weights = [1.0] * len(vectors) if weights is None else [float(w) for w in weights]
    if len(weights) != len(vectors):
        raise CapVectorError(f"{len(weights)} weights for {len(vectors)} vectors")
    if method == "ties" and not 0.0 < density <= 1.0:
        raise CapVectorError(f"--density is a fraction in (0, 1], got {density}")
    check_output(out, overwrite, vectors, folder=True)
    out_dtype = parse_dtype(dtype) if isinstance(dtype, str) else dtype

    folders = [VectorFolder(v) for v in vectors]
    keys = folders[0].keys()
    for path, folder in zip(vectors[1:], folders[1:], strict=True):
        a, b = set(keys), set(folder.keys())
        if a != b:
            raise CapVectorError(
                f"{path} covers other tensors than {vectors[0]}: {len(a - b)} only in the first "
                f"({examples(sorted(a - b))}), {len(b - a)} only in this one "
                f"({examples(sorted(b - a))}); extract them with the same --include/--exclude"
            )
        shapes = [k for k in keys if folder.info(k).shape != folders[0].info(k).shape]
        if shapes:
            raise CapVectorError(
                f"{path} and {vectors[0]} differ in shape for {len(shapes)} tensor(s), e.g. "
                f"{examples(shapes)}; they belong to different architectures"
            )
    infos = {
        k: TensorInfo(
            out_dtype or _promote([f.info(k).dtype for f in folders]),
            folders[0].info(k).shape,
        )
        for k in keys
    }

    with atomic_directory(out, overwrite, vectors) as tmp:
        writer = VectorFolderWriter(tmp, list(infos.items()), max_shard_size)
        try:
            total = sum(i.nbytes for i in infos.values())
            with tqdm(
                total=total, unit="B", unit_scale=True, desc=method, disable=not progress
            ) as bar:
                for key, info in infos.items():
                    if method == "sum":
                        for rows in row_chunks(info):
                            acc = torch.zeros((), dtype=torch.float32)
                            for folder, w in zip(folders, weights, strict=True):
                                acc = acc + w * folder.read(key, rows).float()
                            writer.write(key, acc.to(info.dtype))
                    else:
                        stacked = torch.stack([f.read(key).float() for f in folders])
                        writer.write(key, ties(stacked, weights, density, consensus).to(info.dtype))
                    bar.update(info.nbytes)
            meta = writer.finish(
                {
                    "kind": "composition",
                    "definition": "sum of w_i * c_i" if method == "sum" else "TIES merge of c_i",
                    "method": method,
                    "weights": weights,
                    "density": density if method == "ties" else None,
                    "consensus": consensus if method == "ties" else None,
                    "dtype": dtype_summary(i.dtype for i in infos.values()),
                    "sources": {"vectors": [f.describe() for f in folders]},
                    "command": command,
                }
            )
        except BaseException:
            writer.abort()
            raise
    return meta


def trim(delta: Tensor, density: float) -> Tensor:
    """Keep the ``density`` fraction of entries with the largest magnitude (at least one)."""
    if density >= 1.0:
        return delta
    k = max(1, int(density * delta.numel()))
    flat = delta.reshape(-1)
    keep = torch.topk(flat.abs(), k, sorted=False).indices
    out = torch.zeros_like(flat)
    out[keep] = flat[keep]
    return out.view_as(delta)


def ties(
    deltas: Tensor, weights: Sequence[float], density: float, consensus: str = "sum"
) -> Tensor:
    """TIES-merge ``deltas`` (n, ...) with per-vector ``weights``: trim, elect sign, disjoint mean."""
    trimmed = torch.stack([trim(d, density) for d in deltas])
    w = torch.tensor(weights, dtype=trimmed.dtype).view(-1, *([1] * (trimmed.dim() - 1)))
    weighted = trimmed * w
    signs = weighted.sign()
    votes = weighted.sum(0) if consensus == "sum" else signs.sum(0)
    elected = torch.where(votes >= 0, 1.0, -1.0).to(trimmed.dtype)
    mask = (signs == elected).to(trimmed.dtype)
    divisor = (w * mask).sum(0)
    divisor[divisor == 0] = 1.0
    return (weighted * mask).sum(0) / divisor


def _promote(dtypes: Sequence[torch.dtype]) -> torch.dtype:
    out = dtypes[0]
    for d in dtypes[1:]:
        out = torch.promote_types(out, d)
    return out
