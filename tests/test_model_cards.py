"""Export and vector folders carry a model card (README.md) that the model hubs read as is."""

from __future__ import annotations

import json
from pathlib import Path

import torch
import yaml

from capvector.backbones import build_backbone
from capvector.cli import main
from capvector.io.modelcard import read_model_card


def read_card(folder: Path) -> tuple[dict, str]:
    text = (folder / "README.md").read_text()
    _, header, body = text.split("---\n", 2)
    return yaml.safe_load(header), body


def test_exports_vectors_and_merges_carry_model_cards(tmp_path: Path) -> None:
    model = build_backbone("openvla-oft-tiny")
    model.save_pretrained(tmp_path / "sft")
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1e-3 * torch.randn_like(p))
    model.save_pretrained(tmp_path / "aux")
    header, body = read_card(tmp_path / "aux")
    assert header["library_name"] == "capvector" and "openvla-oft" in header["tags"]
    assert read_model_card(tmp_path / "aux").data.pipeline_tag == "robotics"  # checked as well
    assert "openvla-oft-tiny" in body

    extract = ["extract", "--aux", str(tmp_path / "aux"), "--sft", str(tmp_path / "sft")]
    assert main([*extract, "--out", str(tmp_path / "vec"), "--rank", "2"]) == 0
    header, body = read_card(tmp_path / "vec")
    meta = json.loads((tmp_path / "vec" / "capability_vector.json").read_text())
    # base_model holds hub ids only: local sources are named in the body (tests/test_hub.py)
    assert "base_model" not in header
    assert all(str((tmp_path / n).resolve()) in body for n in ("aux", "sft"))
    assert {"capability-vector", "peft", "lora"} <= set(header["tags"])
    assert meta["fingerprint"] in body and meta["sources"]["aux"]["preset"] == "openvla-oft-tiny"
    assert meta["command"].startswith("capvector extract --aux") and meta["command"] in body

    merge = ["merge", "--base", str(tmp_path / "sft"), "--vector", f"{tmp_path / 'vec'}:0.7"]
    assert main([*merge, "--out", str(tmp_path / "meta")]) == 0
    header, body = read_card(tmp_path / "meta")
    assert "base_model" not in header
    assert f"| base model (local path) | {(tmp_path / 'sft').resolve()} |" in body
    assert "x 0.7" in body and "capvector merge --base" in body


def test_written_folders_and_files_follow_the_umask(tmp_path: Path) -> None:
    """tempfile makes private folders (0700) and files (0600); finished outputs get what an
    ordinary mkdir/open gives under the umask, so a shared group can read them."""
    import os
    import stat

    from capvector.io.outputs import atomic_write_bytes

    old = os.umask(0o022)
    try:
        build_backbone("openvla-oft-tiny").save_pretrained(tmp_path / "export")
        atomic_write_bytes(tmp_path / "results.json", b"{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "export").stat().st_mode) == 0o755
    assert stat.S_IMODE((tmp_path / "export" / "model.safetensors").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "results.json").stat().st_mode) == 0o644


def test_shipped_cards_hold_hub_ids_only_as_base_model() -> None:
    """The cards in assets/ are read by the hub as they are: base_model, if any, is a hub id."""
    assets = Path(__file__).resolve().parents[1] / "assets"
    # A card is the README beside weights (assets/mini_study's README is a study's, not a model's).
    cards = sorted(r for r in assets.rglob("README.md") if any(r.parent.glob("*.safetensors")))
    # θ_pre, the capability vector and its two task vectors; and the mini study's exports so far
    vector = assets / "capability_vector"
    shipped = [assets / "theta_pre", vector, vector / "task_vector_aux", vector / "task_vector_sft"]
    assert set(shipped) <= {card.parent for card in cards}, cards
    study = [c for c in cards if c.parent not in shipped]
    assert all(c.is_relative_to(assets / "mini_study" / "run_folder") for c in study), study
    for card in cards:
        read_model_card(card.parent)
