"""``--device`` and ``--precision`` of the tools that run a model: the policy's parameters are
where the flags say and its forwards run in the dtype they say, inside real MuJoCo rollouts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch

from capvector.backbones.base import VLABackbone
from capvector.cli import main
from capvector.errors import CapVectorError
from capvector.eval.device import precision_context, resolve_device, resolve_precision

THETA_PRE = Path(__file__).resolve().parents[1] / "assets" / "theta_pre"


def spy_on_rollout_forwards(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """What each ``predict_action`` of a rollout runs with: the parameters' devices and dtypes,
    and the dtypes the model's linear layers compute in (autocast shows there)."""
    seen: list[dict[str, Any]] = []
    original = VLABackbone.predict_action

    def recording(self: VLABackbone, batch: Any, *args: Any, **kwargs: Any) -> Any:
        linear_dtypes: set[torch.dtype] = set()
        hooks = [
            m.register_forward_hook(lambda _m, _i, out: linear_dtypes.add(out.dtype))
            for m in self.modules()
            if isinstance(m, torch.nn.Linear)
        ]
        try:
            actions = original(self, batch, *args, **kwargs)
        finally:
            for hook in hooks:
                hook.remove()
        seen.append({
            "devices": {p.device for p in self.parameters()},
            "dtypes": {p.dtype for p in self.parameters()},
            "linear": linear_dtypes,
            "inputs": batch["images"].device,
        })  # fmt: skip
        return actions

    monkeypatch.setattr(VLABackbone, "predict_action", recording)
    return seen


@pytest.mark.sim
@pytest.mark.parametrize(
    ("flags", "compute_dtype"),
    [([], torch.float32), (["--device", "cpu", "--precision", "bf16-mixed"], torch.bfloat16)],
    ids=["default", "cpu-bf16-mixed"],
)
def test_evaluate_runs_the_policy_on_the_requested_device_and_precision(
    flags: list[str], compute_dtype: torch.dtype, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The default here (no GPU) is the CPU in float32; bf16-mixed keeps float32 weights and
    computes the linear layers in bf16, as Lightning's bf16-mixed does."""
    seen = spy_on_rollout_forwards(monkeypatch)
    code = main([
        "evaluate", "--ckpt", str(THETA_PRE), "--task", "Lift", "--episodes", "1",
        "--max-steps", "16", "--batch-size", "1", "--workers", "0",
        "--json", str(tmp_path / "eval.json"), *flags,
    ])  # fmt: skip
    assert code == 0
    assert len(seen) >= 2  # chunks of 8 steps: every forward of the episode was seen
    for forward in seen:
        assert forward["devices"] == {torch.device("cpu")} and forward["inputs"].type == "cpu"
        assert forward["dtypes"] == {torch.float32}
        assert forward["linear"] == {compute_dtype}
    (row,) = json.loads((tmp_path / "eval.json").read_text())
    assert row["episodes"] == 1 and row["per_episode"][0]["steps"] == 16


def test_device_and_precision_defaults_and_refusals() -> None:
    cpu = torch.device("cpu")
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device(None).type == expected
    assert resolve_precision(cpu, None) == "32-true"
    assert resolve_precision(torch.device("cuda"), None) == "bf16-mixed"
    with precision_context(cpu, "bf16-mixed")():
        assert torch.nn.functional.linear(torch.ones(1, 2), torch.ones(3, 2)).dtype == (
            torch.bfloat16
        )
    with pytest.raises(CapVectorError, match="16-mixed needs a GPU"):
        resolve_precision(cpu, "16-mixed")
    with pytest.raises(CapVectorError, match="none of 32-true, bf16-mixed, 16-mixed"):
        resolve_precision(cpu, "bf16")
    if not torch.cuda.is_available():
        with pytest.raises(CapVectorError, match="--device cuda is not usable here"):
            resolve_device("cuda")
