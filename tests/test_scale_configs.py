"""Full-size configs parse for every family and strategy; their strategy objects instantiate
(DeepSpeed needs GPUs to run, so here it is only built)."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
import yaml

from capvector.cli import main

REPO = Path(__file__).resolve().parents[1]
FAMILIES = ["openvla-oft.yaml", "pi05.yaml", "starvla.yaml"]
STRATEGIES = ["ddp.yaml", "fsdp2.yaml", "deepspeed_zero2.yaml", "deepspeed_zero3.yaml"]


@pytest.mark.parametrize("strategy", STRATEGIES)
@pytest.mark.parametrize("family", FAMILIES)
def test_full_size_config_parses_and_its_strategy_instantiates(
    family: str, strategy: str, capsys: pytest.CaptureFixture[str], demo_file: Path
) -> None:
    configs = [
        "configs/recipes/sft.yaml",
        f"configs/backbones/{family}",
        f"configs/scale/{strategy}",
        "configs/scale/batch.yaml",
    ]
    args = ["fit"] + [a for c in configs for a in ("--config", str(REPO / c))]
    with pytest.raises(SystemExit) as exit_info:
        main([*args, f"--data.train_files=[{demo_file}]", "--print_config"])
    assert exit_info.value.code in (0, None)
    printed = capsys.readouterr().out
    resolved = yaml.safe_load(
        printed[printed.index("seed_everything") :]
    )  # DeepSpeed logs to stdout first
    strategy_config = resolved["trainer"]["strategy"]
    module_name, _, class_name = strategy_config["class_path"].rpartition(".")
    strategy_object = getattr(importlib.import_module(module_name), class_name)(
        **strategy_config.get("init_args", {})
    )
    assert type(strategy_object).__name__ == class_name
    assert resolved["trainer"]["precision"] == "bf16-mixed"
    assert resolved["model"]["frozen_dtype"] == "bfloat16"
    assert (
        resolved["data"]["batch_size"] == 8 and resolved["trainer"]["accumulate_grad_batches"] == 1
    )
