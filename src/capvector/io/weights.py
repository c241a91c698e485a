"""Reading model weights (export folders, Lightning checkpoints) and streaming safetensors writes.

Everything here works tensor by tensor, and within a tensor row-chunk by row-chunk, so the memory
a tool needs is bounded by a chunk size, not by the model size. Reads go through
``safetensors.safe_open`` with one short-lived handle per chunk: a long-lived handle keeps its whole
memory map resident as it is read (measured: RSS grew to the file size), a closed one does not.
Writes go through ``SafetensorsWriter``, which writes the header first (the layout is known up
front) and then appends tensor bytes as they are computed.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import math
import os
import re
import struct
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from capvector.errors import CapVectorError  # noqa: F401 (re-exported: the vector tools' error)
from capvector.io.hub import hub_id, local_folder
from capvector.io.loading import read_json
from capvector.io.lora_layers import LoraFormatError, LoraLayer, split_lora
from capvector.io.names import (  # noqa: F401 (re-exported: the vector modules' names)
    ADAPTER_CONFIG,
    ADAPTER_WEIGHTS,
    CHECKPOINT_MODEL_PREFIX,
    CHECKPOINT_OBJECTIVES_PREFIX,
    EXPORT_CONFIG,
    EXPORT_FORMAT,
    EXPORT_INDEX,
    EXPORT_WEIGHTS,
    VECTOR_FORMAT,
    VECTOR_INDEX,
    VECTOR_META,
    VECTOR_WEIGHTS,
    CheckpointMetadata,
)
from capvector.io.tensors import TensorInfo, tensor_info

DEFAULT_MAX_SHARD_SIZE = 2 * 10**9
"""2 GB, counted like transformers' ``max_shard_size="2GB"``."""
StorageDtype = Literal["float32", "bfloat16", "float16"]
"""What a vector or merged model may be stored in, by name (``parse_dtype`` reads these)."""
CHUNK_BYTES = 32 * 1024**2
"""Row chunks are sized so that one chunk in float32 takes about this many bytes: a handful of
chunk-sized temporaries stay well under the 1 GB budget next to torch's own ~0.5 GB."""


def examples(items: Sequence[str], n: int = 3) -> str:
    """A few items for an error message: "`a`, `b`, `c` ..."."""
    shown = ", ".join(f"`{x}`" for x in items[:n])
    return shown + (" ..." if len(items) > n else "")


# -- dtypes ---------------------------------------------------------------------------------

_SAFETENSORS_DTYPES: dict[str, torch.dtype] = {
    "F64": torch.float64,
    "F32": torch.float32,
    "F16": torch.float16,
    "BF16": torch.bfloat16,
    "F8_E4M3": torch.float8_e4m3fn,
    "F8_E5M2": torch.float8_e5m2,
    "I64": torch.int64,
    "I32": torch.int32,
    "I16": torch.int16,
    "I8": torch.int8,
    "U64": torch.uint64,
    "U32": torch.uint32,
    "U16": torch.uint16,
    "U8": torch.uint8,
    "BOOL": torch.bool,
}
_SAFETENSORS_CODES = {dtype: code for code, dtype in _SAFETENSORS_DTYPES.items()}


def dtype_name(dtype: torch.dtype) -> str:
    """``torch.bfloat16`` -> ``"bfloat16"`` (the spelling used in JSON metadata and on the CLI)."""
    return str(dtype).removeprefix("torch.")


def parse_size(size: int | str) -> int:
    """Bytes from ``2GB`` (10^9 bytes, as in transformers), ``2GiB`` (2^30), ``500MB`` or a number."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(?:([KMGT])(i?)B)?\s*", str(size), re.IGNORECASE)
    if not match:
        raise CapVectorError(f"not a size: {size!r} (try 2GB or 500MB)")
    number, unit, binary = match.groups()
    power = "KMGT".index(unit.upper()) + 1 if unit else 0
    return int(float(number) * (1024 if binary else 1000) ** power)


def parse_dtype(name: str) -> torch.dtype:
    dtype = getattr(torch, name, None)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise CapVectorError(f"unknown floating dtype {name!r}; use float32, bfloat16 or float16")
    return dtype


def compute_dtype(*dtypes: torch.dtype) -> torch.dtype:
    """Arithmetic runs in float32, or float64 when an input is float64."""
    return torch.float64 if torch.float64 in dtypes else torch.float32


class Scratch:
    """Work buffers reused across chunks.

    glibc serves every large allocation with a fresh mmap, so a new 64 MB tensor costs ~16k page
    faults on first touch; in the streaming loops that cost more than the arithmetic (measured).
    A buffer handed out is valid until the next ``get`` with the same name.
    """

    def __init__(self) -> None:
        self._buffers: dict[tuple[str, torch.dtype], Tensor] = {}

    def get(self, name: str, shape: Sequence[int], dtype: torch.dtype) -> Tensor:
        numel = math.prod(shape)
        buffer = self._buffers.get((name, dtype))
        if buffer is None or buffer.numel() < numel:
            buffer = torch.empty(numel, dtype=dtype)
            self._buffers[(name, dtype)] = buffer
        return buffer[:numel].view(tuple(shape))

    def cast(self, name: str, t: Tensor, dtype: torch.dtype) -> Tensor:
        """``t`` in ``dtype``: itself when it already is, else a copy in the buffer ``name``."""
        return t if t.dtype == dtype else self.get(name, t.shape, dtype).copy_(t)


def all_finite(t: Tensor) -> bool:
    """True when no entry is NaN/Inf. One reduction; the elementwise check only when it fails
    (a sum also overflows for huge finite values)."""
    return bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


def row_chunks(info: TensorInfo, chunk_bytes: int = CHUNK_BYTES) -> Iterator[slice | None]:
    """Slices along dim 0 covering the tensor; ``None`` means "the whole tensor" (0-d tensors)."""
    if not info.shape:
        yield None
        return
    if info.shape[0] == 0:
        yield slice(0, 0)  # empty tensors still get one (empty) write so writers see them
        return
    row_bytes = max(1, info.numel // max(1, info.shape[0])) * 4
    step = max(1, chunk_bytes // row_bytes)
    for start in range(0, info.shape[0], step):
        yield slice(start, min(start + step, info.shape[0]))


def select_keys(
    keys: Sequence[str], include: Sequence[str] | None, exclude: Sequence[str] | None
) -> list[str]:
    """Keys matching any ``include`` glob (all when None) and no ``exclude`` glob (fnmatch, case-sensitive)."""
    chosen = [k for k in keys if include is None or any(fnmatch.fnmatchcase(k, g) for g in include)]
    return [k for k in chosen if not any(fnmatch.fnmatchcase(k, g) for g in exclude or ())]


# -- content fingerprints --------------------------------------------------------------------

FINGERPRINT_PREFIX = "tensors-sha256:"
"""Marks a content fingerprint (``fingerprint_of``); earlier records hold sampled "sha256:" ones."""
_HASH_PIECE = 8 * 1024**2


def tensor_bytes(t: Tensor) -> memoryview:
    """The bytes of ``t`` in row-major order, as safetensors stores them."""
    return memoryview(t.detach().contiguous().reshape(-1).view(torch.uint8).numpy())


def fingerprint_of(lines: Mapping[str, str]) -> str:
    """The content fingerprint of named tensors: sha256 over ``name: line`` in sorted name order.

    Each line describes one tensor (dtype, shape, how it is stored, the sha256 of its bytes), so the
    fingerprint changes exactly when a tensor does, whatever the file layout, shard split or order.
    """
    hasher = hashlib.sha256()
    for key in sorted(lines):
        hasher.update(f"{key}: {lines[key]}\n".encode())
    return FINGERPRINT_PREFIX + hasher.hexdigest()


def full_line(info: TensorInfo, digest: str) -> str:
    """``fingerprint_of``'s line of a tensor stored as is; ``digest``: the sha256 of its bytes."""
    return f"{dtype_name(info.dtype)} {list(info.shape)} {digest}"


def short_fingerprint(fingerprint: str) -> str:
    """``tensors-sha256:0123456789ab…``, for messages and model cards."""
    kind, _, digest = fingerprint.rpartition(":")
    return f"{kind}:{digest[:12]}…"


def safetensors_digests(path: Path) -> dict[str, str]:
    """The sha256 of every tensor's bytes in the safetensors file ``path``, by name.

    One sequential read of the file in 8 MiB pieces through one buffer: bounded memory, and no
    memory map whose pages would stay resident.
    """
    buffer = memoryview(bytearray(_HASH_PIECE))
    digests: dict[str, str] = {}
    with open(path, "rb", buffering=0) as f:
        (header_size,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(header_size))
        header.pop("__metadata__", None)
        for key, entry in sorted(header.items(), key=lambda item: item[1]["data_offsets"][0]):
            begin, end = entry["data_offsets"]
            f.seek(8 + header_size + begin)
            hasher = hashlib.sha256()
            remaining = end - begin
            while remaining:
                n = f.readinto(buffer[: min(remaining, _HASH_PIECE)])
                if not n:
                    raise CapVectorError(
                        f"{path} ends inside tensor `{key}`: it is truncated; write it again"
                    )
                hasher.update(buffer[:n])
                remaining -= n
            digests[key] = hasher.hexdigest()
    return digests


# -- reading --------------------------------------------------------------------------------


class WeightSource(ABC):
    """Read-only access to named tensors, by key and row range, without loading everything."""

    path: Path
    kind: str
    config: dict[str, Any]
    hub_id: str | None = None
    """The hub repository the source was read from (``io.hub``), when it was named by one."""

    @abstractmethod
    def keys(self) -> list[str]:
        """The tensor names."""

    def __iter__(self) -> Iterator[str]:
        return iter(self.keys())

    def __contains__(self, key: object) -> bool:
        return key in self.keys()

    @abstractmethod
    def info(self, key: str) -> TensorInfo:
        """The info of this source."""

    @abstractmethod
    def read(self, key: str, rows: slice | None = None) -> Tensor:
        """Rows ``rows`` (all when None) of tensor ``key``; the caller owns the returned tensor."""

    @property
    def capability_parameters(self) -> list[str] | None:
        globs = self.config.get("capability_parameters")
        return list(globs) if globs is not None else None

    @property
    def embedding_parameters(self) -> set[str]:
        """``nn.Embedding`` weights, as the backbone recorded them (empty for older exports)."""
        return set(self.config.get("embedding_parameters") or [])

    @property
    def objectives(self) -> list[str] | None:
        names = self.config.get("objectives")
        return list(names) if names is not None else None

    def describe(self) -> dict[str, Any]:
        """Provenance recorded in the metadata of what is written from this source.

        By path, not by content: hashing the inputs would cost another read of every model
        (vectors, what the merge record compares, are fingerprinted by content).
        """
        out: dict[str, Any] = {"path": str(self.path.resolve()), "kind": self.kind}
        if self.hub_id is not None:
            out["hub_id"] = self.hub_id
        preset = self.config.get("preset") or (self.config.get("backbone_config") or {}).get(
            "preset"
        )
        for field, value in (("family", self.config.get("family")), ("preset", preset)):
            if value is not None:
                out[field] = value
        return out


class SafetensorsFolder(WeightSource):
    """A folder with ``<stem>.safetensors`` or HF-style shards + ``<stem>.safetensors.index.json``.

    Every file's header is read (and so validated by safetensors: a truncated file fails here, before
    anything is written) when the folder is opened; tensor data is read on demand.
    """

    def __init__(
        self,
        folder: str | Path,
        weights_name: str = EXPORT_WEIGHTS,
        index_name: str = EXPORT_INDEX,
        config_name: str | None = EXPORT_CONFIG,
        kind: str = "export",
    ) -> None:
        from safetensors import safe_open

        self.path = Path(folder)
        self.kind = kind
        self.weights_name = weights_name
        self.index_name = index_name
        self.config = {}
        if config_name and (self.path / config_name).is_file():
            self.config = read_json(self.path / config_name)
        single, index = self.path / weights_name, self.path / index_name
        if single.is_file():
            self.index_path: Path | None = None
            files = [weights_name]
            expected: dict[str, str] | None = None
        elif index.is_file():
            self.index_path = index
            weight_map = read_json(index).get("weight_map")
            if not isinstance(weight_map, dict) or not weight_map:
                raise CapVectorError(f"{index} has no `weight_map`; it is not a safetensors index")
            expected = {str(k): str(v) for k, v in weight_map.items()}
            files = sorted(set(expected.values()))
        else:
            raise CapVectorError(f"{self.path} has neither {weights_name} nor {index_name}")

        self.files: dict[str, list[str]] = {}
        self.file_metadata: dict[str, dict[str, str]] = {}
        self._infos: dict[str, TensorInfo] = {}
        self._file_of: dict[str, Path] = {}
        for name in files:
            path = self.path / name
            if not path.is_file():
                raise CapVectorError(
                    f"{index} lists shard {name}, which is missing from {self.path}"
                )
            try:
                with safe_open(str(path), framework="pt") as f:
                    keys = list(f.keys())
                    self.file_metadata[name] = dict(f.metadata() or {})
                    for key in keys:
                        sl = f.get_slice(key)
                        code = sl.get_dtype()
                        if code not in _SAFETENSORS_DTYPES:
                            raise CapVectorError(
                                f"{path}: tensor `{key}` has unsupported dtype {code}"
                            )
                        self._infos[key] = TensorInfo(
                            _SAFETENSORS_DTYPES[code], tuple(sl.get_shape())
                        )
                        self._file_of[key] = path
            except CapVectorError:
                raise
            except Exception as err:  # safetensors raises its own SafetensorError (an Exception)
                raise CapVectorError(
                    f"{path} is not a readable safetensors file ({err}); it is truncated or "
                    "corrupted: write it again"
                ) from err
            self.files[name] = keys
        if expected is not None:
            found = {k: p.name for k, p in self._file_of.items()}
            wrong = sorted(k for k, f in expected.items() if found.get(k) != f)
            extra = sorted(set(found) - set(expected))
            if wrong or extra:
                raise CapVectorError(
                    f"{index} does not match its shards: {len(wrong)} indexed tensor(s) missing from "
                    f"the shard the index names ({examples(wrong)}), {len(extra)} unindexed "
                    f"tensor(s) ({examples(extra)}); the folder is corrupted or mixes two exports"
                )

    def keys(self) -> list[str]:
        return list(self._infos)

    def __contains__(self, key: object) -> bool:
        return key in self._infos

    def info(self, key: str) -> TensorInfo:
        return self._infos[key]

    def read(self, key: str, rows: slice | None = None) -> Tensor:
        from safetensors import safe_open

        with safe_open(str(self._file_of[key]), framework="pt") as f:
            if rows is None:
                return f.get_tensor(key)
            return f.get_slice(key)[rows]

    def weight_files(self) -> list[str]:
        return list(self.files) + ([self.index_path.name] if self.index_path else [])

    def tensor_lines(self) -> dict[str, str]:
        """``fingerprint_of``'s line of every tensor: each file read once."""
        lines = {}
        for name in self.files:
            for key, digest in safetensors_digests(self.path / name).items():
                lines[key] = full_line(self._infos[key], digest)
        return lines


class CheckpointSource(WeightSource):
    """A Lightning ``.ckpt`` seen as plain backbone keys, with peft LoRA layers merged.

    ``backbone.X.base_layer.weight`` + ``lora_A``/``lora_B`` become ``X.weight`` = base + scaling·B@A
    (``checkpoint["capvector"]["lora"]["scaling"]``); ``objectives.*`` (auxiliary loss modules) are
    never part of a vector and are dropped. The file is memory-mapped, so only what is read is loaded.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.kind = "checkpoint"
        try:
            checkpoint = torch.load(self.path, map_location="cpu", weights_only=False, mmap=True)
        except Exception as err:
            raise CapVectorError(
                f"cannot read checkpoint {self.path} ({err}); it is truncated, corrupted or not a "
                "torch checkpoint"
            ) from err
        state = checkpoint.get("state_dict") if isinstance(checkpoint, dict) else None
        if not isinstance(state, Mapping):
            raise CapVectorError(
                f"{self.path} has no `state_dict`: it is not a Lightning checkpoint"
            )
        meta = CheckpointMetadata.from_checkpoint(checkpoint, str(self.path))
        self.config = {
            "family": meta.family,
            "preset": meta.backbone_config.get("preset"),
            "capability_parameters": meta.capability_parameters,
            "embedding_parameters": meta.embedding_parameters,
        }
        objective_names = sorted(
            {k.split(".")[1] for k in state if k.startswith(CHECKPOINT_OBJECTIVES_PREFIX)}
        )
        self.config["objectives"] = meta.objectives or objective_names or None
        model = {
            k[len(CHECKPOINT_MODEL_PREFIX) :]: v
            for k, v in state.items()
            if k.startswith(CHECKPOINT_MODEL_PREFIX) and isinstance(v, Tensor)
        }
        if not model:
            raise CapVectorError(
                f"{self.path} has no `{CHECKPOINT_MODEL_PREFIX}*` tensors in its state_dict; "
                "is it a capvector checkpoint?"
            )
        self._tensors: dict[str, Tensor | tuple[Tensor, LoraLayer]] = {}
        self._merge_lora(model, meta.lora)

    def _merge_lora(self, model: dict[str, Tensor], lora: Mapping[str, Any] | None) -> None:
        # Lazily: a weight with LoRA is kept as (base, layer) and merged rows at a time on read.
        scaling = None if not lora or lora.get("scaling") is None else float(lora["scaling"])

        def layer_scaling(module: str, rank: int) -> float:
            if scaling is None:
                raise CapVectorError(
                    f"{self.path} has LoRA layers (e.g. `{module}`) but no "
                    "checkpoint['capvector']['lora']['scaling'] to merge them with"
                )
            return scaling

        try:
            fan_in_fan_out = bool(lora and lora.get("fan_in_fan_out"))
            plain, layers = split_lora(model, layer_scaling, fan_in_fan_out)
            tensors: dict[str, Tensor | tuple[Tensor, LoraLayer]] = dict(plain)
            for module, layer in layers.items():
                weight = plain.get(f"{module}.weight")
                if weight is None:
                    raise LoraFormatError(f"LoRA layer `{module}` has no base weight")
                tensors[f"{module}.weight"] = (weight, layer)
                bias = layer.merged_bias(plain.get(f"{module}.bias"))
                if bias is not None:
                    tensors[f"{module}.bias"] = bias.to(plain[f"{module}.bias"].dtype)
        except LoraFormatError as err:
            raise CapVectorError(
                f"{self.path}: {err}; export the merged model and extract from the export folder"
            ) from err
        self._tensors = tensors

    def keys(self) -> list[str]:
        return list(self._tensors)

    def __contains__(self, key: object) -> bool:
        return key in self._tensors

    def info(self, key: str) -> TensorInfo:
        t = self._tensors[key]
        base = t[0] if isinstance(t, tuple) else t
        return TensorInfo(base.dtype, tuple(base.shape))

    def read(self, key: str, rows: slice | None = None) -> Tensor:
        t = self._tensors[key]
        if isinstance(t, tuple):
            base, layer = t
            return layer.merged(base, rows).to(base.dtype)
        return (t if rows is None else t[rows]).clone()


def open_weights(path: str | Path) -> WeightSource:
    """An export folder (a local one, or a hub id's snapshot), a bare ``.safetensors`` file's
    folder, or a Lightning ``.ckpt``."""
    source = _open_weights(local_folder(path))
    source.hub_id = hub_id(path)
    return source


def _open_weights(p: Path) -> WeightSource:
    if p.is_dir():
        if (p / VECTOR_META).is_file() or (p / ADAPTER_CONFIG).is_file():
            raise CapVectorError(f"{p} is a vector folder, not model weights")
        config = p / EXPORT_CONFIG
        if config.is_file():
            fmt = read_json(config).get("format")
            if fmt not in (None, EXPORT_FORMAT):
                raise CapVectorError(f"{config} has format {fmt!r}, expected {EXPORT_FORMAT!r}")
        return SafetensorsFolder(p)
    if p.is_file():
        if p.suffix == ".safetensors":
            return SafetensorsFolder(
                p.parent, weights_name=p.name, config_name=None, kind="safetensors"
            )
        return CheckpointSource(p)
    raise CapVectorError(f"{p} does not exist")


# -- writing --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ShardLayout:
    """Which tensors go into which file, in write order."""

    files: list[tuple[str, list[tuple[str, TensorInfo]]]]
    index_name: str | None
    """Written when not None (sharded folders)."""

    @staticmethod
    def plan(
        tensors: Sequence[tuple[str, TensorInfo]], stem: str, max_shard_size: int
    ) -> ShardLayout:
        """Greedy HF-style sharding: ``<stem>.safetensors``, or numbered shards + an index."""
        shards: list[list[tuple[str, TensorInfo]]] = [[]]
        size = 0
        for key, info in tensors:
            if shards[-1] and size + info.nbytes > max_shard_size:
                shards.append([])
                size = 0
            shards[-1].append((key, info))
            size += info.nbytes
        if len(shards) == 1:
            return ShardLayout([(f"{stem}.safetensors", shards[0])], None)
        n = len(shards)
        names = [f"{stem}-{i + 1:05d}-of-{n:05d}.safetensors" for i in range(n)]
        return ShardLayout(list(zip(names, shards, strict=True)), f"{stem}.safetensors.index.json")


class SafetensorsWriter:
    """Writes a ``ShardLayout`` tensor by tensor, chunk by chunk, in layout order.

    The header (names, dtypes, shapes, offsets) is known before any data, so it is written first and
    tensor bytes are appended as they are computed; nothing larger than a chunk is held. The writer
    refuses bytes out of order or of the wrong size, so a bug cannot produce a malformed file.
    With ``digests``, the sha256 of every tensor's bytes is computed as they are written
    (``self.digests``), so fingerprinting what was written costs no second read.
    """

    def __init__(
        self,
        folder: Path,
        layout: ShardLayout,
        metadata: Mapping[str, str] | None = None,
        digests: bool = False,
    ) -> None:
        self.folder = folder
        self.layout = layout
        self.metadata = {"format": "pt", **dict(metadata or {})}
        self._queue = [(name, key, info) for name, items in layout.files for key, info in items]
        self._pos = 0
        self._written = 0
        self._file: Any = None
        self._file_name: str | None = None
        self.digests: dict[str, str] | None = {} if digests else None
        self._hasher: Any = None

    @property
    def current_key(self) -> str | None:
        return self._queue[self._pos][1] if self._pos < len(self._queue) else None

    def write(self, key: str, chunk: Tensor) -> None:
        """Append ``chunk`` (rows of ``key``, cast to the planned dtype) to the output."""
        if self._pos >= len(self._queue) or self._queue[self._pos][1] != key:
            raise RuntimeError(f"write order: got `{key}`, expected `{self.current_key}`")
        name, _, info = self._queue[self._pos]
        if self._file_name != name:
            self._open(name)
        raw = tensor_bytes(chunk.to(device="cpu", dtype=info.dtype))
        self._file.write(raw)
        if self.digests is not None:
            if self._written == 0:
                self._hasher = hashlib.sha256()
            self._hasher.update(raw)
        self._written += raw.nbytes
        if self._written > info.nbytes:
            raise RuntimeError(f"`{key}`: {self._written} bytes written, {info.nbytes} planned")
        if self._written == info.nbytes:
            if self.digests is not None:
                self.digests[key] = self._hasher.hexdigest()
            self._pos += 1
            self._written = 0
            if self._pos == len(self._queue) or self._queue[self._pos][0] != name:
                self._close_file()

    def _open(self, name: str) -> None:
        items = dict(self.layout.files)[name]
        header: dict[str, Any] = {"__metadata__": self.metadata}
        offset = 0
        for key, info in items:
            header[key] = {
                "dtype": _SAFETENSORS_CODES[info.dtype],
                "shape": list(info.shape),
                "data_offsets": [offset, offset + info.nbytes],
            }
            offset += info.nbytes
        raw = json.dumps(header, separators=(",", ":")).encode()
        raw += b" " * (-len(raw) % 8)  # safetensors pads the header to 8-byte alignment
        self._file = open(self.folder / name, "wb")  # noqa: SIM115 - closed in _close_file
        self._file_name = name
        self._file.write(struct.pack("<Q", len(raw)) + raw)

    def _close_file(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self._file = None

    def finish(self) -> None:
        """Check everything was written; write the index of a sharded layout."""
        if not self._queue:  # a layout without tensors is one empty (header-only) file
            self._open(self.layout.files[0][0])
            self._close_file()
        if self._pos != len(self._queue):
            raise RuntimeError(f"output incomplete: `{self.current_key}` was not written")
        if self.layout.index_name is not None:
            total = sum(info.nbytes for _, items in self.layout.files for _, info in items)
            weight_map = {key: name for name, items in self.layout.files for key, _ in items}
            write_json(
                self.folder / self.layout.index_name,
                {"metadata": {"total_size": total}, "weight_map": weight_map},
            )

    def abort(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def write_safetensors(path: Path, tensors: Mapping[str, Tensor]) -> None:
    """One safetensors file of ``tensors``, written tensor by tensor (``SafetensorsWriter``):
    ``safetensors.torch.save_file`` first copies every tensor into one bytes object, which doubles
    a full-size export's memory (6.7 GB more for ``pi05-3b`` in bf16). ``LazyTensors`` are made
    one at a time, as they are written."""
    infos = [(k, tensor_info(tensors, k)) for k in tensors]
    layout = ShardLayout([(path.name, infos)], None)
    writer = SafetensorsWriter(path.parent, layout)
    try:
        for key, tensor in tensors.items():
            writer.write(key, tensor)
        writer.finish()
    except BaseException:
        writer.abort()
        raise


def write_json(path: Path, content: Any) -> None:
    with open(path, "w") as f:
        json.dump(content, f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())


def dtype_summary(dtypes: Iterable[torch.dtype]) -> str:
    """The one dtype name of a set of tensors, or ``"mixed"``."""
    names = {dtype_name(d) for d in dtypes}
    return names.pop() if len(names) == 1 else "mixed"


def capvector_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("capvector")
    except PackageNotFoundError:
        return "unknown"
