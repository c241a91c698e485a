"""LoRA-form exports of ``openvla-oft-mini`` (issue 59, item 3): an export holds what trains and
the base's low-rank deltas over the weight packages, a capability vector of two such exports is
exact LoRA, and a merge stacks it onto θ_pre's deltas; loading rebuilds the base from the packages.

Cut to 1 Gemma layer and 32 px images: the packaged weights are the real ones (the referees in
``test_mini.py`` check them at the preset's size); what is tested here is the bookkeeping.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from capvector.backbones import from_pretrained
from capvector.backbones.packaged import EFFICIENTNET_LITE0, GEMMA3_270M
from capvector.data import keys
from capvector.io.names import BASE_DELTA
from capvector.module import VLAModule, load_module
from capvector.training.lora import LoraSettings
from capvector.vectors import extract, merge

pytestmark = pytest.mark.slow

CUT = {"llm": {"num_layers": 1}, "image_size": 32}
BUDGET = 25 * 2**20
R = 4
Q_PROJ = "language_model.model.layers.0.self_attn.q_proj.weight"


@pytest.fixture(scope="module")
def module() -> VLAModule:
    torch.manual_seed(0)
    return VLAModule(
        backbone="openvla-oft-mini", backbone_overrides=CUT, lora=LoraSettings(r=R, alpha=2 * R)
    )


def observation(model) -> dict:
    c = model.config
    g = torch.Generator().manual_seed(0)
    return {
        keys.IMAGES: torch.rand(2, c.num_images, 3, c.image_size, c.image_size, generator=g),
        keys.INSTRUCTION: ["put the bowl on the plate", "open the drawer"],
        keys.PROPRIO: torch.rand(2, c.proprio_dim, generator=g) * 2 - 1,
    }


def train_like(module: VLAModule, seed: int) -> None:
    """Weights as a fit leaves them: LoRA B no longer zero, projector and head moved."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.backbone.parameters():
            if p.requires_grad:
                p.add_(torch.randn(p.shape, generator=g) * 0.02)


def tensors(folder: Path) -> dict[str, torch.Tensor]:
    with safe_open(str(folder / "model.safetensors"), framework="pt") as f:
        return {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118


def dense(state: dict[str, torch.Tensor], key: str) -> torch.Tensor:
    module = key.removesuffix(".weight")
    return state[f"{module}.lora_B.weight"] @ state[f"{module}.lora_A.weight"]


def test_exports_extract_and_merge_stay_lora_form(module: VLAModule, tmp_path: Path) -> None:
    obs = observation(module.backbone)
    train_like(module, 1)
    sft = module.export(tmp_path / "sft")
    train_like(module, 2)
    aux = module.export(tmp_path / "aux")
    with torch.no_grad():
        expected = module.backbone.eval().predict_action(obs)

    # The export: trained tensors and per LoRA target its delta (s·B, A); no base, no tokenizer.
    state = tensors(aux)
    assert (aux / "model.safetensors").stat().st_size <= BUDGET
    assert not (aux / "tokenizer.json").exists()
    assert json.loads((aux / "config.json").read_text())[BASE_DELTA] == {
        "form": "lora",
        "scaling": 1.0,
    }
    assert not [k for k in state if "embed_tokens" in k or k.startswith("vision_backbone.")]
    lora = dict(module.backbone.named_parameters())
    b, a = (lora[f"{Q_PROJ[:-7]}.lora_{x}.default.weight"] for x in "BA")
    torch.testing.assert_close(dense(state, Q_PROJ), module.lora_settings.scaling * b @ a)
    card = (aux / "README.md").read_text()
    for fact in (GEMMA3_270M.sha256, EFFICIENTNET_LITE0.sha256, "dequantised", "Gemma Terms"):
        assert fact in card, fact

    # c = θ_aux − θ_sft: exact LoRA for the base deltas (rank ≤ 2r), dense for the projector.
    vector = tmp_path / "c"
    meta = extract(aux, sft, vector)
    assert meta["tensors"][Q_PROJ]["storage"] == "lora"
    assert meta["tensors"][Q_PROJ]["rank"] <= 2 * R
    assert meta["tensors"]["projector.fc1.weight"]["storage"] == "full"
    assert sum(f.stat().st_size for f in vector.iterdir()) <= BUDGET

    # θ_sft + 1·c: θ_aux's projector and base deltas, θ_sft's heads (no capability parameters).
    meta_export = tmp_path / "meta"
    merge(sft, [(vector, 1.0)], meta_export)
    merged, wanted, start = tensors(meta_export), tensors(aux), tensors(sft)
    plain = {k for k in merged if ".lora_" not in k}
    assert plain == {k for k in wanted if ".lora_" not in k}
    for key in plain:
        target = wanted if key in meta["tensors"] else start
        torch.testing.assert_close(merged[key], target[key], rtol=0, atol=1e-6)
    assert any(key.startswith("action_head.") for key in plain - set(meta["tensors"]))
    torch.testing.assert_close(dense(merged, Q_PROJ), dense(wanted, Q_PROJ), rtol=0, atol=1e-6)
    assert merged[Q_PROJ[:-7] + ".lora_A.weight"].shape[0] <= 3 * R

    # Loaded back with θ_aux's heads, it acts as θ_aux: the base rebuilt, the deltas applied.
    with torch.no_grad():
        for key in plain - set(meta["tensors"]):
            merged[key] = wanted[key]
    (meta_export / "model.safetensors").unlink()
    save_file(merged, str(meta_export / "model.safetensors"))
    loaded = from_pretrained(meta_export).eval()
    assert loaded.base_delta is not None and Q_PROJ in loaded.base_delta
    with torch.no_grad():
        torch.testing.assert_close(loaded.predict_action(obs), expected, rtol=1e-4, atol=1e-5)

    # A fit from that export (θ_pre for the next stage): its base carries θ_meta's deltas, its
    # state dict still leaves Gemma out, and its export stacks the new LoRA on them.
    torch.manual_seed(1)
    downstream = VLAModule(pretrained=str(meta_export), lora=LoraSettings(r=R, alpha=2 * R))
    with torch.no_grad():
        torch.testing.assert_close(
            downstream.backbone.eval().predict_action(obs), expected, rtol=1e-4, atol=1e-5
        )
    assert not [k for k in downstream.backbone.state_dict() if "q_proj.base_layer" in k]
    train_like(downstream, 3)
    state = tensors(downstream.export(tmp_path / "downstream"))
    rank = merged[Q_PROJ[:-7] + ".lora_A.weight"].shape[0]
    assert state[Q_PROJ[:-7] + ".lora_A.weight"].shape[0] == rank + R

    # Its checkpoint carries those deltas: rebuilt from its saved config alone (as `capvector
    # evaluate --ckpt` does, θ_pre's export not read), it acts as the fit left it.
    checkpoint = {
        "state_dict": {f"backbone.{k}": v for k, v in downstream.backbone.state_dict().items()},
        "hyper_parameters": dict(downstream.hparams),
    }
    downstream.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, tmp_path / "downstream.ckpt")
    again = load_module(tmp_path / "downstream.ckpt").backbone.eval()
    with torch.no_grad():
        torch.testing.assert_close(
            again.predict_action(obs), downstream.backbone.eval().predict_action(obs)
        )
