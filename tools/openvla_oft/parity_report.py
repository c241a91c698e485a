"""Print the max abs difference between capvector's OpenVLA-OFT and upstream's references.

Uses only the committed fixtures (``tests/fixtures/upstream/openvla_oft``), in capvector's own
environment::

    PYTHONPATH=src python tools/openvla_oft/parity_report.py

Besides each output it measures what the fixed mismatches of issue 16 cost: SigLIP with the
tanh-approximate GELU, and an OFT+ folder loaded without its FiLM vision backbone file (what the
loader did before: the file was skipped).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from capvector.backbones import OutputRequest
from capvector.backbones.openvla_oft import OpenVLAOFT
from capvector.data import keys

FIXTURES = Path(__file__).resolve().parents[2] / "tests" / "fixtures" / "upstream" / "openvla_oft"


def outputs(model: OpenVLAOFT, batch: dict) -> dict[str, torch.Tensor]:
    seen: dict[str, torch.Tensor] = {}

    def keep_first(_module: torch.nn.Module, _args: object, output: torch.Tensor) -> None:
        seen.setdefault("v", output)  # the batch pass, not the predict_action passes

    hook = model.vision_backbone.register_forward_hook(keep_first)
    with torch.no_grad():
        out = model(batch, OutputRequest(hidden_layers=(0, 1, 2)))
        predicted = [
            model.predict_action({k: v[i : i + 1] for k, v in batch.items() if k != keys.ACTIONS})[
                0
            ]
            for i in range(len(batch[keys.INSTRUCTION]))
        ]
    hook.remove()
    b = batch[keys.IMAGES].shape[0]
    result = {"train.vision_features": seen["v"].reshape(b, -1, seen["v"].shape[-1])}
    result.update({f"train.hidden.{k}": out.hidden_states[k] for k in (0, 1, 2)})
    result["train.actions"] = out.actions
    result["train.loss"] = out.loss.reshape(1)
    result.update({f"predict.{i}.actions": a for i, a in enumerate(predicted)})
    return result


def report(variant: str, root: Path, label: str, **overrides: object) -> None:
    references = load_file(str(FIXTURES / variant / "reference_outputs.safetensors"))
    inputs = np.load(FIXTURES / variant / "inputs.npz")
    batch = {
        keys.IMAGES: torch.from_numpy(inputs["images"]).permute(0, 1, 4, 2, 3).float() / 255,
        keys.PROPRIO: torch.from_numpy(inputs["proprio"]),
        keys.ACTIONS: torch.from_numpy(inputs["actions"]),
        keys.INSTRUCTION: [str(s) for s in inputs["instructions"]],
    }
    model = OpenVLAOFT.from_original(root, preset="openvla-oft-tiny", overrides=overrides).model
    ours = outputs(model.eval(), batch)
    diffs = {k: (v - references[k]).abs().max().item() for k, v in ours.items()}
    predict = max(v for k, v in diffs.items() if k.startswith("predict."))
    print(
        f"| {variant} | {label} | {diffs['train.vision_features']:.2e} | "
        f"{max(diffs[f'train.hidden.{k}'] for k in (0, 1, 2)):.2e} | "
        f"{diffs['train.actions']:.2e} | {predict:.2e} | {diffs['train.loss']:.2e} |"
    )


def main() -> None:
    print(
        "| variant | loaded as | vision features | hidden 0-2 | train actions | predict_action | L1 loss |"
    )
    print("|---|---|---|---|---|---|---|")
    for variant in ("libero", "aloha_film"):
        report(variant, FIXTURES / variant, "capvector (this branch)")
        report(
            variant,
            FIXTURES / variant,
            "SigLIP with gelu_tanh (before)",
            fused_featurizer={"act_layer": "gelu_tanh"},
        )
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "aloha_film"
        shutil.copytree(FIXTURES / "aloha_film", root)
        next(root.glob("vision_backbone--*")).unlink()
        report("aloha_film", root, "FiLM file skipped (before)")


if __name__ == "__main__":
    main()
