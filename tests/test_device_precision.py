"""``--device`` and ``--precision`` of the tools that run a model: the policy's parameters are
where the flags say and its forwards run in the dtype they say, inside real MuJoCo rollouts."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch

from capvector.backbones.openvla_oft import OpenVLAOFT
from capvector.cli import main
from capvector.errors import CapVectorError
from capvector.eval.device import precision_context, resolve_device, resolve_precision
from capvector.workflows.sweep import trainer_placement

THETA_PRE = Path(__file__).resolve().parents[1] / "assets" / "theta_pre"


def spy_on_forwards(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """What each forward of an OpenVLA-OFT runs with (a rollout's ``predict_action`` and a
    training or validation step alike): the parameters' devices and dtypes, the inputs' device,
    and the dtypes the model's linear layers compute in (autocast shows there)."""
    seen: list[dict[str, Any]] = []
    original = OpenVLAOFT.forward

    def recording(self: OpenVLAOFT, batch: Any, *args: Any, **kwargs: Any) -> Any:
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

    monkeypatch.setattr(OpenVLAOFT, "forward", recording)
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
    seen = spy_on_forwards(monkeypatch)
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


def test_sweep_fine_tunes_and_validates_on_the_requested_device_and_precision(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``sweep-scale --device --precision`` become the trainer's accelerator and precision: the
    fine-tuning steps and the validation of each λ run there."""
    from capvector.data.datamodule import RobotDataModule
    from capvector.module import VLAModule
    from capvector.vectors import extract
    from conftest import write_demo_file

    data = write_demo_file(tmp_path / "demos.hdf5", lengths=(12, 12))
    spec = RobotDataModule(train_files=[str(data)], batch_size=4).spec
    for seed, name in ((0, "pre"), (1, "other")):
        torch.manual_seed(seed)
        VLAModule(data_spec=spec).export(tmp_path / name)
    extract(aux=tmp_path / "other", sft=tmp_path / "pre", out=tmp_path / "vector")
    seen = spy_on_forwards(monkeypatch)
    code = main([
        "sweep-scale", "--base", str(tmp_path / "pre"), "--vector", str(tmp_path / "vector"),
        "--scales", "1", "--demos", str(data), "--finetune-steps", "2",
        "--out", str(tmp_path / "sweep"), "--device", "cpu", "--precision", "bf16-mixed",
    ])  # fmt: skip
    assert code == 0
    assert len(seen) >= 3  # 2 training steps and the validation
    for forward in seen:
        assert forward["devices"] == {torch.device("cpu")} and forward["inputs"].type == "cpu"
        assert forward["linear"] == {torch.bfloat16}


def test_import_original_checks_the_import_on_the_requested_device_and_precision(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One forward of the imported upstream OpenVLA-OFT run folder where the flags say, before
    the export is written; --no-check skips it."""
    from conftest import UPSTREAM_FIXTURES

    seen = spy_on_forwards(monkeypatch)
    common = ["import-original", "--preset", "openvla-oft-tiny",
              "--folder", str(UPSTREAM_FIXTURES / "openvla_oft" / "libero")]  # fmt: skip
    flags = ["--device", "cpu", "--precision", "bf16-mixed"]
    assert main([*common, *flags, "--out", str(tmp_path / "checked")]) == 0
    (forward,) = seen
    assert forward["devices"] == {torch.device("cpu")} and forward["linear"] == {torch.bfloat16}
    assert main([*common, *flags, "--no-check", "--out", str(tmp_path / "unchecked")]) == 0
    assert len(seen) == 1 and (tmp_path / "unchecked" / "model.safetensors").is_file()


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
    assert trainer_placement("cpu", None, defaults=False) == {
        "trainer.accelerator": "cpu",
        "trainer.devices": 1,
    }
    assert trainer_placement(None, None, defaults=False) == {}  # the fit config's, untouched
    assert trainer_placement(None, None, defaults=True) == {
        "trainer.accelerator": expected, "trainer.devices": 1,
        "trainer.precision": "bf16-mixed" if expected == "cuda" else "32-true",
    }  # fmt: skip
    if not torch.cuda.is_available():
        with pytest.raises(CapVectorError, match="--device cuda is not usable here"):
            resolve_device("cuda")
