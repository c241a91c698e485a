"""Max abs differences between capvector's StarVLA and StarVLA's own outputs, per fixture variant.

Runs in capvector's environment on the committed fixtures (no StarVLA code)::

    PYTHONPATH=src python tools/starvla/parity_report.py [--fixtures tests/fixtures/upstream/starvla]

Prints one Markdown table row per variant: token ids equal, and the max abs difference of the
vision features, each stored hidden-state layer, the training loss (recorded noise and times) and
the predicted actions (recorded initial noise).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file

TESTS = Path(__file__).resolve().parents[2] / "tests"
sys.path[:0] = [str(TESTS), str(TESTS / "backbones" / "starvla")]  # conftest, test_parity_starvla

from test_parity_starvla import FIXTURES, batch_of, qwen_folder  # noqa: E402

from capvector.backbones.starvla import StarVLA  # noqa: E402
from capvector.data import keys  # noqa: E402


def diff(a: torch.Tensor, b: torch.Tensor) -> float:
    return (a.double() - b.double()).abs().max().item()


def report(fixtures: Path, variant: str) -> str:
    imported = StarVLA.from_original(fixtures / variant / "run", qwen_folder=qwen_folder(variant))
    model = imported.model.eval()
    ref = load_file(str(fixtures / variant / "reference.safetensors"))
    batch = batch_of(ref)
    layers = sorted(int(k.split(".")[1]) for k in ref if k.startswith("hidden_states."))
    head = model.action_head
    state = batch.get(keys.PROPRIO) if model.config.state_mode == "head" else None
    with torch.no_grad():
        enc = model.encode(batch, [0], all_layers=True)
        pixel_values, grid = model.pixel_values(batch[keys.IMAGES])
        vision = model.vlm.model.get_image_features(pixel_values, grid)
        vision = getattr(vision, "pooler_output", vision)
        vision = torch.cat(list(vision))  # per-image embeds (transformers 5: pooler_output)
        cond = enc.head_input
        if "loss_noise" in ref:
            loss = head.flow_loss(cond, ref["actions"], state, ref["loss_noise"], ref["loss_time"])
            actions = head.sample(cond, state, noise=ref["predict_noise"])
        else:
            loss, actions = head.loss_and_actions(cond, ref["actions"], state)
    mask = cond.mask
    ours = (enc.requested[0], *cond.layers)  # HF's hidden_states as StarVLA's heads read them
    hidden = [diff(ours[i][mask], ref[f"hidden_states.{i}"][mask]) for i in layers]
    ids = torch.equal(enc.input_ids, ref["input_ids"])
    return (
        f"| {variant} | {'equal' if ids else 'DIFFER'} | {diff(vision, ref['vision_features']):.1e} | "
        f"{' / '.join(f'{h:.1e}' for h in hidden)} | {abs(loss.item() - ref['loss'].item()):.1e} | "
        f"{diff(actions, ref['actions_pred']):.1e} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--fixtures", type=Path, default=FIXTURES)
    args = parser.parse_args()
    print("| variant | token ids | vision features | hidden states (layers) | loss | actions |")
    print("|---|---|---|---|---|---|")
    for path in sorted(args.fixtures.glob("*/reference.safetensors")):
        print(report(args.fixtures, path.parent.name))


if __name__ == "__main__":
    main()
