"""Plumbing the VLA families share, so that no family imports another.

What is here is written once for every backbone: the ignore index of text labels, ragged-row
padding, the camera-count check, the 256-bin state discretisation (openpi, LeRobot and StarVLA all
use ``np.digitize``'s bins) and OpenVLA-OFT's MLP-ResNet (StarVLA's OFT head is the same network).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from capvector.backbones.base import BackboneError
from capvector.io.loading import read_json


def right_pad(
    rows: Sequence[Sequence[int]], value: int, device: torch.device
) -> tuple[Tensor, Tensor]:
    """Ragged rows -> (B, L) right-padded with ``value`` and the (B, L) bool mask of real entries."""
    length = max(len(r) for r in rows)
    out = torch.full((len(rows), length), value, dtype=torch.long)
    valid = torch.zeros((len(rows), length), dtype=torch.bool)
    for i, row in enumerate(rows):
        out[i, : len(row)] = torch.tensor(row, dtype=torch.long)
        valid[i, : len(row)] = True
    return out.to(device), valid.to(device)


def answer_ids_then_eos(tokenizer: Any, answer: str) -> list[int]:
    """``answer``'s token ids and the tokenizer's end of sequence: what OpenVLA-OFT's and Pi0.5's
    text passes score. ``verbose=False``: a scene annotation can run past the tokenizer's
    ``model_max_length`` (the tiny presets' 512), which rotary positions allow, so its warning of
    "indexing errors" is wrong here."""
    ids = tokenizer(answer, add_special_tokens=False, verbose=False)["input_ids"]
    return [*ids, tokenizer.eos_token_id]


def rename_prefix(key: str, prefixes: Iterable[tuple[str, str]]) -> str:
    """``key`` with its first matching ``old`` prefix replaced by ``new`` (a checkpoint's key map);
    unchanged when none matches."""
    for old, new in prefixes:
        if key.startswith(old):
            return new + key[len(old) :]
    return key


def read_required_json(path: Path, why: str) -> dict[str, Any]:
    """The JSON object at ``path``; a missing file is a ``BackboneError`` saying ``why`` it is
    needed."""
    if not path.is_file():
        raise BackboneError(f"{path} is missing: {why}")
    return read_json(path)


def check_cameras(images: Tensor, num_images: int) -> None:
    """``images`` (B, N_cam, ...) must carry the cameras the backbone was built for."""
    n_cam = images.shape[1]
    if n_cam != num_images:
        raise BackboneError(
            f"batch has {n_cam} camera(s) but the backbone was built for "
            f"num_images={num_images}; set it to the dataset's camera count"
        )


def discretize_state(state: Tensor, bins: int = 256) -> Tensor:
    """Normalised state -> integer bins, -1 .. bins - 1, any shape.

    openpi ``PaligemmaTokenizer.tokenize`` (``src/openpi/models/tokenizer.py``), LeRobot
    ``Pi05PrepareStateTokenizerProcessorStep`` (``processor_pi05.py``) and StarVLA
    ``share_tools.state2str_transform``: ``np.digitize(s, linspace(-1, 1, bins + 1)[:-1]) - 1``.
    Inside [-1, 1) that is bin floor((s + 1) / 2 * bins); a value below -1 gives -1 and one at or
    above 1 - 2/bins gives bins - 1, as upstream: none of them clamps, and their normalisations let
    states outside [-1, 1] through (openpi's quantiles unclipped, StarVLA's q99 clamped to ±2.2
    only), so trained checkpoints have seen these values. Edges in float64 as numpy's, so values on
    a bin edge land in the same bin.
    """
    edges = torch.linspace(-1.0, 1.0, bins + 1, dtype=torch.float64, device=state.device)[:-1]
    values = state.detach().to(torch.float64)
    # torch.bucketize(right=True) returns i with edges[i-1] <= x < edges[i], as np.digitize.
    return torch.bucketize(values, edges, right=True) - 1


class MLPResNetBlock(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.ffn = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.ReLU())

    def forward(self, x: Tensor) -> Tensor:
        return x + self.ffn(x)


class MLPResNet(nn.Module):
    """OpenVLA-OFT's ``MLPResNet`` (``prismatic/models/action_heads.py``), parameter names kept."""

    def __init__(self, num_blocks: int, input_dim: int, hidden_dim: int, output_dim: int) -> None:
        super().__init__()
        self.layer_norm1 = nn.LayerNorm(input_dim)
        self.fc1 = nn.Linear(input_dim, hidden_dim)
        self.relu = nn.ReLU()
        self.mlp_resnet_blocks = nn.ModuleList(
            MLPResNetBlock(hidden_dim) for _ in range(num_blocks)
        )
        self.layer_norm2 = nn.LayerNorm(hidden_dim)
        self.fc2 = nn.Linear(hidden_dim, output_dim)

    def forward(self, x: Tensor) -> Tensor:
        x = self.relu(self.fc1(self.layer_norm1(x)))
        for block in self.mlp_resnet_blocks:
            x = block(x)
        return self.fc2(self.layer_norm2(x))
