"""Helpers shared by the ``test_vectors_*`` modules: a tiny model named like a real VLA, and writers
of the two input formats (export folders, Lightning checkpoints) as the rest of the project writes
them. Holds no tests itself."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from safetensors.torch import save_file
from torch import Tensor, nn

from capvector.io.names import CheckpointMetadata

CAPABILITY = ("language_model.*",)
HIDDEN, FFN, VOCAB = 16, 24, 32


class Attention(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.q_proj = nn.Linear(HIDDEN, HIDDEN)
        self.k_proj = nn.Linear(HIDDEN, HIDDEN)
        self.v_proj = nn.Linear(HIDDEN, HIDDEN)
        self.o_proj = nn.Linear(HIDDEN, HIDDEN, bias=False)


class MLP(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.gate_proj = nn.Linear(HIDDEN, FFN, bias=False)
        self.up_proj = nn.Linear(HIDDEN, FFN, bias=False)
        self.down_proj = nn.Linear(FFN, HIDDEN, bias=False)


class DecoderLayer(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.self_attn = Attention()
        self.mlp = MLP()
        self.input_layernorm = nn.LayerNorm(HIDDEN)


class Decoder(nn.Module):
    def __init__(self, layers: int) -> None:
        super().__init__()
        self.embed_tokens = nn.Embedding(VOCAB, HIDDEN)
        self.layers = nn.ModuleList(DecoderLayer() for _ in range(layers))
        self.norm = nn.LayerNorm(HIDDEN)
        self.register_buffer("position_ids", torch.arange(8))  # an integer buffer: never a vector


class LanguageModel(nn.Module):
    def __init__(self, layers: int) -> None:
        super().__init__()
        self.model = Decoder(layers)


class ActionHead(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.model = nn.Sequential()
        self.model.add_module("fc1", nn.Linear(HIDDEN, 12))
        self.model.add_module("fc2", nn.Linear(12, 7))


class TinyVLA(nn.Module):
    """Keys like ``language_model.model.layers.0.self_attn.q_proj.weight`` and ``action_head.model.fc1.weight``."""

    def __init__(self, layers: int = 2) -> None:
        super().__init__()
        self.language_model = LanguageModel(layers)
        self.action_head = ActionHead()


def tiny_state(seed: int, layers: int = 2) -> dict[str, Tensor]:
    torch.manual_seed(seed)
    return {k: v.clone() for k, v in TinyVLA(layers).state_dict().items()}


def finetune(state: Mapping[str, Tensor], seed: int, scale: float = 0.05) -> dict[str, Tensor]:
    """A stand-in for a fine-tune: every floating tensor moves by a random delta."""
    g = torch.Generator().manual_seed(seed)
    return {
        k: v + scale * torch.randn(v.shape, generator=g) if v.is_floating_point() else v.clone()
        for k, v in state.items()
    }


def write_export(
    folder: Path,
    state: Mapping[str, Tensor],
    shards: int = 1,
    capability_parameters: Sequence[str] | None = CAPABILITY,
) -> Path:
    """An export folder as ``VLAModule.export`` writes it (single file or HF-style shards)."""
    folder.mkdir(parents=True)
    tensors = {k: v.contiguous() for k, v in state.items()}
    if shards == 1:
        save_file(tensors, str(folder / "model.safetensors"), metadata={"format": "pt"})
    else:
        keys = list(tensors)
        groups = [keys[i::shards] for i in range(shards)]
        weight_map = {}
        for i, group in enumerate(groups):
            name = f"model-{i + 1:05d}-of-{shards:05d}.safetensors"
            save_file({k: tensors[k] for k in group}, str(folder / name), metadata={"format": "pt"})
            weight_map.update(dict.fromkeys(group, name))
        total = sum(t.numel() * t.element_size() for t in tensors.values())
        index = {"metadata": {"total_size": total}, "weight_map": weight_map}
        (folder / "model.safetensors.index.json").write_text(json.dumps(index))
    config = {
        "format": "capvector-export",
        "family": "tiny",
        "preset": "tiny-test",
        "backbone_config": {},
    }
    if capability_parameters is not None:
        config["capability_parameters"] = list(capability_parameters)
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "dataset_statistics.json").write_text(
        json.dumps({"action": {"q01": [0.0], "q99": [1.0]}})
    )
    (folder / "tokenizer").mkdir()
    (folder / "tokenizer" / "vocab.txt").write_text("a\nb\n")
    return folder


def write_checkpoint(
    path: Path,
    backbone_state: Mapping[str, Tensor],
    lora: Mapping[str, float] | None = None,
    capability_parameters: Sequence[str] = CAPABILITY,
) -> Path:
    """A Lightning checkpoint as ``VLAModule`` saves it: ``backbone.*`` + ``objectives.*`` keys."""
    state = {f"backbone.{k}": v for k, v in backbone_state.items()}
    state["objectives.alignment.projector.weight"] = torch.randn(4, HIDDEN)
    checkpoint = {
        "epoch": 1,
        "global_step": 10,
        "state_dict": state,
        "capvector": CheckpointMetadata(
            family="openvla-oft",
            backbone_config={"preset": "openvla-oft-tiny"},
            capability_parameters=list(capability_parameters),
            lora=dict(lora) if lora else None,
        ).to_dict(),
    }
    torch.save(checkpoint, path)
    return path
