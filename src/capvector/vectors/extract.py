"""``extract``: the capability vector c = θ_aux − θ_sft (and, with a base, the two task vectors).

Streams tensor by tensor and row-chunk by row-chunk (``io.row_chunks``): peak memory is a few
chunks, not the model. Low-rank storage needs each 2-D delta whole for its SVD, so there the peak is
a few times the largest 2-D tensor.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

import torch
from torch import Tensor
from tqdm.auto import tqdm

from capvector.io.outputs import atomic_directory, check_output
from capvector.io.weights import (
    DEFAULT_MAX_SHARD_SIZE,
    CapVectorError,
    Scratch,
    StorageDtype,
    TensorInfo,
    WeightSource,
    compute_dtype,
    dtype_name,
    dtype_summary,
    examples,
    open_weights,
    parse_dtype,
    parse_size,
    row_chunks,
    select_keys,
)
from capvector.vectors.lora_form import LoraFormExport, delta_difference, lora_form_views
from capvector.vectors.lowrank import SvdMethod, lowrank_candidate, svd_factors
from capvector.vectors.vector import VectorFolderWriter

TASK_VECTOR_AUX = "task_vector_aux"
TASK_VECTOR_SFT = "task_vector_sft"


@dataclass
class _Output:
    """One vector folder to write: ``minuend − subtrahend`` into ``subdir`` of the output."""

    subdir: str
    minuend: str
    subtrahend: str
    kind: str


def extract(
    aux: str | Path,
    sft: str | Path,
    out: str | Path,
    base: str | Path | None = None,
    include: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
    rank: int | None = None,
    energy: float | None = None,
    objectives: Sequence[str] | None = None,
    *,
    full_rank: Sequence[str] = (),
    svd: SvdMethod = "exact",
    dtype: StorageDtype | None = None,
    max_shard_size: int | str = DEFAULT_MAX_SHARD_SIZE,
    overwrite: bool = False,
    progress: bool = False,
    command: str | None = None,
) -> dict[str, Any]:
    """Write the capability vector c = θ_aux − θ_sft to the vector folder ``out``.

    Args:
        aux, sft: export folders or Lightning checkpoints of the two fine-tunes.
        out: the vector folder to create (atomically; an existing one needs ``overwrite``).
        base: θ_pre; when given, also write θ_aux − θ_pre and θ_sft − θ_pre into
            ``out/task_vector_aux`` and ``out/task_vector_sft``.
        include, exclude: fnmatch globs over parameter names. ``include`` defaults to the inputs'
            ``capability_parameters`` (an error when aux and sft disagree).
        rank, energy: store each 2-D ``*.weight`` delta as a truncated SVD (a PEFT LoRA adapter)
            of this rank, or of the smallest rank keeping this fraction of its squared norm.
        objectives: names of the auxiliary objectives behind θ_aux (default: what aux records).
        full_rank: globs of 2-D weights kept in full even in low-rank mode (e.g. embeddings).
        svd: ``exact`` (mergekit's full SVD) or ``randomized`` (with ``rank`` only: the top
            singular vectors by a seeded range finder, seconds instead of hours for a 7 B model's
            language model; ``lowrank.svd_factors``).
        dtype: storage dtype (default: the inputs'). Differences are computed in float32.
        max_shard_size: bytes per ``capability_vector`` shard, or a size such as ``2GB``.
        overwrite: replace an existing ``out``.
        progress: show a tqdm bar.
        command: the command line that asked for it, recorded in the metadata and model card.

    Returns:
        The metadata written to ``capability_vector.json``.

    Raises:
        CapVectorError: for bad input, including aux and sft being the same folder (before any
            work) or holding identical values (after streaming them; nothing is written).
    """
    max_shard_size = parse_size(max_shard_size)
    if rank is not None and energy is not None:
        raise CapVectorError("pass either --rank or --energy, not both")
    if rank is not None and rank < 1:
        raise CapVectorError(f"--rank must be ≥ 1, got {rank}")
    if energy is not None and not 0.0 < energy <= 1.0:
        raise CapVectorError(f"--energy is a fraction in (0, 1], got {energy}")
    if svd not in get_args(SvdMethod):
        raise CapVectorError(f"--svd is one of {list(get_args(SvdMethod))}, got {svd!r}")
    if svd == "randomized" and rank is None:
        raise CapVectorError("--svd randomized finds a fixed --rank; use --svd exact for --energy")
    out_dtype = parse_dtype(dtype) if isinstance(dtype, str) else dtype
    inputs = [aux, sft, base]
    check_output(out, overwrite, inputs, folder=True)
    if Path(aux).resolve() == Path(sft).resolve():
        raise CapVectorError(
            f"--aux and --sft are the same ({aux}): c = θ_aux − θ_sft would be all zeros; give "
            "the fine-tune with auxiliary objectives and the plain SFT one"
        )

    sources: dict[str, WeightSource] = {"aux": open_weights(aux), "sft": open_weights(sft)}
    if base is not None:
        sources["base"] = open_weights(base)
    # Exports of a packaged-base preset (the mini): base deltas, exactly low-rank (lora_form).
    sources = lora_form_views(sources)
    lora_form = isinstance(sources["aux"], LoraFormExport)
    include, include_origin = _default_include(include, sources["aux"], sources["sft"])
    keys, skipped = _select(sources, include, exclude)

    infos = {}
    for key in keys:
        stored = [sources[name].info(key).dtype for name in ("aux", "sft")]
        infos[key] = TensorInfo(
            out_dtype or torch.promote_types(*stored), sources["aux"].info(key).shape
        )
    lowrank = (rank is not None or energy is not None) and bool(keys)
    lowrank_keys = {
        k
        for k in keys
        if lowrank
        and lowrank_candidate(k, len(infos[k].shape))
        and not select_keys([k], list(full_rank), None)
    }
    exact = {k for k in keys if lora_form and sources["aux"].is_delta(k)}  # type: ignore[attr-defined]
    lowrank_keys |= exact
    full = [(k, infos[k]) for k in keys if k not in lowrank_keys]

    outputs = [_Output("", "aux", "sft", "capability_vector")]
    if base is not None:
        outputs += [
            _Output(TASK_VECTOR_AUX, "aux", "base", "task_vector"),
            _Output(TASK_VECTOR_SFT, "sft", "base", "task_vector"),
        ]
    common = {
        "include": list(include),
        "include_origin": include_origin,
        "exclude": list(exclude or []),
        "objectives": list(objectives) if objectives is not None else sources["aux"].objectives,
        "dtype": dtype_summary(i.dtype for i in infos.values()),
        "lowrank": (
            {"rank": rank, "energy": energy, "full_rank": list(full_rank), "svd": svd}
            if lowrank
            else None
        ),
        # The inputs' base deltas over the weight packages, differenced exactly (no SVD of them).
        "exact_lowrank": sorted(exact) if exact else None,
        "skipped": skipped,
        "command": command,
    }
    described = {name: src.describe() for name, src in sources.items()}

    with atomic_directory(out, overwrite, inputs) as tmp:
        embeddings = sources["aux"].embedding_parameters & lowrank_keys
        writers = [
            VectorFolderWriter(tmp / o.subdir, full, max_shard_size, embeddings) for o in outputs
        ]
        try:
            bar = tqdm(
                total=sum(i.nbytes for i in infos.values()),
                unit="B",
                unit_scale=True,
                desc="extract",
                disable=not progress,
            )
            scratch = Scratch()
            with bar:
                for key in keys:
                    if key not in lowrank_keys:
                        _stream_full(
                            sources, outputs, writers, key, infos[key], bar.update, scratch
                        )
                        continue
                    for o, w in zip(outputs, writers, strict=True):
                        if key in exact:
                            minuend, subtrahend = sources[o.minuend], sources[o.subtrahend]
                            factors = delta_difference(minuend, subtrahend, key)  # type: ignore[arg-type]
                            norm = math.sqrt(max(factors.norm_sq(), 0.0))
                            w.add_lowrank(key, factors, norm, 1.0, infos[key].dtype)
                            continue
                        delta = _whole_delta(sources, o, key, infos[key])
                        norm = float(torch.linalg.vector_norm(delta))
                        factors, retained = svd_factors(delta, rank, energy, svd)
                        del delta  # before the next output's delta: one whole tensor at a time
                        w.add_lowrank(key, factors, norm, retained, infos[key].dtype)
                    bar.update(infos[key].nbytes)
            metas = []
            for o, w in zip(outputs, writers, strict=True):
                meta = {
                    "kind": o.kind,
                    "definition": f"{o.minuend} - {o.subtrahend}",
                    "sources": {
                        o.minuend: described[o.minuend],
                        o.subtrahend: described[o.subtrahend],
                    },
                    **common,
                }
                if o.kind == "capability_vector":
                    meta["sources"] = described
                    if base is not None:
                        meta["task_vectors"] = [TASK_VECTOR_AUX, TASK_VECTOR_SFT]
                metas.append(w.finish(meta))
            if metas[0]["norm"] == 0.0:  # raised inside the output block: nothing is left
                raise CapVectorError(
                    f"aux {aux} and sft {sft} are identical in all {len(keys)} extracted tensors: "
                    "c would be all zeros. Were they the same export? Nothing was written"
                )
        except BaseException:
            for w in writers:
                w.abort()
            raise
    return metas[0]


def _default_include(
    include: Sequence[str] | None, aux: WeightSource, sft: WeightSource
) -> tuple[list[str], str]:
    if include:
        return list(include), "explicit"
    a, s = aux.capability_parameters, sft.capability_parameters
    if a is not None and s is not None and sorted(a) != sorted(s):
        raise CapVectorError(
            f"aux and sft disagree on capability_parameters ({a} vs {s}); are they fine-tunes of "
            "the same backbone? Pass --include explicitly to choose"
        )
    globs = a if a is not None else s
    if globs is None:
        return ["*"], "all (the inputs record no capability_parameters)"
    return list(globs), "capability_parameters of the inputs"


def _select(
    sources: dict[str, WeightSource], include: Sequence[str], exclude: Sequence[str] | None
) -> tuple[list[str], dict[str, list[str]]]:
    aux, sft, base = sources["aux"], sources["sft"], sources.get("base")
    aux_keys, sft_keys = aux.keys(), sft.keys()
    aux_set, sft_set = set(aux_keys), set(sft_keys)
    shared = select_keys([k for k in aux_keys if k in sft_set], include, exclude)
    skipped = {
        "only_in_aux": select_keys([k for k in aux_keys if k not in sft_set], include, exclude),
        "only_in_sft": select_keys([k for k in sft_keys if k not in aux_set], include, exclude),
        # Integer/bool buffers (step counters, masks) are not weights; task_vectors skips them too.
        "not_floating": [
            k
            for k in shared
            if not (aux.info(k).dtype.is_floating_point and sft.info(k).dtype.is_floating_point)
        ],
    }
    keys = [k for k in shared if k not in skipped["not_floating"]]
    if not keys:
        raise CapVectorError(
            f"no tensors to extract: --include {list(include)} --exclude {list(exclude or [])} "
            f"match none of the floating tensors aux and sft share (e.g. "
            f"{examples(sorted(aux_set & sft_set))})"
        )
    mismatched = [
        f"{k}: aux {aux.info(k).shape} vs sft {sft.info(k).shape}"
        for k in keys
        if aux.info(k).shape != sft.info(k).shape
    ]
    if mismatched:
        raise CapVectorError(
            f"aux and sft differ in shape for {len(mismatched)} tensor(s), e.g. "
            f"{examples(mismatched)}; they are not fine-tunes of the same model"
        )
    if base is not None:
        _check_base(base, aux, keys)
    return keys, skipped


def _check_base(base: WeightSource, aux: WeightSource, keys: Sequence[str]) -> None:
    """The base must hold every extracted tensor, floating and of aux's shape (the same check as a
    merge of the task vectors into it)."""
    from capvector.vectors.merge import check_compatible

    names = base.keys()
    targets = {k: base.info(k) for k in names}
    check_compatible(targets, {k: aux.info(k) for k in keys}, "the base", "θ_aux")


def _stream_full(
    sources: dict[str, WeightSource],
    outputs: Sequence[_Output],
    writers: Sequence[VectorFolderWriter],
    key: str,
    info: TensorInfo,
    advance: Callable[[int], Any],
    scratch: Scratch,
) -> None:
    for rows in row_chunks(info):
        chunks = {name: src.read(key, rows) for name, src in sources.items()}
        work = compute_dtype(*(c.dtype for c in chunks.values()))
        shape = chunks["aux"].shape
        for o, w in zip(outputs, writers, strict=True):
            a, b = chunks[o.minuend], chunks[o.subtrahend]
            if a.dtype == b.dtype == info.dtype:
                # torch's reduced-precision kernels subtract in float32 and round once: the same
                # result as the general path below, without its casts.
                stored = torch.sub(a, b, out=scratch.get("stored", shape, info.dtype))
            else:
                a, b = scratch.cast("a", a, work), scratch.cast("b", b, work)
                diff = torch.sub(a, b, out=scratch.get("diff", shape, work))
                stored = scratch.cast("stored", diff, info.dtype)
            # The recorded norm is the stored (rounded) tensor's, accumulated in float32.
            norm = torch.linalg.vector_norm(scratch.cast("norm", stored, work))
            if not torch.isfinite(norm):
                raise _not_finite(sources, chunks, key, o, info)
            w.write(key, stored, norm)
        advance(chunks["aux"].numel() * info.dtype.itemsize)


def _whole_delta(
    sources: dict[str, WeightSource], o: _Output, key: str, info: TensorInfo
) -> Tensor:
    """The full delta in float32, assembled chunk by chunk (no whole copies of the inputs)."""
    delta = torch.empty(info.shape, dtype=torch.float32)
    for rows in row_chunks(info):
        a = sources[o.minuend].read(key, rows).float()
        b = sources[o.subtrahend].read(key, rows).float()
        delta[rows] = a - b
    if not torch.isfinite(delta).all():
        chunks = {
            o.minuend: sources[o.minuend].read(key),
            o.subtrahend: sources[o.subtrahend].read(key),
        }
        raise _not_finite(sources, chunks, key, o, info)
    return delta


def _not_finite(
    sources: dict[str, WeightSource],
    chunks: dict[str, Tensor],
    key: str,
    o: _Output,
    info: TensorInfo,
) -> CapVectorError:
    for name in (o.minuend, o.subtrahend):
        if not torch.isfinite(chunks[name]).all():
            return CapVectorError(
                f"`{key}` in {name} ({sources[name].path}) has NaN/Inf values; that checkpoint is "
                "corrupted or diverged. Nothing was written"
            )
    return CapVectorError(
        f"`{key}`: {o.minuend} − {o.subtrahend} overflows {dtype_name(info.dtype)}; pass "
        "--dtype float32. Nothing was written"
    )
