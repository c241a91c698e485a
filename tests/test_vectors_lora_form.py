"""Extract and merge on LoRA-form exports (a base rebuilt from weight packages, as
``openvla-oft-mini``'s): the base deltas are differenced and stacked exactly as factors, what two
fine-tunes inherited from θ_pre cancels, and a mix with whole exports is refused. Synthetic
exports, so no weight package is read (``tests/backbones/openvla_oft/test_mini_export.py`` runs the
same path on the real preset)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file
from torch import Tensor

from capvector.io.lora_layers import compact_factors, stack_factors
from capvector.io.names import BASE_DELTA
from capvector.io.weights import CapVectorError
from capvector.vectors import extract, merge
from capvector.vectors.vector import VectorFolder
from test_vectors_common import write_export

CAPABILITY = ("language_model.*", "projector.*")
Q, V = (f"language_model.model.layers.0.self_attn.{m}_proj" for m in "qv")
OUT, IN, R = 12, 10, 2


def factors(seed: int, rank: int = R) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(OUT, rank, generator=g), torch.randn(rank, IN, generator=g)


def lora_form_export(folder: Path, deltas: dict[str, tuple[Tensor, Tensor]], seed: int) -> Path:
    """An export as ``VLAModule.export`` writes one of the mini: trained tensors plus base deltas."""
    g = torch.Generator().manual_seed(seed)
    state = {"projector.fc1.weight": torch.randn(4, 3, generator=g),
             "action_head.fc.weight": torch.randn(2, 4, generator=g)}  # fmt: skip
    for module, (b, a) in deltas.items():
        state[f"{module}.lora_A.weight"], state[f"{module}.lora_B.weight"] = a, b
    write_export(folder, state, capability_parameters=CAPABILITY)
    config = json.loads((folder / "config.json").read_text())
    config["backbone_config"] = {"preset": "mini-test", "base_weights": "packages"}
    config[BASE_DELTA] = {"form": "lora", "scaling": 1.0}
    (folder / "config.json").write_text(json.dumps(config))
    return folder


def delta(state: dict[str, Tensor], module: str) -> Tensor:
    return state[f"{module}.lora_B.weight"] @ state[f"{module}.lora_A.weight"]


def test_compact_factors_keeps_the_product_at_its_rank() -> None:
    shared, own = factors(0), factors(1)
    b, a = stack_factors(shared, own, (-shared[0], shared[1]))  # rank 6 written, 2 meant
    small = compact_factors((b, a))
    assert small[0].shape == (OUT, R) and small[1].shape == (R, IN)
    torch.testing.assert_close(small[0] @ small[1], own[0] @ own[1], rtol=1e-5, atol=1e-5)


def test_a_vector_of_lora_form_exports_is_exact_lora_and_merges_back(tmp_path: Path) -> None:
    pre = factors(0)  # θ_pre's delta: both fine-tunes stack their LoRA onto it
    aux_q, sft_q, aux_v = factors(1), factors(2), factors(3)
    aux = lora_form_export(tmp_path / "aux", {Q: stack_factors(pre, aux_q), V: aux_v}, 1)
    sft = lora_form_export(tmp_path / "sft", {Q: stack_factors(pre, sft_q)}, 2)  # V: packaged

    meta = extract(aux, sft, tmp_path / "c")
    assert meta["exact_lowrank"] == [f"{Q}.weight", f"{V}.weight"]
    vector = VectorFolder(tmp_path / "c")
    assert vector.storage(f"{Q}.weight") == "lora" and vector.info(f"{Q}.weight").shape == (OUT, IN)
    assert vector.factors(f"{Q}.weight").rank == 2 * R  # θ_pre's part cancelled
    expected_q = aux_q[0] @ aux_q[1] - sft_q[0] @ sft_q[1]
    torch.testing.assert_close(vector.read(f"{Q}.weight"), expected_q, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(
        vector.read(f"{V}.weight"), aux_v[0] @ aux_v[1], rtol=1e-4, atol=1e-4
    )
    a, s = load_file(aux / "model.safetensors"), load_file(sft / "model.safetensors")
    proj = "projector.fc1.weight"
    torch.testing.assert_close(vector.read(proj), a[proj] - s[proj])
    assert "action_head.fc.weight" not in vector  # not a capability parameter

    # θ_sft + 0.5·c: the deltas stacked (V gains one), the projector summed, the heads kept.
    merge(sft, [(tmp_path / "c", 0.5)], tmp_path / "meta")
    config = json.loads((tmp_path / "meta/config.json").read_text())
    assert config[BASE_DELTA] == {"form": "lora", "scaling": 1.0}
    merged = load_file(tmp_path / "meta/model.safetensors")
    torch.testing.assert_close(
        delta(merged, Q), delta(s, Q) + 0.5 * expected_q, rtol=1e-4, atol=1e-4
    )
    torch.testing.assert_close(delta(merged, V), 0.5 * aux_v[0] @ aux_v[1], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(merged[proj], s[proj] + 0.5 * (a[proj] - s[proj]))
    assert torch.equal(merged["action_head.fc.weight"], s["action_head.fc.weight"])


def test_a_lora_form_export_and_a_whole_one_are_refused_together(tmp_path: Path) -> None:
    mini = lora_form_export(tmp_path / "mini", {Q: factors(1)}, 1)
    whole = write_export(tmp_path / "whole", {"projector.fc1.weight": torch.zeros(4, 3)})
    with pytest.raises(CapVectorError, match=r"mix an export whose base is rebuilt .* aux \(LoRA"):
        extract(mini, whole, tmp_path / "c")
    assert not (tmp_path / "c").exists()
