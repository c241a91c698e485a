"""θ_meta = θ_pre + Σ λ_i c_i: streamed into an export folder (``merge``) or applied in memory
(``apply_vector_``, what the ``MergeCapabilityVector`` callback calls). Both use ``add_scaled``,
so the CLI and the callback produce the same weights.
"""

from __future__ import annotations

import datetime
import math
import shutil
from collections.abc import Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from capvector.io.modelcard import render_model_card, write_model_card
from capvector.io.names import MODEL_CARD
from capvector.io.outputs import atomic_directory, check_output
from capvector.io.weights import (
    EXPORT_CONFIG,
    EXPORT_WEIGHTS,
    CapVectorError,
    SafetensorsFolder,
    SafetensorsWriter,
    Scratch,
    ShardLayout,
    TensorInfo,
    all_finite,
    capvector_version,
    compute_dtype,
    dtype_name,
    examples,
    open_weights,
    parse_dtype,
    read_json,
    row_chunks,
    short_fingerprint,
    write_json,
)
from capvector.vectors.lora_form import (
    LoraFormExport,
    delta_config,
    delta_infos,
    is_lora_form,
    merged_tensors,
)
from capvector.vectors.precision import MergePrecision
from capvector.vectors.record import (
    BY_MERGE,
    MERGED_VECTORS,
    MergedVector,
    check_not_merged,
    read_record,
    record_dicts,
)
from capvector.vectors.vector import CapabilityVector, VectorFolder, load_vector

MERGE_RECORD = "capvector_merge.json"
MAX_SCALE = 100.0
"""|λ| above this is refused unless allowed: θ + λ·c would be mostly c (λ ≈ 1 in the paper)."""

# Module names that wrappers insert between a model's own names: peft's LoRA layers
# (`X.base_layer.weight`), torch.compile, activation checkpointing and FSDP1.
_WRAPPER_NAMES = frozenset(
    {"base_layer", "_orig_mod", "_checkpoint_wrapped_module", "_fsdp_wrapped_module"}
)


def add_scaled(
    base: Tensor, deltas: Sequence[tuple[Tensor, float]], scratch: Scratch | None = None
) -> Tensor:
    """``base + Σ λ·delta`` computed in float32 (float64 for float64 inputs), cast to base's dtype.

    With ``scratch`` the casts and the sum go to reused buffers (the result too: it is valid until
    the next call); without, the result is a new tensor.
    """
    if not deltas:
        return base.clone()
    if len(deltas) == 1 and deltas[0][0].dtype == base.dtype and deltas[0][1] == 1.0:
        # torch's reduced-precision kernels add in float32 and round once, like the general path,
        # at a quarter of its memory traffic. Not for λ ≠ 1: alpha is rounded to base's dtype.
        out = scratch.get("result", base.shape, base.dtype) if scratch is not None else None
        return torch.add(base, deltas[0][0].to(base.device), out=out)
    work = compute_dtype(base.dtype, *(d.dtype for d, _ in deltas))

    def cast(name: str, t: Tensor, dtype: torch.dtype) -> Tensor:
        return scratch.cast(name, t, dtype) if scratch is not None else t.to(dtype)

    acc: Tensor | None = None
    for delta, scale in deltas:
        d = cast("delta", delta.to(base.device), work)
        if acc is None:
            out = scratch.get("sum", base.shape, work) if scratch is not None else None
            acc = torch.add(cast("base", base, work), d, alpha=scale, out=out)
        else:
            acc.add_(d, alpha=scale)
    assert acc is not None
    return cast("result", acc, base.dtype)


def check_compatible(
    target: Mapping[str, TensorInfo],
    vector: Mapping[str, TensorInfo],
    target_name: str,
    vector_name: str,
) -> None:
    """Raise ``CapVectorError`` unless every vector tensor has a floating target of the same shape."""
    missing = [k for k in vector if k not in target]
    if missing:
        raise CapVectorError(
            f"{vector_name} has {len(missing)} tensor(s) {target_name} lacks, e.g. "
            f"{examples(missing)}; pass --exclude '{missing[0].split('.')[0]}.*' when extracting "
            "or use the matching base"
        )
    shapes = [
        f"{k}: vector {tuple(v.shape)} vs {tuple(target[k].shape)}"
        for k, v in vector.items()
        if tuple(v.shape) != tuple(target[k].shape)
    ]
    if shapes:
        raise CapVectorError(
            f"{vector_name} does not fit {target_name}: {len(shapes)} shape mismatch(es), e.g. "
            f"{examples(shapes)}; it was extracted from another architecture or preset"
        )
    dtypes = [
        f"{k}: vector {dtype_name(v.dtype)}, target {dtype_name(target[k].dtype)}"
        for k, v in vector.items()
        if not (v.dtype.is_floating_point and target[k].dtype.is_floating_point)
    ]
    if dtypes:
        raise CapVectorError(
            f"{vector_name} and {target_name} disagree on dtype for {len(dtypes)} tensor(s), e.g. "
            f"{examples(dtypes)}; only floating tensors can be merged"
        )


def check_scale(scale: float, vector: str = "the vector", allow_large_scale: bool = False) -> None:
    """λ must be finite, fit float32 (the merge adds in float32) and, unless allowed, |λ| ≤ 100."""
    if not math.isfinite(scale):
        raise CapVectorError(f"λ for {vector} is {scale}; it must be a finite number")
    if abs(scale) > torch.finfo(torch.float32).max:
        raise CapVectorError(f"λ = {scale:g} for {vector} overflows float32, in which it is added")
    if abs(scale) > MAX_SCALE and not allow_large_scale:
        raise CapVectorError(
            f"λ = {scale:g} for {vector} is outside [-{MAX_SCALE:g}, {MAX_SCALE:g}]: the result "
            "would be mostly the vector (λ ≈ 1 is usual); pass --allow-large-scale "
            "(allow_large_scale: true) if you mean it"
        )


def check_scale_not_zero(scale: float, vector: str, what_to_do: str) -> None:
    """A merge that is recorded (``merge``, the fit-start callback) refuses a λ that is zero in
    float32, as it refuses a zero vector: it would change nothing, yet record the vector as
    merged, and a later real merge of it would be refused as already held. (An in-memory λ = 0,
    ``sweep-scale``'s baseline, records nothing and stays allowed.)"""
    if abs(scale) < torch.finfo(torch.float32).tiny:  # 0, -0, and what float32 cannot hold
        raise CapVectorError(
            f"λ = {scale:g} for {vector} is zero (in float32, in which it is added): the merge "
            "would change nothing yet record the vector as merged; "
            + what_to_do.format(path=vector)
        )


# -- streaming merge into an export folder ---------------------------------------------------


def merge(
    base: str | Path,
    vectors: Sequence[tuple[str | Path, float]],
    out: str | Path,
    *,
    overwrite: bool = False,
    progress: bool = False,
    allow_repeat: bool = False,
    allow_large_scale: bool = False,
    command: str | None = None,
    dtype: torch.dtype | str | None = None,
) -> dict[str, Any]:
    """Write the export folder ``out`` = base + Σ λ_i·vector_i, sharded like the base.

    Vectors may be full, low-rank or plain PEFT LoRA folders. Every non-weight file of the base
    (tokenizer, dataset statistics) is copied unchanged; ``config.json`` gains the merged vectors
    (``merged_vectors``: fingerprint and λ) and ``capvector_merge.json`` records what was merged.
    A vector the base already holds is refused unless ``allow_repeat``, as are a vector whose
    tensors no longer match its recorded fingerprint, a zero vector, and |λ| > 100 unless
    ``allow_large_scale``. All vectors are checked against the base before anything is written,
    and a NaN/Inf found while streaming leaves no output. The sum is computed in float32 and
    written in ``dtype`` (default: the base's); how much of Σλc that dtype kept is measured
    (``capvector.vectors.precision``) and recorded under ``precision``.

    Returns:
        The record written to ``capvector_merge.json``.
    """
    if not vectors:
        raise CapVectorError("no vectors to merge: pass --vector DIR[:λ] at least once")
    inputs = [base, *(v for v, _ in vectors)]
    check_output(out, overwrite, inputs, folder=True)
    source = open_weights(base)
    if not isinstance(source, SafetensorsFolder) or source.kind != "export":
        raise CapVectorError(
            f"merge writes an export folder and needs one as --base; {base} is a "
            f"{source.kind}: export it first"
        )
    folders = []
    for path, scale in vectors:
        check_scale(scale, str(path), allow_large_scale)
        check_scale_not_zero(scale, str(path), "drop --vector {path} or give a non-zero λ")
        folders.append((VectorFolder(path), float(scale)))
    # A base rebuilt from weight packages (the mini): its deltas and the vector's stay low-rank.
    view = (
        LoraFormExport(source, delta_infos(f for f, _ in folders)) if is_lora_form(source) else None
    )
    target = view or source
    for folder, _ in folders:
        path = folder.path
        folder.check_family(source.config.get("family"), f"the base {base}")
        infos = {k: folder.info(k) for k in folder}
        check_compatible(
            {k: target.info(k) for k in target}, infos, f"the base {base}", f"vector {path}"
        )
        folder.check_not_zero()
    record = read_record(source.config.get(MERGED_VECTORS))
    for folder, scale in folders:
        entry = MergedVector.of(folder, scale, BY_MERGE)
        check_not_merged(record, entry, f"the base {base}", allow_repeat)
        record.append(entry)

    out_dtype = parse_dtype(dtype) if isinstance(dtype, str) else dtype

    def out_info(key: str) -> TensorInfo:
        info = source.info(key)
        keep = out_dtype is None or not info.dtype.is_floating_point
        return info if keep else TensorInfo(out_dtype, info.shape)

    layout = ShardLayout(
        [(name, [(k, out_info(k)) for k in keys]) for name, keys in source.files.items()],
        source.index_path.name if source.index_path else None,
    )
    precision = MergePrecision()
    first_meta = next(iter(source.file_metadata.values()), {})
    provenance: dict[str, Any] = {
        "base": source.describe(),
        "vectors": [{**f.describe(), "scale": s} for f, s in folders],
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "capvector_version": capvector_version(),
        "command": command,
    }
    if (source.path / MERGE_RECORD).is_file():
        provenance["previous"] = read_json(source.path / MERGE_RECORD)

    with atomic_directory(out, overwrite, inputs) as tmp:
        skip = set(source.weight_files()) | {MERGE_RECORD, EXPORT_CONFIG, MODEL_CARD}
        config = {**source.config, MERGED_VECTORS: record_dicts(record)}
        write_json(tmp / EXPORT_CONFIG, delta_config(config) if view else config)
        write_model_card(tmp, _merged_card(source, provenance))
        for item in source.path.iterdir():
            if item.name in skip:
                continue
            if item.is_dir():
                shutil.copytree(item, tmp / item.name)
            else:
                shutil.copy2(item, tmp / item.name)
        if view is not None:  # small: the trained tensors and the deltas' factors, in memory
            from safetensors.torch import save_file

            tensors, summed = merged_tensors(view, folders)
            for key, before, after, change in summed:
                precision.add(key, before, after, change)
            bad = [k for k, t in tensors.items() if not all_finite(t)]
            if bad:
                raise CapVectorError(f"merging gives NaN/Inf in `{bad[0]}`. Nothing was written")
            save_file(tensors, str(tmp / EXPORT_WEIGHTS), metadata=first_meta or None)
            provenance["precision"] = precision.summary()
            write_json(tmp / MERGE_RECORD, provenance)
            return provenance
        writer = SafetensorsWriter(tmp, layout, metadata=first_meta)
        total = sum(info.nbytes for _, items in layout.files for _, info in items)
        try:
            with tqdm(
                total=total, unit="B", unit_scale=True, desc="merge", disable=not progress
            ) as bar:
                scratch = Scratch()
                for _, items in layout.files:
                    for key, info in items:
                        _merge_tensor(source, folders, writer, key, info, scratch, precision)
                        bar.update(info.nbytes)
            writer.finish()
        except BaseException:
            writer.abort()
            raise
        provenance["precision"] = precision.summary()
        write_json(tmp / MERGE_RECORD, provenance)
    return provenance


def _merged_card(source: SafetensorsFolder, provenance: Mapping[str, Any]) -> str:
    # A vector read by hub id is named by that id, not by its snapshot folder in the hub cache.
    terms = " + ".join(
        f"{v['scale']:g}·c({v.get('hub_id') or Path(v['path']).name})"
        for v in provenance["vectors"]
    )
    facts: dict[str, Any] = {
        "family": source.config.get("family"),
        "preset": (source.config.get("backbone_config") or {}).get("preset"),
    }
    for i, v in enumerate(provenance["vectors"], 1):
        facts[f"vector {i}"] = (
            f"{v.get('hub_id') or v['path']} x {v['scale']:g} "
            f"({short_fingerprint(v['fingerprint'])})"
        )
    return render_model_card(
        "θ_meta: pretrained weights with capability vectors merged",
        f"θ_meta = θ_pre + {terms}, written by `capvector merge` in capvector's export layout; "
        "use it as `--model.pretrained` for downstream fine-tuning.",
        facts,
        base_model=source.hub_id or str(source.path.resolve()),
        tags=["capability-vector", "merge", *[t for t in [source.config.get("family")] if t]],
        command=provenance.get("command"),
    )


def _merge_tensor(
    source: SafetensorsFolder,
    folders: Sequence[tuple[VectorFolder, float]],
    writer: SafetensorsWriter,
    key: str,
    info: TensorInfo,
    scratch: Scratch,
    precision: MergePrecision,
) -> None:
    touching = [(f, s) for f, s in folders if key in f]
    for rows in row_chunks(info):
        chunk = source.read(key, rows).to(info.dtype)
        if touching:
            deltas = [(f.read(key, rows), s) for f, s in touching]
            merged = add_scaled(chunk, deltas, scratch)
            precision.add(key, chunk, merged, sum(s * d.float() for d, s in deltas))
            if not all_finite(merged):  # after the cast back, which may overflow float16
                culprits = [
                    str(f.path)
                    for (f, _), (d, _) in zip(touching, deltas, strict=True)
                    if not torch.isfinite(d).all()
                ]
                where = (
                    f"vector {culprits[0]} has NaN/Inf there"
                    if culprits
                    else (
                        "the base has NaN/Inf there"
                        if not torch.isfinite(chunk).all()
                        else f"the sum overflows {dtype_name(info.dtype)}"
                    )
                )
                raise CapVectorError(f"merging `{key}` gives NaN/Inf: {where}. Nothing was written")
            chunk = merged
        writer.write(key, chunk)


# -- in memory -------------------------------------------------------------------------------


def canonical_name(name: str) -> str:
    """A parameter name without wrapper modules: ``X.base_layer.weight`` -> ``X.weight``."""
    return ".".join(part for part in name.split(".") if part not in _WRAPPER_NAMES)


def match_tensors(
    target: nn.Module | Mapping[str, Tensor], keys: Sequence[str]
) -> dict[str, tuple[str, Tensor]]:
    """Vector key -> (target name, tensor) for a module's parameters and buffers or a state dict.

    Names are compared without wrapper modules, so ``X.weight`` finds peft's ``X.base_layer.weight``.
    Raises ``CapVectorError`` naming keys with no match, several matches, or a shared (tied) match.
    """
    if isinstance(target, nn.Module):
        items = [
            *target.named_parameters(remove_duplicate=False),
            *target.named_buffers(remove_duplicate=False),
        ]
    else:
        items = list(target.items())
    by_name: dict[str, list[tuple[str, Tensor]]] = {}
    for name, tensor in items:
        entries = by_name.setdefault(canonical_name(name), [])
        if all(t is not tensor for _, t in entries):
            entries.append((name, tensor))
    missing = [k for k in keys if k not in by_name]
    if missing:
        raise CapVectorError(
            f"vector has {len(missing)} tensor(s) the model lacks, e.g. {examples(missing)}; "
            f"pass --exclude '{missing[0].split('.')[0]}.*' when extracting or use the matching base"
        )
    ambiguous = [
        f"{k} ({', '.join(n for n, _ in by_name[k])})" for k in keys if len(by_name[k]) > 1
    ]
    if ambiguous:
        raise CapVectorError(
            f"vector keys match several tensors of the model, e.g. {examples(ambiguous)}"
        )
    resolved = {k: by_name[k][0] for k in keys}
    owner: dict[int, str] = {}
    for key, (_, tensor) in resolved.items():
        other = owner.setdefault(id(tensor), key)
        if other != key:
            raise CapVectorError(
                f"vector keys `{other}` and `{key}` are the same (tied) tensor of the model; "
                "exclude one of them"
            )
    return resolved


def _resolve(
    target: nn.Module | MutableMapping[str, Tensor], vec: CapabilityVector
) -> dict[str, tuple[str, Tensor]]:
    """``match_tensors`` plus shape/dtype checks and finite vector values."""
    resolved = match_tensors(target, vec.keys())
    target_infos = {k: _info(t) for k, (_, t) in resolved.items()}
    vector_infos = {k: TensorInfo(_vector_dtype(vec, k), vec.shape(k)) for k in vec}
    check_compatible(target_infos, vector_infos, "the model", "the vector")
    vec.check()
    return resolved


def _info(t: Tensor) -> TensorInfo:
    return TensorInfo(t.dtype, tuple(t.shape))


def _vector_dtype(vec: CapabilityVector, key: str) -> torch.dtype:
    return vec.lowrank[key].dtype if key in vec.lowrank else vec.dense[key].dtype


def validate_vector(
    target: nn.Module | MutableMapping[str, Tensor],
    vector: str | Path | Mapping[str, Tensor] | CapabilityVector,
    scale: float = 1.0,
    allow_large_scale: bool = False,
) -> None:
    """Raise ``CapVectorError`` unless ``apply_vector_(target, vector, scale)`` would succeed.

    Checks that every vector tensor has a matching target tensor (``X.weight`` also matches peft's
    ``X.base_layer.weight``), with the same shape, both floating, that the vector is finite and
    ``scale`` passes ``check_scale``.
    """
    check_scale(scale, allow_large_scale=allow_large_scale)
    _resolve(target, load_vector(vector))


def apply_vector_(
    target: nn.Module | MutableMapping[str, Tensor],
    vector: str | Path | Mapping[str, Tensor] | CapabilityVector,
    scale: float = 1.0,
    precision: MergePrecision | None = None,
    allow_large_scale: bool = False,
) -> list[str]:
    """In place: θ ← θ + scale·c for every tensor of the vector; validates everything first.

    With ``precision``, how much of scale·c each tensor's dtype kept is measured into it.

    ``target`` is a module (parameters and buffers) or a state dict whose tensors are updated in
    place. Nothing changes when validation fails. DTensor parameters (FSDP2) are updated shard by
    shard with no communication: every rank reads the same vector and keeps its own slice.

    Returns:
        The target names that were changed.
    """
    check_scale(scale, allow_large_scale=allow_large_scale)
    vec = load_vector(vector)
    resolved = _resolve(target, vec)
    # θ + 0 is θ bit for bit: a vector between two LoRA fits names every tensor, and its zeros
    # (Pi0.5's 257 k-token embedding among them) would cost whole float32 copies for nothing.
    nonzero = set(vec.changed_keys())
    changed = []
    with torch.no_grad():
        for key, (name, tensor) in resolved.items():
            if key not in nonzero:
                continue
            _add_in_place(tensor, vec, key, scale, precision)
            changed.append(name)
    return changed


def _add_in_place(
    tensor: Tensor,
    vec: CapabilityVector,
    key: str,
    scale: float,
    precision: MergePrecision | None,
) -> None:
    from torch.distributed.tensor import DTensor, distribute_tensor

    if isinstance(tensor, DTensor):
        # src_data_rank=None: each rank slices its shard from its own copy, no scatter.
        delta = distribute_tensor(
            vec.delta(key).to(tensor.to_local().device),
            tensor.device_mesh,
            tensor.placements,
            src_data_rank=None,
        ).to_local()
        _add_block(tensor.to_local(), delta, scale, precision, key)  # per rank: its shard
        return
    # A block of rows at a time, as `merge` streams files: the float32 delta of a large tensor
    # and the precision check's copies of it would otherwise be several times its size at once.
    for rows in row_chunks(TensorInfo.of(tensor)):
        block = tensor if rows is None else tensor[rows]
        _add_block(block, vec.delta(key, rows), scale, precision, key)


def _add_block(
    local: Tensor, delta: Tensor, scale: float, precision: MergePrecision | None, key: str
) -> None:
    merged = add_scaled(local, [(delta, scale)])
    if precision is not None:
        precision.add(key, local, merged, scale * delta.float().to(local.device))
    local.copy_(merged)
