"""Vector folders: reading them (streaming or whole), writing them, and the in-memory vector.

A vector folder holds ``capability_vector.json`` (metadata) and the tensors in one or both of:

- ``capability_vector.safetensors`` (or numbered shards + ``capability_vector.safetensors.index.json``):
  tensors stored in full;
- ``adapter_config.json`` + ``adapter_model.safetensors``: a PEFT LoRA adapter holding the 2-D
  tensors stored in low-rank form.

A plain PEFT LoRA adapter folder (no metadata) is read as a vector too.

``capability_vector.json`` records the vector's ``fingerprint`` (a hash of every tensor, the identity
the merge record compares) and ``metadata_sha256`` (a hash of the JSON's own content), both checked
when the folder is read: edited tensors or an edited JSON are an error, a re-indented JSON is not.
Folders written before these fields existed are read as they are, their fingerprint computed.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from capvector.io.hub import hub_id, local_folder
from capvector.io.modelcard import render_model_card, write_model_card
from capvector.io.tensors import squared_norm
from capvector.io.weights import (
    ADAPTER_CONFIG,
    EXPORT_CONFIG,
    VECTOR_FORMAT,
    VECTOR_INDEX,
    VECTOR_META,
    VECTOR_WEIGHTS,
    CapVectorError,
    SafetensorsFolder,
    SafetensorsWriter,
    ShardLayout,
    TensorInfo,
    capvector_version,
    dtype_name,
    examples,
    fingerprint_of,
    full_line,
    read_json,
    row_chunks,
    short_fingerprint,
    tensor_bytes,
    write_json,
)
from capvector.vectors.lowrank import LoraFactors, read_adapter, write_adapter

FINGERPRINT = "fingerprint"
METADATA_DIGEST = "metadata_sha256"


def metadata_digest(meta: Mapping[str, Any]) -> str:
    """sha256 of ``meta`` (without this digest) as canonical JSON: formatting and key order do not
    count, any changed value does."""
    fields = {k: v for k, v in meta.items() if k != METADATA_DIGEST}
    text = json.dumps(fields, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def lora_line(factors: LoraFactors) -> str:
    """``fingerprint_of``'s line of a tensor stored as low-rank factors (c = scale · B @ A)."""
    b, a = factors.lora_b, factors.lora_a
    hasher = hashlib.sha256(tensor_bytes(b))
    hasher.update(tensor_bytes(a))
    return (
        f"lora B {dtype_name(b.dtype)} {list(b.shape)} A {dtype_name(a.dtype)} {list(a.shape)} "
        f"scale {factors.scale!r} {hasher.hexdigest()}"
    )


class VectorFolder:
    """Streaming access to a vector folder: ``read(key, rows)`` gives rows of the dense delta."""

    def __init__(self, path: str | Path) -> None:
        """``path``: a local vector folder, or a hub id (``io.hub``)."""
        self.path = local_folder(path, "vector folder")
        self.hub_id = hub_id(path)
        if self.path.is_file():
            raise CapVectorError(
                f"vector folder {self.path} is a file: pass the folder that holds it, "
                f"{self.path.parent}"
            )
        if not self.path.is_dir():
            raise CapVectorError(f"vector folder {self.path} does not exist")
        self.metadata: dict[str, Any] = {}
        if (self.path / VECTOR_META).is_file():
            self.metadata = read_json(self.path / VECTOR_META)
            if self.metadata.get("format") != VECTOR_FORMAT:
                raise CapVectorError(
                    f"{self.path / VECTOR_META} has format {self.metadata.get('format')!r}, "
                    f"expected {VECTOR_FORMAT!r}"
                )
        has_full = (self.path / VECTOR_WEIGHTS).is_file() or (self.path / VECTOR_INDEX).is_file()
        has_adapter = (self.path / ADAPTER_CONFIG).is_file()
        if not (has_full or has_adapter):
            hint = (
                " It is a model export: extract a vector from it with `capvector extract`."
                if (self.path / EXPORT_CONFIG).is_file()
                else ""
            )
            raise CapVectorError(
                f"{self.path} is not a vector folder: it has neither {VECTOR_WEIGHTS} nor "
                f"{ADAPTER_CONFIG}.{hint}"
            )
        self._full = (
            SafetensorsFolder(
                self.path, VECTOR_WEIGHTS, VECTOR_INDEX, config_name=None, kind="vector"
            )
            if has_full
            else None
        )
        self._lowrank: dict[str, LoraFactors] = {}
        self._extra: dict[str, Tensor] = {}
        if has_adapter:
            self._lowrank, self._extra = read_adapter(self.path)
        full_keys = set(self._full.keys()) if self._full else set()
        twice = sorted(
            ((full_keys | set(self._extra)) & set(self._lowrank)) | (full_keys & set(self._extra))
        )
        if twice:
            raise CapVectorError(f"{self.path} stores some tensors twice, e.g. {examples(twice)}")
        listed = self.metadata.get("tensors")
        if isinstance(listed, dict):
            self._check_listed(listed)
        recorded = self.metadata.get(METADATA_DIGEST)
        if recorded is not None and recorded != metadata_digest(self.metadata):
            raise CapVectorError(
                f"{self.path / VECTOR_META} was edited after the vector was written (it no longer "
                f"matches its {METADATA_DIGEST}), so its family, preset, shapes and sources cannot "
                "be trusted: restore it, or extract the vector again"
            )
        self._fingerprint: str | None = None

    def check_family(self, family: str | None, target: str) -> None:
        """Refuse a vector whose metadata says it was extracted from another family's models than
        ``target``'s ``family``. Matching names and shapes do not make two families' tensors mean
        the same; a JSON without a digest (written before digests) is held to its claim too."""
        sources = self.metadata.get("sources")
        claimed = {
            str(src["family"])
            for src in (sources.values() if isinstance(sources, Mapping) else [])
            if isinstance(src, Mapping) and src.get("family")
        }
        if not family or not claimed or claimed == {family}:
            return
        trust = "" if METADATA_DIGEST in self.metadata else (
            "; written before metadata digests, so unchecked"
        )  # fmt: skip
        raise CapVectorError(
            f"vector {self.path} was extracted from {' and '.join(sorted(claimed))} models (its "
            f"{VECTOR_META} says{trust}), but {target} is {family}: merge a vector of {family} "
            "models, or extract this one again"
        )

    def _check_listed(self, listed: Mapping[str, Any]) -> None:
        """What ``capability_vector.json`` says of each tensor must be what the weight files hold."""
        missing = sorted(set(listed) - set(self.keys()))
        if missing:
            raise CapVectorError(
                f"{self.path}: {len(missing)} tensor(s) listed in {VECTOR_META} are missing "
                f"from its weight files, e.g. {examples(missing)}; the folder is incomplete"
            )
        wrong = [
            f"{key}: {field} {claim[field]} in the JSON, {actual} in the weights"
            for key, claim in listed.items()
            if isinstance(claim, Mapping)
            for field, actual in (
                ("shape", list(self.info(key).shape)),
                ("dtype", dtype_name(self.info(key).dtype)),
                ("storage", self.storage(key)),
            )
            if field in claim and claim[field] != actual
        ]
        wrong += [f"{key}: not listed" for key in self.keys() if key not in listed]
        if wrong:
            raise CapVectorError(
                f"{self.path / VECTOR_META} does not describe this folder's weight files "
                f"({len(wrong)} mismatch(es), e.g. {examples(wrong, 1)}): it was edited or belongs "
                "to another vector; restore it, or extract the vector again"
            )

    def keys(self) -> list[str]:
        full = self._full.keys() if self._full else []
        return [*full, *self._extra, *self._lowrank]

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __contains__(self, key: object) -> bool:
        return (
            (self._full is not None and key in self._full)
            or key in self._extra
            or key in self._lowrank
        )

    def __len__(self) -> int:
        return len(self.keys())

    def storage(self, key: str) -> str:
        return "lora" if key in self._lowrank else "full"

    def info(self, key: str) -> TensorInfo:
        if key in self._lowrank:
            f = self._lowrank[key]
            return TensorInfo(f.dtype, f.shape)
        if key in self._extra:
            t = self._extra[key]
            return TensorInfo(t.dtype, tuple(t.shape))
        assert self._full is not None
        return self._full.info(key)

    def factors(self, key: str) -> LoraFactors | None:
        return self._lowrank.get(key)

    def read(self, key: str, rows: slice | None = None) -> Tensor:
        """Rows of the dense delta: stored dtype for full tensors, float32 for low-rank ones."""
        if key in self._lowrank:
            return self._lowrank[key].rows(rows)
        if key in self._extra:
            t = self._extra[key]
            return (t if rows is None else t[rows]).clone()
        assert self._full is not None
        return self._full.read(key, rows)

    def fingerprint(self) -> str:
        """The content fingerprint of the tensors (``io.fingerprint_of``), checked against the one
        recorded when the vector was written: one read of the weight files per folder object.

        Raises ``CapVectorError`` when they differ (the tensors changed since). A folder that
        records none (written before fingerprints, or a plain PEFT adapter) gets it computed.
        """
        if self._fingerprint is None:
            lines = self._full.tensor_lines() if self._full is not None else {}
            lines.update({key: lora_line(f) for key, f in self._lowrank.items()})
            for key, t in self._extra.items():
                digest = hashlib.sha256(tensor_bytes(t)).hexdigest()
                lines[key] = full_line(TensorInfo(t.dtype, tuple(t.shape)), digest)
            actual = fingerprint_of(lines)
            recorded = self.metadata.get(FINGERPRINT)
            if recorded is not None and recorded != actual:
                raise CapVectorError(
                    f"vector {self.path}: its tensors changed since it was written (they hash to "
                    f"{short_fingerprint(actual)}, {VECTOR_META} records "
                    f"{short_fingerprint(str(recorded))}); restore its weight files, or extract "
                    "the vector again"
                )
            self._fingerprint = actual
        return self._fingerprint

    def norm(self) -> float:
        """‖c‖: as recorded when the vector was written, else computed from its tensors."""
        recorded = self.metadata.get("norm")
        if isinstance(recorded, (int, float)):
            return float(recorded)
        total = sum(f.norm_sq() for f in self._lowrank.values())
        total += sum(float(t.double().square().sum()) for t in self._extra.values())
        for key in self._full.keys() if self._full is not None else []:
            for rows in row_chunks(self._full.info(key)):
                total += float(self._full.read(key, rows).double().square().sum())
        return math.sqrt(total)

    def check_not_zero(self) -> None:
        """A zero vector merges to nothing: it is a mistake upstream, said before any work."""
        if self.norm() == 0.0:
            raise CapVectorError(
                f"vector {self.path} is all zeros (‖c‖ = 0): were aux and sft the same export? "
                "Extract it again from the two different fine-tunes"
            )

    def describe(self) -> dict[str, Any]:
        out = {
            "path": str(self.path.resolve()),
            "kind": "vector",
            "fingerprint": self.fingerprint(),
        }
        if self.hub_id is not None:
            out["hub_id"] = self.hub_id
        if "sources" in self.metadata:
            out["sources"] = self.metadata["sources"]
        return out

    def load(self) -> CapabilityVector:
        dense = {key: self.read(key) for key in self.keys() if key not in self._lowrank}
        return CapabilityVector(dense, dict(self._lowrank), dict(self.metadata))

    def load_outside_adapter(self) -> CapabilityVector:
        """The tensors stored in full (``capability_vector.safetensors``): what a plain
        ``PeftModel.from_pretrained`` of this folder does not add, because peft has no delta form
        for them (norms, biases, tokens, convolutions)."""
        full = self._full.keys() if self._full else []
        return CapabilityVector({key: self.read(key) for key in full}, {}, dict(self.metadata))


@dataclass
class CapabilityVector:
    """A vector in memory: dense tensors and low-rank factors, by parameter name."""

    dense: dict[str, Tensor] = field(default_factory=dict)
    lowrank: dict[str, LoraFactors] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def keys(self) -> list[str]:
        return [*self.dense, *self.lowrank]

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __contains__(self, key: object) -> bool:
        return key in self.dense or key in self.lowrank

    def __len__(self) -> int:
        return len(self.dense) + len(self.lowrank)

    def shape(self, key: str) -> tuple[int, ...]:
        return self.lowrank[key].shape if key in self.lowrank else tuple(self.dense[key].shape)

    def delta(self, key: str, rows: slice | None = None) -> Tensor:
        """The dense delta (float32 for low-rank entries), or its ``rows``."""
        if key in self.lowrank:
            return self.lowrank[key].rows(rows)
        return self.dense[key] if rows is None else self.dense[key][rows]

    def changed_keys(self) -> list[str]:
        """The keys whose delta is not zero: the tensors a merge changes. A vector between two
        LoRA fits names every tensor, but only the LoRA targets (and what trained in full) differ."""
        return [key for key in self.keys() if self.norm_sq(key) > 0.0]

    def norm_sq(self, key: str) -> float:
        if key in self.lowrank:
            return self.lowrank[key].norm_sq()
        return squared_norm(self.dense[key])

    def check(self) -> None:
        """Raise ``CapVectorError`` naming every non-floating or non-finite tensor."""
        bad_dtype = sorted(k for k, t in self.dense.items() if not t.dtype.is_floating_point)
        if bad_dtype:
            raise CapVectorError(
                f"vector has {len(bad_dtype)} non-floating tensor(s), e.g. {examples(bad_dtype)}"
            )
        not_finite = sorted(
            [k for k, t in self.dense.items() if not bool(torch.isfinite(t).all())]
            + [k for k, f in self.lowrank.items() if not f.is_finite()]
        )
        if not_finite:
            raise CapVectorError(
                f"vector has NaN/Inf values in {len(not_finite)} tensor(s), e.g. "
                f"{examples(not_finite)}; it is corrupted: extract it again"
            )


def load_vector(source: str | Path | Mapping[str, Tensor] | CapabilityVector) -> CapabilityVector:
    """A ``CapabilityVector`` from a vector folder, a plain ``{name: delta}`` mapping, or itself."""
    if isinstance(source, CapabilityVector):
        return source
    if isinstance(source, (str, Path)):
        return VectorFolder(source).load()
    if isinstance(source, Mapping):
        not_tensors = [k for k, v in source.items() if not isinstance(v, Tensor)]
        if not_tensors:
            raise CapVectorError(f"vector values must be tensors; not for {examples(not_tensors)}")
        return CapabilityVector(dense=dict(source))
    raise TypeError(f"cannot read a vector from {type(source).__name__}")


class VectorFolderWriter:
    """Writes a vector folder into ``folder`` (a temporary folder inside ``io.outputs.atomic_directory``).

    Full tensors stream through ``SafetensorsWriter`` chunk by chunk (their layout is planned up
    front); low-rank factors are small and collected for the adapter, written in ``finish``.
    """

    def __init__(
        self,
        folder: Path,
        full: Sequence[tuple[str, TensorInfo]],
        max_shard_size: int,
        embeddings: Collection[str] = (),
    ) -> None:
        """``embeddings``: keys of ``nn.Embedding`` weights, written under peft's embedding names."""
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.embeddings = frozenset(embeddings)
        stem = VECTOR_WEIGHTS.removesuffix(".safetensors")
        self._writer = (
            SafetensorsWriter(folder, ShardLayout.plan(full, stem, max_shard_size), digests=True)
            if full
            else None
        )
        self._infos = dict(full)
        self._norm_sq: dict[str, float] = {}
        self.tensors: dict[str, dict[str, Any]] = {}
        self._lowrank: dict[str, LoraFactors] = {}

    def write(self, key: str, chunk: Tensor, norm: Tensor | None = None) -> None:
        """Append rows of a full tensor; ``norm`` is the chunk's L2 norm when already computed."""
        assert self._writer is not None
        if norm is None:
            norm = torch.linalg.vector_norm(chunk.float())
        self._norm_sq[key] = self._norm_sq.get(key, 0.0) + float(norm) ** 2
        self._writer.write(key, chunk)
        info = self._infos[key]
        if self._writer.current_key != key:
            self.tensors[key] = {
                "shape": list(info.shape),
                "dtype": dtype_name(info.dtype),
                "storage": "full",
                "norm": math.sqrt(self._norm_sq.pop(key)),
            }

    def add_lowrank(
        self, key: str, factors: LoraFactors, norm: float, retained: float, dtype: torch.dtype
    ) -> None:
        """Keep ``factors`` (stored as ``dtype``) for the adapter; ``norm`` is the untruncated one."""
        b, a = factors.scaled()
        factors = LoraFactors(b.to(dtype), a.to(dtype))
        self._lowrank[key] = factors
        self.tensors[key] = {
            "shape": list(factors.shape),
            "dtype": dtype_name(dtype),
            "storage": "lora",
            "rank": factors.rank,
            "retained_energy": retained,
            "norm": norm,
        }

    def finish(self, metadata: Mapping[str, Any]) -> dict[str, Any]:
        if self._writer is not None:
            self._writer.finish()
        if self._lowrank:
            write_adapter(self.folder, self._lowrank, self.embeddings)
        total_sq = sum(t["norm"] ** 2 for t in self.tensors.values())
        written = (self._writer.digests if self._writer is not None else None) or {}
        lines = {key: full_line(self._infos[key], digest) for key, digest in written.items()}
        lines.update({key: lora_line(f) for key, f in self._lowrank.items()})
        meta: dict[str, Any] = {
            "format": VECTOR_FORMAT,
            **metadata,
            "norm": math.sqrt(total_sq),
            "num_tensors": len(self.tensors),
            "num_parameters": sum(math.prod(t["shape"]) for t in self.tensors.values()),
            "storage": "lowrank" if self._lowrank else "full",
            "tensors": self.tensors,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "capvector_version": capvector_version(),
            FINGERPRINT: fingerprint_of(lines),
        }
        meta[METADATA_DIGEST] = metadata_digest(meta)
        write_json(self.folder / VECTOR_META, meta)
        write_model_card(self.folder, vector_card(meta))
        return meta

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.abort()


def vector_card(meta: Mapping[str, Any]) -> str:
    """The model card of a vector folder, from its ``capability_vector.json``."""
    sources: dict[str, Any] = {}
    for name, src in (meta.get("sources") or {}).items():
        if isinstance(src, list):  # compositions list their vectors
            sources.update({f"{name} {i}": item for i, item in enumerate(src, 1)})
        else:
            sources[name] = src
    kind = meta.get("kind", "capability_vector")
    title = "Capability vector" if kind == "capability_vector" else kind.replace("_", " ").title()
    lowrank = meta.get("storage") == "lowrank"
    summary = (
        f"A CapVector {title.lower()}: the parameter difference "
        f"`{meta.get('definition', 'aux - sft')}`. Merge it into a model with "
        "`capvector merge --base MODEL --vector THIS_FOLDER:λ` or the `MergeCapabilityVector` "
        "callback."
        + (
            " The 2-D weights are also a PEFT LoRA adapter (`adapter_config.json`): "
            "`PeftModel.from_pretrained` adds them; the tensors in `capability_vector.safetensors` "
            "are not part of the adapter."
            if lowrank
            else ""
        )
    )
    facts: dict[str, Any] = {
        f"source {name}": str(src.get("hub_id") or src.get("path"))
        + (f" ({short_fingerprint(src['fingerprint'])})" if src.get("fingerprint") else "")
        for name, src in sources.items()
        if isinstance(src, Mapping)
    }
    facts.update(
        {
            "fingerprint": meta.get(FINGERPRINT),
            "objectives": meta.get("objectives"),
            "method": meta.get("method"),
            "include": meta.get("include"),
            "exclude": meta.get("exclude"),
            "storage": meta.get("storage"),
            "norm ‖c‖": meta.get("norm"),
            "tensors": meta.get("num_tensors"),
            "parameters": meta.get("num_parameters"),
            "dtype": meta.get("dtype"),
        }
    )
    families = {src.get("family") for src in sources.values() if isinstance(src, Mapping)}
    return render_model_card(
        title,
        summary,
        facts,
        # Sources named by hub id link to them; local paths are in the "source" rows above.
        base_model=[
            src["hub_id"]
            for src in sources.values()
            if isinstance(src, Mapping) and "hub_id" in src
        ],
        tags=[
            "capability-vector",
            *(f for f in families if f),
            *(["lora", "peft"] if lowrank else []),
        ],
        command=meta.get("command"),
    )
